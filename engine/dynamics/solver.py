"""The linear solve of `K D = F` behind one function: a sparse direct factorization for
small systems, preconditioned conjugate gradients (block Jacobi, warm start, compiled) for
large ones.

K is symmetric positive definite (inertia + penalty springs; friction is explicit).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from engine.dynamics._solver_kernels import (
    cholesky,
    cholesky_solve,
    factor_components,
    invert_spd_blocks,
    pcg_bsr,
    solve_components,
)

#: systems with more unknowns use conjugate gradients. Measured on real DDA systems
#: (`python benchmarks/bench_solver.py`, cubes in contact, 2 cores): SuperLU 12.7 ms vs
#: CG 2.8 ms at 384 unknowns, 0.74 s vs 0.03 s at 6,000; a factorization is reused for the
#: friction cycles of an open-close iteration, so direct pays off only for small systems
DIRECT_SOLVE_MAX_UNKNOWNS = 300
CG_RTOL = 1e-12
#: coupled components of at most this many blocks are solved exactly by a dense Cholesky
#: instead of conjugate gradients: CG needs about as many iterations as a stiff component
#: has unknowns, and all components iterate as long as the slowest (a landing pile: 42
#: components of 2 - 4 blocks, 48 iterations a solve)
COMPONENT_DIRECT_MAX_BLOCKS = 16


class SolveError(RuntimeError):
    """The linear system could not be solved (singular or not converged)."""


def _dense_solver(k: np.ndarray) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
    """Cholesky of a small dense K (symmetric positive definite; compiled), LU if it is
    not."""
    k = np.ascontiguousarray(k, dtype=np.float64)
    low, ok = cholesky(k) if np.all(np.isfinite(k)) else (k, False)
    if ok:
        def solve_with(f: np.ndarray) -> np.ndarray:
            return cholesky_solve(low, np.ascontiguousarray(f, dtype=np.float64))
    else:
        try:
            fac = sla.lu_factor(k, check_finite=True)
        except (sla.LinAlgError, ValueError) as exc:
            raise SolveError(f"singular system: {exc}") from exc

        def solve_with(f: np.ndarray) -> np.ndarray:
            return sla.lu_solve(fac, f)

    def dense(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        x = solve_with(f)
        if not np.all(np.isfinite(x)):
            raise SolveError("dense solve produced non-finite values")
        return x

    return dense


def diagonal_blocks(k: sp.spmatrix, block: int) -> np.ndarray:
    """The `block`×`block` diagonal blocks of K, `(n / block, block, block)`."""
    n = k.shape[0]
    kc = sp.csr_matrix(k)
    diag = np.zeros((n // block, block, block))
    for a in range(block):
        for b in range(block):
            diag[:, a, b] = kc[np.arange(a, n, block), np.arange(b, n, block)].A1
    return diag


def block_jacobi(diag: np.ndarray) -> np.ndarray:
    """Inverses of K's diagonal blocks `diag (m, b, b)`: the preconditioner of :func:`pcg`
    (SolveError if a block is not positive definite, i.e. K is not SPD)."""
    inv, ok = invert_spd_blocks(np.ascontiguousarray(diag, dtype=np.float64))
    if not ok:
        raise SolveError("the system matrix is not positive definite (a diagonal block)")
    return inv


class BlockJacobi:
    """The block-Jacobi preconditioner across the matrices of one open-close iteration:
    only the diagonal blocks that changed since the last K (the blocks whose contacts
    changed mode) are inverted again."""

    def __init__(self) -> None:
        self.diag: np.ndarray | None = None
        self.inv: np.ndarray | None = None

    def __call__(self, diag: np.ndarray) -> np.ndarray:
        """Inverses of `diag (m, b, b)` (see :func:`block_jacobi`)."""
        if self.diag is None or self.inv is None or self.diag.shape != diag.shape:
            inv = block_jacobi(diag)
        else:
            changed = np.flatnonzero(np.any(diag != self.diag, axis=(1, 2)))
            inv = self.inv.copy()
            inv[changed] = block_jacobi(diag[changed])
        self.diag, self.inv = diag.copy(), inv
        return inv


def make_solver(
    k: sp.spmatrix, block: int = 6, diag_blocks: np.ndarray | None = None,
    jacobi: BlockJacobi | None = None, components: np.ndarray | None = None,
    rtol: float = CG_RTOL,
) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
    """A function `solve(F, x0) -> D` for this K, factorized or CG by size.

    The factorization (or preconditioner) is built once and reused for every
    right-hand side of the open-close iteration that keeps the same K. `diag_blocks
    (n / block, block, block)`, when given, are K's diagonal blocks (saves extracting them);
    `jacobi` keeps the preconditioner of the previous K to update it; `components (n /
    block,)`, when given, are the coupled components of the block rows
    (:func:`engine.dynamics._assembly_kernels.coupled_components`): the small ones are factorized
    (:func:`split_components`), CG iterates on the others, to the relative residual `rtol`
    (its last solve's iterations are the returned function's `iterations`).
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
    if diag_blocks is None or diag_blocks.shape != (n // block, block, block):
        diag_blocks = diagonal_blocks(k, block)
    pre = (jacobi or block_jacobi)(diag_blocks)
    kc = k if sp.isspmatrix_bsr(k) and k.blocksize == (block, block) else sp.bsr_matrix(
        k, blocksize=(block, block))
    if components is None:
        ptr, small, rows = np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), \
            coupled_rows(kc)
    else:
        ptr, small, rows = split_components(components, COMPONENT_DIRECT_MAX_BLOCKS)
    factors, offsets, ok = factor_components(kc.indptr, kc.indices, np.ascontiguousarray(
        kc.data, dtype=np.float64), ptr, small)
    if not ok:
        raise SolveError("the system matrix is not positive definite (a coupled component)")

    def cg(f: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        x, iters = pcg(kc, f, pre, x0, rtol, 10 * n, rows)
        if iters < 0:
            raise SolveError(f"conjugate gradients did not converge in {10 * n} iterations")
        cg.iterations = iters  # type: ignore[attr-defined]
        solve_components(factors, offsets, ptr, small, block, f, x)
        if not np.all(np.isfinite(x)):
            raise SolveError("the solve produced non-finite values")
        return x

    return cg


def split_components(components: np.ndarray, max_blocks: int) -> tuple[np.ndarray, ...]:
    """The coupled components of at most `max_blocks` block rows, as `(ptr, rows)` (the
    rows of component c are `rows[ptr[c]:ptr[c + 1]]`), and the rows of the larger ones
    `(r,)`, from the component of each block row `components (m,)` (-1: uncoupled)."""
    coupled = np.flatnonzero(components >= 0)
    label = components[coupled]
    sizes = np.bincount(label)
    small = sizes[label] <= max_blocks
    rows = coupled[small][np.argsort(label[small], kind="stable")]
    counts = sizes[sizes <= max_blocks]
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return ptr, rows.astype(np.int64), coupled[~small].astype(np.int64)


def coupled_rows(k: sp.bsr_matrix) -> np.ndarray:
    """Block rows of K with a nonzero off-diagonal block `(r,) int`: the blocks that
    share a closed contact with another free block (the others are solved on their own)."""
    m = k.shape[0] // k.blocksize[0]
    row = np.repeat(np.arange(m), np.diff(k.indptr))
    nonzero = (row != k.indices) & np.any(k.data != 0.0, axis=(1, 2))
    return np.unique(row[nonzero]).astype(np.int64)


def pcg(k: sp.bsr_matrix, f: np.ndarray, m_inv: np.ndarray, x0: np.ndarray | None,
        rtol: float, maxiter: int, coupled: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Preconditioned conjugate gradients for SPD `k` (BSR) with the block-Jacobi
    inverse `m_inv (m, b, b)` of :func:`block_jacobi`: `(x, iterations)`, iterations -1
    when ‖f − K x‖ ≤ rtol ‖f‖ was not reached. Only the `coupled` block rows (default:
    :func:`coupled_rows`) iterate; the others are exact after the preconditioner.

    The whole loop is compiled: on the systems of a DDA step (hundreds to thousands of
    unknowns, ~20-50 iterations, ~10 solves per step) the Python recurrence spent most of
    its time dispatching its two sparse products.
    """
    f = np.ascontiguousarray(f, dtype=np.float64)
    x = np.zeros_like(f) if x0 is None else np.ascontiguousarray(x0, dtype=np.float64)
    rows = coupled_rows(k) if coupled is None else coupled
    return pcg_bsr(k.indptr, k.indices, np.ascontiguousarray(k.data, dtype=np.float64),
                   m_inv, rows, f, x, rtol, maxiter)
