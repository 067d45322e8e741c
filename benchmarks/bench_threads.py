"""Both cores on a rock mass: serial against threaded kernels, on the jointed cube's own work.

The first steps of the jointed cube (`benchmarks.timestep.jointed_cube`, sets at SPACING m)
are run once while every conjugate-gradient solve and every K the open-close iteration
builds is recorded; then, in one run:

- CG: the serial compiled kernel against the threaded one (numba's threads, sums over
  fixed slices) on exactly the recorded systems;
- K: every recorded K filled afresh against updated from the one before (only the
  contacts whose stiffness changed);
- detection: the narrow phase in one piece against in slices on threads.

Answers are compared (relative difference of the CG solutions; K data; the contact sets).
Run: `python -m benchmarks.bench_threads [SPACING] [STEPS]` (default 1.5 m, 3 steps).
"""

from __future__ import annotations

import dataclasses
import sys
import time
import warnings

import numba
import numpy as np

import engine.assembly as asm
import engine.detection as det
import engine.solver as es
from benchmarks.timestep import jointed_cube
from engine._assembly_kernels import fill_bsr
from engine._solver_kernels import pcg_bsr, pcg_bsr_parallel
from engine.contact_step import detect
from engine.simulation import Simulation


def _record(spacing: float, steps: int) -> tuple[Simulation, list[tuple], list[tuple]]:
    """Step the cube, keeping every CG system `(indptr, indices, data, inv, rows, f, x0)`
    and every K request `(plan, kn, ks)`."""
    solves: list[tuple] = []
    fills: list[tuple] = []
    pcg, matrix = es.pcg, asm.SystemPlan.matrix

    def recording_pcg(k, f, m_inv, x0, rtol, maxiter, coupled=None):  # noqa: ANN001, ANN202
        rows = es.coupled_rows(k) if coupled is None else coupled
        x0 = np.zeros_like(f) if x0 is None else np.ascontiguousarray(x0)
        solves.append((k.indptr, k.indices, np.ascontiguousarray(k.data), m_inv, rows,
                       np.ascontiguousarray(f), x0.copy()))
        return pcg(k, f, m_inv, x0, rtol, maxiter, coupled)

    def recording_matrix(plan, kn, ks):  # noqa: ANN001, ANN202
        fills.append((plan, np.array(kn, dtype=float), np.array(ks, dtype=float)))
        return matrix(plan, kn, ks)

    es.pcg, asm.SystemPlan.matrix = recording_pcg, recording_matrix
    try:
        sim = Simulation(jointed_cube(spacing))
        for _ in range(steps):
            sim.step()
    finally:
        es.pcg, asm.SystemPlan.matrix = pcg, matrix
    return sim, solves, fills


def _time(fn, repeat: int = 2) -> float:  # noqa: ANN001
    """Best wall time (s) of `repeat` calls of `fn`."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _cg(solves: list[tuple]) -> None:
    serial = [pcg_bsr(*s, es.CG_RTOL, 100000) for s in solves]
    threaded = [pcg_bsr_parallel(*s, es.CG_RTOL, 100000) for s in solves]
    diff = max(float(np.abs(a[0] - b[0]).max() / max(np.abs(a[0]).max(), 1e-300))
               for a, b in zip(serial, threaded, strict=True))
    t_s = _time(lambda: [pcg_bsr(*s, es.CG_RTOL, 100000) for s in solves])
    t_p = _time(lambda: [pcg_bsr_parallel(*s, es.CG_RTOL, 100000) for s in solves])
    its = sum(r[1] for r in serial)
    print(f"CG, {len(solves)} solves ({its} iterations, {len(solves[0][5])} unknowns): "
          f"serial {t_s:.3f} s, threaded {t_p:.3f} s, x{t_s / t_p:.2f}; "
          f"largest relative difference {diff:.1e}")


def _fills(fills: list[tuple]) -> None:
    def fresh() -> list[np.ndarray]:
        return [fill_bsr(p.base, p.unit, p.slot_ii, p.slot_jj, p.slot_ij, p.slot_ji, kn, ks)
                for p, kn, ks in fills]

    def updated() -> list[np.ndarray]:
        out = []
        for p, kn, ks in fills:
            out.append(p._data(kn, ks))
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
    t_u = _time(updated, 1)
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
    sim, solves, fills = _record(spacing, steps)
    print(f"jointed cube, sets at {spacing} m, {sim.system.n} blocks, first {steps} steps; "
          f"numba threads {numba.get_num_threads()} ({numba.threading_layer()})")
    _cg(solves)
    _fills(fills)
    _detection(sim)


if __name__ == "__main__":
    main()
