"""Compiled loops of the block motion update: exact rotation matrices (Rodrigues) and the
blocks' affine maps and vertices after a step.

Called once or twice per step for every block; as numpy (and scipy's Rotation) they were
a dozen calls costing ~0.1 ms even for one block. Compiled with numba (cached on disk).
"""

from __future__ import annotations

import numba as nb
import numpy as np


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


@nb.njit(cache=True)
def block_vertices(centroid: np.ndarray, affine: np.ndarray, vertex_block: np.ndarray,
                   rel0: np.ndarray) -> np.ndarray:
    """Current vertices `(V, 3)`: `centroid[b] + affine[b] @ rel0[v]` for the block b of
    each vertex (`vertex_block (V,)`, `rel0 (V, 3)` initial positions about the initial
    centroid)."""
    nv = rel0.shape[0]
    out = np.empty((nv, 3))
    for v in range(nv):
        b = vertex_block[v]
        x, y, z = rel0[v, 0], rel0[v, 1], rel0[v, 2]
        for i in range(3):
            out[v, i] = centroid[b, i] + affine[b, i, 0] * x + affine[b, i, 1] * y \
                + affine[b, i, 2] * z
    return out
