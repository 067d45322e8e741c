"""The displacement matrix T(x) of a block (docs/theory.md, P11): how a point of a block moves
for the block's 12 unknowns (translation, rotation, strain about its centroid)."""

from __future__ import annotations

import numpy as np


def displacement_matrices(points: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """`T(x)` `(p, 3, 12)` for points `(p, 3)` of blocks with centroids `(p, 3)`."""
    from engine.geometry._transform_kernels import T0, TA  # numba: imported when used

    xt = points - centroids
    return T0[None] + np.einsum("pa,aij->pij", xt, TA)
