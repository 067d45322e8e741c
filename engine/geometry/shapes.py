"""Small builders of common block shapes (boxes, oriented boxes, prisms) as Polyhedra."""

from __future__ import annotations

import numpy as np

from engine.geometry.polyhedron import Polyhedron

#: faces of a hexahedron whose vertices are bottom 0-3 then top 4-7, counter-clockwise
#: seen from above; every face counter-clockwise seen from outside
HEXAHEDRON_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6],
                    [3, 0, 4, 7]]


def hexahedron(vertices: np.ndarray) -> Polyhedron:
    """A hexahedron from 8 vertices `(8, 3)`: bottom quad then top quad, both CCW from above."""
    return Polyhedron.from_faces(np.asarray(vertices, float), HEXAHEDRON_FACES)


def box(lo: np.ndarray | list[float], hi: np.ndarray | list[float]) -> Polyhedron:
    """Axis-aligned box between corners `lo (3,)` and `hi (3,)` (m)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return hexahedron(np.array([
        (x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
        (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1),
    ], float))


def oriented_box(origin: np.ndarray, axes: np.ndarray, size: np.ndarray) -> Polyhedron:
    """Box with one corner at `origin (3,)`, edges along the rows of `axes (3, 3)`
    (right-handed, unit) with lengths `size (3,)` (m)."""
    o = np.asarray(origin, float)
    a = np.asarray(axes, float) * np.asarray(size, float)[:, None]
    corners = [o, o + a[0], o + a[0] + a[1], o + a[1]]
    return hexahedron(np.array(corners + [c + a[2] for c in corners]))


def prism(base: np.ndarray, height: float) -> Polyhedron:
    """Vertical prism over a simple polygon `base (k, 2)` (CCW from above, any convexity)
    from z = 0 to z = `height` (m)."""
    b = np.asarray(base, float)
    k = len(b)
    verts = np.vstack([np.column_stack([b, np.zeros(k)]), np.column_stack([b, np.full(k, height)])])
    faces = [list(range(k - 1, -1, -1)), list(range(k, 2 * k))]
    faces += [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
    return Polyhedron.from_faces(verts, faces)


def convex_hull(points: np.ndarray, decimals: int = 9) -> Polyhedron:
    """The convex hull of `points (k, 3)` as a Polyhedron with one polygon per hull facet.

    Coplanar hull triangles are merged into one face (vertices ordered counter-clockwise
    seen from outside), so a box comes back with 6 quads, not 12 triangles.
    """
    from scipy.spatial import ConvexHull

    p = np.asarray(points, float)
    hull = ConvexHull(p)
    used = np.unique(hull.simplices)
    remap = np.full(len(p), -1)
    remap[used] = np.arange(len(used))
    verts = p[used]
    eq = np.round(hull.equations, decimals)
    _, group = np.unique(eq, axis=0, return_inverse=True)
    faces = []
    for g in np.unique(group):
        tri = hull.simplices[group.ravel() == g]
        ids = np.unique(tri)
        normal = hull.equations[np.flatnonzero(group.ravel() == g)[0], :3]
        centre = p[ids].mean(axis=0)
        u = p[ids[0]] - centre
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        ang = np.arctan2((p[ids] - centre) @ v, (p[ids] - centre) @ u)
        faces.append(remap[ids[np.argsort(ang)]].tolist())
    return Polyhedron.from_faces(verts, faces)
