"""Rock-mass domains as engineers describe them: a slope's section profile extruded along its
strike, and a terrain (a regular grid of ground elevations) closed down to a base.

Plain arrays in, :class:`Polyhedron` out. A terrain is concave and has many facets, so it
also returns its convex columns (one vertical prism under each triangle of the grid); the
cutter starts from those (`cut_blocks(..., tiles=columns)`) instead of cutting the bounding
box by every facet's plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.geometry.polyhedron import Polyhedron


def horizontal(azimuth_deg: float) -> np.ndarray:
    """Unit horizontal vector `(3,)` pointing to the azimuth (degrees clockwise from North,
    x = East, y = North)."""
    a = np.radians(azimuth_deg)
    return np.array([np.sin(a), np.cos(a), 0.0])


def _oriented(poly: Polyhedron) -> Polyhedron:
    """`poly` with its faces reversed if they run clockwise seen from outside."""
    if poly.volume > 0:
        return poly
    faces = [f[::-1].tolist() for f in poly.faces]
    return Polyhedron.from_faces(poly.vertices, faces, poly.face_tags)


def extrude_section(section: np.ndarray, origin: np.ndarray, across: np.ndarray,
                    along: np.ndarray, length: float) -> Polyhedron:
    """The prism of a simple polygon `section (k, 2)` given as `(s, z)`: the point
    `origin + s across + z ẑ + t along` for `t` in `[0, length]` (m). Any convexity; faces
    counter-clockwise seen from outside whatever the polygon's orientation."""
    sec = np.asarray(section, float)
    k = len(sec)
    o, a, e = (np.asarray(x, float) for x in (origin, across, along))
    ring = o[None] + sec[:, :1] * a[None] + sec[:, 1:] * np.array([0.0, 0.0, 1.0])[None]
    verts = np.vstack([ring, ring + length * e[None]])
    faces = [list(range(k - 1, -1, -1)), list(range(k, 2 * k))]
    faces += [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
    return _oriented(Polyhedron.from_faces(verts, faces))


def profile_problems(profile: np.ndarray, base: float) -> list[str]:
    """What is wrong with a slope profile `(k, 2)` of `(s, z)` points from the toe to the
    crest (s horizontal into the slope, z elevation) over a base at elevation `base`."""
    p = np.asarray(profile, float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        return ["needs at least 2 points [s, z]"]
    if not np.all(np.isfinite(p)):
        return ["the points must be finite numbers"]
    out = []
    ds = np.diff(p[:, 0])
    if np.any(ds < 0):
        k = int(np.flatnonzero(ds < 0)[0])
        out.append(f"s must not decrease from the toe to the crest (point {k + 1} is behind "
                   f"point {k}): a profile has no overhang")
    if not p[-1, 0] > p[0, 0]:
        out.append("the profile has no horizontal extent (the crest's s equals the toe's)")
    if np.any((np.abs(ds) == 0) & (np.diff(p[:, 1]) == 0)):
        out.append("the profile repeats a point")
    if not np.all(p[:, 1] > base):
        out.append(f"every point must lie above the base elevation {base:g} m")
    return out


def slope_polyhedron(profile: np.ndarray, width: float, dip_direction_deg: float,
                     origin: np.ndarray, base: float) -> Polyhedron:
    """A slope of section `profile (k, 2)`: `(s, z)` points from the toe to the crest, `s`
    (m) horizontal into the slope (against the face's dip direction), `z` the elevation
    (m), closed by vertical ends down to the `base` elevation and extruded along the strike
    over `width` m. The strike runs to the right of a person facing the slope (dip
    direction + 90°... seen from the valley: `along = ẑ × across`), from `origin (2 or 3,)`
    (x, y of the profile's s = 0; its z is ignored)."""
    p = np.asarray(profile, float)
    section = np.vstack([p, [[p[-1, 0], base], [p[0, 0], base]]])
    keep = np.ones(len(section), bool)  # a vertical end on a profile point is one corner
    keep[1:] = np.any(np.abs(np.diff(section, axis=0)) > 0, axis=1)
    if np.all(section[0] == section[-1]):
        keep[-1] = False
    section = section[keep]
    across = -horizontal(dip_direction_deg)
    along = np.cross([0.0, 0.0, 1.0], across)
    o = np.asarray(origin, float)
    o = np.array([o[0], o[1], 0.0])
    return extrude_section(section, o, across, along, width)


@dataclass(frozen=True)
class Terrain:
    """A terrain closed down to a base: the closed surface `domain` and the convex
    `columns` that tile it (two triangular prisms under each grid cell)."""

    domain: Polyhedron
    columns: tuple[Polyhedron, ...]


def grid_problems(x: np.ndarray, y: np.ndarray, z: np.ndarray, base: float) -> list[str]:
    """What is wrong with a terrain grid: node coordinates `x (nx,)`, `y (ny,)` and
    elevations `z (ny, nx)` over a base at elevation `base`."""
    x, y, z = (np.asarray(a, float) for a in (x, y, z))
    if len(x) < 2 or len(y) < 2:
        return ["the grid needs at least 2 x 2 nodes"]
    if z.shape != (len(y), len(x)):
        return [f"elevations have shape {z.shape}, expected ({len(y)}, {len(x)})"]
    out = []
    if not (np.all(np.diff(x) > 0) and np.all(np.diff(y) > 0)):
        out.append("grid coordinates must increase")
    holes = ~np.isfinite(z)
    if holes.any():
        j, i = np.argwhere(holes)[0]
        out.append(f"the grid has {int(holes.sum())} node(s) without an elevation (a hole; "
                   f"first at x = {x[i]:g}, y = {y[j]:g})")
    elif not np.all(z > base):
        j, i = np.argwhere(z <= base)[0]
        out.append(f"every elevation must lie above the base {base:g} m (x = {x[i]:g}, "
                   f"y = {y[j]:g}: {z[j, i]:g})")
    return out


def _column(top: np.ndarray, base: float) -> Polyhedron:
    """The vertical prism under the triangle `top (3, 3)` (counter-clockwise from above)
    down to the `base` elevation."""
    bottom = top.copy()
    bottom[:, 2] = base
    verts = np.vstack([bottom, top])
    faces = [[2, 1, 0], [3, 4, 5], [0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]]
    return Polyhedron.from_faces(verts, faces)


def terrain(x: np.ndarray, y: np.ndarray, z: np.ndarray, base: float) -> Terrain:
    """The rock mass under a terrain grid (nodes `x (nx,)`, `y (ny,)`, elevations
    `z (ny, nx)`, linear on the two triangles of each cell split along its diagonal from
    (x_i, y_j) to (x_i+1, y_j+1)), closed by vertical sides and a flat base at `base`."""
    x, y, z = (np.asarray(a, float) for a in (x, y, z))
    nx, ny = len(x), len(y)
    xx, yy = np.meshgrid(x, y)
    top = np.column_stack([xx.ravel(), yy.ravel(), z.ravel()])

    def node(i: int, j: int) -> int:
        return j * nx + i

    tris = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a, b, c, d = node(i, j), node(i + 1, j), node(i + 1, j + 1), node(i, j + 1)
            tris += [[a, b, c], [a, c, d]]
    ring = ([node(i, 0) for i in range(nx)] + [node(nx - 1, j) for j in range(1, ny)]
            + [node(i, ny - 1) for i in range(nx - 2, -1, -1)]
            + [node(0, j) for j in range(ny - 2, 0, -1)])  # counter-clockwise from above
    m = len(top)
    under = {v: m + k for k, v in enumerate(ring)}
    bottom = top[ring].copy()
    bottom[:, 2] = base
    verts = np.vstack([top, bottom])
    faces = [list(t) for t in tris]
    faces += [[ring[k], under[ring[k]], under[ring[(k + 1) % len(ring)]],
               ring[(k + 1) % len(ring)]] for k in range(len(ring))]
    faces.append([under[v] for v in ring[::-1]])
    columns = tuple(_column(top[t], base) for t in tris)
    return Terrain(Polyhedron.from_faces(verts, faces), columns)


def crop_grid(x: np.ndarray, y: np.ndarray, z: np.ndarray, footprint: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nodes of a grid inside the rectangle `footprint (4,)` = x0, y0, x1, y1 (the
    footprint snaps inward to the grid lines)."""
    x0, y0, x1, y1 = (float(v) for v in footprint)
    ix = (x >= x0 - 1e-9 * abs(x0)) & (x <= x1 + 1e-9 * abs(x1))
    iy = (y >= y0 - 1e-9 * abs(y0)) & (y <= y1 + 1e-9 * abs(y1))
    return x[ix], y[iy], z[np.ix_(iy, ix)]
