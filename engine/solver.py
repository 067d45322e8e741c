"""The linear solve of `K D = F` behind one function: a sparse direct factorization for
small systems, preconditioned conjugate gradients (block Jacobi, warm start) for large ones.

K is symmetric positive definite (inertia + penalty springs; friction is explicit).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

#: systems with more unknowns use conjugate gradients. Measured on real DDA systems
#: (`python benchmarks/bench_solver.py`, cubes in contact, 2 cores): SuperLU 12.7 ms vs
#: CG 2.8 ms at 384 unknowns, 0.74 s vs 0.03 s at 6,000; a factorization is reused for the
#: friction cycles of an open-close iteration, so direct pays off only for small systems
DIRECT_SOLVE_MAX_UNKNOWNS = 300
CG_RTOL = 1e-12


class SolveError(RuntimeError):
    """The linear system could not be solved (singular or not converged)."""


def _dense_solver(k: np.ndarray) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
    """Cholesky of a small dense K (symmetric positive definite), LU if it is not."""
    try:
        fac = sla.cho_factor(k, check_finite=True)
        solve_with = sla.cho_solve
    except (sla.LinAlgError, ValueError):
        try:
            fac = sla.lu_factor(k, check_finite=True)
        except (sla.LinAlgError, ValueError) as exc:
            raise SolveError(f"singular system: {exc}") from exc
        solve_with = sla.lu_solve

    def dense(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        x = solve_with(fac, f)
        if not np.all(np.isfinite(x)):
            raise SolveError("dense solve produced non-finite values")
        return x

    return dense


def _block_jacobi(k: sp.csc_matrix, block: int) -> spla.LinearOperator:
    """Inverse of the `block`×`block` diagonal blocks of K as a preconditioner."""
    n = k.shape[0]
    nb = n // block
    kc = k.tocsr()
    diag = np.zeros((nb, block, block))
    for a in range(block):
        for b in range(block):
            diag[:, a, b] = kc[np.arange(a, n, block), np.arange(b, n, block)].A1
    return _inverse_blocks(diag)


def _inverse_blocks(diag: np.ndarray) -> spla.LinearOperator:
    """Block-diagonal inverse of `diag (nb, b, b)` as a linear operator."""
    nb, block, _ = diag.shape
    n = nb * block
    inv = np.linalg.inv(diag)

    def apply(x: np.ndarray) -> np.ndarray:
        return np.einsum("kij,kj->ki", inv, x.reshape(nb, block)).ravel()

    return spla.LinearOperator((n, n), matvec=apply, dtype=float)


def make_solver(
    k: sp.spmatrix, block: int = 6, diag_blocks: np.ndarray | None = None
) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
    """A function `solve(F, x0) -> D` for this K, factorized or CG by size.

    The factorization (or preconditioner) is built once and reused for every
    right-hand side of the open-close iteration that keeps the same K. `diag_blocks
    (n / block, block, block)`, when given, are K's diagonal blocks (saves extracting them).
    """
    n = k.shape[0]
    if n == 0:
        return lambda f, x0=None: np.zeros(0)
    if isinstance(k, np.ndarray):
        return _dense_solver(k)
    if n <= DIRECT_SOLVE_MAX_UNKNOWNS or n % block:
        try:
            lu = spla.splu(sp.csc_matrix(k))
        except RuntimeError as exc:  # exactly singular
            raise SolveError(f"singular system: {exc}") from exc

        def direct(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
            x = lu.solve(f)
            if not np.all(np.isfinite(x)):
                raise SolveError("direct solve produced non-finite values")
            return x

        return direct
    if diag_blocks is not None and diag_blocks.shape == (n // block, block, block):
        pre = _inverse_blocks(diag_blocks)
    else:
        pre = _block_jacobi(sp.csc_matrix(k), block)

    def cg(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        x, info = spla.cg(k, f, x0=x0, rtol=CG_RTOL, atol=0.0, M=pre, maxiter=10 * n)
        if info != 0 or not np.all(np.isfinite(x)):
            raise SolveError(f"conjugate gradients did not converge (info={info})")
        return x

    return cg
