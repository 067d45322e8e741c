"""Water pressure in the joints (issue 16): pressure normal to the wetted contact faces.

A face of one block wets where it lies against a face of another (opposite outward normals,
the same plane within a tolerance): the wetted polygon is their overlap. The pressure on it
is hydrostatic below a phreatic surface (a plane), `γw (h(x, y) − z)` with `h` the
surface's elevation above the point, plus a uniform pressure per joint material. It acts on
both faces, `−p n dA` on each block (n its outward normal), and follows the blocks: the
wetted polygons are found again at every step from the blocks' current faces. The loads
enter a step as point loads at quadrature points (three edge midpoints per triangle, exact
for the resultant and moment of a linear pressure); their work counts as the work of loads.
Faces are assumed convex (the overlap is clipped by the other face's edges).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from engine.geometry.polyhedron import Polyhedron

#: faces wet each other when their outward normals are opposite within this cosine ...
ANTIPARALLEL_COS = 0.9995
#: ... and their planes are closer than this fraction of the model size (a joint that opens
#: keeps its water up to that aperture: the thrust in a tension crack acts while it opens)
PLANE_GAP_RATIO = 0.02


@dataclass(frozen=True)
class Water:
    """Water in the joints: `unit_weight` (N/m³); a phreatic surface (a plane through
    `surface_point (3,)` m with upward unit normal `surface_normal (3,)`, None: none) below
    which the pressure is hydrostatic; a uniform pressure (Pa) per joint material index.
    See :mod:`engine.loads.water`."""

    unit_weight: float = 9810.0
    surface_point: np.ndarray | None = None
    surface_normal: np.ndarray | None = None
    joint_pressure: dict[int, float] = field(default_factory=dict)


@dataclass
class WaterLoads:
    """Water forces of one state: per quadrature point its `block (m,)`, `point (m, 3)` m
    and `force (m, 3)` N; and each block's resultant `(n, 3)` N."""

    block: np.ndarray
    point: np.ndarray
    force: np.ndarray
    resultant: np.ndarray


def _clip(poly: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The part `(k', 3)` of the convex polygon `poly (k, 3)` where the linear function with
    values `s (k,)` at its vertices is >= 0 (Sutherland-Hodgman, one half-space)."""
    out = []
    k = len(poly)
    for a in range(k):
        b = (a + 1) % k
        pa, pb, sa, sb = poly[a], poly[b], s[a], s[b]
        if sa >= 0:
            out.append(pa)
        if (sa >= 0) != (sb >= 0):
            out.append(pa + (sa / (sa - sb)) * (pb - pa))
    return np.array(out).reshape(-1, 3)


def overlap(face_i: np.ndarray, normal_i: np.ndarray, face_j: np.ndarray) -> np.ndarray:
    """The overlap `(k, 3)` of face `face_i` (counter-clockwise about its outward normal
    `normal_i`) and the face `face_j` of a block on its other side (counter-clockwise
    about the opposite normal), in the plane of face i."""
    origin = face_i[0]
    q = face_j - np.outer((face_j - origin) @ normal_i, normal_i)  # onto plane i
    q = q[::-1]  # counter-clockwise about normal_i
    poly = face_i
    for a in range(len(q)):
        if len(poly) < 3:
            break
        edge = q[(a + 1) % len(q)] - q[a]
        inward = np.cross(normal_i, edge)
        poly = _clip(poly, (poly - q[a]) @ inward)
    return poly if len(poly) >= 3 else np.zeros((0, 3))


def quadrature(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points `(q, 3)` and weights (m², `(q,)`) on a convex polygon: the edge midpoints of
    its fan triangles, a third of the triangle's area each (exact for quadratics)."""
    pts, wts = [], []
    for t in range(1, len(poly) - 1):
        a, b, c = poly[0], poly[t], poly[t + 1]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a))
        pts += [0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)]
        wts += [area / 3.0] * 3
    return np.array(pts).reshape(-1, 3), np.array(wts)


def _depth(water: Water, points: np.ndarray) -> np.ndarray:
    """Vertical depth (m) of points `(k, 3)` below the phreatic surface (negative above)."""
    n = water.surface_normal
    return -((points - water.surface_point) @ n) / n[2]


def _face_pressure(water: Water, poly: np.ndarray, uniform: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature points `(q, 3)` and pressure × weight `(q,)` (N) on a wetted polygon."""
    pts, out = [], []
    if water.surface_normal is not None:
        wet = _clip(poly, _depth(water, poly))
        if len(wet) >= 3:
            x, w = quadrature(wet)
            pts.append(x)
            out.append(water.unit_weight * _depth(water, x) * w)
    if uniform:
        x, w = quadrature(poly)
        pts.append(x)
        out.append(uniform * w)
    if not pts:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(pts), np.concatenate(out)


def _joint_material(pair: tuple[int, int], tags: tuple[int, int],
                    water_pairs: dict[tuple[int, int], int], of_tag: dict[int, int],
                    default: int) -> int:
    """Joint material of two faces in contact (as the contacts choose it)."""
    if pair in water_pairs:
        return water_pairs[pair]
    for t in tags:
        if t >= 0:
            return of_tag.get(t, default)
    return default


def water_loads(water: Water, polys: list[Polyhedron], fixed: np.ndarray, scale: float,
                pair_material: dict[tuple[int, int], int], material_of_tag: dict[int, int],
                default_material: int) -> WaterLoads:
    """The water forces on blocks `polys` (their current geometry; `fixed (n,)`)."""
    n = len(polys)
    gap = PLANE_GAP_RATIO * scale
    lo = np.array([p.bounds[0] for p in polys]) - gap
    hi = np.array([p.bounds[1] for p in polys]) + gap
    blocks, points, forces = [], [], []
    for i in range(n):
        near = np.flatnonzero(np.all((lo[i + 1:] <= hi[i]) & (hi[i + 1:] >= lo[i]), axis=1))
        for j in (near + i + 1).tolist():
            if fixed[i] and fixed[j]:
                continue
            pi, pj = polys[i], polys[j]
            ni, nj = pi.face_normals, pj.face_normals
            cos = ni @ nj.T
            for fi, fj in zip(*np.nonzero(cos < -ANTIPARALLEL_COS), strict=True):
                face_j = pj.vertices[pj.faces[fj]]
                if np.abs((face_j - pi.vertices[pi.faces[fi][0]]) @ ni[fi]).max() > gap:
                    continue
                poly = overlap(pi.vertices[pi.faces[fi]], ni[fi], face_j)
                if len(poly) < 3:
                    continue
                jm = _joint_material(
                    (i, j), (int(pi.face_tags[fi]), int(pj.face_tags[fj])), pair_material,
                    material_of_tag, default_material)
                x, pw = _face_pressure(water, poly, water.joint_pressure.get(jm, 0.0))
                if not len(x):
                    continue
                f = -pw[:, None] * ni[fi][None]  # on block i; block j gets the opposite
                for b, sign in ((i, 1.0), (j, -1.0)):
                    if not fixed[b]:
                        blocks.append(np.full(len(x), b))
                        points.append(x)
                        forces.append(sign * f)
    if not blocks:
        return WaterLoads(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                          np.zeros((n, 3)))
    b, x, f = np.concatenate(blocks), np.concatenate(points), np.concatenate(forces)
    resultant = np.zeros((n, 3))
    np.add.at(resultant, b, f)
    return WaterLoads(b, x, f, resultant)
