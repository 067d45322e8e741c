"""The linear solve of a cut rock mass, solver against solver (issue 14).

`python -m benchmarks.bench_rockmass_solver [spacing] [steps]` runs the first `steps` steps
of the jointed cube (examples/jointed_cube.json, sets at `spacing` m; 1.5: 726 blocks),
records every system K the open-close iteration factorized and every right-hand side it
solved with it (with the warm start the engine gave), and times on exactly those systems:

- `cg-jacobi`: the engine's solver (compiled CG, block-Jacobi preconditioner, warm start);
- `superlu`: scipy's sparse LU, factorized for every K;
- `cholmod`: CHOLMOD's supernodal Cholesky (scikit-sparse) with the symbolic analysis
  done once per sparsity pattern and reused, a numeric factorization per K (it also
  prints how many unknowns' rows change from one K to the next: the rank a factorization
  update instead of a factorization would take);
- `amg-cg`: scipy CG preconditioned by pyamg's smoothed aggregation (set up per K).

Each solver's answers are checked against the engine's (relative residual ≤ 1e-8). It
prints, per solver, the set-up time (per K), the solve time (per right-hand side), and the
total for the recorded steps, on the 2 cores as they are (ratios in one run).
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import engine.contact.solvers.open_close as oc
from benchmarks.timestep import jointed_cube
from engine.dynamics.solver import BlockJacobi
from engine.step.simulation import Simulation


@dataclass
class Recorded:
    """One factorized K with the right-hand sides `(f, x0)` solved with it."""

    k: sp.csr_matrix
    rhs: list[tuple[np.ndarray, np.ndarray | None]] = field(default_factory=list)


def record(spacing: float, steps: int) -> tuple[list[Recorded], int]:
    """The systems of the first `steps` steps of the jointed cube, and its block count."""
    systems: list[Recorded] = []
    original = oc.make_solver

    def recording(k, *args, **kwargs):  # noqa: ANN001, ANN202 (make_solver's signature)
        rec = Recorded(sp.csr_matrix(k))
        systems.append(rec)
        solve = original(k, *args, **kwargs)

        def wrapped(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
            rec.rhs.append((np.array(f), None if x0 is None else np.array(x0)))
            return solve(f, x0)

        return wrapped

    oc.make_solver = recording
    try:
        sim = Simulation(jointed_cube(spacing, duration=1.0))
        for _ in range(steps):
            sim.step()
    finally:
        oc.make_solver = original
    return systems, sim.system.n


class _CgJacobi:
    """The engine's solver, its block-Jacobi preconditioner updated from K to K."""

    def __init__(self) -> None:
        self.jacobi = BlockJacobi()

    def __call__(self, k: sp.csr_matrix) -> Callable:
        return original_make_solver(sp.bsr_matrix(k, blocksize=(6, 6)), 6, None, self.jacobi)


def _superlu(k: sp.csr_matrix) -> Callable:
    lu = spla.splu(sp.csc_matrix(k))
    return lambda f, x0=None: lu.solve(f)


class _Cholmod:
    """CHOLMOD with the symbolic analysis reused while the sparsity pattern stays."""

    def __init__(self) -> None:
        self.pattern: tuple[bytes, bytes] | None = None
        self.factor = None

    def __call__(self, k: sp.csr_matrix) -> Callable:
        from sksparse.cholmod import analyze

        kc = sp.csc_matrix(k)
        key = (kc.indptr.tobytes(), kc.indices.tobytes())
        if key != self.pattern:
            self.factor, self.pattern = analyze(kc), key
        self.factor.cholesky_inplace(kc)
        factor = self.factor
        return lambda f, x0=None: factor(f)


def _amg_cg(k: sp.csr_matrix) -> Callable:
    import pyamg

    kc = sp.csr_matrix(k)
    ml = pyamg.smoothed_aggregation_solver(kc, B=np.ones((k.shape[0], 1)))
    m = ml.aspreconditioner()

    def solve(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        x, info = spla.cg(kc, f, x0=x0, rtol=1e-12, maxiter=2000, M=m)
        return x

    return solve


original_make_solver = oc.make_solver
SOLVERS: dict[str, Callable[[], Callable[[sp.csr_matrix], Callable]]] = {
    "cg-jacobi": _CgJacobi,
    "superlu": lambda: _superlu,
    "cholmod": _Cholmod,
    "amg-cg": lambda: _amg_cg,
}


def changed_unknowns(systems: list[Recorded]) -> np.ndarray:
    """Unknowns whose row of K changed from one factorized K to the next of the same
    pattern `(m,) int`: an upper bound of the rank a factorization update would take."""
    out = []
    for a, b in zip(systems, systems[1:], strict=False):
        if a.k.shape == b.k.shape and a.k.nnz == b.k.nnz and np.array_equal(
                a.k.indices, b.k.indices):
            d = (b.k - a.k).tocoo()
            out.append(len(np.unique(d.row[d.data != 0])))
    return np.array(out, dtype=np.int64)


def time_solvers(systems: list[Recorded]) -> dict[str, dict[str, float]]:
    """Set-up and solve seconds of each solver on the recorded systems, and the worst
    relative residual of its answers."""
    out: dict[str, dict[str, float]] = {}
    for name, make in SOLVERS.items():
        factory = make()
        setup = solve = 0.0
        worst = 0.0
        for rec in systems:
            t0 = time.perf_counter()
            try:
                fn = factory(rec.k)
            except Exception as exc:  # a solver that cannot take the system says so
                print(f"  {name}: {type(exc).__name__}: {exc}")
                setup = solve = float("nan")
                break
            t1 = time.perf_counter()
            setup += t1 - t0
            for f, x0 in rec.rhs:
                t2 = time.perf_counter()
                x = fn(f, x0)
                solve += time.perf_counter() - t2
                worst = max(worst, float(np.linalg.norm(rec.k @ x - f)
                                         / max(np.linalg.norm(f), 1e-300)))
        out[name] = {"setup_s": setup, "solve_s": solve, "total_s": setup + solve,
                     "worst_residual": worst}
    return out


def main() -> None:
    spacing = float(sys.argv[1]) if len(sys.argv) > 1 else 1.5
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    systems, n = record(spacing, steps)
    nk = len(systems)
    nrhs = sum(len(r.rhs) for r in systems)
    size = systems[0].k.shape[0] if systems else 0
    nnz = np.mean([r.k.nnz for r in systems]) if systems else 0
    print(f"jointed cube, sets at {spacing:g} m: {n} blocks, {steps} steps recorded in "
          f"{time.perf_counter() - t0:.1f} s: {nk} K ({size} unknowns, {nnz:.0f} nonzeros on "
          f"average), {nrhs} right-hand sides")
    ch = changed_unknowns(systems)
    if len(ch):
        print(f"unknowns changed between consecutive K of a step: median {np.median(ch):.0f}, "
              f"min {ch.min()}, max {ch.max()} of {size} (the rank an update would take)")
    res = time_solvers(systems)
    base = res["cg-jacobi"]["total_s"]
    print(f"{'solver':<10} {'set-up/K ms':>12} {'solve/rhs ms':>13} {'total s':>9} "
          f"{'vs engine':>9} {'residual':>9}")
    for name, r in res.items():
        print(f"{name:<10} {1e3 * r['setup_s'] / max(nk, 1):>12.2f} "
              f"{1e3 * r['solve_s'] / max(nrhs, 1):>13.2f} {r['total_s']:>9.3f} "
              f"{r['total_s'] / base:>9.2f} {r['worst_residual']:>9.1e}")


if __name__ == "__main__":
    main()
