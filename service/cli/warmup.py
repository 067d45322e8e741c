"""`polydda warm-up`: compile the engine's numba kernels into their on-disk cache before the
first run, on every core, so that the first `polydda run` starts at once.

Numba compiles a kernel the first time it is called, for the types it is called with, one
after another in one process. The warm-up runs a small scene (the paper's wedge, a few steps,
written to a result file: the kernels of a default run) in several processes at once, each
compiling one group of kernel modules: a worker runs the other groups' modules as plain
Python (their `py_func`), which is quick on a two-block scene, so no kernel is compiled
twice. A group is a module with the modules whose kernels it calls; the largest go first,
each next one to the first process that is free. Any kernel module
that cannot run as Python (an intrinsic without a stand-in) is compiled by every worker
that needs it. A last run in this process, compiled throughout, loads everything from the
cache and compiles whatever the workers left (a kernel met only under types a worker did
not give it), so the cache is complete whatever happened in the workers. Nothing here
depends on which kernels exist: it finds the modules (`engine/**/_*_kernels.py`) and their
calls when it runs.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from service.cli.common import EXIT_OK, EXIT_RUN

#: the scene of the warm-up: the README's wedge (examples/wedge.json: a tetrahedral wedge on
#: two bounded joints over a concave fixed base block), a few steps
WARM_UP_SCENE: dict[str, Any] = {
    "name": "warm-up",
    "materials": {"rock": {"density": 2600}},
    "joint_materials": {"joint": {"friction_angle": 40}},
    "domain": {"box": {"min": [-10, -4, 0], "max": [10, 10, 10]}},
    "joints": [
        {"name": "J1", "dip": 50, "dip_direction": 110, "point": [0, 3, 10],
         "extent": {"polygon": [[0.136458, 4.166667, 10.322721],
                                [-3.048282, -4.583333, 10.322721],
                                [1.274329, -4.583333, 5.481907]]}},
        {"name": "J2", "dip": 55, "dip_direction": 240, "point": [0, 3, 10],
         "extent": {"polygon": [[-0.412646, 4.166667, 10.322721],
                                [4.639169, -4.583333, 10.322721],
                                [0.725226, -4.583333, 5.481907]]}},
    ],
    "boundary": {"fixed_blocks": [{"contains": [-8, 8, 2]}]},
    "analysis": {"duration": 0.005, "time_step": 0.001, "penalty": 3e10,
                 "block_model": "rigid", "record_interval": 1},
}

#: pure-Python stand-ins for the kernels' intrinsics (LLVM code that plain Python cannot
#: call), by name, so that a worker can run their module as Python; a module with another
#: intrinsic is compiled by each worker that runs it
INTRINSIC_STAND_INS: dict[str, Any] = {"_fma": lambda a, b, c: a * b + c}

ENGINE = Path(__file__).resolve().parents[2] / "engine"


def kernel_modules() -> list[str]:
    """The engine's kernel modules (`engine/**/_*_kernels.py`) as dotted names."""
    return sorted(".".join(p.relative_to(ENGINE.parent).with_suffix("").parts)
                  for p in ENGINE.rglob("_*_kernels.py"))


def _calls(modules: list[str]) -> dict[str, set[str]]:
    """For each kernel module, the other kernel modules it imports (whose kernels its
    kernels may call)."""
    out: dict[str, set[str]] = {}
    for m in modules:
        text = (ENGINE.parent / Path(*m.split("."))).with_suffix(".py").read_text()
        out[m] = {o for o in modules if o != m and (
            re.search(rf"\b{re.escape(o)}\b", text)
            or re.search(rf"from {re.escape(o.rsplit('.', 1)[0])} import [^\n]*"
                         rf"\b{re.escape(o.rsplit('.', 1)[1])}\b", text))}
    return out


def groups(modules: list[str] | None = None) -> list[list[str]]:
    """The kernel modules in groups that compile together (a module and the modules whose
    kernels its kernels call), the largest (by source size) first."""
    modules = kernel_modules() if modules is None else modules
    calls = _calls(modules)
    found: list[set[str]] = []
    for m in modules:  # connected components of the call graph
        linked = {m} | calls[m] | {o for o in modules if m in calls[o]}
        for g in [g for g in found if g & linked]:
            found.remove(g)
            linked |= g
        found.append(linked)
    size = {m: (ENGINE.parent / Path(*m.split("."))).with_suffix(".py").stat().st_size
            for m in modules}
    return [sorted(g) for g in sorted(found, key=lambda g: -sum(size[m] for m in g))]


def pythonize(modules: list[str]) -> list[str]:
    """Make the kernels of `modules` plain Python functions in this process (their
    py_func, wherever the engine's modules hold them); the modules that cannot (an
    intrinsic without a stand-in) stay compiled. Returns the modules made Python."""
    from numba.core.dispatcher import Dispatcher
    from numba.core.extending import _Intrinsic

    done, swapped = [], {}
    for name in modules:
        mod = importlib.import_module(name)
        own = vars(mod)
        if any(isinstance(v, _Intrinsic) and k not in INTRINSIC_STAND_INS
               for k, v in own.items()):
            continue
        for k, v in list(own.items()):
            if isinstance(v, Dispatcher):
                py = v.py_func
                py.py_func = py  # code that calls `kernel.py_func` directly still works
                swapped[id(v)] = py
                setattr(mod, k, py)
            elif isinstance(v, _Intrinsic):
                setattr(mod, k, INTRINSIC_STAND_INS[k])
        done.append(name)
    for mod in [m for n, m in list(sys.modules.items()) if n.startswith("engine.") and m]:
        for k, v in list(vars(mod).items()):  # names imported from them before the swap
            if id(v) in swapped and getattr(mod, k) is v:
                setattr(mod, k, swapped[id(v)])
    return done


def run_scene() -> float:
    """Run the warm-up scene to its end, written to a temporary result file (the kernels
    of a run and of its recording); the seconds it took."""
    from engine.results.writer import ResultWriter
    from engine.step.staged_run import run_scene as run
    from schemas.convert import build_model

    t0 = time.perf_counter()
    built = build_model(WARM_UP_SCENE)
    with tempfile.TemporaryDirectory() as d:
        writer = ResultWriter(Path(d) / "warm-up.h5", overwrite=True)
        res = run(built.model, built.stages, recorder=writer,
                  scene_json=json.dumps(WARM_UP_SCENE))
    if res.status != "completed":
        raise RuntimeError(f"the warm-up scene {res.status}: {res.message}")
    return time.perf_counter() - t0


def worker(compiled: list[str]) -> dict[str, Any]:
    """One worker: run the warm-up scene compiling the kernel modules `compiled`, the
    others as Python (those that can be)."""
    cpu = time.process_time()
    python = pythonize([m for m in kernel_modules() if m not in compiled])
    seconds = run_scene()
    return {"compiled": compiled, "python": python, "seconds": seconds,
            "cpu_seconds": time.process_time() - cpu}


def warm_up(workers: int | None = None) -> dict[str, Any]:
    """Compile the kernels of a run into numba's cache: each group of kernel modules in a
    worker process, `workers` at once (default: the cores; the largest groups first, the
    next to the first free process), then a run in this process that loads them all (and
    compiles what is left). The seconds of each part."""
    from engine import kernel_cache_dir, kernels_cached

    workers = workers or os.cpu_count() or 1
    t0 = time.perf_counter()
    cached = kernels_cached()
    reports: list[dict[str, Any]] = []
    if not cached and workers > 1:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(kernel_cache_dir())}
        queue, running = groups(), []
        while queue or running:
            while queue and len(running) < workers:
                share = queue.pop(0)
                running.append(subprocess.Popen(
                    [sys.executable, "-m", "service.cli.warmup", "--worker", ",".join(share)],
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                    cwd=str(ENGINE.parent)))
            done = next((p for p in running if p.poll() is not None), None)
            if done is None:
                time.sleep(0.05)
                continue
            running.remove(done)
            out, err = done.communicate()
            reports.append(json.loads(out) if done.returncode == 0 and out.strip()
                           else {"failed": (err.strip().splitlines() or ["?"])[-1]})
    parallel = time.perf_counter() - t0
    last = run_scene()
    return {"cache": str(kernel_cache_dir()), "already_cached": cached,
            "workers": reports, "parallel_seconds": parallel, "last_run_seconds": last,
            "seconds": time.perf_counter() - t0}


def note_compilation(show: bool = True) -> bool:
    """Whether the engine's kernels had to compile first (numba's cache was empty): then
    they are compiled here, on every core at once (`polydda warm-up`; one core: as the run
    meets them), said on stderr unless not `show`. The progress keeps what compiles later
    out of its estimate of the time left."""
    from engine import kernels_cached

    if kernels_cached():
        return False
    cores = os.cpu_count() or 1
    parallel = (cores > 1 and os.environ.get("POLYDDA_WARM_UP", "1") != "0"
                and os.environ.get("NUMBA_DISABLE_JIT", "0") in ("", "0"))  # nothing to cache
    if show:
        print("compiling the engine's numerical kernels first (once per machine"
              + (f", on {cores} cores" if parallel else "")
              + "; `polydda warm-up` does it ahead)", file=sys.stderr, flush=True)
    if parallel:
        try:
            warm_up(cores)
        except RuntimeError as exc:  # the run compiles what is left as it meets it
            print(f"warning: the parallel compilation stopped ({exc})", file=sys.stderr)
    return True


def cmd_warm_up(args: argparse.Namespace) -> int:
    """Compile the engine's kernels into numba's cache on every core, and say how long it
    took (nothing to do when they are cached)."""
    from engine import kernels_cached

    if kernels_cached() and not args.json:
        print("the engine's kernels are compiled already (numba's cache): nothing to do")
        return EXIT_OK
    if not args.json:
        print(f"compiling the engine's kernels on {args.workers or os.cpu_count()} "
              "cores...", file=sys.stderr, flush=True)
    try:
        report = warm_up(args.workers)
    except RuntimeError as exc:
        print(f"polydda warm-up: {exc}", file=sys.stderr)
        return EXIT_RUN
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return EXIT_OK
    from service import readable as rd

    n = len(report["workers"])
    how = (f"{rd.plural(n, 'group')} of kernels in {args.workers or os.cpu_count()} "
           "processes at once" if n else "in this process")
    print(f"kernels compiled in {rd.duration(report['seconds'])} ({how}, then a check run "
          f"of {rd.duration(report['last_run_seconds'])}); cached in {report['cache']}")
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """`python -m service.cli.warmup --worker MOD,MOD`: one worker (JSON on stdout)."""
    p = argparse.ArgumentParser(description="one worker of polydda warm-up")
    p.add_argument("--worker", required=True, help="kernel modules this worker compiles")
    args = p.parse_args(argv)
    json.dump(worker([m for m in args.worker.split(",") if m]), sys.stdout)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
