"""The facets of a cut: cell vertices merged globally, facets of neighbour cells matched,
and which matched facets are real joint faces (the rest are fictitious and glue cells)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from engine.geometry.cutting.cells import Cell
from engine.geometry.cutting.planes import Joint, Planes
from engine.geometry.polyhedron import (
    face_centroids,
    face_normals_areas,
    faces_to_csr,
    fan_triangles,
)


def merge_points(pts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
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


@dataclass
class Facets:
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


def build_facets(cells: list[Cell], planes: Planes, merge_r: float) -> Facets:
    """Merge cell vertices globally, match identical facets of neighbour cells."""
    counts = np.array([len(c.verts) for c in cells])
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    gmap, coords = merge_points(np.vstack([c.verts for c in cells]), merge_r)
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
    return Facets(coords, cell_arr, label_arr, orient, fids, other, normal, area, centroid,
                   volume, broken, multi, np.asarray(planes.normal).reshape(-1, 3),
                   np.asarray(planes.offset, dtype=float))


def real_joints(fac: Facets, planes: Planes, joints: list[Joint]) -> np.ndarray:
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
