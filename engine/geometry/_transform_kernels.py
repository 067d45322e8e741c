"""Shi's first-order displacement function T(x) (THEORY.md, paper eq. 11) and the compiled
loops of block motion: the motion T(x) v of points, exact rotation matrices (Rodrigues), the
blocks' affine maps after a step and the points `c + A (X0 − c0)` of moved blocks.

T is defined once here (the constant matrices below); the assembly builds its matrices from
them and every point motion is evaluated from them. Called once or twice per step for every
block; as numpy (and scipy's Rotation) they were a dozen calls costing ~0.1 ms even for one
block. Compiled with numba (cached on disk).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def point_motion(v: np.ndarray, x: float, y: float, z: float, out: np.ndarray) -> None:
    """T(x) v: the motion `out (3,)` of the point at `(x, y, z)` from its block's centroid
    for block motion `v (12,)` (u, v, w, rx, ry, rz, εx, εy, εz, γyz, γzx, γxy: a velocity
    or a step's displacement; engineering shear strains act half on each side)."""
    out[0] = v[0] + v[4] * z - v[5] * y + v[6] * x + 0.5 * (v[11] * y + v[10] * z)
    out[1] = v[1] + v[5] * x - v[3] * z + v[7] * y + 0.5 * (v[11] * x + v[9] * z)
    out[2] = v[2] + v[3] * y - v[4] * x + v[8] * z + 0.5 * (v[10] * x + v[9] * y)


def _columns(x: float, y: float, z: float) -> np.ndarray:
    """T at the point `(x, y, z)` `(3, 12)`, column q = the motion of unit v = e_q (exact:
    every entry is 0, ±1, ±x, ±y, ±z or half of one)."""
    out = np.zeros((3, 12))
    for q in range(12):
        point_motion.py_func(np.eye(12)[q], x, y, z, out[:, q])
    return out


#: T(x) = T0 + x_t TX + y_t TY + z_t TZ with x_t = x − x_c, from :func:`point_motion`
T0 = _columns(0.0, 0.0, 0.0)
#: (TX, TY, TZ) stacked `(3, 3, 12)`
TA = np.stack([_columns(*e) - T0 for e in np.eye(3)])


@nb.njit(cache=True, nogil=True)
def point_motions(points: np.ndarray, centroids: np.ndarray, v: np.ndarray) -> np.ndarray:
    """T(x) v `(p, 3)` for points `(p, 3)` of blocks with `centroids (p, 3)` moving with
    `v (p, 12)`."""
    p = points.shape[0]
    out = np.empty((p, 3))
    for k in range(p):
        point_motion(v[k], points[k, 0] - centroids[k, 0], points[k, 1] - centroids[k, 1],
                     points[k, 2] - centroids[k, 2], out[k])
    return out


@nb.njit(cache=True)
def rotation_matrices(rotvec: np.ndarray) -> np.ndarray:
    """Exact rotation matrices `(n, 3, 3)` of rotation vectors `(n, 3)` (rad):
    `R = cos θ I + (sin θ / θ) [r]x + ((1 − cos θ) / θ²) r rᵀ`, with the Taylor series of
    both ratios for tiny angles."""
    n = rotvec.shape[0]
    out = np.empty((n, 3, 3))
    for k in range(n):
        x, y, z = rotvec[k, 0], rotvec[k, 1], rotvec[k, 2]
        t2 = x * x + y * y + z * z
        if t2 < 1e-8:
            a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
            b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        else:
            t = np.sqrt(t2)
            a = np.sin(t) / t
            h = np.sin(0.5 * t)
            b = 2.0 * h * h / t2
        c = 1.0 - b * t2
        out[k, 0, 0] = c + b * x * x
        out[k, 0, 1] = b * x * y - a * z
        out[k, 0, 2] = b * x * z + a * y
        out[k, 1, 0] = b * y * x + a * z
        out[k, 1, 1] = c + b * y * y
        out[k, 1, 2] = b * y * z - a * x
        out[k, 2, 0] = b * z * x - a * y
        out[k, 2, 1] = b * z * y + a * x
        out[k, 2, 2] = c + b * z * z
    return out


@nb.njit(cache=True)
def move_blocks(d: np.ndarray, centroid: np.ndarray, affine: np.ndarray,
                rotation: np.ndarray) -> None:
    """Apply block displacements `d (n, 12)` in place: centroid += translation, affine ←
    R (I + ε) affine and rotation ← R rotation, with R the exact rotation of d[3:6] and ε
    the symmetric strain tensor of d[6:12] (engineering shear strains halved)."""
    n = d.shape[0]
    rot = rotation_matrices(np.ascontiguousarray(d[:, 3:6]))
    m = np.empty((3, 3))
    s = np.empty((3, 3))
    for k in range(n):
        for j in range(3):
            centroid[k, j] += d[k, j]
        # R (I + ε)
        s[0, 0], s[1, 1], s[2, 2] = 1.0 + d[k, 6], 1.0 + d[k, 7], 1.0 + d[k, 8]
        s[1, 2] = s[2, 1] = 0.5 * d[k, 9]
        s[0, 2] = s[2, 0] = 0.5 * d[k, 10]
        s[0, 1] = s[1, 0] = 0.5 * d[k, 11]
        for i in range(3):
            for j in range(3):
                m[i, j] = rot[k, i, 0] * s[0, j] + rot[k, i, 1] * s[1, j] + rot[k, i, 2] * s[2, j]
        for j in range(3):
            a0, a1, a2 = affine[k, 0, j], affine[k, 1, j], affine[k, 2, j]
            r0, r1, r2 = rotation[k, 0, j], rotation[k, 1, j], rotation[k, 2, j]
            for i in range(3):
                affine[k, i, j] = m[i, 0] * a0 + m[i, 1] * a1 + m[i, 2] * a2
                rotation[k, i, j] = rot[k, i, 0] * r0 + rot[k, i, 1] * r1 + rot[k, i, 2] * r2


@nb.njit(cache=True, nogil=True)
def block_vertices(centroid: np.ndarray, affine: np.ndarray, vertex_block: np.ndarray,
                   rel0: np.ndarray) -> np.ndarray:
    """Moved points `(V, 3)`: `centroid[b] + affine[b] @ rel0[v]` for the block b of each
    point (`vertex_block (V,)`, `rel0 (V, 3)` initial positions about the initial
    centroid). The one evaluation of `c + A (X0 − c0)`."""
    nv = rel0.shape[0]
    out = np.empty((nv, 3))
    for v in range(nv):
        b = vertex_block[v]
        x, y, z = rel0[v, 0], rel0[v, 1], rel0[v, 2]
        for i in range(3):
            out[v, i] = centroid[b, i] + affine[b, i, 0] * x + affine[b, i, 1] * y \
                + affine[b, i, 2] * z
    return out


@nb.njit(cache=True)
def advance_blocks(d: np.ndarray, dt: float, v0: np.ndarray, fixed: np.ndarray,
                   centroid: np.ndarray, affine: np.ndarray, rotation: np.ndarray,
                   vertex_block: np.ndarray, rel0: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The update of a step's solution `d (n, 12)` of `dt` s in one pass: the blocks moved
    in place (:func:`move_blocks`), the end velocities `(n, 12)` of the constant-acceleration
    scheme `2 d / Δt − v0` (zero for `fixed` blocks) and the moved vertices `(V, 3)`
    (:func:`block_vertices`), so that the next step's detection finds them computed."""
    move_blocks(d, centroid, affine, rotation)
    n, w = d.shape
    v1 = np.empty((n, w))
    for k in range(n):
        for j in range(w):
            v1[k, j] = 0.0 if fixed[k] else 2.0 * d[k, j] / dt - v0[k, j]
    return v1, block_vertices(centroid, affine, vertex_block, rel0)


@nb.njit(cache=True, inline="always")
def _contact_matrix(points: np.ndarray, centroids: np.ndarray, block: np.ndarray, nd: int,
                    k: int, out: np.ndarray) -> None:
    """T at point `k` of block `block[k]` on its first `nd` columns, into `out[k]`:
    `T0 + x_t TX + y_t TY + z_t TZ` term by term as :func:`displacement_matrices` sums it
    (each entry has one nonzero term, so any order gives the same bits)."""
    b = block[k]
    x = points[k, 0] - centroids[b, 0]
    y = points[k, 1] - centroids[b, 1]
    z = points[k, 2] - centroids[b, 2]
    for i in range(3):
        for j in range(nd):
            out[k, i, j] = T0[i, j] + (x * TA[0, i, j] + y * TA[1, i, j] + z * TA[2, i, j])


@nb.njit(cache=True)
def contact_matrices(points: np.ndarray, centroids: np.ndarray, block: np.ndarray,
                     nd: int) -> np.ndarray:
    """T at the contact points `points (c, 3)` of blocks `block (c,)` (centroids
    `centroids (n, 3)`), on the first `nd` unknowns `(c, 3, nd)`: the values of
    `displacement_matrices(points, centroids[block])[:, :, :nd]`, without its temporaries."""
    c = points.shape[0]
    out = np.empty((c, 3, nd))
    for k in range(c):
        _contact_matrix(points, centroids, block, nd, k, out)
    return out


@nb.njit(cache=True, parallel=True)
def contact_matrices_threads(points: np.ndarray, centroids: np.ndarray, block: np.ndarray,
                             nd: int) -> np.ndarray:
    """:func:`contact_matrices` on numba's threads (each contact on its own: the same
    values whatever the number of threads)."""
    c = points.shape[0]
    out = np.empty((c, 3, nd))
    for k in nb.prange(c):
        _contact_matrix(points, centroids, block, nd, k, out)
    return out
