"""`polydda fos examples/wedge.json` end to end, and the wedge's 2-block step, here and (with
`--baseline COMMIT`) at an earlier commit of this repository, in one run: ratios measured under
the same load.

Run: `python benchmarks/bench_fos.py [--baseline COMMIT] [--repeat N]`. The baseline is
extracted with `git archive` into a temporary folder and run there in subprocesses (its
kernels compile once, in that folder). Each measurement is the best of `--repeat` runs
(wall and CPU seconds of the whole command, interpreter start and imports included); the
step cost is CPU time per step, best of 5 × 300 steps of the wedge at rest after 50 steps.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

STEP_SCRIPT = """
import dataclasses, time
from schemas.convert import build_model
from engine.step.simulation import Simulation
m = build_model("examples/wedge.json").model
m.controls = dataclasses.replace(m.controls, duration=1000.0, record_contacts=False)
sim = Simulation(m)
for _ in range(50):
    sim.step()
best = 1e9
for _ in range(5):
    t = time.process_time()
    for _ in range(300):
        sim.step()
    best = min(best, (time.process_time() - t) / 300)
print(best)
"""


def _run(cmd: list[str], cwd: Path) -> tuple[float, float, str]:
    """Wall and CPU seconds (children's user + system) of `cmd` in `cwd`, and its stdout."""
    env = dict(os.environ, PYTHONPATH=str(cwd))
    env.pop("NUMBA_CACHE_DIR", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, out.stdout


def fos(tree: Path, repeat: int) -> dict:
    """Best wall / CPU of `polydda fos examples/wedge.json --json --quiet` in `tree`, its
    factor of safety and trials."""
    cmd = [sys.executable, "-c", "import sys; from service.cli.main import main; "
           "sys.exit(main(sys.argv[1:]))", "fos", "examples/wedge.json", "--json", "--quiet"]
    runs = [_run(cmd, tree) for _ in range(repeat)]
    doc = json.loads(runs[0][2])
    return {"wall": min(r[0] for r in runs), "cpu": min(r[1] for r in runs),
            "fs": doc["factor_of_safety"], "trials": len(doc["runs"])}


def step_ms(tree: Path) -> float:
    """CPU ms per step of the wedge in `tree`."""
    return 1e3 * float(_run([sys.executable, "-c", STEP_SCRIPT], tree)[2].strip())


def extract(commit: str, into: Path) -> Path:
    """The tree of `commit` in `into` (git archive)."""
    archive = into / "tree.tar"
    with open(archive, "wb") as fh:
        subprocess.run(["git", "archive", commit], cwd=ROOT, stdout=fh, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into / "tree", filter="data")
    return into / "tree"


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--baseline", metavar="COMMIT", help="also measure this commit")
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    trees = {"here": ROOT}
    with tempfile.TemporaryDirectory() as tmp:
        if args.baseline:
            trees[args.baseline] = extract(args.baseline, Path(tmp))
            step_ms(trees[args.baseline])  # compile its kernels once, untimed
        step_ms(ROOT)
        rows = {name: {**fos(tree, args.repeat), "step_ms": step_ms(tree)}
                for name, tree in trees.items()}
    print(f"{'tree':>12} {'wall (s)':>9} {'CPU (s)':>8} {'FS':>8} {'trials':>7} "
          f"{'step (ms CPU)':>14}")
    for name, r in rows.items():
        print(f"{name:>12} {r['wall']:9.2f} {r['cpu']:8.2f} {r['fs']:8.4f} {r['trials']:7d} "
              f"{r['step_ms']:14.3f}")
    if args.baseline:
        a, b = rows["here"], rows[args.baseline]
        print(f"ratios here / {args.baseline}: wall {a['wall'] / b['wall']:.3f}, CPU "
              f"{a['cpu'] / b['cpu']:.3f}, step {a['step_ms'] / b['step_ms']:.3f}")


if __name__ == "__main__":
    main()
