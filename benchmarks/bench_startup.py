"""Benchmark: how fast `polydda` starts, and how validation grows with explicit blocks.

Run as `python -m benchmarks.bench_startup [--repeat N] [--out FILE.json]`. Part 1 times
fresh interpreters (the median of N runs, wall and CPU) for `polydda --version`, `--help`,
`schema`, `validate` of a cut scene (examples/wedge.json) and of explicit blocks
(examples/stack.json), against a bare `python -c pass` and against importing what every
command imported before the CLI imported lazily (the engine's run, strength reduction,
the scene conversion): the ratios are the result, absolute times follow the machine's load
(printed). Part 2 validates scenes of 1,001 / 3,001 / 12,001 explicit unit cubes in this
process (CPU time; the exponent of time against blocks: 1 is linear, it was 1.8) and
times the refusal of 25,001 (over the format's limits).

Part 3 (`--cold`) measures the first run of the README's example on a fresh machine: the
repository's files are copied to a temporary folder (a fresh clone: no compiled kernels),
installed into a fresh virtual environment (`pip install -e .`, timed apart), and with
numba's cache empty each time it times (wall and CPU) the README's wedge run three ways:
compiling the kernels as the run meets them, one after another (`POLYDDA_WARM_UP=0`: what
the first run did before `polydda warm-up`); after `polydda warm-up` (the README's first
command: the warm-up and the run timed apart); and a first run that warms up by itself
(on every core). The copy and its environment are deleted afterwards.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.harness import ROOT, growth_exponent

EXAMPLES = ROOT / "examples"
#: what every command imported before the CLI imported its commands lazily
EAGER = ("import engine.analyses.strength_reduction, engine.results.writer, "
         "engine.step.simulation, schemas.convert, service.documents")
CUBE_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _cli(*argv: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from service.cli.main import main; "
            f"sys.exit(main({list(argv)!r}))"]


COMMANDS: dict[str, list[str]] = {
    "python -c pass (interpreter alone)": [sys.executable, "-c", "pass"],
    "polydda --version": _cli("--version"),
    "polydda --help": _cli("--help"),
    "polydda schema": _cli("schema"),
    "polydda validate examples/stack.json (explicit blocks)":
        _cli("validate", str(EXAMPLES / "stack.json")),
    "polydda validate examples/wedge.json (cut by joints)":
        _cli("validate", str(EXAMPLES / "wedge.json")),
    "import of the engine as before (every command)": [sys.executable, "-c", EAGER],
}


def time_command(cmd: list[str], repeat: int) -> dict[str, float]:
    """Median wall and CPU seconds of `cmd` run `repeat` times (output discarded)."""
    walls, cpus = [], []
    for _ in range(repeat):
        before = os.times()
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT,
                       check=False)
        walls.append(time.perf_counter() - t0)
        after = os.times()
        cpus.append(after.children_user + after.children_system
                    - before.children_user - before.children_system)
    return {"wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus)}


def cubes(n: int, gap: float = 0.5) -> dict[str, Any]:
    """`n` unit cubes on a square grid, `gap` m apart, the first fixed."""
    side = int(n ** 0.5) + 1
    blocks = []
    for i in range(n):
        x, y = (1 + gap) * (i % side), (1 + gap) * (i // side)
        v = [[x + a, y + b, c] for c in (0, 1) for a, b in ((0, 0), (1, 0), (1, 1), (0, 1))]
        blocks.append({"name": f"c{i}", "vertices": v, "faces": CUBE_FACES, "fixed": i == 0})
    return {"blocks": blocks}


def validation_scaling(sizes: tuple[int, ...] = (1001, 3001, 12001)) -> dict[str, Any]:
    """CPU seconds to validate scenes of `sizes` explicit cubes (from their JSON file), the
    exponent, and the refusal of 25,001 cubes."""
    from schemas.convert import build_model
    from schemas.errors import SceneError

    build_model(cubes(2))  # imports and first calls out of the timing
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for n in (*sizes, 25_001):
            path = Path(d) / f"cubes_{n}.json"
            path.write_text(json.dumps(cubes(n)))
            c0, t0 = time.process_time(), time.perf_counter()
            try:
                build_model(path)
                outcome = "valid"
            except SceneError as exc:
                outcome = "refused: " + "; ".join(exc.lines())
            rows.append({"blocks": n, "cpu_s": time.process_time() - c0,
                         "wall_s": time.perf_counter() - t0, "outcome": outcome})
    timed = [r for r in rows if r["outcome"] == "valid"]
    return {"rows": rows, "exponent": growth_exponent([r["blocks"] for r in timed],
                                                      [r["cpu_s"] for r in timed])}


#: the README's example, as its first command runs it
README_RUN = ["run", "examples/wedge.json", "--out", "out/wedge.h5", "--summary",
              "out/wedge-summary.json"]


def _timed(cmd: list[str], cwd: Path, env: dict[str, str]) -> dict[str, Any]:
    """Wall and CPU seconds (this process's children) of `cmd`, and how it ended."""
    before = os.times()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = os.times()
    cpu = (after.children_user + after.children_system
           - before.children_user - before.children_system)
    return {"command": " ".join(Path(cmd[0]).name if k == 0 else c for k, c in enumerate(cmd)),
            "wall_s": wall, "cpu_s": cpu, "exit": proc.returncode,
            "last_line": (proc.stdout.strip().splitlines() or [""])[-1]}


def cold_first_run() -> dict[str, Any]:
    """The README's wedge run in a fresh copy of the repository, installed into a fresh
    virtual environment, with numba's cache empty: compiled as met (before), after
    `polydda warm-up`, and warming up by itself (module docstring, part 3)."""
    import shutil
    import venv

    with tempfile.TemporaryDirectory(prefix="polydda-cold-") as d:
        copy, env_dir = Path(d) / "polydda", Path(d) / "venv"
        files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                               cwd=ROOT, capture_output=True, text=True, check=True).stdout
        for f in files.splitlines():
            if (ROOT / f).is_file():
                (copy / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / f, copy / f)
        venv.create(env_dir, with_pip=True)
        bin_dir = env_dir / "bin"
        env = {k: v for k, v in os.environ.items()
               if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH", "VIRTUAL_ENV")}
        env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
        install = _timed([str(bin_dir / "pip"), "install", "--quiet", "-e", "."], copy, env)
        polydda = str(bin_dir / "polydda")
        cache = copy / "engine" / "__pycache__"
        runs: dict[str, Any] = {"install": install}

        def cold() -> None:
            shutil.rmtree(cache, ignore_errors=True)

        cold()
        runs["first run, compiling as met (before)"] = _timed(
            [polydda, *README_RUN], copy, env | {"POLYDDA_WARM_UP": "0"})
        cold()
        runs["polydda warm-up"] = _timed([polydda, "warm-up"], copy, env)
        runs["first run after polydda warm-up"] = _timed([polydda, *README_RUN], copy, env)
        cold()
        runs["first run, warming up by itself"] = _timed([polydda, *README_RUN], copy, env)
        runs["second run"] = _timed([polydda, *README_RUN], copy, env)
    return runs


#: where `--cold --out` keeps its measurement for the README's sentence
COLD_RESULT = ROOT / "benchmarks" / "results" / "startup_cold.json"


def _clock(seconds: float) -> str:
    """12 s, 2 min 09 s."""
    s = int(round(seconds))
    return f"{s} s" if s < 60 else f"{s // 60} min {s % 60:02d} s"


def cold_sentence(doc: dict[str, Any]) -> str:
    """What the README says of the first run, from a `--cold` measurement."""
    r = {k: f"{_clock(v['wall_s'])} ({_clock(v['cpu_s'])} of CPU)"
         for k, v in doc["cold"].items()}
    start, end = doc["load_average"][0][0], doc["load_average"][1][0]
    return (f"Measured in a fresh copy with a fresh virtual environment and an empty kernel "
            f"cache on {doc['cores']} cores shared with other work (load average {start:.1f} "
            f"at the start, {end:.1f} at the end; "
            f"`python -m benchmarks.bench_startup --cold`): `polydda warm-up` "
            f"{r['polydda warm-up']}, then the run {r['first run after polydda warm-up']}; "
            f"a first run that compiles as it goes took "
            f"{r['first run, compiling as met (before)']}, one that warms up by itself "
            f"{r['first run, warming up by itself']}; later runs {r['second run']}.")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5, help="runs per command (median)")
    p.add_argument("--out", type=Path, help="also write the numbers as JSON")
    p.add_argument("--cold", action="store_true",
                   help="only part 3: the README's first run in a fresh copy, fresh venv, "
                        "empty kernel cache (several minutes)")
    args = p.parse_args(argv)
    load = os.getloadavg()
    if args.cold:
        print(f"load average {load[0]:.2f} on {os.cpu_count()} cores; a fresh copy, venv "
              "and kernel cache", flush=True)
        runs = cold_first_run()
        for name, r in runs.items():
            print(f"  {name:<40} wall {r['wall_s']:7.1f} s  cpu {r['cpu_s']:7.1f} s  "
                  f"exit {r['exit']}", flush=True)
        after = os.getloadavg()
        print(f"load average at the end {after[0]:.2f}")
        if args.out:
            args.out.write_text(json.dumps({"load_average": [load, after],
                                            "cores": os.cpu_count(), "cold": runs},
                                           indent=2) + "\n")
        return 0
    print(f"load average {load[0]:.2f} on {os.cpu_count()} cores; median of {args.repeat}")
    startup = {name: time_command(cmd, args.repeat) for name, cmd in COMMANDS.items()}
    eager = startup["import of the engine as before (every command)"]["cpu_s"]
    for name, r in startup.items():
        r["cpu_ratio_to_eager_import"] = r["cpu_s"] / eager if eager > 0 else float("nan")
        print(f"  {name:<58} wall {r['wall_s']:6.2f} s  cpu {r['cpu_s']:5.2f} s  "
              f"({r['cpu_ratio_to_eager_import']:.2f} x the eager import)")
    scaling = validation_scaling()
    print("validation of explicit cubes (CPU, in process):")
    for r in scaling["rows"]:
        print(f"  {r['blocks']:>6,} blocks  cpu {r['cpu_s']:6.2f} s  wall {r['wall_s']:6.2f} s"
              f"  {r['outcome']}")
    print(f"  exponent of CPU time against blocks: {scaling['exponent']:.2f} (1: linear)")
    if args.out:
        args.out.write_text(json.dumps({"load_average": load, "repeat": args.repeat,
                                        "startup": startup, "validation": scaling},
                                       indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
