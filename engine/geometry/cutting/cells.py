"""The cells of a cut: convex cells split plane by plane from a starting box or convex
domain (the arrangement of all planes), so neighbour cells share identical facets."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.geometry.cutting.planes import Planes
from engine.geometry.joints import plane_basis
from engine.geometry.polyhedron import Polyhedron, winding_numbers


@dataclass(slots=True)
class Cell:
    """A convex cell: vertices `(n, 3)`, faces (CCW from outside), plane id per face."""

    verts: np.ndarray
    faces: list[list[int]]
    labels: list[int]


def chain_loop(nxt: dict[int, int]) -> list[int] | None:
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
    cell: Cell, normal: np.ndarray, offset: float, label: int, eps: float
) -> tuple[Cell, Cell] | None:
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
    cap = chain_loop(nxt) if ok else None
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


def _compact(allv: np.ndarray, faces: list[list[int]], labels: list[int]) -> Cell:
    """A cell keeping only the vertices its faces use."""
    used = sorted({i for f in faces for i in f})
    remap = dict(zip(used, range(len(used)), strict=True))
    return Cell(allv[used], [[remap[i] for i in f] for f in faces], labels)


def _box_cell(lo: np.ndarray, hi: np.ndarray, planes: Planes) -> Cell:
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
    return Cell(verts, faces, labels)


def _polyhedron_cell(poly: Polyhedron, planes: Planes) -> Cell:
    """A convex polyhedron as one cell, its face planes registered."""
    used = poly.surface_vertex_ids
    remap = {int(i): k for k, i in enumerate(used)}
    faces = [[remap[int(i)] for i in f] for f in poly.faces]
    labels = [
        planes.add(n, off) for n, off in zip(poly.face_normals, poly.face_offsets, strict=True)
    ]
    return Cell(poly.vertices[used].copy(), faces, labels)


def arrange(cells: list[Cell], planes: Planes, cut_ids: Sequence[int]) -> list[Cell]:
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
        new_cells: list[Cell] = []
        changed: list[int] = []
        for i in np.flatnonzero(last > first).tolist():
            cell = cells[i]
            s = cell.verts @ g
            k0 = int(np.searchsorted(offs, s.min() + eps, side="right"))
            k1 = int(np.searchsorted(offs, s.max() - eps, side="left"))
            parts: list[Cell] = []
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


def initial_cells(
    domain: Polyhedron, planes: Planes, tiles: Sequence[Polyhedron] | None = None
) -> tuple[list[Cell], list[int], bool]:
    """Starting cells, extra planes to cut by, and whether to filter cells by the domain.

    `tiles`: convex solids that tile a concave domain face to face (a terrain's columns, a
    block's convex pieces): they are the starting cells, so no face plane of the domain
    cuts across it (a terrain of many facets would otherwise be cut by every facet's plane).
    """
    if tiles:
        return [_polyhedron_cell(t, planes) for t in tiles], [], False
    if domain.is_convex:
        return [_polyhedron_cell(domain, planes)], [], False
    lo, hi = domain.bounds
    box = _box_cell(lo, hi, planes)
    cut = [planes.add(n, off) for n, off in zip(domain.face_normals, domain.face_offsets,
                                                strict=True)]
    return [box], cut, True


def inside(cells: list[Cell], domain: Polyhedron) -> list[Cell]:
    """Cells whose vertex mean lies inside the (concave) domain."""
    if not cells:
        return cells
    pts = np.array([c.verts.mean(axis=0) for c in cells])
    w = winding_numbers(pts, domain.vertices, domain.face_indptr, domain.face_indices)
    return [c for c, x in zip(cells, w, strict=True) if x > 0.5]
