"""Joint planes: the `JointPlane` the cutting takes, and the makers of the joints a scene
describes (the members of a joint set across a domain, a disc joint's extent polygon)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.geometry.polyhedron import Polyhedron


@dataclass(frozen=True)
class JointPlane:
    """One joint plane for block cutting.

    `normal (3,)` unit normal, `point (3,)` a point on the plane, `tag` the joint id
    the faces it makes will carry, `extent (k, 3)` a convex polygon in the plane that
    bounds a non-persistent joint (None: persistent, cuts everything it crosses).
    """

    normal: np.ndarray
    point: np.ndarray
    tag: int = 0
    extent: np.ndarray | None = None


def unit(v: np.ndarray | Sequence[float]) -> np.ndarray:
    """Unit vector `(3,)` along `v`; raises on a zero vector."""
    a = np.asarray(v, dtype=float).reshape(3)
    n = float(np.linalg.norm(a))
    if not n > 0:
        raise ValueError("a plane normal must be a non-zero vector")
    return a / n


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors `u, v (3,)` spanning the plane, with `u x v = normal`."""
    n = unit(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def disc_polygon(
    center: np.ndarray | Sequence[float],
    normal: np.ndarray | Sequence[float],
    radius: float,
    sides: int = 24,
) -> np.ndarray:
    """`(sides, 3)` polygon, counter-clockwise about `normal`, circumscribing a disc.

    The disc of `radius` is inscribed (the polygon's edges touch the circle), so the
    polygon covers the whole disc: a joint is never made smaller than asked.
    """
    if sides < 3 or radius <= 0:
        raise ValueError("a disc polygon needs at least 3 sides and a positive radius")
    u, v = plane_basis(np.asarray(normal, float))
    r = radius / np.cos(np.pi / sides)
    t = 2.0 * np.pi * np.arange(sides) / sides
    return np.asarray(center, float)[None] + r * (
        np.cos(t)[:, None] * u[None] + np.sin(t)[:, None] * v[None]
    )


def joint_set_planes(
    normal: np.ndarray | Sequence[float],
    point: np.ndarray | Sequence[float],
    spacing: float,
    domain: Polyhedron,
    tag: int,
    extent: np.ndarray | None = None,
) -> list[JointPlane]:
    """Members of a parallel joint set that cross the domain's bounding box.

    Member k passes through `point + k * spacing * normal`; its extent `(m, 3)` (or
    None: persistent) is `extent` moved by the same offset.
    """
    if not spacing > 0:
        raise ValueError("joint spacing must be positive")
    n = unit(normal)
    p0 = np.asarray(point, dtype=float).reshape(3)
    lo, hi = domain.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    s = (corners - p0) @ n
    margin = 1e-9 * max(float(np.ptp(corners, axis=0).max()), 1e-12)
    k0 = int(np.ceil((s.min() + margin) / spacing))
    k1 = int(np.floor((s.max() - margin) / spacing))
    ext = None if extent is None else np.asarray(extent, dtype=float)
    out = []
    for k in range(k0, k1 + 1):
        shift = k * spacing * n
        out.append(JointPlane(normal=n.copy(), point=p0 + shift, tag=tag,
                              extent=None if ext is None else ext + shift))
    return out
