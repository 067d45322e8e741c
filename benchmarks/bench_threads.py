"""A rock mass's K and contact detection: filled afresh against updated, one thread against two.

The first steps of the jointed cube (`benchmarks.timestep.jointed_cube`, sets at SPACING m)
are run once while every K the open-close iteration builds is recorded; then, in one run:

- K: every recorded K filled afresh against updated from the one before (only the
  contacts whose stiffness changed);
- detection: the narrow phase in one piece against in slices on threads.

Answers are compared (K data; the contact sets). The threaded CG that was measured beside
them is on branch `parallel-cg` (benchmarks/TIMESTEP-FINDINGS.md says why it is not used).
Run: `python -m benchmarks.bench_threads [SPACING] [STEPS]` (default 1.5 m, 3 steps).
"""

from __future__ import annotations

import dataclasses
import sys
import time
import warnings

import numba
import numpy as np

import engine.contact.detection as det
import engine.dynamics.assembly as asm
from benchmarks.timestep import jointed_cube
from engine.contact.search import detect
from engine.dynamics._assembly_kernels import fill_bsr
from engine.step.simulation import Simulation


def _record(spacing: float, steps: int) -> tuple[Simulation, list[tuple]]:
    """Step the cube, keeping every K request `(plan, kn, ks)`."""
    fills: list[tuple] = []
    matrix = asm.SystemPlan.matrix

    def recording_matrix(plan, kn, ks):  # noqa: ANN001, ANN202
        fills.append((plan, np.array(kn, dtype=float), np.array(ks, dtype=float)))
        return matrix(plan, kn, ks)

    asm.SystemPlan.matrix = recording_matrix
    try:
        sim = Simulation(jointed_cube(spacing))
        for _ in range(steps):
            sim.step()
    finally:
        asm.SystemPlan.matrix = matrix
    return sim, fills


def _time(fn, repeat: int = 2) -> float:  # noqa: ANN001
    """Best wall time (s) of `repeat` calls of `fn`."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _fills(fills: list[tuple]) -> None:
    def fresh() -> list[np.ndarray]:
        return [fill_bsr(p.base, p.ti, p.tj, p.normal, p.slot_ii, p.slot_jj, p.slot_ij,
                         p.slot_ji, kn, ks) for p, kn, ks in fills]

    def updated(keep: bool = True) -> list[np.ndarray]:
        out = []
        for p, kn, ks in fills:
            data = p._data(kn, ks)
            if keep:  # a copy: the plan's next update is in place
                out.append(data.copy())
        return out

    for p, _, _ in fills:
        p.last = None
    a = fresh()
    b = updated()
    diff = max(float(np.abs(x - y).max() / max(np.abs(x).max(), 1e-300))
               for x, y in zip(a, b, strict=True))
    t_f = _time(fresh, 1)
    for p, _, _ in fills:
        p.last = None
    t_u = _time(lambda: updated(False), 1)
    print(f"K, {len(fills)} matrices ({len(fills[0][1])} contacts): filled afresh "
          f"{t_f:.3f} s, updated from the last {t_u:.3f} s, x{t_f / t_u:.2f}; largest "
          f"relative difference {diff:.1e}")


def _detection(sim: Simulation) -> None:
    times, sets = {}, {}
    keep = det.THREADED_MIN_PAIRS
    try:
        for name, threshold in (("one piece", 10**12), ("slices", 0)):
            det.THREADED_MIN_PAIRS = threshold
            sets[name] = detect(sim.system, sim.state)
            times[name] = _time(lambda: detect(sim.system, sim.state), 5)
    finally:
        det.THREADED_MIN_PAIRS = keep
    a, b = sets.values()
    same = all(np.array_equal(getattr(a, f.name), getattr(b, f.name))
               for f in dataclasses.fields(a))
    t1, t2 = times.values()
    print(f"detection ({len(a)} contacts): one piece {t1 * 1e3:.1f} ms, in slices "
          f"{t2 * 1e3:.1f} ms, x{t1 / t2:.2f}; identical contact sets: {same}")


def main() -> None:
    warnings.simplefilter("ignore")
    spacing = float(sys.argv[1]) if len(sys.argv) > 1 else 1.5
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    sim, fills = _record(spacing, steps)
    print(f"jointed cube, sets at {spacing} m, {sim.system.n} blocks, first {steps} steps; "
          f"threads {numba.config.NUMBA_NUM_THREADS}")
    _fills(fills)
    _detection(sim)


if __name__ == "__main__":
    main()
