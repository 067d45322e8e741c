"""Blocks from glued cells: surface faces merged across coplanar facets, convex pieces of a
concave block, a bulk check of single-cell blocks, and pieces attached to a given block."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from engine.geometry.cutting.cells import Cell, chain_loop
from engine.geometry.cutting.facets import Facets, merge_points
from engine.geometry.cutting.planes import points_in_polygon
from engine.geometry.joints import plane_basis
from engine.geometry.polyhedron import (
    FACE_TAG_BOUNDARY,
    ConvexPiece,
    Polyhedron,
    face_centroids,
    face_normals_areas,
    faces_to_csr,
)
from engine.tolerances import Tolerances


def _merge_coplanar(
    facets: list[int], fac: Facets, tag_of: dict[int, int]
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
            loop = chain_loop(nxt) if ok else None
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


def build_block(
    cells: list[int],
    cell_facets: list[list[int]],
    fac: Facets,
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
    part: list[int], cell_facets: list[list[int]], fac: Facets, face_of: dict[int, int]
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


def _inner(f: int, fac: Facets, cellset: set[int], find, parts: tuple[int, int]) -> bool:
    """Whether facet `f` lies between two cells of the parts `parts` (of one block)."""
    o = int(fac.other[f])
    if o < 0:
        return False
    c = int(fac.cell[o])
    return c in cellset and find(c) in parts


def _convex_parts(
    cells: list[int], cell_facets: list[list[int]], fac: Facets, face_of: dict[int, int],
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


def closed_cells(fac: Facets, cells: np.ndarray, scale: float, tol: Tolerances) -> np.ndarray:
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


def attach_pieces(
    block: Polyhedron, cells: list[Cell], tol: Tolerances, scale: float
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
        gm, extra = merge_points(pts[~hit], r)
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
                if points_in_polygon(np.array([[cen[k] @ u, cen[k] @ v]]), q)[0]:
                    surf_of[k] = f
                    break
        pieces.append(ConvexPiece(indptr, indices, surf_of))
    return Polyhedron(verts, block.face_indptr, block.face_indices, block.face_tags,
                      tuple(pieces))
