"""Block cutting: split a domain polyhedron into rock blocks along joint planes.

The domain is cut by the full arrangement of all planes involved (joint planes, the
side planes of bounded joints' extent prisms, and for a concave domain its own face
planes), so neighbouring convex cells share identical facets. Cells are then glued
back together across fictitious facets (outside a joint's extent, or on an auxiliary
plane); every group of glued cells is one block, its cells are its convex pieces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from engine.geometry.joints import JointPlane, plane_basis, unit
from engine.geometry.polyhedron import (
    FACE_TAG_BOUNDARY,
    ConvexPiece,
    Polyhedron,
    face_centroids,
    face_normals_areas,
    faces_to_csr,
    fan_triangles,
    winding_numbers,
)
from engine.tolerances import DEFAULT_TOLERANCES, Tolerances

_SAME_NORMAL = 1e-12  #: unit normals closer than this are treated as exactly parallel


# --------------------------------------------------------------------------- public types


@dataclass
class CutResult:
    """Blocks from cutting, and what went wrong on the way (slivers, idle joints)."""

    blocks: list[Polyhedron]
    warnings: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- small helpers


def _points_in_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """`(p,) bool`: which 2-D points `(p, 2)` lie inside the polygon `(m, 2)` (even-odd)."""
    x, y = pts[:, 0][:, None], pts[:, 1][:, None]
    x0, y0 = poly[:, 0][None], poly[:, 1][None]
    x1, y1 = np.roll(poly[:, 0], -1)[None], np.roll(poly[:, 1], -1)[None]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (np.count_nonzero(crosses & (x < xi), axis=1) % 2) == 1


# --------------------------------------------------------------------------- planes


@dataclass
class _Joint:
    """A joint as the cutter sees it: tag and extent polygon in plane coordinates."""

    tag: int
    origin: np.ndarray  # (3,) a point of the plane
    basis: tuple[np.ndarray, np.ndarray]  # in-plane unit vectors
    polygon: np.ndarray | None  # (m, 2) extent in (u, v) coordinates; None = persistent

    def contains(self, pts: np.ndarray) -> np.ndarray:
        """`(p,) bool`: which points `(p, 3)` on the plane lie on the joint."""
        if self.polygon is None:
            return np.ones(len(pts), dtype=bool)
        rel = pts - self.origin
        q = np.stack([rel @ self.basis[0], rel @ self.basis[1]], axis=1)
        return _points_in_polygon(q, self.polygon)


class _Planes:
    """Registry of distinct planes; exactly parallel planes share one normal (a group)."""

    def __init__(self, eps: float) -> None:
        self.eps = eps
        self.group_normals: list[np.ndarray] = []
        self.group_planes: list[list[int]] = []
        self.normal: list[np.ndarray] = []
        self.offset: list[float] = []
        self.group: list[int] = []
        self.members: list[list[int]] = []  # joint indices lying on the plane
        self._normals = np.zeros((0, 3))  # group normals, with spare rows

    def add(self, normal: np.ndarray, offset: float, member: int | None = None) -> int:
        """Id of the plane `normal . x = offset`, registering it if new."""
        n = unit(normal)
        gid = -1
        if self.group_normals:
            g = self._normals[: len(self.group_normals)]
            same = np.flatnonzero(np.abs(g - n).max(axis=1) < _SAME_NORMAL)
            flip = np.flatnonzero(np.abs(g + n).max(axis=1) < _SAME_NORMAL)
            if len(same):
                gid = int(same[0])
            elif len(flip):
                gid, offset = int(flip[0]), -offset
        if gid < 0:
            gid = len(self.group_normals)
            if gid == len(self._normals):
                self._normals = np.vstack([self._normals, np.zeros((max(gid, 8), 3))])
            self._normals[gid] = n
            self.group_normals.append(n)
            self.group_planes.append([])
        pid = -1
        for q in self.group_planes[gid]:
            if abs(self.offset[q] - offset) <= self.eps:
                pid = q
                break
        if pid < 0:
            pid = len(self.offset)
            self.normal.append(self.group_normals[gid])
            self.offset.append(float(offset))
            self.group.append(gid)
            self.members.append([])
            self.group_planes[gid].append(pid)
        if member is not None and member not in self.members[pid]:
            self.members[pid].append(member)
        return pid


# --------------------------------------------------------------------------- cells


@dataclass(slots=True)
class _Cell:
    """A convex cell: vertices `(n, 3)`, faces (CCW from outside), plane id per face."""

    verts: np.ndarray
    faces: list[list[int]]
    labels: list[int]


def _chain_loop(nxt: dict[int, int]) -> list[int] | None:
    """The single closed loop through a successor map, or None if it is not one loop."""
    if not nxt:
        return None
    start = next(iter(nxt))
    loop = [start]
    cur = nxt[start]
    while cur != start:
        if len(loop) > len(nxt) or cur not in nxt:
            return None
        loop.append(cur)
        cur = nxt[cur]
    return loop if len(loop) == len(nxt) else None


def _cap_by_angle(pts: np.ndarray, ids: list[int], normal: np.ndarray) -> list[int]:
    """On-plane points ordered counter-clockwise about `normal` (fallback cap builder)."""
    p = pts[ids]
    u, v = plane_basis(normal)
    rel = p - p.mean(axis=0)
    ang = np.arctan2(rel @ v, rel @ u)
    return [ids[k] for k in np.argsort(ang)]


def _split_cell(
    cell: _Cell, normal: np.ndarray, offset: float, label: int, eps: float
) -> tuple[_Cell, _Cell] | None:
    """Split a convex cell by a plane into (below, above) parts; None if it does not cut.

    Vertices within `eps` of the plane are snapped onto it. Intersection points are
    computed from the edge's lower end, so neighbour cells get bit-identical points.
    """
    v = cell.verts
    d = v[:, 0] * normal[0] + v[:, 1] * normal[1] + v[:, 2] * normal[2] - offset
    if d.min() >= -eps or d.max() <= eps:
        return None
    d[np.abs(d) <= eps] = 0.0
    sgn = np.sign(d).astype(np.int64).tolist()
    dl = d.tolist()
    nv = len(v)
    new_pts: list[np.ndarray] = []
    new_of_edge: dict[tuple[int, int], int] = {}
    neg_faces, neg_labels, pos_faces, pos_labels = [], [], [], []
    for face, lab in zip(cell.faces, cell.labels, strict=True):
        neg: list[int] = []
        pos: list[int] = []
        has_neg = has_pos = False
        m = len(face)
        for i in range(m):
            a = face[i]
            b = face[i + 1 - m]
            sa = sgn[a]
            if sa < 0:
                has_neg = True
                neg.append(a)
            elif sa > 0:
                has_pos = True
                pos.append(a)
            else:
                neg.append(a)
                pos.append(a)
            if sa * sgn[b] < 0:
                key = (a, b) if a < b else (b, a)
                k = new_of_edge.get(key)
                if k is None:
                    lo_, hi_ = (a, b) if sa < 0 else (b, a)
                    t = dl[lo_] / (dl[lo_] - dl[hi_])
                    new_pts.append(v[lo_] + (v[hi_] - v[lo_]) * t)
                    k = nv + len(new_pts) - 1
                    new_of_edge[key] = k
                    sgn.append(0)
                neg.append(k)
                pos.append(k)
        if has_neg:
            neg_faces.append(neg)
            neg_labels.append(lab)
        if has_pos:
            pos_faces.append(pos)
            pos_labels.append(lab)
    allv = np.vstack([v, np.asarray(new_pts)]) if new_pts else v
    # cap of the lower part: reverse of its faces' on-plane edges
    nxt: dict[int, int] = {}
    ok = True
    for f in neg_faces:
        m = len(f)
        for i in range(m):
            a, b = f[i], f[i + 1 - m]
            if sgn[a] == 0 and sgn[b] == 0:
                if b in nxt:
                    ok = False
                nxt[b] = a
    cap = _chain_loop(nxt) if ok else None
    if cap is None:
        on = sorted({i for f in neg_faces for i in f if sgn[i] == 0})
        cap = _cap_by_angle(allv, on, normal)
    if len(cap) < 3:
        return None
    neg_faces.append(cap)
    neg_labels.append(label)
    pos_faces.append(cap[::-1])
    pos_labels.append(label)
    return _compact(allv, neg_faces, neg_labels), _compact(allv, pos_faces, pos_labels)


def _compact(allv: np.ndarray, faces: list[list[int]], labels: list[int]) -> _Cell:
    """A cell keeping only the vertices its faces use."""
    used = sorted({i for f in faces for i in f})
    remap = dict(zip(used, range(len(used)), strict=True))
    return _Cell(allv[used], [[remap[i] for i in f] for f in faces], labels)


def _box_cell(lo: np.ndarray, hi: np.ndarray, planes: _Planes) -> _Cell:
    """The axis-aligned box `[lo, hi]` as a cell, its face planes registered."""
    verts = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1])
                      for x in (lo[0], hi[0])])
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    axes = [(2, -1), (2, 1), (1, -1), (1, 1), (0, -1), (0, 1)]
    labels = []
    for axis, s in axes:
        n = np.zeros(3)
        n[axis] = s
        labels.append(planes.add(n, s * (hi[axis] if s > 0 else lo[axis])))
    return _Cell(verts, faces, labels)


def _polyhedron_cell(poly: Polyhedron, planes: _Planes) -> _Cell:
    """A convex polyhedron as one cell, its face planes registered."""
    used = poly.surface_vertex_ids
    remap = {int(i): k for k, i in enumerate(used)}
    faces = [[remap[int(i)] for i in f] for f in poly.faces]
    labels = [
        planes.add(n, off) for n, off in zip(poly.face_normals, poly.face_offsets, strict=True)
    ]
    return _Cell(poly.vertices[used].copy(), faces, labels)


def _arrange(cells: list[_Cell], planes: _Planes, cut_ids: Sequence[int]) -> list[_Cell]:
    """Split the cells by every plane in `cut_ids` that passes through their interior.

    Parallel planes are handled together: a cell is tested once per group and cut by
    the group's planes in order; cells are prefiltered by their bounding boxes.
    """
    eps = planes.eps
    by_group: dict[int, list[int]] = {}
    for pid in dict.fromkeys(cut_ids):
        by_group.setdefault(planes.group[pid], []).append(pid)
    cells = list(cells)
    lo = np.array([c.verts.min(axis=0) for c in cells]).reshape(-1, 3)
    hi = np.array([c.verts.max(axis=0) for c in cells]).reshape(-1, 3)
    for gid, pids in by_group.items():
        g = planes.group_normals[gid]
        pids = sorted(pids, key=lambda p: planes.offset[p])
        offs = np.array([planes.offset[p] for p in pids])
        centre, half = 0.5 * (lo + hi) @ g, 0.5 * (hi - lo) @ np.abs(g)
        first = np.searchsorted(offs, centre - half + eps, side="right")
        last = np.searchsorted(offs, centre + half - eps, side="left")
        new_cells: list[_Cell] = []
        changed: list[int] = []
        for i in np.flatnonzero(last > first).tolist():
            cell = cells[i]
            s = cell.verts @ g
            k0 = int(np.searchsorted(offs, s.min() + eps, side="right"))
            k1 = int(np.searchsorted(offs, s.max() - eps, side="left"))
            parts: list[_Cell] = []
            for k in range(k0, k1):
                res = _split_cell(cell, g, offs[k], pids[k], eps)
                if res is not None:
                    parts.append(res[0])
                    cell = res[1]
            if parts:
                parts.append(cell)
                cells[i] = parts[0]
                changed.append(i)
                new_cells.extend(parts[1:])
        if changed:
            lo[changed] = [cells[i].verts.min(axis=0) for i in changed]
            hi[changed] = [cells[i].verts.max(axis=0) for i in changed]
        if new_cells:
            cells.extend(new_cells)
            lo = np.vstack([lo, [c.verts.min(axis=0) for c in new_cells]])
            hi = np.vstack([hi, [c.verts.max(axis=0) for c in new_cells]])
    return cells


# --------------------------------------------------------------------------- vertices


def _merge_points(pts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Cluster points `(p, 3)` closer than `radius`: `(p,) int` cluster ids, `(q, 3)` coords."""
    uniq, inv = np.unique(pts, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    pairs = cKDTree(uniq).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return inv, uniq
    graph = coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(uniq), len(uniq))
    )
    _, comp = connected_components(graph, directed=False)
    _, first, comp_ids = np.unique(comp, return_index=True, return_inverse=True)
    return comp_ids.reshape(-1)[inv], uniq[first]


def _dedupe_cycle(ids: list[int]) -> list[int] | None:
    """A polygon without consecutive repeats, or None if fewer than 3 distinct vertices."""
    out = [x for k, x in enumerate(ids) if x != ids[k - 1]]
    if len(out) < 3 or len(set(out)) != len(out):
        return None
    return out


# --------------------------------------------------------------------------- facets


@dataclass
class _Facets:
    """All cell facets over merged vertices `coords (q, 3)`.

    `cell, label, orient (f,)`: owning cell, plane id, +1/-1 facet normal along/against
    the plane normal; `ids`: vertex-id polygons; `other (f,)`: the matching facet of the
    neighbour cell or -1; `normal, area, centroid`: Newell geometry.
    """

    coords: np.ndarray
    cell: np.ndarray
    label: np.ndarray
    orient: np.ndarray
    ids: list[list[int]]
    other: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    centroid: np.ndarray
    cell_volume: np.ndarray
    cell_broken: np.ndarray  # (c,) bool: a facet degenerated when vertices merged
    multi: int  # facets shared by more than two cells (should be 0)
    plane_normal: np.ndarray  # (P, 3) normals of the plane ids
    plane_offset: np.ndarray  # (P,) offsets of the plane ids


def _build_facets(cells: list[_Cell], planes: _Planes, merge_r: float) -> _Facets:
    """Merge cell vertices globally, match identical facets of neighbour cells."""
    counts = np.array([len(c.verts) for c in cells])
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    gmap, coords = _merge_points(np.vstack([c.verts for c in cells]), merge_r)
    gl = gmap.tolist()
    fcell: list[int] = []
    flabel: list[int] = []
    fids: list[list[int]] = []
    broken = np.zeros(len(cells), dtype=bool)
    for ci, c in enumerate(cells):
        s = int(start[ci])
        for f, lab in zip(c.faces, c.labels, strict=True):
            poly = _dedupe_cycle([gl[s + i] for i in f])
            if poly is None:
                broken[ci] = True
                continue
            fcell.append(ci)
            flabel.append(lab)
            fids.append(poly)
    cell_arr = np.asarray(fcell, dtype=np.int64)
    label_arr = np.asarray(flabel, dtype=np.int64)
    indptr, indices = faces_to_csr(fids)
    normal, area = face_normals_areas(coords, indptr, indices)
    centroid = face_centroids(coords, indptr, indices)
    pn = np.asarray(planes.normal)[label_arr] if len(label_arr) else np.zeros((0, 3))
    orient = np.where(np.einsum("ij,ij->i", normal, pn) >= 0, 1, -1)
    # volumes: signed tetrahedra against each cell's first vertex
    tris, face_of = fan_triangles(indptr, indices)
    ref = np.array([c.verts[0] for c in cells])[cell_arr[face_of]]
    a, b, cc = (coords[tris[:, k]] - ref for k in range(3))
    v6 = np.einsum("ij,ij->i", a, np.cross(b, cc))
    volume = np.bincount(cell_arr[face_of], weights=v6, minlength=len(cells)) / 6.0
    # match facets by their vertex sets
    other = np.full(len(fids), -1, dtype=np.int64)
    seen: dict[tuple[int, ...], int] = {}
    multi = 0
    for k, poly in enumerate(fids):
        key = tuple(sorted(poly))
        j = seen.get(key)
        if j is None:
            seen[key] = k
        elif other[j] < 0 and cell_arr[j] != cell_arr[k]:
            other[j], other[k] = k, j
        else:
            multi += 1
    return _Facets(coords, cell_arr, label_arr, orient, fids, other, normal, area, centroid,
                   volume, broken, multi, np.asarray(planes.normal).reshape(-1, 3),
                   np.asarray(planes.offset, dtype=float))


def _real_joints(fac: _Facets, planes: _Planes, joints: list[_Joint]) -> np.ndarray:
    """`(f,) int`: the joint each matched facet is a real part of, or -1 (fictitious)."""
    owner = np.full(len(fac.label), -1, dtype=np.int64)
    matched = np.flatnonzero(fac.other >= 0)
    matched = matched[np.argsort(fac.label[matched], kind="stable")]
    pids, starts = np.unique(fac.label[matched], return_index=True)
    groups = np.split(matched, starts[1:]) if len(matched) else []
    for pid, sel in zip(pids.tolist(), groups, strict=True):
        for j in planes.members[pid]:
            todo = owner[sel] < 0
            inside = todo & joints[j].contains(fac.centroid[sel])
            owner[sel[inside]] = j
    return owner


# --------------------------------------------------------------------------- blocks


def _merge_coplanar(
    facets: list[int], fac: _Facets, tag_of: dict[int, int]
) -> tuple[list[list[int]], list[int], dict[int, int]]:
    """Merge adjacent surface facets on the same plane, side and tag into single faces.

    Returns faces (vertex-id loops), their tags, and facet -> face index. A group whose
    outline is not one simple loop (a hole, a pinch) keeps its facets as they are.
    """
    groups: dict[tuple[int, int, int], list[int]] = {}
    for f in facets:
        groups.setdefault((int(fac.label[f]), int(fac.orient[f]), tag_of[f]), []).append(f)
    faces: list[list[int]] = []
    tags: list[int] = []
    face_of: dict[int, int] = {}

    def emit(poly: list[int], tag: int, members: list[int]) -> None:
        for m in members:
            face_of[m] = len(faces)
        faces.append(poly)
        tags.append(tag)

    for (_, _, tag), fs in groups.items():
        if len(fs) == 1:
            emit(fac.ids[fs[0]], tag, fs)
            continue
        edge_owner: dict[tuple[int, int], int] = {}
        for f in fs:
            p = fac.ids[f]
            for i in range(len(p)):
                edge_owner[(p[i - 1], p[i])] = f
        parent = {f: f for f in fs}

        def find(x: int, parent: dict[int, int] = parent) -> int:
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for (a, b), f in edge_owner.items():
            g = edge_owner.get((b, a))
            if g is not None:
                parent[find(f)] = find(g)
        comps: dict[int, list[int]] = {}
        for f in fs:
            comps.setdefault(find(f), []).append(f)
        for members in comps.values():
            if len(members) == 1:
                emit(fac.ids[members[0]], tag, members)
                continue
            mset = set(members)
            nxt: dict[int, int] = {}
            ok = True
            for (a, b), f in edge_owner.items():
                if f in mset and (b, a) not in edge_owner:
                    if a in nxt:
                        ok = False
                    nxt[a] = b
            loop = _chain_loop(nxt) if ok else None
            if loop is None or len(loop) < 3:
                for m in members:
                    emit(fac.ids[m], tag, [m])
            else:
                emit(loop, tag, members)
    return faces, tags, face_of


def _drop_collinear(faces: list[list[int]], face_label: list[int]) -> list[list[int]]:
    """Remove vertices where only two faces on different planes meet (points on an edge)."""
    where: dict[int, list[int]] = {}
    for k, f in enumerate(faces):
        for v in f:
            where.setdefault(v, []).append(k)
    drop = {v for v, ks in where.items()
            if len(ks) == 2 and face_label[ks[0]] != face_label[ks[1]]}
    if not drop:
        return faces
    out = [[v for v in f if v not in drop] for f in faces]
    return faces if any(len(f) < 3 for f in out) else out


def _build_block(
    cells: list[int],
    cell_facets: list[list[int]],
    fac: _Facets,
    group_of: np.ndarray,
    tag_of_pair: np.ndarray,
    eps: float,
) -> Polyhedron:
    """The block made of `cells`: merged surface faces, pieces if concave."""
    gid = group_of[cells[0]]
    surface: list[int] = []
    tag_of: dict[int, int] = {}
    for c in cells:
        for f in cell_facets[c]:
            o = fac.other[f]
            if o >= 0 and group_of[fac.cell[o]] == gid:
                continue
            surface.append(f)
            tag_of[f] = int(tag_of_pair[f]) if o >= 0 else FACE_TAG_BOUNDARY
    if len(cells) == 1:
        faces = [fac.ids[f] for f in surface]
        tags = [tag_of[f] for f in surface]
        face_of = {f: k for k, f in enumerate(surface)}
        labels = [int(fac.label[f]) for f in surface]
    else:
        faces, tags, face_of = _merge_coplanar(surface, fac, tag_of)
        labels = [0] * len(faces)
        for f, k in face_of.items():
            labels[k] = int(fac.label[f])
        faces = _drop_collinear(faces, labels)
    surf_ids = sorted({v for f in faces for v in f})
    local = {v: k for k, v in enumerate(surf_ids)}
    block = Polyhedron.from_faces(
        fac.coords[surf_ids], [[local[v] for v in f] for f in faces], tags
    )
    if len(cells) == 1 or block.is_convex:
        return block
    parts = [_piece_faces(part, cell_facets, fac, face_of)
             for part in _convex_parts(cells, cell_facets, fac, face_of, eps)]
    extra = sorted({v for pfaces, _ in parts for f in pfaces for v in f} - set(surf_ids))
    local.update({v: len(surf_ids) + k for k, v in enumerate(extra)})
    pieces = []
    for pfaces, psurf in parts:
        indptr, indices = faces_to_csr([[local[v] for v in f] for f in pfaces])
        pieces.append(ConvexPiece(indptr, indices, np.asarray(psurf, dtype=np.int64)))
    return Polyhedron(fac.coords[surf_ids + extra], block.face_indptr, block.face_indices,
                      block.face_tags, tuple(pieces))


def _piece_faces(
    part: list[int], cell_facets: list[list[int]], fac: _Facets, face_of: dict[int, int]
) -> tuple[list[list[int]], list[int]]:
    """Faces (vertex-id loops) of a convex part of glued cells and their block faces (-1)."""
    inner = set(part)
    pf = [f for c in part for f in cell_facets[c]
          if fac.other[f] < 0 or int(fac.cell[fac.other[f]]) not in inner]
    pfaces, psurf, pface_of = _merge_coplanar(pf, fac, {f: face_of.get(f, -1) for f in pf})
    plabels = [0] * len(pfaces)
    for f, k in pface_of.items():
        plabels[k] = int(fac.label[f])
    return _drop_collinear(pfaces, plabels), psurf


def _inner(f: int, fac: _Facets, cellset: set[int], find, parts: tuple[int, int]) -> bool:
    """Whether facet `f` lies between two cells of the parts `parts` (of one block)."""
    o = int(fac.other[f])
    if o < 0:
        return False
    c = int(fac.cell[o])
    return c in cellset and find(c) in parts


def _convex_parts(
    cells: list[int], cell_facets: list[list[int]], fac: _Facets, face_of: dict[int, int],
    eps: float,
) -> list[list[int]]:
    """Greedily glue adjacent cells of a block while their union stays convex.

    Two convex parts sharing a facet plane form a convex union when each one's vertices
    satisfy all face half-spaces of the other except the shared plane. A glued part must
    also keep each of its face planes on a single block face (for `face_surface`).
    """
    cellset = set(cells)
    parent = {c: c for c in cells}
    verts = {c: {v for f in cell_facets[c] for v in fac.ids[f]} for c in cells}
    bound = {c: set(cell_facets[c]) for c in cells}

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    def halfspaces(fs: set[int]) -> tuple[np.ndarray, np.ndarray]:
        lab = fac.label[list(fs)]
        ori = fac.orient[list(fs)]
        return fac.plane_normal[lab] * ori[:, None], fac.plane_offset[lab] * ori

    def inside(vs: set[int], fs: set[int], skip: int) -> bool:
        keep = {f for f in fs if fac.label[f] != skip}
        n, off = halfspaces(keep)
        x = fac.coords[list(vs)]
        return bool((x @ n.T - off[None]).max(initial=-1.0) <= eps)

    pairs = sorted(
        ((float(fac.area[f]), f) for c in cells for f in cell_facets[c]
         if fac.other[f] > f and int(fac.cell[fac.other[f]]) in cellset),
        reverse=True,
    )
    for _, f in pairs:
        a, b = find(int(fac.cell[f])), find(int(fac.cell[fac.other[f]]))
        if a == b:
            continue
        skip = int(fac.label[f])
        if not (inside(verts[b], bound[a], skip) and inside(verts[a], bound[b], skip)):
            continue
        union = {g for g in bound[a] | bound[b] if not _inner(g, fac, cellset, find, (a, b))}
        where: dict[tuple[int, int], set[int]] = {}
        for g in union:
            where.setdefault((int(fac.label[g]), int(fac.orient[g])), set()).add(
                face_of.get(g, -1))
        if any(len(v) > 1 for v in where.values()):
            continue
        parent[b] = a
        verts[a] |= verts.pop(b)
        bound[a] = union
        del bound[b]
    parts: dict[int, list[int]] = {}
    for c in cells:
        parts.setdefault(find(c), []).append(c)
    return list(parts.values())


def _joints_of(joints: Sequence[JointPlane], planes: _Planes) -> tuple[list[_Joint], list[int]]:
    """Register joint planes and their extent prism sides; `(joints, planes to cut by)`."""
    out: list[_Joint] = []
    cut: list[int] = []
    for j, jp in enumerate(joints):
        n = unit(jp.normal)
        p0 = np.asarray(jp.point, dtype=float).reshape(3)
        cut.append(planes.add(n, float(n @ p0), member=j))
        u, v = plane_basis(n)
        poly2 = None
        if jp.extent is not None:
            ext = np.asarray(jp.extent, dtype=float).reshape(-1, 3)
            if len(ext) < 3:
                raise ValueError(f"joint {j}: an extent polygon needs at least 3 points")
            rel = ext - p0
            poly2 = np.stack([rel @ u, rel @ v], axis=1)
            flat = p0 + poly2[:, :1] * u + poly2[:, 1:] * v  # extent projected on the plane
            for a, b in zip(flat, np.roll(flat, -1, axis=0), strict=True):
                m = np.cross(b - a, n)
                if np.linalg.norm(m) > planes.eps:
                    m = m / np.linalg.norm(m)
                    cut.append(planes.add(m, float(m @ a)))
        out.append(_Joint(int(jp.tag), p0, (u, v), poly2))
    return out, cut


def _initial_cells(
    domain: Polyhedron, planes: _Planes
) -> tuple[list[_Cell], list[int], bool]:
    """Starting cells, extra planes to cut by, and whether to filter cells by the domain."""
    if domain.is_convex:
        return [_polyhedron_cell(domain, planes)], [], False
    lo, hi = domain.bounds
    box = _box_cell(lo, hi, planes)
    cut = [planes.add(n, off) for n, off in zip(domain.face_normals, domain.face_offsets,
                                                strict=True)]
    return [box], cut, True


def _inside(cells: list[_Cell], domain: Polyhedron) -> list[_Cell]:
    """Cells whose vertex mean lies inside the (concave) domain."""
    if not cells:
        return cells
    pts = np.array([c.verts.mean(axis=0) for c in cells])
    w = winding_numbers(pts, domain.vertices, domain.face_indptr, domain.face_indices)
    return [c for c, x in zip(cells, w, strict=True) if x > 0.5]


def _components(n: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """`(n,) int` connected component of each node of an undirected edge list."""
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _glued(
    fac: _Facets, real: np.ndarray, n_cells: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells joined across fictitious facets (no real joint between them): `(c,) int`
    group per cell, and the cell pairs `(k,)`, `(k,)` that were joined."""
    glue = (fac.other > np.arange(len(fac.other))) & ~real
    rows, cols = fac.cell[glue], fac.cell[fac.other[glue]]
    return _components(n_cells, rows, cols), rows, cols


def _cell_widths(fac: _Facets, n_cells: int) -> np.ndarray:
    """`(c,)` m: each convex cell's smallest extent across its own face planes (its
    width, as :attr:`Polyhedron.width` of a convex block)."""
    width = np.full(n_cells, np.inf)
    cell_of = fac.cell
    order = np.argsort(cell_of, kind="stable")
    bounds = np.searchsorted(cell_of[order], np.arange(n_cells + 1))
    for c in range(n_cells):
        fs = order[bounds[c]:bounds[c + 1]]
        if not len(fs):
            continue
        ids = np.unique(np.concatenate([fac.ids[f] for f in fs.tolist()]))
        h = fac.coords[ids] @ fac.plane_normal[fac.label[fs]].T
        width[c] = float((h.max(axis=0) - h.min(axis=0)).min())
    return width


def _groups(
    fac: _Facets, glued: tuple[np.ndarray, np.ndarray, np.ndarray], sliver: float,
    merge_below: float, min_width: float, warnings: list[str],
) -> tuple[np.ndarray, np.ndarray]:
    """Blocks of the cells `glued` across fictitious facets (:func:`_glued`); blocks
    smaller than `merge_below` (m³) or thinner than `min_width` (m: the widest of their
    cells, so a block glued from cells is as wide as its widest cell) join the neighbour
    block they share the most facet area with, repeated until none is left (a sliver
    merged into another sliver is merged again).

    Returns `(c,) int` group per cell and `(c,) bool` cells dropped (isolated slivers
    below `sliver` m³).
    """
    group, rows, cols = glued
    n_cells = len(group)
    cell_width = _cell_widths(fac, n_cells) if min_width > 0 else np.full(n_cells, np.inf)
    dropped = np.zeros(n_cells, dtype=bool)
    n_small = n_thin = 0
    thinnest = np.inf
    for _ in range(8):
        n_g = int(group.max()) + 1 if n_cells else 0
        gvol = np.bincount(group, weights=fac.cell_volume, minlength=n_g)
        gwidth = np.full(n_g, -np.inf)
        np.maximum.at(gwidth, group, cell_width)
        small = gvol < max(sliver, merge_below)
        thin = ~small & (gwidth < min_width)
        if not (small | thin).any():
            break
        g_own = group[fac.cell]
        cand = np.flatnonzero((small | thin)[g_own] & (fac.other >= 0))
        g_nb = group[fac.cell[fac.other[cand]]]
        keep = g_nb != g_own[cand]
        cand, g_nb = cand[keep], g_nb[keep]
        if not len(cand):
            break
        # shared area per (block, neighbour block): merge across the largest
        pair_keys, inv = np.unique(np.stack([g_own[cand], g_nb], axis=1), axis=0,
                                   return_inverse=True)
        area = np.bincount(inv.reshape(-1), weights=fac.area[cand])
        order = np.lexsort((-area, pair_keys[:, 0]))
        _, first = np.unique(pair_keys[order, 0], return_index=True)
        best = order[first]
        src, dst = pair_keys[best, 0], pair_keys[best, 1]
        n_small += int(small[src].sum())
        n_thin += int(thin[src].sum())
        if thin[src].any():
            thinnest = min(thinnest, float(gwidth[src][thin[src]].min()))
        # one facet pair between each merged block and its neighbour joins them
        rep = np.zeros(n_g, dtype=np.int64)
        rep[group] = np.arange(n_cells)
        rows = np.concatenate([rows, rep[src]])
        cols = np.concatenate([cols, rep[dst]])
        group = _components(n_cells, rows, cols)
    n_g = int(group.max()) + 1 if n_cells else 0
    gvol = np.bincount(group, weights=fac.cell_volume, minlength=n_g)
    has_nb = np.zeros(n_g, dtype=bool)
    m = fac.other >= 0
    has_nb[group[fac.cell[m]][group[fac.cell[m]] != group[fac.cell[fac.other[m]]]]] = True
    dropped = ((gvol < sliver) & ~has_nb)[group]
    if n_small:
        warnings.append(f"{n_small} small block(s) below {max(sliver, merge_below):.3g} m³ "
                        "merged into a neighbour block")
    if n_thin:
        warnings.append(f"{n_thin} thin block(s) (sliver: narrower than {min_width:.3g} m, "
                        f"the thinnest {thinnest:.3g} m) merged into the neighbour they "
                        "share the largest face with")
    if dropped.any():
        warnings.append(f"{len(np.unique(group[dropped]))} isolated sliver block(s) dropped")
    return group, dropped


def _closed_cells(fac: _Facets, cells: np.ndarray, scale: float, tol: Tolerances) -> np.ndarray:
    """`(k,) bool`: which single cells pass the checks of `Polyhedron.problems` in bulk.

    A cell is planar and convex by construction; this checks that it is closed and
    consistently oriented, has no zero-area facet and a positive volume, and is not so
    small that the block-relative planarity tolerance could fail (those get the full check).
    """
    if len(cells) == 0:
        return np.zeros(0, dtype=bool)
    pos = np.full(len(fac.cell_volume), -1, dtype=np.int64)
    pos[cells] = np.arange(len(cells))
    sel = np.flatnonzero(pos[fac.cell] >= 0)
    ok = (fac.cell_volume[cells] > 0) & ~fac.cell_broken[cells]
    small_area = sel[fac.area[sel] <= tol.lengths(scale).point_merge ** 2]
    ok[pos[fac.cell[small_area]]] = False
    indptr, indices = faces_to_csr([fac.ids[f] for f in sel.tolist()])
    counts = np.diff(indptr)
    owner = np.repeat(pos[fac.cell[sel]], counts)
    nxt = np.arange(len(indices)) + 1
    nxt[indptr[1:] - 1] = indptr[:-1]
    a, b = indices, indices[nxt]
    rows = np.stack([owner, np.minimum(a, b), np.maximum(a, b)], axis=1)
    _, inv, cnt = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    fwd = np.bincount(inv, weights=(a < b).astype(float), minlength=len(cnt))
    bad_edge = (cnt != 2) | (fwd != 1)
    ok[owner[bad_edge[inv]]] = False
    span = np.zeros((len(cells), 2, 3))
    pts = fac.coords[indices]
    span[:, 0] = np.inf
    span[:, 1] = -np.inf
    np.minimum.at(span[:, 0], owner, pts)
    np.maximum.at(span[:, 1], owner, pts)
    ok &= (span[:, 1] - span[:, 0]).max(axis=1) > 1e-2 * scale
    return ok


def _idle_joint_warnings(joints: Sequence[JointPlane], separating: set[int]) -> list[str]:
    """One warning per joint tag whose planes (some or all) separate no blocks."""
    planes_of: dict[int, list[int]] = {}
    for j, jp in enumerate(joints):
        planes_of.setdefault(int(jp.tag), []).append(j)
    out = []
    for tag, js in planes_of.items():
        idle = [j for j in js if j not in separating]
        if len(js) == 1 and idle:
            out.append(f"joint {tag} cuts nothing (joint plane {idle[0]})")
        elif len(idle) == len(js):
            out.append(f"joint {tag}: none of its {len(js)} planes cuts anything")
        elif idle:
            out.append(f"joint {tag}: {len(idle)} of its {len(js)} planes cut nothing")
    return out


def _set_spacing(planes: _Planes) -> float | None:
    """Median spacing (m) of parallel joint planes (joint sets), None if there are none."""
    gaps: list[float] = []
    for pids in planes.group_planes:
        offs = np.sort([planes.offset[q] for q in pids if planes.members[q]])
        if len(offs) > 1:
            gaps.extend(np.diff(offs).tolist())
    return float(np.median(gaps)) if gaps else None


#: default smallest block, as a fraction of the median block volume of the cut
MIN_BLOCK_VOLUME_RATIO = 1e-3
#: default thinnest block, as a fraction of the median spacing of the joint sets (of the
#: median block width without sets): thinner blocks are slivers and merge
MIN_BLOCK_WIDTH_RATIO = 0.1


def cut_blocks(
    domain: Polyhedron, joints: Sequence[JointPlane], tol: Tolerances = DEFAULT_TOLERANCES,
    min_block_volume: float | None = None, min_block_width: float | None = None,
) -> CutResult:
    """Cut `domain` into blocks by `joints` (persistent or bounded by an extent polygon).

    Faces carry the tag of the joint they lie on, or FACE_TAG_BOUNDARY on the domain
    surface; concave blocks carry their convex pieces (the arrangement cells). Blocks
    smaller than `min_block_volume` m³ (default MIN_BLOCK_VOLUME_RATIO of the median
    block volume; 0 keeps all but numerical slivers) merge into the neighbour they share
    the largest face with: corner slivers weigh nothing, and their tiny inertia would force
    the time step down to microseconds. Slivers - blocks thinner than `min_block_width` m
    (default MIN_BLOCK_WIDTH_RATIO of the joint sets' median spacing, or of the median
    block width without sets; 0 keeps them), however
    large - merge the same way: a thin block bounds every step's displacement (nothing may
    tunnel through it) and its narrow faces confuse the contact search. A merged block may
    be concave; its convex pieces are cells of the same arrangement, so it touches its
    neighbours exactly as the cells did.
    """
    warnings: list[str] = []
    scale = float(np.ptp(domain.vertices[domain.surface_vertex_ids], axis=0).max())
    planes = _Planes(tol.lengths(scale).on_plane)
    cells, cut, filter_inside = _initial_cells(domain, planes)
    jlist, jcut = _joints_of(joints, planes)
    cells = _arrange(cells, planes, cut + jcut)
    if filter_inside:
        cells = _inside(cells, domain)
    if not cells:
        return CutResult([], ["the domain has no volume to cut"])
    fac = _build_facets(cells, planes, tol.lengths(scale).point_merge)
    if fac.multi:
        warnings.append(f"{fac.multi} facet(s) shared by more than two cells (degenerate cut)")
    owner = _real_joints(fac, planes, jlist)
    real = owner >= 0
    tag_of_pair = np.where(real, np.array([j.tag for j in jlist] + [-1])[owner], -1)
    vol_dom = abs(domain.volume)
    sliver = tol.sliver_volume * vol_dom
    glued = _glued(fac, real, len(cells))
    if min_block_volume is None:
        vols = np.bincount(glued[0], weights=fac.cell_volume)
        min_block_volume = MIN_BLOCK_VOLUME_RATIO * float(np.median(vols[vols > 0]))
    if min_block_width is None:
        typical = _set_spacing(planes)
        if typical is None:
            widths = np.full(int(glued[0].max()) + 1, -np.inf)
            np.maximum.at(widths, glued[0], _cell_widths(fac, len(cells)))
            typical = float(np.median(widths[widths > 0]))
        min_block_width = MIN_BLOCK_WIDTH_RATIO * typical
    group, dropped = _groups(fac, glued, sliver, min_block_volume, min_block_width, warnings)
    cell_facets: list[list[int]] = [[] for _ in cells]
    for f, c in enumerate(fac.cell.tolist()):
        cell_facets[c].append(f)
    members: dict[int, list[int]] = {}
    for c, g in enumerate(group.tolist()):
        if not dropped[c]:
            members.setdefault(g, []).append(c)
    singles = np.array([cs[0] for cs in members.values() if len(cs) == 1], dtype=np.int64)
    trusted = set(singles[_closed_cells(fac, singles, scale, tol)].tolist())
    blocks: list[Polyhedron] = []
    n_small = n_bad = 0
    for cs in members.values():
        if float(fac.cell_volume[cs].sum()) < sliver:
            n_small += 1
            continue
        block = _build_block(cs, cell_facets, fac, group, tag_of_pair, planes.eps)
        if not (len(cs) == 1 and cs[0] in trusted) and block.problems(tol):
            n_bad += 1
            continue
        blocks.append(block)
    if n_small:
        warnings.append(f"{n_small} sliver block(s) dropped")
    if n_bad:
        warnings.append(f"{n_bad} block(s) dropped because the cut produced invalid geometry")
    apart = real & ~dropped[fac.cell] & (group[fac.cell] != group[fac.cell[fac.other]])
    warnings.extend(_idle_joint_warnings(joints, set(owner[apart].tolist())))
    return CutResult(blocks, warnings)


# --------------------------------------------------------------------------- decomposition


def convex_decomposition(block: Polyhedron, tol: Tolerances = DEFAULT_TOLERANCES) -> Polyhedron:
    """The same block surface with `.pieces` set to a convex decomposition.

    Pieces are the cells of the arrangement of the block's own face planes; a convex
    block comes back with no pieces (it is its own single piece).
    """
    base = Polyhedron(block.vertices, block.face_indptr, block.face_indices, block.face_tags)
    if block.is_convex:
        return base
    scale = float(np.ptp(block.vertices[block.surface_vertex_ids], axis=0).max())
    planes = _Planes(tol.lengths(scale).on_plane)
    cells, cut, _ = _initial_cells(block, planes)
    cells = _inside(_arrange(cells, planes, cut), block)
    return _attach_pieces(base, cells, tol, scale)


def _attach_pieces(
    block: Polyhedron, cells: list[_Cell], tol: Tolerances, scale: float
) -> Polyhedron:
    """`block` with `cells` as pieces indexing its vertices (new points appended at the end)."""
    lengths = tol.lengths(scale)
    r, planarity = lengths.point_merge, lengths.planarity
    surf = block.surface_vertex_ids
    pts = np.vstack([c.verts for c in cells])
    dist, near = cKDTree(block.vertices[surf]).query(pts, distance_upper_bound=10 * r)
    hit = np.isfinite(dist)
    ids = np.empty(len(pts), dtype=np.int64)
    ids[hit] = surf[near[hit]]
    extra = np.zeros((0, 3))
    if (~hit).any():
        gm, extra = _merge_points(pts[~hit], r)
        ids[~hit] = len(block.vertices) + gm
    verts = np.vstack([block.vertices, extra])
    fn, fo = block.face_normals, block.face_offsets
    u_v = [plane_basis(n) for n in fn]
    pieces = []
    s = 0
    for c in cells:
        faces = [[int(ids[s + i]) for i in f] for f in c.faces]
        s += len(c.verts)
        indptr, indices = faces_to_csr(faces)
        nrm, _ = face_normals_areas(verts, indptr, indices)
        cen = face_centroids(verts, indptr, indices)
        surf_of = np.full(len(faces), -1, dtype=np.int64)
        for k in range(len(faces)):
            cand = np.flatnonzero((fn @ nrm[k] > 1 - 1e-9)
                                  & (np.abs(fo - fn @ cen[k]) < planarity))
            for f in cand.tolist():
                poly = verts[block.faces[f]]
                u, v = u_v[f]
                q = np.stack([poly @ u, poly @ v], axis=1)
                if _points_in_polygon(np.array([[cen[k] @ u, cen[k] @ v]]), q)[0]:
                    surf_of[k] = f
                    break
        pieces.append(ConvexPiece(indptr, indices, surf_of))
    return Polyhedron(verts, block.face_indptr, block.face_indices, block.face_tags,
                      tuple(pieces))
