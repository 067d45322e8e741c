"""Shi's block terms and the penalty contact terms of the global system `K D = F`.

Everything is vectorised over blocks or contacts. Each block has 12 local columns
`(u, v, w, rx, ry, rz, εx, εy, εz, γyz, γzx, γxy)`; rigid blocks use the first 6, fixed
blocks none. `dof_map (n, 12) int` gives the global unknown of each column, -1 where the
column is not an unknown. The global K is assembled block-sparse (:class:`SystemPlan`):
contact terms are first summed per block and per block pair, so its size follows the
blocks and pairs in contact, not the number of contact points.
"""

from __future__ import annotations

from dataclasses import dataclass

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


#: systems with at most this many unknowns are assembled and factorized dense: for a few
#: blocks the sparse machinery costs more than the arithmetic
DENSE_MAX_UNKNOWNS = 120


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


def contact_parts(
    ti: np.ndarray, tj: np.ndarray, normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit-stiffness contact terms: `(normal, shear)` each `(3, c, d, d)` holding
    `(kii, kij, kjj)` for kn = 1 (P = n nᵀ) and ks = 1 (P = I − n nᵀ); the contact's
    terms are `kn·normal + ks·shear` (eqs. 24, 29). `ti`, `tj (c, 3, d)`."""
    a = np.einsum("ck,ckj->cj", normal, ti)
    b = np.einsum("ck,ckj->cj", normal, tj)
    n_ii = np.einsum("ci,cj->cij", a, a)
    n_ij = -np.einsum("ci,cj->cij", a, b)
    n_jj = np.einsum("ci,cj->cij", b, b)
    s_ii = np.einsum("cki,ckj->cij", ti, ti) - n_ii
    s_ij = -np.einsum("cki,ckj->cij", ti, tj) - n_ij
    s_jj = np.einsum("cki,ckj->cij", tj, tj) - n_jj
    return np.stack([n_ii, n_ij, n_jj]), np.stack([s_ii, s_ij, s_jj])


@dataclass
class SystemPlan:
    """The global K of one step as a function of the contact modes.

    Everything that does not depend on which contacts are closed or locked (block terms,
    unit contact terms, the block pairs and the sparsity pattern) is computed once per
    step by :func:`plan_system`; each open-close cycle then only re-weights and sums.
    """

    m: int
    d: int
    dblk0: np.ndarray  # (m, d, d) block terms of the free blocks
    diag_n: np.ndarray  # (k, d*d) unit normal terms landing on diagonal blocks
    diag_s: np.ndarray  # (k, d*d) unit shear terms landing on diagonal blocks
    diag_contact: np.ndarray  # (k,) contact of each diagonal term
    diag_row: np.ndarray  # (k,) its block row
    off_n: np.ndarray  # (q, d*d) unit normal terms of off-diagonal blocks (upper)
    off_s: np.ndarray  # (q, d*d)
    off_contact: np.ndarray  # (q,)
    off_pair: np.ndarray  # (q,) its block pair
    pair_a: np.ndarray  # (p,) block rows of each pair, pair_a < pair_b
    pair_b: np.ndarray
    order: np.ndarray  # BSR order of [diagonal, upper, lower] blocks
    indices: np.ndarray
    indptr: np.ndarray
    dense: bool
    diag_sum: sp.csr_matrix | None = None  # (m, k) sums diagonal terms (sparse path)
    off_sum: sp.csr_matrix | None = None  # (p, q) sums off-diagonal terms (sparse path)

    def matrix(self, kn: np.ndarray, ks: np.ndarray) -> tuple[sp.bsr_matrix | np.ndarray,
                                                               np.ndarray]:
        """K and its diagonal blocks `(m, d, d)` for per-contact normal and shear
        stiffness `kn`, `ks (c,)` (0 where the contact is open / not locked)."""
        m, d = self.m, self.d
        wn, ws = kn[self.diag_contact, None], ks[self.diag_contact, None]
        dterms = wn * self.diag_n + ws * self.diag_s
        wn, ws = kn[self.off_contact, None], ks[self.off_contact, None]
        oterms = wn * self.off_n + ws * self.off_s
        if self.dense:
            dblk = self.dblk0.copy()
            np.add.at(dblk, self.diag_row, dterms.reshape(-1, d, d))
            off = np.zeros((len(self.pair_a), d, d))
            np.add.at(off, self.off_pair, oterms.reshape(-1, d, d))
            k4 = np.zeros((m, m, d, d))
            r = np.arange(m)
            k4[r, r] = dblk
            k4[self.pair_a, self.pair_b] = off
            k4[self.pair_b, self.pair_a] = np.transpose(off, (0, 2, 1))
            return k4.transpose(0, 2, 1, 3).reshape(m * d, m * d), dblk
        assert self.diag_sum is not None and self.off_sum is not None
        dblk = self.dblk0 + np.asarray(self.diag_sum @ dterms).reshape(m, d, d)
        off = np.asarray(self.off_sum @ oterms).reshape(-1, d, d)
        data = np.concatenate([dblk, off, np.transpose(off, (0, 2, 1))])[self.order]
        k = sp.bsr_matrix((data, self.indices, self.indptr), shape=(m * d, m * d))
        return k, dblk


def _incidence(rows: np.ndarray, n_rows: int) -> sp.csr_matrix:
    """`(n_rows, len(rows))` 0/1 matrix that sums item k into row rows[k]."""
    return sp.csr_matrix((np.ones(len(rows)), (rows, np.arange(len(rows)))),
                         shape=(n_rows, len(rows)))


def plan_system(
    row_of: np.ndarray, diag: np.ndarray, bi: np.ndarray, bj: np.ndarray,
    ti: np.ndarray, tj: np.ndarray, normal: np.ndarray,
) -> SystemPlan:
    """The :class:`SystemPlan` of one step. `row_of (n,) int` is each block's block row
    (-1 for fixed blocks, rows in block order), `diag (n, d, d)` the block terms; contacts
    `bi`, `bj (c,)` with `ti`, `tj (c, 3, d)` and `normal (c, 3)`. K is dense for systems
    of at most DENSE_MAX_UNKNOWNS unknowns, else block-sparse (BSR)."""
    d = diag.shape[1]
    m = int(row_of.max(initial=-1)) + 1
    nparts, sparts = contact_parts(ti, tj, normal)
    fi, fj = row_of[bi], row_of[bj]
    a, b = fi >= 0, fj >= 0
    ca, cb = np.flatnonzero(a), np.flatnonzero(b)
    diag_rows = np.concatenate([fi[ca], fj[cb]])
    diag_n = np.concatenate([nparts[0][ca], nparts[2][cb]]).reshape(-1, d * d)
    diag_s = np.concatenate([sparts[0][ca], sparts[2][cb]]).reshape(-1, d * d)
    both = np.flatnonzero(a & b)
    pa, pb = fi[both], fj[both]
    swap = pa > pb
    tr = (0, 2, 1)
    off_n = np.where(swap[:, None, None], np.transpose(nparts[1][both], tr), nparts[1][both])
    off_s = np.where(swap[:, None, None], np.transpose(sparts[1][both], tr), sparts[1][both])
    pa, pb = np.where(swap, pb, pa), np.where(swap, pa, pb)
    pairs, inv = np.unique(pa * m + pb, return_inverse=True)
    pair_a, pair_b = pairs // m, pairs % m
    rows = np.concatenate([np.arange(m), pair_a, pair_b])
    cols = np.concatenate([np.arange(m), pair_b, pair_a])
    order = np.lexsort((cols, rows))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=m))])
    dense = m * d <= DENSE_MAX_UNKNOWNS
    inv = inv.ravel()
    return SystemPlan(
        m=m, d=d, dblk0=diag[row_of >= 0], diag_n=diag_n, diag_s=diag_s,
        diag_contact=np.concatenate([ca, cb]), diag_row=diag_rows,
        off_n=off_n.reshape(-1, d * d), off_s=off_s.reshape(-1, d * d), off_contact=both,
        off_pair=inv, pair_a=pair_a, pair_b=pair_b, order=order, indices=cols[order],
        indptr=indptr, dense=dense,
        diag_sum=None if dense else _incidence(diag_rows, m),
        off_sum=None if dense else _incidence(inv, len(pairs)),
    )
