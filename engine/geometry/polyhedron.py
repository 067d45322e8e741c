"""Polyhedral blocks: topology, planes, edge convexity, mass properties, validation.

Pure functions on arrays do the work; :class:`Polyhedron` is a thin cached facade.
Faces are planar polygons (possibly non-convex) whose vertices run counter-clockwise
seen from outside. Blocks may be concave; a concave block also carries a convex
decomposition (:class:`ConvexPiece`) that the contact detection works on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from engine.tolerances import DEFAULT_TOLERANCES, Tolerances

FACE_TAG_BOUNDARY = -1  #: face on the domain boundary or of an explicit block
FACE_TAG_INTERNAL = -2  #: fictitious face inside a block (between convex pieces)


# --------------------------------------------------------------------------- planes


def dip_normal(dip_deg: float, dip_direction_deg: float) -> np.ndarray:
    """Upward unit normal `(3,)` of a plane given by dip / dip direction in degrees.

    x = East, y = North, z = Up; dip direction clockwise from North (docs/theory.md).
    """
    d, a = np.radians(dip_deg), np.radians(dip_direction_deg)
    return np.array([np.sin(d) * np.sin(a), np.sin(d) * np.cos(a), np.cos(d)])


def normal_to_dip(normal: np.ndarray) -> tuple[float, float]:
    """Dip and dip direction (degrees) of the plane with normal `(3,)` (either sign)."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    if n[2] < 0:
        n = -n
    dip = float(np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0))))
    ddir = float(np.degrees(np.arctan2(n[0], n[1]))) % 360.0
    return dip, ddir


# --------------------------------------------------------------------------- faces


def faces_to_csr(faces: Sequence[Sequence[int]]) -> tuple[np.ndarray, np.ndarray]:
    """Polygon list -> CSR arrays `(indptr (m+1,) int, indices (k,) int)`."""
    lengths = np.array([len(f) for f in faces], dtype=np.int64)
    indptr = np.zeros(len(faces) + 1, dtype=np.int64)
    np.cumsum(lengths, out=indptr[1:])
    indices = (
        np.concatenate([np.asarray(f, dtype=np.int64) for f in faces])
        if len(faces)
        else np.zeros(0, dtype=np.int64)
    )
    return indptr, indices


def fan_triangles(indptr: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangulation of every face: `(t, 3) int` triangles and `(t,)` face ids.

    Fans of non-convex planar polygons overlap with signed areas that cancel, so
    they are exact for every integral of the divergence theorem (volume, moments,
    winding number), though not for drawing.
    """
    counts = np.diff(indptr)
    ntri = np.maximum(counts - 2, 0)
    face_of = np.repeat(np.arange(len(counts)), ntri)
    first = np.repeat(indptr[:-1], ntri)
    offs = np.arange(ntri.sum()) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    tris = np.stack(
        [indices[first], indices[first + offs + 1], indices[first + offs + 2]], axis=1
    )
    return tris, face_of


def face_normals_areas(
    vertices: np.ndarray, indptr: np.ndarray, indices: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Newell unit normals `(m, 3)` and areas `(m,)` of polygon faces."""
    tris, face_of = fan_triangles(indptr, indices)
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    vec = np.zeros((len(indptr) - 1, 3))
    np.add.at(vec, face_of, cross)
    norm = np.linalg.norm(vec, axis=1)
    area = 0.5 * norm
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = np.where(norm[:, None] > 0, vec / np.where(norm > 0, norm, 1)[:, None], 0.0)
    return normals, area


def face_centroids(vertices: np.ndarray, indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Area centroids `(m, 3)` of planar polygon faces (vertex mean for zero area)."""
    tris, face_of = fan_triangles(indptr, indices)
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    normals, _ = face_normals_areas(vertices, indptr, indices)
    w = np.einsum("ij,ij->i", np.cross(b - a, c - a), normals[face_of])  # 2*signed area
    m = len(indptr) - 1
    num = np.zeros((m, 3))
    np.add.at(num, face_of, w[:, None] * (a + b + c) / 3.0)
    den = np.zeros(m)
    np.add.at(den, face_of, w)
    counts = np.diff(indptr)
    mean = np.add.reduceat(vertices[indices], indptr[:-1], axis=0) / counts[:, None]
    ok = np.abs(den) > 1e-300
    out = mean.copy()
    out[ok] = num[ok] / den[ok, None]
    return out


# --------------------------------------------------------------------------- edges


def edge_topology(
    indptr: np.ndarray, indices: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Directed half-edges grouped into undirected edges.

    Returns `edges (e, 2)` as (a, b) in the direction of the first face that uses it,
    `edge_faces (e, 2)` (the face with a->b, the face with b->a; -1 if missing),
    `half_count (e,)` how many half-edges map to the edge, and `bad (e,)` True where
    both half-edges run the same way (inconsistent orientation).
    """
    counts = np.diff(indptr)
    face_of = np.repeat(np.arange(len(counts)), counts)
    nxt = np.arange(len(indices)) + 1
    ends = indptr[1:] - 1
    nxt[ends] = indptr[:-1]
    a = indices
    b = indices[nxt]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo.astype(np.int64) * (int(indices.max(initial=0)) + 1) + hi
    uniq, inverse, cnt = np.unique(key, return_inverse=True, return_counts=True)
    e = len(uniq)
    edges = np.full((e, 2), -1, dtype=np.int64)
    edge_faces = np.full((e, 2), -1, dtype=np.int64)
    bad = np.zeros(e, dtype=bool)
    forward = a < b
    # first occurrence defines the direction
    order = np.argsort(inverse, kind="stable")
    first = order[np.r_[0, np.cumsum(cnt)[:-1]]] if e else np.zeros(0, dtype=np.int64)
    edges[:, 0] = a[first]
    edges[:, 1] = b[first]
    same_dir = forward == forward[first][inverse]
    slot = np.where(same_dir, 0, 1)
    # a second half-edge in the same direction marks an orientation error
    dup = np.zeros(e, dtype=np.int64)
    np.add.at(dup, inverse[same_dir], 1)
    bad = dup > 1
    edge_faces[inverse, slot] = face_of
    return edges, edge_faces, cnt, bad


def edge_convexity(
    vertices: np.ndarray,
    edges: np.ndarray,
    edge_faces: np.ndarray,
    normals: np.ndarray,
    tol: float = 1e-9,
) -> np.ndarray:
    """`(e,) int`: +1 convex, -1 concave (reflex), 0 flat, for each edge.

    With the edge running a->b in its first face f1, it is convex where
    `(n1 x n2) . (b - a) > 0`.
    """
    n1 = normals[edge_faces[:, 0]]
    n2 = normals[edge_faces[:, 1]]
    d = vertices[edges[:, 1]] - vertices[edges[:, 0]]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    s = np.einsum("ij,ij->i", np.cross(n1, n2), d)
    return np.where(s > tol, 1, np.where(s < -tol, -1, 0)).astype(np.int8)


# --------------------------------------------------------------------------- mass


def mass_properties(
    vertices: np.ndarray, indptr: np.ndarray, indices: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume, centroid `(3,)` and `C = ∫ x_t x_tᵀ dV` `(3, 3)` about the centroid.

    Exact for closed polyhedra with planar faces (signed tetrahedra of a fan
    triangulation against a reference point near the block, for accuracy).
    """
    tris, _ = fan_triangles(indptr, indices)
    ref = vertices[indices].mean(axis=0)
    a, b, c = (vertices[tris[:, k]] - ref for k in range(3))
    v6 = np.einsum("ij,ij->i", a, np.cross(b, c))  # 6 * signed tet volume
    volume = v6.sum() / 6.0
    if volume == 0:
        return 0.0, ref.copy(), np.zeros((3, 3))
    s = a + b + c
    centroid_rel = (v6[:, None] * s).sum(axis=0) / 24.0 / volume
    # ∫ x xᵀ over tet (0, a, b, c) = V/20 (aaᵀ + bbᵀ + ccᵀ + s sᵀ)
    outer = (
        np.einsum("i,ij,ik->jk", v6, a, a)
        + np.einsum("i,ij,ik->jk", v6, b, b)
        + np.einsum("i,ij,ik->jk", v6, c, c)
        + np.einsum("i,ij,ik->jk", v6, s, s)
    ) / 120.0
    second = outer - volume * np.outer(centroid_rel, centroid_rel)
    return float(volume), centroid_rel + ref, 0.5 * (second + second.T)


def winding_numbers(
    points: np.ndarray, vertices: np.ndarray, indptr: np.ndarray, indices: np.ndarray
) -> np.ndarray:
    """Generalized winding number `(p,)` of points w.r.t. a closed surface (1 inside, 0 out).

    Sum of signed solid angles of the fan triangles (van Oosterom & Strackee).
    """
    tris, _ = fan_triangles(indptr, indices)
    pts = np.atleast_2d(points)
    out = np.empty(len(pts))
    for k0 in range(0, len(pts), 256):
        p = pts[k0 : k0 + 256, None, :]
        a = vertices[tris[:, 0]][None] - p
        b = vertices[tris[:, 1]][None] - p
        c = vertices[tris[:, 2]][None] - p
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        num = np.einsum("pij,pij->pi", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("pij,pij->pi", a, b) * lc
            + np.einsum("pij,pij->pi", b, c) * la
            + np.einsum("pij,pij->pi", c, a) * lb
        )
        out[k0 : k0 + 256] = 2.0 * np.arctan2(num, den).sum(axis=1) / (4.0 * np.pi)
    return out


# --------------------------------------------------------------------------- validation


def polyhedron_problems(
    vertices: np.ndarray,
    faces: Sequence[Sequence[int]],
    tol: Tolerances = DEFAULT_TOLERANCES,
) -> list[str]:
    """Everything wrong with a vertex/face description, in a rock engineer's words.

    Checks: indices in range, faces with >= 3 distinct vertices, closed and manifold
    (every edge in exactly two faces), consistent orientation, planar faces, positive
    volume (faces counter-clockwise seen from outside). Empty list: valid.
    """
    v = np.asarray(vertices, dtype=float)
    problems: list[str] = []
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        return ["needs at least 4 vertices, each [x, y, z]"]
    if not np.all(np.isfinite(v)):
        return ["vertex coordinates must be finite numbers"]
    if len(faces) < 4:
        return ["needs at least 4 faces to enclose a volume"]
    for k, f in enumerate(faces):
        if len(f) < 3:
            problems.append(f"face {k} has {len(f)} vertices; a face needs at least 3")
        elif any(i < 0 or i >= len(v) for i in f):
            problems.append(f"face {k} refers to a vertex index outside 0..{len(v) - 1}")
        elif len(set(f)) != len(f):
            problems.append(f"face {k} repeats a vertex")
    if problems:
        return problems
    indptr, indices = faces_to_csr(faces)
    edges, edge_faces, cnt, bad = edge_topology(indptr, indices)
    for k in np.flatnonzero(cnt == 1)[:5]:
        a, b = sorted(edges[k])
        problems.append(f"faces are not closed: edge ({a}, {b}) has one face")
    for k in np.flatnonzero(cnt > 2)[:5]:
        a, b = sorted(edges[k])
        problems.append(f"not manifold: edge ({a}, {b}) has {cnt[k]} faces")
    for k in np.flatnonzero(bad & (cnt == 2))[:5]:
        a, b = sorted(edges[k])
        problems.append(
            f"faces are not consistently oriented: both faces at edge ({a}, {b}) run it "
            "the same way (list every face counter-clockwise seen from outside)"
        )
    if problems:
        return problems
    lengths = tol.lengths(float(np.ptp(v, axis=0).max()))
    normals, area = face_normals_areas(v, indptr, indices)
    for k, f in enumerate(faces):
        if area[k] <= lengths.point_merge ** 2:
            problems.append(f"face {k} has zero area")
            continue
        p = v[list(f)]
        off = np.abs((p - p.mean(axis=0)) @ normals[k]).max()
        if off > lengths.planarity:
            problems.append(f"face {k} is not planar: a vertex is {off:.3g} m off its plane")
    if problems:
        return problems
    vol, _, _ = mass_properties(v, indptr, indices)
    if vol <= 0:
        problems.append(
            "volume is not positive: faces must run counter-clockwise seen from outside"
            if vol < 0
            else "volume is zero"
        )
    return problems


# --------------------------------------------------------------------------- types


class _Faces:
    """What follows from polygon faces given as CSR (`face_indptr`, `face_indices`): the
    vertices they use and their edges; shared by blocks and their convex pieces."""

    face_indptr: np.ndarray
    face_indices: np.ndarray

    @cached_property
    def _used(self) -> np.ndarray:
        return np.unique(self.face_indices)

    @cached_property
    def _edges(self) -> tuple[np.ndarray, np.ndarray]:
        e, ef, _, _ = edge_topology(self.face_indptr, self.face_indices)
        return e, ef


@dataclass(frozen=True, eq=False)
class ConvexPiece(_Faces):
    """A convex part of a (possibly concave) block, sharing the block's vertex array.

    `face_indptr`, `face_indices` index the block's vertices; `face_surface (m,)` is
    the block face the piece face lies on, or -1 for a fictitious internal face.
    """

    face_indptr: np.ndarray
    face_indices: np.ndarray
    face_surface: np.ndarray

    vertex_ids = property(lambda self: self._used,
                          doc="Block vertex indices used by this piece `(k,) int`.")
    edges = property(lambda self: self._edges,
                     doc="`(edges (e, 2), edge_faces (e, 2))` of the piece.")


def _part(source: str, index: int, doc: str) -> property:
    """A read-only property: item `index` of the cached tuple attribute `source`."""
    return property(lambda self: getattr(self, source)[index], doc=doc)


@dataclass(frozen=True, eq=False)
class Polyhedron(_Faces):
    """A block's closed surface: vertices `(n, 3)`, polygon faces (CSR), face tags.

    `face_tags (m,)` say what each face lies on: a joint id (>= 0) or
    :data:`FACE_TAG_BOUNDARY`. `vertices` may hold extra points after the surface
    vertices (seam points of the convex pieces); surface faces never use them.
    """

    vertices: np.ndarray
    face_indptr: np.ndarray
    face_indices: np.ndarray
    face_tags: np.ndarray
    pieces: tuple[ConvexPiece, ...] = field(default=())

    @classmethod
    def from_faces(
        cls,
        vertices: np.ndarray | Sequence[Sequence[float]],
        faces: Sequence[Sequence[int]],
        face_tags: Sequence[int] | np.ndarray | None = None,
        pieces: tuple[ConvexPiece, ...] = (),
    ) -> Polyhedron:
        """Build from a vertex array and a list of vertex-index polygons."""
        indptr, indices = faces_to_csr(faces)
        tags = (
            np.full(len(faces), FACE_TAG_BOUNDARY, dtype=np.int64)
            if face_tags is None
            else np.asarray(face_tags, dtype=np.int64)
        )
        return cls(np.asarray(vertices, dtype=float), indptr, indices, tags, pieces)

    def moved(self, vertices: np.ndarray) -> Polyhedron:
        """The same topology at new vertex positions `(n, 3)`."""
        return Polyhedron(vertices, self.face_indptr, self.face_indices, self.face_tags,
                          self.pieces)

    # --- topology
    @property
    def n_faces(self) -> int:
        return len(self.face_indptr) - 1

    @cached_property
    def faces(self) -> list[np.ndarray]:
        """Faces as a list of vertex-index arrays."""
        return np.split(self.face_indices, self.face_indptr[1:-1])

    surface_vertex_ids = property(lambda self: self._used,
                                  doc="Indices of the vertices the surface uses `(k,) int`.")
    edges = _part("_edges", 0, "Undirected edges `(e, 2) int`, directed as in their first face.")
    edge_faces = _part("_edges", 1, "The two faces of each edge `(e, 2) int`: the one running "
                       "a->b, then b->a.")

    @cached_property
    def edge_convexity(self) -> np.ndarray:
        """`(e,) int8`: +1 convex, -1 concave, 0 flat."""
        return edge_convexity(self.vertices, self.edges, self.edge_faces, self.face_normals)

    @property
    def is_convex(self) -> bool:
        return bool(np.all(self.edge_convexity >= 0))

    # --- geometry
    @cached_property
    def _normals_areas(self) -> tuple[np.ndarray, np.ndarray]:
        return face_normals_areas(self.vertices, self.face_indptr, self.face_indices)

    face_normals = _part("_normals_areas", 0, "Outward unit normals `(m, 3)`.")
    face_areas = _part("_normals_areas", 1, "Face areas `(m,)` in m².")

    @cached_property
    def face_offsets(self) -> np.ndarray:
        """Plane offsets `(m,)`: points x of face k satisfy `n_k . x = offset_k`."""
        first = self.vertices[self.face_indices[self.face_indptr[:-1]]]
        return np.einsum("ij,ij->i", self.face_normals, first)

    @cached_property
    def _mass(self) -> tuple[float, np.ndarray, np.ndarray]:
        return mass_properties(self.vertices, self.face_indptr, self.face_indices)

    volume = _part("_mass", 0, "Volume in m³.")
    centroid = _part("_mass", 1, "Centroid `(3,)` in m.")
    second_moments = _part("_mass", 2, "`C = ∫ x_t x_tᵀ dV` `(3, 3)` about the centroid, m⁵.")

    @cached_property
    def width(self) -> float:
        """How thick the block is where it is thinnest (m): the smallest extent of its
        convex pieces across their own face planes. A unit cube is 1 m wide (its 2 V / A
        is 1/3 m), a plate its thickness, an L block the thickness of its arms."""
        out = np.inf
        for piece in self.convex_pieces():
            nrm, _ = face_normals_areas(self.vertices, piece.face_indptr, piece.face_indices)
            nrm = nrm[np.linalg.norm(nrm, axis=1) > 0.5]  # degenerate faces: no plane
            h = self.vertices[piece.vertex_ids] @ nrm.T  # (k vertices, m faces)
            out = min(out, float((h.max(axis=0) - h.min(axis=0)).min()))
        return out

    @cached_property
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box `(2, 3)`: min, max."""
        p = self.vertices[self.surface_vertex_ids]
        return np.stack([p.min(axis=0), p.max(axis=0)])

    def problems(self, tol: Tolerances = DEFAULT_TOLERANCES) -> list[str]:
        """Validation messages (empty when the block is valid)."""
        used = self.surface_vertex_ids
        remap = np.full(len(self.vertices), -1)
        remap[used] = np.arange(len(used))
        faces = [remap[f].tolist() for f in self.faces]
        return polyhedron_problems(self.vertices[used], faces, tol)

    def convex_pieces(self) -> tuple[ConvexPiece, ...]:
        """The convex decomposition (the block itself when convex and none was given)."""
        if self.pieces:
            return self.pieces
        return (
            ConvexPiece(self.face_indptr, self.face_indices, np.arange(self.n_faces)),
        )


# --------------------------------------------------------------------------- motion


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Exact rotation matrix `(3, 3)` of a rotation vector `(3,)` (rad), or matrices
    `(n, 3, 3)` of vectors `(n, 3)`: Rodrigues' formula."""
    from engine.geometry._transform_kernels import rotation_matrices  # numba: when used

    rv = np.asarray(rotvec, dtype=np.float64)
    out = rotation_matrices(np.ascontiguousarray(rv.reshape(-1, 3)))
    return out[0] if rv.ndim == 1 else out
