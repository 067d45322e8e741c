"""Contact patches: the constraints of one face-to-face contact as one bond.

A joint's cohesion c and tensile strength σt act over the area where two blocks touch, not at
points. The constraints of one block pair that share a contact plane (the vertex-face and
edge-edge contacts of two faces lying against each other) form a *patch* whose area is the
convex hull of their points in that plane; each constraint carries an equal share of it.
The patch is one bond: it carries c·A in shear as a whole, so it slips (and loses its bond)
only when the patch's total shear force exceeds `Σ tan φ N + c A_bonded`, not vertex by
vertex (engine.contact.solvers._open_close_kernels.update_modes). Tension stays local: a constraint
pulled beyond its share σt·A/n opens and breaks its share of the bond, which is how a bond
under bending or toppling really fails, from the edge in (progressively; counted per step by
:func:`bond_breaks` and said in the run's summary).

The patch is data on the contacts (a patch id per contact, each patch's area); its bond state
is the contacts' `broken` flags in the contact memory (a patch is bonded where its contacts
are not broken), so any contact solver of a step reads the same patches. The
complementarity solve also sweeps each plane group (:func:`patch_ids`, edges and corners
included) as a unit: a rigid face's stuck corners are redundant, and point by point
Gauss–Seidel crawls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from engine.contact.constraints import ContactSet
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem

#: normals of one patch agree to 1 / this (their components are rounded to it)
NORMAL_SCALE = 1e6


@dataclass
class ContactPatches:
    """The patches of a step's contacts. Shapes: `c` contacts, `p` patches.

    `patch (c,) int64`: each contact's patch (-1: none, e.g. an edge or a corner, which
    carries no area); `area (p,)` m²: each patch's area; `share (c,)` m²: each contact's
    share of its patch's area (0 outside patches)."""

    patch: np.ndarray
    area: np.ndarray
    share: np.ndarray

    def __len__(self) -> int:
        return len(self.area)

    @classmethod
    def none(cls, c: int) -> ContactPatches:
        """No patches for `c` contacts (joints without cohesion or tensile strength)."""
        return cls(np.full(c, -1, dtype=np.int64), np.zeros(0), np.zeros(c))


def patch_ids(contacts: ContactSet) -> np.ndarray:
    """Each constraint's plane group `(c,) int` (0 .. groups − 1, numbered by block pair):
    the constraints of one block pair on one plane (a face on a face, an edge on a face)."""
    if not len(contacts):
        return np.zeros(0, dtype=np.int64)
    key = np.column_stack([contacts.block_i, contacts.block_j,
                           np.round(contacts.normal * NORMAL_SCALE)]).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    return group.ravel().astype(np.int64)


def sweep_order(contacts: ContactSet, patch: np.ndarray, gravity: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Constraints grouped by plane group (`patch`, :func:`patch_ids`), groups from the top
    down along gravity (a Gauss–Seidel sweep then carries a load down a stack in one pass):
    the order `(c,)` and each group's bounds in it `(p + 1,)`."""
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


def contact_patches(contacts: ContactSet) -> ContactPatches:
    """The patches of `contacts`: constraints of one block pair with a common plane form a
    patch when there are at least three of them and their points span an area (the convex
    hull of the points in the plane), shared equally."""
    c = len(contacts)
    patch = np.full(c, -1, dtype=np.int64)
    share = np.zeros(c)
    areas: list[float] = []
    if not c:
        return ContactPatches(patch, np.zeros(0), share)
    group = patch_ids(contacts)
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        if len(idx) < 3:
            continue
        nrm = contacts.normal[idx[0]]
        u = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(nrm, u)
        p = contacts.point_j[idx]
        pts = np.column_stack([p @ u, p @ v])
        try:
            area = ConvexHull(pts).volume
        except QhullError:
            area = 0.0
        share[idx] = area / len(idx)
        if area > 0:
            patch[idx] = len(areas)
            areas.append(area)
    return ContactPatches(patch, np.array(areas), share)


def bond_breaks(patches: ContactPatches, broken_start: np.ndarray,
                broken_end: np.ndarray) -> tuple[int, int]:
    """How many patches lost their whole bond in a step, and how many lost part of it and
    kept the rest (progressively), from the contacts' broken flags at the step's start and
    end `(c,) bool`."""
    if not len(patches):
        return 0, 0
    inside = patches.patch >= 0
    p = patches.patch[inside]
    before = np.bincount(p, weights=~broken_start[inside], minlength=len(patches))
    after = np.bincount(p, weights=~broken_end[inside], minlength=len(patches))
    lost = after < before
    return int(np.sum(lost & (after == 0))), int(np.sum(lost & (after > 0)))


def bonded_at_start(system: BlockSystem, state: State, contacts: ContactSet
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Which contacts' joints have cohesion or tensile strength `(c,)`, and which of them
    start the step bonded `(c,)`: they touched at the start of the run (within the bond gap,
    the resolution of a scene's coordinates) or kept their bond since (a contact that forms
    later has friction only). One rule for every contact solver."""
    jm = contacts.joint_material
    strong = (system.cohesion[jm] > 0) | (system.tension[jm] > 0)
    if state.step == 0:
        return strong, strong & (contacts.gap <= system.bond_gap)
    row = state.memory.find(contacts.key)
    kept = np.zeros(len(contacts), dtype=bool)
    again = row >= 0
    kept[again] = ~state.memory.broken[row[again]]
    return strong, strong & kept
