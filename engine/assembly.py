"""Shi's block terms and the penalty contact terms of the global system `K D = F`.

Everything is vectorised over blocks or contacts. Each block has 12 local columns
`(u, v, w, rx, ry, rz, εx, εy, εz, γyz, γzx, γxy)`; rigid blocks use the first 6, fixed
blocks none. `dof_map (n, 12) int` gives the global unknown of each column, -1 where the
column is not an unknown. The global K is assembled block-sparse (:func:`block_system`):
contact terms are first summed per block and per block pair, so its size follows the
blocks and pairs in contact, not the number of contact points.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

# T(x) = T0 + x_t Tx + y_t Ty + z_t Tz (THEORY.md, paper eq. 11)
_T0 = np.zeros((3, 12))
_T0[0, 0] = _T0[1, 1] = _T0[2, 2] = 1.0
_TX = np.zeros((3, 12))
_TY = np.zeros((3, 12))
_TZ = np.zeros((3, 12))
# rotation r x x_t
_TZ[0, 4] = 1.0
_TY[0, 5] = -1.0
_TZ[1, 3] = -1.0
_TX[1, 5] = 1.0
_TY[2, 3] = 1.0
_TX[2, 4] = -1.0
# normal strains
_TX[0, 6] = 1.0
_TY[1, 7] = 1.0
_TZ[2, 8] = 1.0
# engineering shear strains (γ/2 on each side)
_TZ[1, 9] = 0.5
_TY[2, 9] = 0.5
_TZ[0, 10] = 0.5
_TX[2, 10] = 0.5
_TY[0, 11] = 0.5
_TX[1, 11] = 0.5
_TA = np.stack([_TX, _TY, _TZ])  # (3, 3, 12)


def displacement_matrices(points: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """`T(x)` `(p, 3, 12)` for points `(p, 3)` of blocks with centroids `(p, 3)`."""
    xt = points - centroids
    return _T0[None] + np.einsum("pa,aij->pij", xt, _TA)


def mass_matrices(density: np.ndarray, volume: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Block mass matrices `(n, 12, 12)`: `ρ (V T0ᵀT0 + Σ C_ab T_aᵀ T_b)`.

    `density (n,)` kg/m³, `volume (n,)` m³, `second (n, 3, 3)` = ∫ x_t x_tᵀ dV.
    """
    t0 = _T0.T @ _T0
    cross = np.einsum("aki,bkj->abij", _TA, _TA)  # (3, 3, 12, 12)
    m = volume[:, None, None] * t0[None] + np.einsum("nab,abij->nij", second, cross)
    return density[:, None, None] * m


def elastic_matrix(young_modulus: float, poisson_ratio: float) -> np.ndarray:
    """Isotropic 6×6 stiffness for Voigt strains with engineering shear (Pa)."""
    e, nu = young_modulus, poisson_ratio
    lam = e * nu / ((1 + nu) * (1 - 2 * nu))
    g = e / (2 * (1 + nu))
    d = np.zeros((6, 6))
    d[:3, :3] = lam
    d[np.arange(3), np.arange(3)] = lam + 2 * g
    d[np.arange(3, 6), np.arange(3, 6)] = g
    return d


def scatter_vector(dof_map: np.ndarray, block: np.ndarray, values: np.ndarray,
                   n: int) -> np.ndarray:
    """Global vector `(n,)` from per-block 12-vectors `values (p, 12)` of blocks `block (p,)`."""
    idx = dof_map[block]
    keep = idx >= 0
    return np.bincount(idx[keep], weights=values[keep], minlength=n)


def sum_by_index(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of `values (c, ...)` into `(n, ...)` by `index (c,) int`; rows with a
    negative index are skipped (a sparse incidence product: fast for many rows)."""
    keep = index >= 0
    flat = values.reshape(len(values), int(np.prod(values.shape[1:])))[keep]
    inc = sp.csr_matrix((np.ones(int(keep.sum())), (index[keep], np.arange(len(flat)))),
                        shape=(n, len(flat)))
    return np.asarray(inc @ flat).reshape((n, *values.shape[1:]))


#: systems with at most this many unknowns are assembled and factorized dense: for a few
#: blocks the sparse machinery costs more than the arithmetic
DENSE_MAX_UNKNOWNS = 120


def block_system(
    row_of: np.ndarray,
    diag: np.ndarray,
    bi: np.ndarray,
    bj: np.ndarray,
    kii: np.ndarray,
    kij: np.ndarray,
    kjj: np.ndarray,
) -> tuple[sp.bsr_matrix | np.ndarray, np.ndarray]:
    """Global K as a block-sparse matrix of `d × d` blocks, one block row per free block.

    `row_of (n,) int` is each block's block row (-1 for fixed blocks, rows in block
    order), `diag (n, d, d)` the block terms, `bi`, `bj (c,)` the blocks of each contact
    and `kii`, `kij`, `kjj (c, d, d)` its terms. Returns K and its diagonal blocks
    `(m, d, d)` (the block-Jacobi preconditioner needs them); K is a dense array for
    systems of at most DENSE_MAX_UNKNOWNS unknowns.
    """
    d = diag.shape[1]
    m = int(row_of.max(initial=-1)) + 1
    fi, fj = row_of[bi], row_of[bj]
    if m * d <= DENSE_MAX_UNKNOWNS:
        return _dense_system(m, diag[row_of >= 0], fi, fj, kii, kij, kjj)
    dblk = diag[row_of >= 0] + sum_by_index(fi, kii, m) + sum_by_index(fj, kjj, m)
    both = (fi >= 0) & (fj >= 0)
    a, b, kab = fi[both], fj[both], kij[both]
    # one off-diagonal block per pair: contacts of a pair listed as (j, i) are transposed
    swap = a > b
    kab = np.where(swap[:, None, None], np.transpose(kab, (0, 2, 1)), kab)
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    pairs, inv = np.unique(a * m + b, return_inverse=True)
    off = sum_by_index(inv.ravel(), kab, len(pairs))
    pa, pb = pairs // m, pairs % m
    rows = np.concatenate([np.arange(m), pa, pb])
    cols = np.concatenate([np.arange(m), pb, pa])
    data = np.concatenate([dblk, off, np.transpose(off, (0, 2, 1))])
    order = np.lexsort((cols, rows))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=m))])
    k = sp.bsr_matrix((data[order], cols[order], indptr), shape=(m * d, m * d))
    return k, dblk


def _dense_system(
    m: int, dblk: np.ndarray, fi: np.ndarray, fj: np.ndarray, kii: np.ndarray,
    kij: np.ndarray, kjj: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`block_system` as a dense `(m d, m d)` array for small systems."""
    d = dblk.shape[1]
    k4 = np.zeros((m, m, d, d))
    r = np.arange(m)
    k4[r, r] = dblk
    a, b = fi >= 0, fj >= 0
    np.add.at(k4, (fi[a], fi[a]), kii[a])
    np.add.at(k4, (fj[b], fj[b]), kjj[b])
    both = a & b
    np.add.at(k4, (fi[both], fj[both]), kij[both])
    np.add.at(k4, (fj[both], fi[both]), np.transpose(kij[both], (0, 2, 1)))
    return k4.transpose(0, 2, 1, 3).reshape(m * d, m * d), k4[r, r]


def contact_stiffness(
    ti: np.ndarray,
    tj: np.ndarray,
    normal: np.ndarray,
    kn: np.ndarray,
    ks: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal and (locked) shear penalty springs, paper eqs. 24 and 29.

    `ti`, `tj (c, 3, 12)` are T at the two contact points, `normal (c, 3)`, `kn`, `ks (c,)`
    (set ks = 0 for sliding contacts). Returns `(kii, kij, kjj)` each `(c, 12, 12)`.
    """
    # spring matrix P = kn n nᵀ + ks (I - n nᵀ)
    nn = np.einsum("ci,cj->cij", normal, normal)
    p = kn[:, None, None] * nn + ks[:, None, None] * (np.eye(3)[None] - nn)
    pti = np.einsum("cab,cbj->caj", p, ti)
    ptj = np.einsum("cab,cbj->caj", p, tj)
    kii = np.einsum("cai,caj->cij", ti, pti)
    kij = -np.einsum("cai,caj->cij", ti, ptj)
    kjj = np.einsum("cai,caj->cij", tj, ptj)
    return kii, kij, kjj
