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


def _block_jacobi(k: sp.csc_matrix, block: int) -> sp.bsr_matrix:
    """Inverse of the `block`×`block` diagonal blocks of K as a preconditioner."""
    n = k.shape[0]
    nb = n // block
    kc = k.tocsr()
    diag = np.zeros((nb, block, block))
    for a in range(block):
        for b in range(block):
            diag[:, a, b] = kc[np.arange(a, n, block), np.arange(b, n, block)].A1
    return _inverse_blocks(diag)


def _inverse_blocks(diag: np.ndarray) -> sp.bsr_matrix:
    """Block-diagonal inverse of `diag (nb, b, b)` as a block-sparse matrix (its product
    runs in compiled code, not through a Python callback per CG iteration)."""
    nb, block, _ = diag.shape
    inv = np.linalg.inv(diag)
    return sp.bsr_matrix((inv, np.arange(nb), np.arange(nb + 1)),
                         shape=(nb * block, nb * block))


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

    kc = k.tobsr(blocksize=(block, block)) if not sp.isspmatrix_bsr(k) else k

    def cg(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        x, iters = pcg(kc, f, pre, x0, CG_RTOL, 10 * n)
        if iters < 0 or not np.all(np.isfinite(x)):
            raise SolveError(f"conjugate gradients did not converge in {10 * n} iterations")
        return x

    return cg


def pcg(k: sp.spmatrix, f: np.ndarray, m_inv: sp.spmatrix, x0: np.ndarray | None,
        rtol: float, maxiter: int) -> tuple[np.ndarray, int]:
    """Preconditioned conjugate gradients for SPD `k`: `(x, iterations)`, iterations -1
    when ‖f − K x‖ ≤ rtol ‖f‖ was not reached.

    The textbook recurrence with both products in compiled sparse code: on the systems of
    a DDA step (hundreds to thousands of unknowns, ~20 iterations, ~10 solves per step)
    scipy's `cg` spends most of its time in per-iteration Python dispatch (measured ~3×
    slower on the pile of 100 blocks).
    """
    x = np.zeros_like(f) if x0 is None else x0.copy()
    r = f - k @ x if x0 is not None else f.copy()
    stop = rtol * float(np.linalg.norm(f))
    if float(np.linalg.norm(r)) <= stop:
        return x, 0
    z = m_inv @ r
    p = z.copy()
    rz = float(r @ z)
    for it in range(1, maxiter + 1):
        q = k @ p
        alpha = rz / float(p @ q)
        x += alpha * p
        r -= alpha * q
        if float(np.linalg.norm(r)) <= stop:
            return x, it
        z = m_inv @ r
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, -1
