"""Contact patches: the constraints of one block pair on one plane (a face on a face, an
edge on a face: 2–8 points). A patch is what carries a joint's bond (cohesion and tensile
strength over its area, breaking as a whole) and what the complementarity solve sweeps as a
unit (a rigid face's stuck corners are redundant: point by point, Gauss–Seidel crawls)."""

from __future__ import annotations

import numpy as np

from engine.contact.constraints import ContactSet

#: normals of one patch agree to 1 / this (their components are rounded to it)
NORMAL_SCALE = 1e6


def patch_ids(contacts: ContactSet) -> np.ndarray:
    """Each constraint's patch `(c,) int` (0 .. patches − 1, numbered by block pair)."""
    if not len(contacts):
        return np.zeros(0, dtype=np.int64)
    key = np.column_stack([contacts.block_i, contacts.block_j,
                           np.round(contacts.normal * NORMAL_SCALE)]).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    return group.ravel().astype(np.int64)


def sweep_order(contacts: ContactSet, patch: np.ndarray, gravity: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Constraints grouped by patch, patches from the top down along gravity (a sweep then
    carries a load down a stack in one pass): the order `(c,)` and each patch's bounds in
    it `(p + 1,)`."""
    c = len(contacts)
    if not c:
        return np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    g = np.asarray(gravity, float)
    norm = float(np.linalg.norm(g))
    up = -g / norm if norm > 0 else np.array([0.0, 0.0, 1.0])
    height = contacts.point_i @ up
    count = int(patch.max()) + 1
    top = np.full(count, -np.inf)
    np.maximum.at(top, patch, height)
    order = np.lexsort((np.arange(c), patch, -top[patch])).astype(np.int64)
    bounds = np.flatnonzero(np.diff(patch[order])) + 1
    return order, np.concatenate([[0], bounds, [c]]).astype(np.int64)
