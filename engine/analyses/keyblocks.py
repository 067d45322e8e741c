"""Key blocks around an opening (Goodman & Shi's block theory, the table Unwedge gives): for
each block exposed on an excavation's surface, whether it is removable, how it would move
under its weight (falling, sliding on one plane, sliding on two) and the limit-equilibrium
factor of safety of that mode.

This is the key-block LE this analysis needs until the shared limit-equilibrium module
(issue 30, `engine.analyses.limit_equilibrium`) lands: :func:`mode_and_factor` is the one
place to switch to it. Dry, no bolts, no seismic load: weight only, Mohr-Coulomb joints.

A block's contact planes are its distinct face planes that are not on the excavation's
surface; `n` is a plane's outward normal (from the block into its neighbour). A motion
`d` separates from a plane when `n · d <= 0`.

- removable: some direction separates from every contact plane (a linear program);
- falling: the weight's direction `r` itself does (FS 0);
- sliding on plane i: `r · n_i > 0` and the in-plane part of `r` separates from the others;
  FS = (W (r·n_i) tan φ_i + c_i A_i) / (W |r − (r·n_i) n_i|);
- sliding on planes i and j: along their intersection `I` (`I · r > 0`), separating from
  the others, both pressed (N_i, N_j > 0 from `W (r − (r·I) I) = N_i n_i + N_j n_j`);
  FS = (N_i tan φ_i + N_j tan φ_j + c_i A_i + c_j A_j) / (W r·I).
The mode with the lowest FS is the block's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linprog

from engine.geometry.polyhedron import Polyhedron

_TOL = 1e-9


@dataclass(frozen=True)
class Plane:
    """A contact plane of a block: outward unit normal, area (m²), tag, strength."""

    normal: np.ndarray
    area: float
    tag: int
    tan_phi: float
    cohesion: float


@dataclass
class KeyBlock:
    """One exposed block: `removable`, `mode` ("falling", "sliding on one plane",
    "sliding on two planes" or "stable": no mode under its weight), the `planes` (tags) it
    slides on, the factor of safety (inf: stable; 0: falls), its weight (N)."""

    block: int
    removable: bool
    mode: str
    planes: list[int] = field(default_factory=list)
    factor_of_safety: float = float("inf")
    weight: float = 0.0


def contact_planes(poly: Polyhedron, free_tags: set[int], strength: dict[int, tuple[float,
                   float]], default: tuple[float, float]) -> list[Plane]:
    """The block's distinct face planes off the excavation's surface (faces on one plane
    merged, their areas added), with (tan φ, c) by face tag."""
    out: list[Plane] = []
    for n, area, tag in zip(poly.face_normals, poly.face_areas, poly.face_tags, strict=True):
        if int(tag) in free_tags:
            continue
        for k, pl in enumerate(out):
            if pl.normal @ n > 1 - 1e-9:
                out[k] = Plane(pl.normal, pl.area + float(area), pl.tag, pl.tan_phi,
                               pl.cohesion)
                break
        else:
            tan_phi, c = strength.get(int(tag), default)
            out.append(Plane(np.asarray(n, float), float(area), int(tag), tan_phi, c))
    return out


def removable(planes: list[Plane]) -> bool:
    """Whether some direction separates the block from every contact plane (Shi's theorem
    for a convex block: the joint pyramid is not empty)."""
    if not planes:
        return True
    a = np.array([p.normal for p in planes])
    best = -np.inf
    for sign in np.eye(3).tolist() + (-np.eye(3)).tolist():  # maximise along each axis
        res = linprog(-np.asarray(sign), A_ub=a, b_ub=np.zeros(len(a)),
                      bounds=[(-1, 1)] * 3, method="highs")
        if res.status == 0:
            best = max(best, -float(res.fun))
    return best > 1e-9


def _separates(d: np.ndarray, planes: list[Plane], skip: tuple[int, ...]) -> bool:
    return all(p.normal @ d <= _TOL for k, p in enumerate(planes) if k not in skip)


def mode_and_factor(planes: list[Plane], weight: float, r: np.ndarray
                    ) -> tuple[str, list[int], float]:
    """The block's mode under its weight `weight` N along the unit direction `r`, the tags
    of the planes it slides on, and its factor of safety."""
    if _separates(r, planes, ()):
        return "falling", [], 0.0
    best: tuple[str, list[int], float] = ("stable", [], float("inf"))
    for i, p in enumerate(planes):
        rn = float(r @ p.normal)
        s = r - rn * p.normal
        if rn > _TOL and np.linalg.norm(s) > _TOL and _separates(s, planes, (i,)):
            fs = (weight * rn * p.tan_phi + p.cohesion * p.area) / (
                weight * float(np.linalg.norm(s)))
            if fs < best[2]:
                best = ("sliding on one plane", [p.tag], fs)
    for i, p in enumerate(planes):
        for j in range(i + 1, len(planes)):
            q = planes[j]
            line = np.cross(p.normal, q.normal)
            if np.linalg.norm(line) < 1e-9:
                continue
            line /= np.linalg.norm(line)
            line *= np.sign(line @ r) or 1.0
            if line @ r <= _TOL or not _separates(line, planes, (i, j)):
                continue
            perp = weight * (r - (r @ line) * line)
            m = np.column_stack([p.normal, q.normal])
            (ni, nj), *_ = np.linalg.lstsq(m, perp, rcond=None)
            if ni <= 0 or nj <= 0:
                continue
            fs = (ni * p.tan_phi + nj * q.tan_phi + p.cohesion * p.area
                  + q.cohesion * q.area) / (weight * float(line @ r))
            if fs < best[2]:
                best = ("sliding on two planes", [p.tag, q.tag], fs)
    return best


def key_blocks(polys: list[Polyhedron], density: np.ndarray, gravity: np.ndarray,
               exposed: set[int], strength: dict[int, tuple[float, float]],
               default: tuple[float, float], skip: set[int] = frozenset(),
               free: set[int] = frozenset()) -> list[KeyBlock]:
    """The key-block table of every block with a face tagged in `exposed` (an excavation's
    surface), except the blocks in `skip` (the excavated ones). Faces tagged in `exposed`
    or `free` (the domain's outer surface, other openings already dug) touch nothing."""
    free_tags = set(exposed) | set(free)
    g = np.asarray(gravity, float)
    r = g / np.linalg.norm(g)
    out = []
    for b, poly in enumerate(polys):
        if b in skip or not np.isin(poly.face_tags, list(exposed)).any():
            continue
        planes = contact_planes(poly, free_tags, strength, default)
        weight = float(density[b] * poly.volume * np.linalg.norm(g))
        if not removable(planes):
            out.append(KeyBlock(b, False, "stable", weight=weight))
            continue
        mode, tags, fs = mode_and_factor(planes, weight, r)
        out.append(KeyBlock(b, True, mode, tags, fs, weight))
    return out
