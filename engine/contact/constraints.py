"""Generalized contact constraints (paper section 2, Fig. 3, Fig. 7) as structure of arrays.

Every constraint is two points, one plane (unit normal from block j into block i), a
tangent and a mode. `gap = (p_i - p_j) . n` is the normal distance; negative is
penetration (paper eq. 4 and 20).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

# contact types (paper Fig. 2)
VERTEX_FACE, EDGE_EDGE, VERTEX_EDGE, VERTEX_VERTEX = 0, 1, 2, 3
KIND_NAMES = {VERTEX_FACE: "vertex-face", EDGE_EDGE: "edge-edge",
              VERTEX_EDGE: "vertex-edge", VERTEX_VERTEX: "vertex-vertex"}

# contact modes (paper section 2.4)
OPEN, LOCKED, SLIDING = 0, 1, 2
MODE_NAMES = {OPEN: "open", LOCKED: "locked", SLIDING: "sliding"}


def _empty(shape: tuple[int, ...], dtype: type = float) -> np.ndarray:
    return np.zeros(shape, dtype=dtype)


@dataclass
class ContactSet:
    """A list of generalized contact constraints, one row per constraint.

    Shapes: `c` constraints; `q` candidate normals in all.

    - `block_i`, `block_j (c,) int`: the two blocks (normal points from j into i)
    - `kind (c,) int8`: VERTEX_FACE, EDGE_EDGE, VERTEX_EDGE or VERTEX_VERTEX
    - `point_i`, `point_j (c, 3)`: the contact points on block i and block j (m)
    - `normal (c, 3)`: unit normal of the contact plane, from j into i
    - `tangent (c, 3)`: unit tangent (assumed sliding direction; zero if unknown)
    - `mode (c,) int8`: OPEN, LOCKED or SLIDING
    - `gap (c,)`: `(p_i - p_j) . n` (m), negative = penetration
    - `key (c, 4) int64`: stable identity (block i, feature i, block j, feature j),
      feature ids encode piece and vertex / edge / face so the same contact is
      found again in the next step
    - `face_tag (c,) int`: tag (joint id) of the face that defines the plane; for a
      plane through edges (edge-edge, and vertex-edge or vertex-vertex on a cross-product
      plane) the tag of a face at the contact lying along the plane; -1 for a boundary
      face or when no tagged face lies along the plane
    - `joint_material (c,) int`: joint material index (set by the caller)
    - `cand_indptr (c+1,) int`, `cand_normals (q, 3)`: candidate normals of a pure
      vertex-vertex or vertex-edge contact (empty range for the others)
    """

    block_i: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    block_j: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    kind: np.ndarray = field(default_factory=lambda: _empty((0,), np.int8))
    point_i: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    point_j: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    normal: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    tangent: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    mode: np.ndarray = field(default_factory=lambda: _empty((0,), np.int8))
    gap: np.ndarray = field(default_factory=lambda: _empty((0,)))
    key: np.ndarray = field(default_factory=lambda: _empty((0, 4), np.int64))
    face_tag: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    joint_material: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    cand_indptr: np.ndarray = field(default_factory=lambda: _empty((1,), np.int64))
    cand_normals: np.ndarray = field(default_factory=lambda: _empty((0, 3)))

    def __len__(self) -> int:
        return len(self.block_i)

    def same_as(self, other: ContactSet) -> bool:
        """Whether `other` holds exactly these constraints, array for array."""
        return all(np.array_equal(getattr(self, f.name), getattr(other, f.name))
                   for f in fields(self))

    def subset(self, index: np.ndarray) -> ContactSet:
        """The constraints selected by `index` (boolean mask or integer array)."""
        idx = np.arange(len(self))[index]
        counts = np.diff(self.cand_indptr)[idx]
        indptr = np.zeros(len(idx) + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        # each kept constraint's candidate rows, gathered at once (no loop over constraints)
        rows = np.repeat(self.cand_indptr[idx] - indptr[:-1], counts) + np.arange(indptr[-1])
        cand = self.cand_normals[rows].reshape(-1, 3)
        out = {f.name: getattr(self, f.name)[idx] for f in fields(self)
               if f.name not in ("cand_indptr", "cand_normals")}
        return ContactSet(**out, cand_indptr=indptr, cand_normals=cand)

    @staticmethod
    def concatenate(parts: list[ContactSet]) -> ContactSet:
        """One set holding all constraints of `parts`, in order."""
        if not parts:
            return ContactSet()
        out = {}
        for f in fields(ContactSet):
            if f.name == "cand_indptr":
                counts = np.concatenate([np.diff(p.cand_indptr) for p in parts])
                ptr = np.zeros(len(counts) + 1, dtype=np.int64)
                np.cumsum(counts, out=ptr[1:])
                out[f.name] = ptr
            else:
                out[f.name] = np.concatenate([getattr(p, f.name) for p in parts])
        return ContactSet(**out)


def assign_joint_materials(contacts: ContactSet, default: int, of_tag: dict[int, int],
                           of_pair: dict[tuple[int, int], int]) -> None:
    """Fill `contacts.joint_material (c,)` in place: block pair (min, max) wins over the
    face tag of the contact plane, which wins over `default`."""
    mat = np.full(len(contacts), default, dtype=np.int64)
    for tag, m in of_tag.items():
        mat[contacts.face_tag == tag] = m
    lo = np.minimum(contacts.block_i, contacts.block_j)
    hi = np.maximum(contacts.block_i, contacts.block_j)
    for (a, b), m in of_pair.items():
        mat[(lo == min(a, b)) & (hi == max(a, b))] = m
    contacts.joint_material = mat
