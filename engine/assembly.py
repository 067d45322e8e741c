"""Shi's block terms and the penalty contact terms of the global system `K D = F`.

Everything is vectorised over blocks or contacts and returned as COO triplets
(rows, cols, values) that the solver converts to CSR once per open-close cycle.
Each block has 12 local columns `(u, v, w, rx, ry, rz, εx, εy, εz, γyz, γzx, γxy)`;
`dof_map (n, 12) int` gives the global unknown of each column, -1 where the column is
not an unknown (rigid blocks use 6, fixed blocks none).
"""

from __future__ import annotations

import numpy as np

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


def block_triplets(
    dof_map: np.ndarray, blocks_k: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """COO triplets of block-diagonal terms `blocks_k (n, 12, 12)` mapped by `dof_map`."""
    rows = np.broadcast_to(dof_map[:, :, None], blocks_k.shape)
    cols = np.broadcast_to(dof_map[:, None, :], blocks_k.shape)
    keep = (rows >= 0) & (cols >= 0)
    return rows[keep], cols[keep], blocks_k[keep]


def pair_triplets(
    dof_map: np.ndarray,
    bi: np.ndarray,
    bj: np.ndarray,
    kii: np.ndarray,
    kij: np.ndarray,
    kjj: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """COO triplets of contact terms between blocks `bi`, `bj` `(c,)` with `(c,12,12)` parts."""
    di, dj = dof_map[bi], dof_map[bj]
    parts = [
        (di, di, kii),
        (di, dj, kij),
        (dj, di, np.transpose(kij, (0, 2, 1))),
        (dj, dj, kjj),
    ]
    rows, cols, vals = [], [], []
    for a, b, k in parts:
        r = np.broadcast_to(a[:, :, None], k.shape)
        c = np.broadcast_to(b[:, None, :], k.shape)
        keep = (r >= 0) & (c >= 0) & (k != 0)
        rows.append(r[keep])
        cols.append(c[keep])
        vals.append(k[keep])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def scatter_vector(dof_map: np.ndarray, block: np.ndarray, values: np.ndarray,
                   n: int) -> np.ndarray:
    """Global vector `(n,)` from per-block 12-vectors `values (p, 12)` of blocks `block (p,)`."""
    out = np.zeros(n)
    idx = dof_map[block]
    keep = idx >= 0
    np.add.at(out, idx[keep], values[keep])
    return out


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
