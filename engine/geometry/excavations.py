"""Excavations cut out of a rock mass: tunnels (circular, horseshoe, D-shaped sections along
an axis), box caverns, and prisms of a vertical section (open-pit benches).

An :class:`Excavation` is a union of convex solids. :func:`excavate` cuts blocks along the
solids' surfaces (the solids' faces act as bounded joints carrying the excavation's face
tag) and says which of the pieces lie inside: those are the rock the excavation removes.
Faces on the blocks' old surfaces keep their tags (joint ids), so joint materials still
apply; faces on the excavation's surface carry `tag`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.geometry.cutting.cut import cut_blocks
from engine.geometry.cutting.planes import points_in_polygon
from engine.geometry.domains import extrude_section, horizontal
from engine.geometry.joints import JointPlane, plane_basis
from engine.geometry.polyhedron import FACE_TAG_BOUNDARY, Polyhedron
from engine.geometry.shapes import convex_hull

#: face tags of excavation surfaces: EXCAVATION_TAG_BASE + the excavation's index (joint ids
#: are small non-negative numbers, so the two never meet)
EXCAVATION_TAG_BASE = 1_000_000
TUNNEL_SHAPES = ("circular", "horseshoe", "d_shaped")


@dataclass(frozen=True)
class Excavation:
    """A named union of convex solids (m) to be dug out of the rock mass."""

    name: str
    solids: tuple[Polyhedron, ...]

    @property
    def bounds(self) -> np.ndarray:
        """`(2, 3)` bounding box of all solids."""
        lo = np.min([s.bounds[0] for s in self.solids], axis=0)
        hi = np.max([s.bounds[1] for s in self.solids], axis=0)
        return np.array([lo, hi])

    @property
    def volume(self) -> float:
        """Sum of the solids' volumes (m³; overlaps of a bent axis count twice)."""
        return float(sum(s.volume for s in self.solids))

    def contains(self, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """`(p,) bool`: which points `(p, 3)` lie inside a solid (deeper than `tol` m)."""
        pts = np.atleast_2d(np.asarray(points, float))
        out = np.zeros(len(pts), bool)
        for s in self.solids:
            dist = pts @ s.face_normals.T - s.face_offsets[None]
            out |= np.all(dist < -tol, axis=1)
        return out


# --------------------------------------------------------------------------- sections


def _arc(cx: float, cz: float, r: float, a0: float, a1: float, n: int) -> np.ndarray:
    """`n` points on the circle (cx, cz, r) from angle a0 to a1 (radians), ends included."""
    t = np.linspace(a0, a1, n)
    return np.column_stack([cx + r * np.cos(t), cz + r * np.sin(t)])


def tunnel_section(shape: str, width: float, height: float | None = None,
                   sides: int = 24) -> np.ndarray:
    """A tunnel's cross-section `(k, 2)`, counter-clockwise, as `(u, w)`: `u` across the
    axis (m), `w` up (m), the floor's middle (the invert) at the origin.

    - `circular`: a circle of diameter `width`, `sides` vertices on it;
    - `d_shaped`: vertical walls `height - width / 2` high under a semicircular crown of
      diameter `width`, flat floor;
    - `horseshoe`: the classic horseshoe: a semicircular crown of radius r = width / 2
      springing at w = r, over walls that are arcs of radius 2 r centred at the opposite
      springline, down to a flat invert at w = 0 (half-width r (√3 − 1)); convex.
    """
    r = 0.5 * width
    n = max(sides // 2, 3)
    if shape == "circular":
        t = 2 * np.pi * np.arange(sides) / sides - 0.5 * np.pi
        return np.column_stack([r * np.cos(t), r + r * np.sin(t)])
    if shape == "d_shaped":
        h = height if height is not None else width
        wall = h - r
        if wall < 0:
            raise ValueError("a D-shaped tunnel's height must be at least half its width")
        crown = _arc(0.0, wall, r, 0.0, np.pi, n + 1)
        return np.vstack([[[-r, 0.0], [r, 0.0]], crown if wall > 0 else crown[1:-1]])
    if shape == "horseshoe":
        # springline at w = r; wall arcs: radius 2r, centres (-r, r) and (r, r); the floor
        # where they reach w = 0: u = -r + sqrt(4r² - r²) = r (√3 - 1)
        spring = r
        crown = _arc(0.0, spring, r, 0.0, np.pi, n + 1)
        a_floor = -np.arcsin(spring / (2 * r))
        right = _arc(-r, spring, 2 * r, a_floor, 0.0, max(n // 3, 2) + 1)
        left = _arc(r, spring, 2 * r, np.pi, np.pi - a_floor, max(n // 3, 2) + 1)
        return np.vstack([right, crown[1:-1], left])
    raise ValueError(f"unknown tunnel shape '{shape}' (known: {', '.join(TUNNEL_SHAPES)})")


def axis_points(start: Sequence[float], trend_deg: float, plunge_deg: float,
                length: float) -> np.ndarray:
    """The two ends `(2, 3)` of a straight axis from `start` along trend / plunge (degrees;
    plunge positive downwards) over `length` m."""
    t, p = np.radians(trend_deg), np.radians(plunge_deg)
    d = np.array([np.sin(t) * np.cos(p), np.cos(t) * np.cos(p), -np.sin(p)])
    s = np.asarray(start, float)
    return np.array([s, s + length * d])


def _frame(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Section axes `u` (horizontal, to the right looking along `d`) and `w` (up-ish) of an
    axis direction `d`; a vertical shaft takes u = x."""
    u = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(u) < 1e-9:
        u = np.array([1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    return u, np.cross(u, d)


def tunnel(name: str, section: np.ndarray, axis: np.ndarray) -> Excavation:
    """A tunnel of cross-section `section (k, 2)` ((u, w) about the invert, convex) along the
    polyline `axis (m, 3)` (m): one convex prism per straight segment (at a bend the prisms
    overlap; their union is the excavation)."""
    pts = np.asarray(axis, float)
    sec = np.asarray(section, float)
    solids = []
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        d = b - a
        length = float(np.linalg.norm(d))
        if not length > 0:
            raise ValueError("the tunnel axis repeats a point")
        u, w = _frame(d / length)
        ring = a[None] + sec[:, :1] * u[None] + sec[:, 1:] * w[None]
        solids.append(convex_hull(np.vstack([ring, ring + d[None]])))
    return Excavation(name, tuple(solids))


def cavern(name: str, center: Sequence[float], size: Sequence[float],
           trend_deg: float = 0.0) -> Excavation:
    """A box cavern: `size` = (length along the trend, width, height) m about its centre;
    horizontal floor and roof."""
    c = np.asarray(center, float)
    along = horizontal(trend_deg)
    across = np.cross(along, [0.0, 0.0, 1.0])
    half = 0.5 * np.asarray(size, float)
    corners = [c + sa * half[0] * along + sb * half[1] * across + sc * half[2] * np.array(
        [0.0, 0.0, 1.0]) for sa in (-1, 1) for sb in (-1, 1) for sc in (-1, 1)]
    return Excavation(name, (convex_hull(np.array(corners)),))


def _triangles(poly: np.ndarray) -> list[np.ndarray]:
    """Ear-clipping triangulation of a simple polygon `(k, 2)` (either orientation)."""
    p = np.asarray(poly, float)
    area = 0.5 * np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
    idx = list(range(len(p))) if area > 0 else list(range(len(p)))[::-1]
    out = []

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    guard = 0
    while len(idx) > 3 and guard < 10 * len(p) ** 2:
        guard += 1
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            if cross(p[i0], p[i1], p[i2]) <= 0:
                continue
            tri = p[[i0, i1, i2]]
            others = [j for j in idx if j not in (i0, i1, i2)]
            if others and np.any(points_in_polygon(p[others], tri)):
                continue
            out.append(tri)
            idx.pop(k)
            break
        else:
            raise ValueError("the section polygon is not simple (it crosses itself)")
    out.append(p[idx])
    scale = float(np.ptp(p, axis=0).max())
    if not scale > 0 or any(abs(cross(t[0], t[1], t[2])) <= 1e-12 * scale**2 for t in out):
        raise ValueError("the section polygon has no area (repeated or collinear corners)")
    return out


def section_prism(name: str, section: np.ndarray, origin: Sequence[float],
                  dip_direction_deg: float, width: float) -> Excavation:
    """The prism of a vertical section polygon `section (k, 2)` of `(s, z)` (the slope
    profile's coordinates: s horizontal against `dip_direction`, z elevation), extruded
    along the strike over `width` m from `origin` (x, y): an open-pit bench or cut."""
    across = -horizontal(dip_direction_deg)
    along = np.cross([0.0, 0.0, 1.0], across)
    o = np.asarray(origin, float)
    o = np.array([o[0], o[1], 0.0])
    return Excavation(name, tuple(extrude_section(t, o, across, along, width)
                                  for t in _triangles(section)))


# --------------------------------------------------------------------------- cutting


def _tiles(block: Polyhedron) -> list[Polyhedron]:
    """A block's convex pieces as polyhedra (the block itself when convex)."""
    if block.is_convex and not block.pieces:
        return [block]
    return [Polyhedron(block.vertices, p.face_indptr, p.face_indices,
                       np.full(len(p.face_indptr) - 1, FACE_TAG_BOUNDARY, dtype=np.int64))
            for p in block.convex_pieces()]


def _face_planes(solid: Polyhedron, tag: int) -> list[JointPlane]:
    """The faces of a convex solid as joints bounded by the faces themselves."""
    return [JointPlane(normal=n, point=solid.vertices[f[0]], tag=tag,
                       extent=solid.vertices[f])
            for n, f in zip(solid.face_normals, solid.faces, strict=True)]


def _retag(piece: Polyhedron, parent: Polyhedron, eps: float) -> Polyhedron:
    """`piece` with each face on the parent's surface given the parent face's tag."""
    tags = piece.face_tags.copy()
    cen = np.array([piece.vertices[f].mean(axis=0) for f in piece.faces])
    for k in np.flatnonzero(tags == FACE_TAG_BOUNDARY):
        n, off = piece.face_normals[k], piece.face_offsets[k]
        same = np.flatnonzero((parent.face_normals @ n > 1 - 1e-9)
                              & (np.abs(parent.face_offsets - off) <= eps))
        for f in same:
            u, v = plane_basis(parent.face_normals[f])
            ring = parent.vertices[parent.faces[f]]
            q = np.column_stack([ring @ u, ring @ v])
            if len(same) == 1 or points_in_polygon(np.array([[cen[k] @ u, cen[k] @ v]]), q)[0]:
                tags[k] = parent.face_tags[f]
                break
    return Polyhedron(piece.vertices, piece.face_indptr, piece.face_indices, tags,
                      piece.pieces)


def _inner_point(block: Polyhedron) -> np.ndarray:
    """A point strictly inside the block: the centroid of its largest convex piece."""
    if block.is_convex:
        return block.centroid
    best, point = -1.0, block.centroid
    for t in _tiles(block):
        if t.volume > best:
            best, point = t.volume, t.centroid
    return point


def _overlaps(block: Polyhedron, solid: Polyhedron, eps: float) -> bool:
    """Whether the bounding boxes of a block and a solid overlap by more than `eps`."""
    (a0, a1), (b0, b1) = block.bounds, solid.bounds
    return bool(np.all((a0 < b1 - eps) & (b0 < a1 - eps)))


def _near(joints: Sequence[JointPlane], part: Polyhedron, eps: float) -> list[JointPlane]:
    """The bounded joints whose extent's bounding box reaches the part's."""
    lo, hi = part.bounds
    return [j for j in joints if j.extent is not None
            and np.all((j.extent.min(axis=0) < hi + eps) & (lo - eps < j.extent.max(axis=0)))]


def excavate(blocks: Sequence[Polyhedron], exc: Excavation, tag: int,
             min_block_volume: float = 0.0, min_block_width: float = 0.0,
             joints: Sequence[JointPlane] = (),
             ) -> tuple[list[Polyhedron], np.ndarray, np.ndarray]:
    """Cut `blocks` along the surface of `exc`: `(new blocks, inside (k,) bool, parent (k,)
    int)`, each new block a part of `blocks[parent]`, inside the excavation when its inner
    point (the centroid of its largest convex piece) is. Blocks the excavation does not
    reach come back unchanged (the same objects); numerical slivers of a cut (below 1e-9
    of the block's volume) are dropped.

    With the thresholds 0 every part lies wholly inside or outside, and the parts inside
    fill the excavation exactly. Parts smaller than `min_block_volume` m³ or thinner than
    `min_block_width` m merge into the neighbouring part of the same block they share the
    largest face with (as :func:`cut_blocks` merges slivers): a sliver of rock left on
    the excavation's surface falls with the excavation (overbreak) or a sliver of the
    excavation stays with the rock, instead of a 2 mm block that would force the time
    step down to microseconds.

    `joints`: the bounded joints the blocks were cut by. Inside a block they are slits
    that separate nothing, until the excavation's surface closes a region they bound (a
    wedge in a tunnel's roof): the cut takes them again, with their own tags."""
    out: list[Polyhedron] = []
    parent: list[int] = []
    for b, block in enumerate(blocks):
        scale = float(np.ptp(block.bounds, axis=0).max())
        eps = 1e-9 * scale
        parts = [block]
        for solid in exc.solids:
            if not _overlaps(block, solid, eps):
                continue
            planes = _face_planes(solid, tag)
            nxt = []
            for part in parts:
                if not _overlaps(part, solid, eps):
                    nxt.append(part)
                    continue
                cut = cut_blocks(part, planes + _near(joints, part, eps),
                                 min_block_volume=min_block_volume,
                                 min_block_width=min_block_width, tiles=_tiles(part)).blocks
                nxt.extend(_retag(q, part, 1e-9 * scale) for q in cut) if len(cut) > 1 \
                    else nxt.append(part)
            parts = nxt
        out.extend(parts)
        parent.extend([b] * len(parts))
    inside = np.array([bool(exc.contains(_inner_point(q)[None])[0]) for q in out], bool)
    return out, inside, np.array(parent, dtype=np.int64)
