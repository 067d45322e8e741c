"""The planes of a cut: the registry of distinct planes (parallel planes share one normal)
and the joints as the cutter sees them (tag and extent polygon in plane coordinates)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.geometry.joints import JointPlane, plane_basis, unit

_SAME_NORMAL = 1e-12  #: unit normals closer than this are treated as exactly parallel


def points_in_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """`(p,) bool`: which 2-D points `(p, 2)` lie inside the polygon `(m, 2)` (even-odd)."""
    x, y = pts[:, 0][:, None], pts[:, 1][:, None]
    x0, y0 = poly[:, 0][None], poly[:, 1][None]
    x1, y1 = np.roll(poly[:, 0], -1)[None], np.roll(poly[:, 1], -1)[None]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (np.count_nonzero(crosses & (x < xi), axis=1) % 2) == 1


@dataclass
class Joint:
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
        return points_in_polygon(q, self.polygon)


class Planes:
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


def joints_of(joints: Sequence[JointPlane], planes: Planes) -> tuple[list[Joint], list[int]]:
    """Register joint planes and their extent prism sides; `(joints, planes to cut by)`."""
    out: list[Joint] = []
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
        out.append(Joint(int(jp.tag), p0, (u, v), poly2))
    return out, cut


def set_spacing(planes: Planes) -> float | None:
    """Median spacing (m) of parallel joint planes (joint sets), None if there are none."""
    gaps: list[float] = []
    for pids in planes.group_planes:
        offs = np.sort([planes.offset[q] for q in pids if planes.members[q]])
        if len(offs) > 1:
            gaps.extend(np.diff(offs).tolist())
    return float(np.median(gaps)) if gaps else None
