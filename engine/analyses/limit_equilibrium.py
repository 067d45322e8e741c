"""Limit equilibrium of a rigid block on one or more planes: the vector method of Hoek & Bray
(Rock Slope Engineering, the comprehensive wedge solution) in Low's (1997) form, for a
planar block (with a tension crack) and a two-plane wedge.

The resultant R of every force on the block (weight, pseudo-static seismic load, water on
the planes and in a tension crack, point loads, bolts and tendons; :mod:`le_model`) is
balanced by normal reactions on the planes it slides on. Each kinematic mode is tried: lifting
off every plane (FS 0), sliding on one plane a along R's component in it (`N_a = −R·n_a`),
and sliding on two planes a, b along their line of intersection i (`N_a n_a + N_b n_b =
−(R − (R·i) i)`). A mode is admissible when its normal reactions press (N > 0) and its
motion leaves every other plane (`u·n ≥ 0`); the factor of safety is that of the admissible
mode (the smallest if more than one):

    FS = (Σ N tan φ + Σ c A + P_r) / D

with D the driving force along the motion of every force but passive bolts, and P_r the
passive bolts' resistance (Hoek & Bray's and Wyllie & Mah's convention: an active tendon
lowers the driving force, a passive bolt adds its force along the motion to the resistance).
`strength_reduction_factor` is the number strength reduction finds instead: the factor F
that, dividing tan φ and c of the weakened joints only, balances every force (passive bolts
in D); the two are equal without passive bolts. Tensile strength is not counted, and the
block is assumed not to rotate: a resultant that passes outside the base of a one-plane
slide raises NotApplicable (the block topples).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.analyses.le_model import BlockLoads, ContactPlane, NotApplicable, block_loads
from engine.geometry.polyhedron import normal_to_dip
from engine.model import Model

__all__ = ["LimitEquilibriumResult", "Mode", "NotApplicable", "limit_equilibrium",
           "solve_modes"]

#: relative tolerance of the mode tests (pressing, leaving a plane, driving)
EPS = 1e-9
MODE_NAMES = {0: "lifting off", 1: "sliding on one plane", 2: "sliding on two planes"}


@dataclass
class Mode:
    """One kinematic mode: the planes it slides on (indices), unit motion `u (3,)` (None
    when lifting off), the normal reactions N (N, effective: water is a load), whether it
    is admissible, and its numbers."""

    planes: tuple[int, ...]
    u: np.ndarray | None
    normal_forces: tuple[float, ...]
    admissible: bool
    driving: float = 0.0
    resisting: float = 0.0
    factor_of_safety: float = math.nan
    strength_reduction_factor: float = math.nan
    why: str = ""


def _resistance(planes: list[ContactPlane], idx: tuple[int, ...], n: tuple[float, ...],
                weakened_only: bool | None) -> float:
    """Σ N tan φ + c A over the sliding planes (only the weakened, or unweakened, ones
    when `weakened_only` is True / False)."""
    out = 0.0
    for k, nk in zip(idx, n, strict=True):
        pl = planes[k]
        if weakened_only is None or pl.weakened == weakened_only:
            out += nk * pl.tan_phi + pl.cohesion * pl.area
    return out


def _score(mode: Mode, planes: list[ContactPlane], total: np.ndarray,
           passive: np.ndarray) -> Mode:
    """Fill the mode's driving and resisting forces, FS and strength-reduction factor."""
    u = mode.u
    drive_all = float(total @ u)
    drive = drive_all - float(passive @ u)  # active forces only (Hoek & Bray)
    res = _resistance(planes, mode.planes, mode.normal_forces, None) - float(passive @ u)
    mode.driving, mode.resisting = drive, res
    scale = max(float(np.linalg.norm(total)), 1e-300)
    mode.factor_of_safety = res / drive if drive > EPS * scale else math.inf
    weak = _resistance(planes, mode.planes, mode.normal_forces, True)
    firm = _resistance(planes, mode.planes, mode.normal_forces, False)
    rest = drive_all - firm
    mode.strength_reduction_factor = (weak / rest if rest > EPS * scale else math.inf)
    return mode


def _leaves(u: np.ndarray, planes: list[ContactPlane], skip: tuple[int, ...]) -> bool:
    """Whether motion along `u` leaves (or slides along) every plane not in `skip`."""
    return all(float(u @ pl.normal) >= -1e-7 for k, pl in enumerate(planes)
               if k not in skip)


def _one_plane(a: int, planes: list[ContactPlane], total: np.ndarray) -> Mode:
    scale = max(float(np.linalg.norm(total)), 1e-300)
    n = planes[a].normal
    na = -float(total @ n)
    s = total + na * n
    if na <= EPS * scale:
        return Mode((a,), None, (na,), False, why="the forces do not press the block on it")
    if np.linalg.norm(s) <= EPS * scale:
        return Mode((a,), n * 0.0, (na,), True, why="no force along the plane")
    u = s / np.linalg.norm(s)
    ok = _leaves(u, planes, (a,))
    return Mode((a,), u, (na,), ok, why="" if ok else "the motion would push into another "
                                                       "plane")


def _two_planes(a: int, b: int, planes: list[ContactPlane], total: np.ndarray) -> Mode:
    scale = max(float(np.linalg.norm(total)), 1e-300)
    na, nb = planes[a].normal, planes[b].normal
    line = np.cross(na, nb)
    if np.linalg.norm(line) < 1e-9:
        return Mode((a, b), None, (0.0, 0.0), False, why="the planes are parallel")
    u = line / np.linalg.norm(line)
    if float(total @ u) < 0:
        u = -u
    across = total - float(total @ u) * u
    m = np.column_stack([na, nb])
    coef = np.linalg.solve(m.T @ m, m.T @ (-across))
    nf = (float(coef[0]), float(coef[1]))
    if min(nf) <= EPS * scale:
        return Mode((a, b), u, nf, False, why="a normal reaction would pull")
    if float(total @ u) <= EPS * scale:
        return Mode((a, b), u * 0.0, nf, True, why="no force along the intersection")
    ok = _leaves(u, planes, (a, b))
    return Mode((a, b), u, nf, ok, why="" if ok else "the motion would push into another "
                                                     "plane")


def solve_modes(planes: list[ContactPlane], total: np.ndarray,
                passive: np.ndarray) -> tuple[Mode, list[Mode]]:
    """The governing mode and every mode tried, for the resultant `total (3,)` N of all
    forces (of which `passive (3,)` N are passive bolts)."""
    scale = max(float(np.linalg.norm(total)), 1e-300)
    lift = Mode((), None, (), all(float(total @ pl.normal) >= -EPS * scale for pl in planes),
                factor_of_safety=0.0, strength_reduction_factor=0.0,
                why="the forces pull the block off every plane")
    tried = [lift]
    tried += [_one_plane(a, planes, total) for a in range(len(planes))]
    tried += [_two_planes(a, b, planes, total)
              for a, b in itertools.combinations(range(len(planes)), 2)]
    for m in tried:
        if m.admissible and m.u is not None:
            if np.linalg.norm(m.u) == 0:
                m.factor_of_safety = m.strength_reduction_factor = math.inf
                m.driving = 0.0
            else:
                _score(m, planes, total, passive)
    ok = [m for m in tried if m.admissible]
    if not ok:
        raise NotApplicable("no mode is admissible: the block cannot lift off or slide on "
                            "one or two of its planes without pushing into another")
    return min(ok, key=lambda m: m.factor_of_safety), tried


def _check_not_toppling(loads: BlockLoads, mode: Mode, total: np.ndarray) -> None:
    """NotApplicable when the resultant of a one-plane slide passes outside its contact
    area: the reaction cannot sit there, the block rotates (topples) instead."""
    if len(mode.planes) != 1:
        return
    pl = loads.planes[mode.planes[0]]
    c = loads.centroid
    moment = sum((np.cross(f.point - c, f.vector) for f in loads.forces), np.zeros(3))
    rr = float(total @ total)
    p0 = c + np.cross(total, moment) / rr  # the resultant's line: p0 + t total
    denom = float(total @ pl.normal)
    if abs(denom) < 1e-12 * math.sqrt(rr):
        return
    hit = p0 + (float((pl.point - p0) @ pl.normal) / denom) * total
    e1 = np.cross(pl.normal, [1.0, 0, 0] if abs(pl.normal[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(pl.normal, e1)
    pts = np.column_stack([(pl.outline - pl.point) @ e1, (pl.outline - pl.point) @ e2])
    q = np.array([(hit - pl.point) @ e1, (hit - pl.point) @ e2])
    if not _inside_hull(pts, q, 1e-6 * math.sqrt(pl.area)):
        raise NotApplicable("the resultant of the forces passes outside the block's base: "
                            "it would topple before it slides (limit equilibrium of "
                            "sliding does not apply)")


def _inside_hull(pts: np.ndarray, q: np.ndarray, tol: float) -> bool:
    """Whether the 2-D point `q` lies in the convex hull of `pts (k, 2)` (within `tol`)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(pts)
    except QhullError:
        return True
    return bool(np.all(hull.equations[:, :2] @ q + hull.equations[:, 2] <= tol))


@dataclass
class LimitEquilibriumResult:
    """The factor of safety (Hoek & Bray's convention; inf: nothing drives the block), the
    strength-reduction factor (what `polydda fos` finds), the governing mode, and
    everything behind them (loads, planes, modes tried, notes)."""

    factor_of_safety: float
    strength_reduction_factor: float
    mode: Mode
    loads: BlockLoads
    modes: list[Mode]
    notes: list[str] = field(default_factory=list)

    @property
    def mode_name(self) -> str:
        if self.mode.u is not None and np.linalg.norm(self.mode.u) == 0:
            return "no force drives it"
        return MODE_NAMES[len(self.mode.planes)]

    def as_dict(self, plane_names: list[str] | None = None,
                block_names: list[str] | None = None) -> dict[str, Any]:
        """The result as plain JSON values (`plane_names`, `block_names` label them)."""
        return _as_dict(self, plane_names, block_names)


def _plane_dict(pl: ContactPlane, name: str, n: float | None,
                block_names: list[str] | None) -> dict[str, Any]:
    dip, ddir = normal_to_dip(pl.normal)
    return {"name": name, "dip": dip, "dip_direction": ddir, "normal": pl.normal.tolist(),
            "area": pl.area, "against": block_names[pl.block] if block_names else pl.block,
            "friction_angle": math.degrees(math.atan(pl.tan_phi)), "cohesion": pl.cohesion,
            "weakened": pl.weakened, "water_force": pl.water,
            "normal_force": n, "sliding": n is not None}


def _as_dict(r: LimitEquilibriumResult, plane_names: list[str] | None,
             block_names: list[str] | None) -> dict[str, Any]:
    names = plane_names or [f"plane {k + 1}" for k in range(len(r.loads.planes))]
    normal = dict(zip(r.mode.planes, r.mode.normal_forces, strict=True))
    u = r.mode.u
    direction = None
    if u is not None and np.linalg.norm(u) > 0:
        trend = math.degrees(math.atan2(u[0], u[1])) % 360.0
        direction = {"vector": u.tolist(), "trend": trend,
                     "plunge": math.degrees(math.asin(max(-1.0, min(1.0, -u[2]))))}
    return {
        "factor_of_safety": r.factor_of_safety,
        "strength_reduction_factor": r.strength_reduction_factor,
        "mode": r.mode_name,
        "sliding_planes": [names[k] for k in r.mode.planes],
        "direction": direction,
        "driving_force": r.mode.driving, "resisting_force": r.mode.resisting,
        "block": block_names[r.loads.block] if block_names else r.loads.block,
        "mass": r.loads.mass,
        "planes": [_plane_dict(pl, names[k], normal.get(k), block_names)
                   for k, pl in enumerate(r.loads.planes)],
        "forces": [{"kind": f.kind, "name": names[f.plane] if f.plane >= 0 else f.name,
                    "vector": f.vector.tolist(), "point": f.point.tolist()}
                   for f in r.loads.forces],
        "modes_tried": [{"planes": [names[k] for k in m.planes],
                         "admissible": m.admissible, "normal_forces": list(m.normal_forces),
                         "factor_of_safety": m.factor_of_safety if m.admissible else None,
                         "why": m.why} for m in r.modes],
        "notes": list(r.notes),
    }


def limit_equilibrium(model: Model, weakened: tuple[int, ...] | None = None,
                      watch: tuple[int, ...] | None = None) -> LimitEquilibriumResult:
    """Limit equilibrium of the model's one free block on the planes it rests on
    (NotApplicable, saying why, for a model it does not describe). `weakened`: the joint
    materials strength reduction would divide (None: all), for the strength-reduction
    factor."""
    loads = block_loads(model, weakened, watch)
    total = sum((f.vector for f in loads.forces), np.zeros(3))
    passive = sum((f.vector for f in loads.forces if f.kind == "passive_bolt"), np.zeros(3))
    best, tried = solve_modes(loads.planes, total, passive)
    if best.planes and best.factor_of_safety > 0:
        _check_not_toppling(loads, best, total)
    notes = list(loads.notes)
    if not any(pl.weakened for pl in loads.planes):
        notes.append("no plane the block rests on is of a weakened joint material")
    return LimitEquilibriumResult(best.factor_of_safety, best.strength_reduction_factor,
                                  best, loads, tried, notes)
