"""Kinematic screening of a rock slope (Markland tests): which joint sets and pairs can move.

Pure functions on orientations in degrees (dip, dip direction clockwise from North; lines as
trend, plunge downward), x = East, y = North, z = Up as in the engine. Tests, each with a
lateral limit about the slope's dip direction (defaults in :class:`LateralLimits`):

- planar sliding (Hoek & Bray): the plane dips out of the face within ±20°, daylights
  (dip < apparent dip of the face along the plane's dip direction) and dips steeper than φ;
- wedge sliding (Markland 1972): for every pair of sets, the line of intersection plunges
  out of the face, daylights (plunge < apparent dip of the face along its trend) and
  plunges steeper than φ (the smaller φ of the two sets); no lateral limit. Hocking's
  refinement names the plane a wedge rides on alone;
- flexural toppling (Goodman 1980): the plane dips into the slope, its pole within ±30°
  of the face's dip direction (Goodman; Wyllie & Mah use ±10°: pass
  ``LateralLimits(flexural_toppling=10)``) and dip ≥ 90° − slope dip + φ (interlayer slip);
- direct toppling (Hudson & Harrison 1997, as drawn in Rocscience Dips): the intersection
  of two sets plunges into the slope within ±20° of the opposite of the face's dip
  direction and at least 90° − slope dip, and a third set (the base plane) dips out of the
  face within ±20° at less than the slope dip; the base releases by sliding when it dips
  steeper than its φ. Steep intersections outside the limits are oblique toppling (noted,
  not admissible).

Stability with cohesion, water or forces is not judged: this says what *can* move.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "Condition", "DirectToppling", "FlexuralToppling", "JointSet", "KinematicResult",
    "LateralLimits", "PlanarSliding", "SlopeFace", "WedgeSliding", "angle_between",
    "apparent_dip", "intersection", "kinematic_analysis", "normal", "pole",
    "trend_plunge",
]

#: angles closer than this (degrees) count as equal in the tests' inequalities
EPS_DEG = 1e-9


@dataclass(frozen=True)
class JointSet:
    """A joint set's mean orientation (degrees) and friction angle (None: the slope's)."""

    name: str
    dip: float
    dip_direction: float
    friction_angle: float | None = None


@dataclass(frozen=True)
class SlopeFace:
    """The slope face (degrees) and the friction angle of sets that state none."""

    dip: float
    dip_direction: float
    friction_angle: float

    def __post_init__(self) -> None:
        if not 0 < self.dip <= 90:
            raise ValueError(f"slope face dip must be in (0, 90] degrees, got {self.dip:g}")
        if not 0 <= self.friction_angle < 90:
            raise ValueError("friction angle must be in [0, 90) degrees, got "
                             f"{self.friction_angle:g}")


@dataclass(frozen=True)
class LateralLimits:
    """± limits (degrees) about the slope's dip direction, per failure mode."""

    planar: float = 20.0
    flexural_toppling: float = 30.0
    direct_toppling: float = 20.0


@dataclass(frozen=True)
class Condition:
    """One test of a failure mode: its name (the condition a mode needs), whether it holds,
    and the numbers as a statement that is true either way (`dip 25° < φ 30°`)."""

    test: str
    passed: bool
    detail: str


def _vs(a: float, b: float) -> str:
    """The relation of `a` to `b` as a sign (equal within EPS_DEG)."""
    return "<" if a < b - EPS_DEG else ">" if a > b + EPS_DEG else "="


def _az(azimuth: float) -> str:
    """An azimuth as geologists write it: 090°, or 172.59° when it is not whole; in
    [0, 360) after rounding (359.999° is 000°, not 360.00°)."""
    a = round(azimuth % 360.0, 2) % 360.0
    return f"{a:03.0f}°" if abs(a - round(a)) < 1e-9 else f"{a:06.2f}°"


def _deg(angle: float) -> str:
    """An angle to two decimals, no negative zero (a plunge of -1e-12° is 0.00°)."""
    return f"{round(angle, 2) + 0.0:.2f}"


def _off(what: str, azimuth: float, reference: str, ref_azimuth: float, off: float,
         limit: float, ok: bool) -> str:
    """`dip direction 215° is 35.00° from the face's 180° (outside the limit ±20°)`."""
    return (f"{what} {_az(azimuth)} is {abs(off):.2f}° from {reference} {_az(ref_azimuth)} "
            f"({'within' if ok else 'outside'} the limit ±{limit:g}°)")


def _away(what: str, off: float) -> str:
    """Why a plane or line pointing `off` degrees from the face's dip direction (|off| ≥ 90)
    cannot daylight."""
    if abs(abs(off) - 90.0) <= EPS_DEG:
        return f"{what} along the face's strike, not out of the face"
    return f"{what} into the slope, away from the face"


# --------------------------------------------------------------------------- geometry


def normal(dip: float, dip_direction: float) -> np.ndarray:
    """Upward unit normal `(3,)` of a plane (x = East, y = North, z = Up)."""
    d, a = math.radians(dip), math.radians(dip_direction)
    return np.array([math.sin(d) * math.sin(a), math.sin(d) * math.cos(a), math.cos(d)])


def trend_plunge(v: np.ndarray) -> tuple[float, float]:
    """Trend and plunge (degrees) of the line along `v` (either sense; plunge ≥ 0)."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    if v[2] > 0:
        v = -v
    plunge = math.degrees(math.asin(min(1.0, -v[2])))
    trend = math.degrees(math.atan2(v[0], v[1])) % 360.0 if plunge < 90 - 1e-12 else 0.0
    return trend, plunge


def pole(dip: float, dip_direction: float) -> tuple[float, float]:
    """Trend and plunge (degrees) of the pole (downward normal) of a plane."""
    return (dip_direction + 180.0) % 360.0, 90.0 - dip


def angle_between(a: float, b: float) -> float:
    """Signed smallest angle from azimuth `b` to azimuth `a`, in (-180, 180] degrees."""
    d = (a - b) % 360.0
    return d - 360.0 if d > 180.0 else d


def apparent_dip(dip: float, dip_direction: float, direction: float) -> float:
    """Dip (degrees) of a plane seen along `direction`; negative when it rises that way."""
    c = math.cos(math.radians(direction - dip_direction))
    if dip >= 90.0:
        return 0.0 if abs(c) < 1e-12 else math.copysign(90.0, c)
    return math.degrees(math.atan(math.tan(math.radians(dip)) * c))


def intersection(a: JointSet, b: JointSet) -> tuple[float, float] | None:
    """Trend and plunge (degrees) of the line where two planes meet (None if parallel)."""
    v = np.cross(normal(a.dip, a.dip_direction), normal(b.dip, b.dip_direction))
    if np.linalg.norm(v) < 1e-9:
        return None
    return trend_plunge(v)


# --------------------------------------------------------------------------- results


@dataclass
class PlanarSliding:
    """Planar sliding on one set."""

    set: str
    admissible: bool
    conditions: list[Condition]


@dataclass
class WedgeSliding:
    """Wedge sliding along the intersection of two sets (`trend`, `plunge` in degrees)."""

    sets: tuple[str, str]
    trend: float | None
    plunge: float | None
    admissible: bool
    conditions: list[Condition]
    #: Hocking: "both" or the name of the single plane the wedge rides on
    sliding_on: str | None = None


@dataclass
class FlexuralToppling:
    """Flexural toppling of slabs of one set dipping into the slope."""

    set: str
    admissible: bool
    conditions: list[Condition]


@dataclass
class DirectToppling:
    """Direct toppling of columns bounded by two sets, released by base planes."""

    sets: tuple[str, str]
    trend: float | None
    plunge: float | None
    admissible: bool
    conditions: list[Condition]
    base_planes: list[str] = field(default_factory=list)
    #: "sliding" or "non-sliding" per base plane (dip above or below its φ)
    base_release: list[str] = field(default_factory=list)
    oblique: bool = False


@dataclass
class KinematicResult:
    """Every test of every set and pair, with the inputs and lateral limits used."""

    slope: SlopeFace
    sets: list[JointSet]
    limits: LateralLimits
    planar: list[PlanarSliding]
    wedge: list[WedgeSliding]
    flexural_toppling: list[FlexuralToppling]
    direct_toppling: list[DirectToppling]

    def admissible(self) -> dict[str, list[Any]]:
        """Names of the admissible sets (planar, flexural) and pairs (wedge, direct)."""
        return {
            "planar": [r.set for r in self.planar if r.admissible],
            "wedge": [list(r.sets) for r in self.wedge if r.admissible],
            "flexural_toppling": [r.set for r in self.flexural_toppling if r.admissible],
            "direct_toppling": [list(r.sets) for r in self.direct_toppling if r.admissible],
        }

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-ready document (lists, floats, strings)."""
        doc = asdict(self)
        doc["admissible"] = self.admissible()
        doc["lateral_limits"] = doc.pop("limits")
        for key in ("wedge", "direct_toppling"):
            for r in doc[key]:
                r["sets"] = list(r["sets"])
        return doc


# --------------------------------------------------------------------------- tests


def _phi(s: JointSet, slope: SlopeFace) -> float:
    return slope.friction_angle if s.friction_angle is None else s.friction_angle


def _planar(s: JointSet, slope: SlopeFace, limit: float) -> PlanarSliding:
    phi = _phi(s, slope)
    off = angle_between(s.dip_direction, slope.dip_direction)
    face = apparent_dip(slope.dip, slope.dip_direction, s.dip_direction)
    within = abs(off) <= limit + EPS_DEG
    daylight = (f"dip {s.dip:g}° {_vs(s.dip, face)} the face's apparent dip {_deg(face)}° "
                f"along {_az(s.dip_direction)}" if abs(off) < 90 else
                _away("the plane dips", off))
    conds = [
        Condition("lateral limit", within, _off("dip direction", s.dip_direction,
                                                "the face's", slope.dip_direction, off,
                                                limit, within)),
        Condition("daylights", abs(off) < 90 and s.dip < face - EPS_DEG, daylight),
        Condition("steeper than friction", s.dip > phi + EPS_DEG,
                  f"dip {s.dip:g}° {_vs(s.dip, phi)} φ {phi:g}°"),
    ]
    return PlanarSliding(s.name, all(c.passed for c in conds), conds)


def _between(azimuth: float, start: float, end: float) -> bool:
    """Whether `azimuth` lies on the shorter arc from `start` to `end` (inclusive)."""
    d, span = angle_between(azimuth, start), angle_between(end, start)
    return (d == 0) or (d * span > 0 and abs(d) <= abs(span))


def _wedge(a: JointSet, b: JointSet, slope: SlopeFace) -> WedgeSliding:
    line = intersection(a, b)
    if line is None:
        return WedgeSliding((a.name, b.name), None, None, False,
                            [Condition("planes meet", False, "the two sets are parallel")])
    trend, plunge = line
    phi = min(_phi(a, slope), _phi(b, slope))
    off = angle_between(trend, slope.dip_direction)
    face = apparent_dip(slope.dip, slope.dip_direction, trend)
    out = abs(off) < 90 - EPS_DEG
    daylight = (f"plunge {_deg(plunge)}° {_vs(plunge, face)} the face's apparent dip "
                f"{_deg(face)}° along {_az(trend)}" if abs(off) < 90 else
                _away("the intersection plunges", off))
    where = ("the intersection is horizontal" if plunge <= EPS_DEG else
             f"intersection trend {_az(trend)} is {abs(off):.2f}° from the face's dip "
             f"direction {_az(slope.dip_direction)} "
             + ("(out of the face)" if out else "(not out of the face)"))
    conds = [
        Condition("plunges out of the face", out and plunge > EPS_DEG, where),
        Condition("daylights", abs(off) < 90 and plunge < face - EPS_DEG, daylight),
        Condition("steeper than friction", plunge > phi + EPS_DEG,
                  f"plunge {_deg(plunge)}° {_vs(plunge, phi)} φ {phi:g}°"),
    ]
    ok = all(c.passed for c in conds)
    on = None
    if ok:  # Hocking (1976): a plane whose dip direction lies between the two carries it
        alone = [s.name for s in (a, b) if _between(s.dip_direction, trend,
                                                    slope.dip_direction)]
        on = alone[0] if len(alone) == 1 else "both"
    return WedgeSliding((a.name, b.name), trend, plunge, ok, conds, on)


def _flexural(s: JointSet, slope: SlopeFace, limit: float) -> FlexuralToppling:
    phi = _phi(s, slope)
    pole_trend, _ = pole(s.dip, s.dip_direction)
    off = angle_between(pole_trend, slope.dip_direction)
    need = 90.0 - slope.dip + phi
    within = abs(off) <= limit + EPS_DEG
    conds = [
        Condition("dips into the slope within the lateral limit", within,
                  _off("pole trend", pole_trend, "the face's dip direction",
                       slope.dip_direction, off, limit, within)),
        Condition("interlayer slip", s.dip >= need - EPS_DEG,
                  f"dip {s.dip:g}° {_vs(s.dip, need)} 90° − slope dip {slope.dip:g}° + "
                  f"φ {phi:g}° = {need:g}°"),
    ]
    return FlexuralToppling(s.name, all(c.passed for c in conds), conds)


def _direct(a: JointSet, b: JointSet, others: list[JointSet], slope: SlopeFace,
            limit: float) -> DirectToppling:
    line = intersection(a, b)
    if line is None:
        return DirectToppling((a.name, b.name), None, None, False,
                              [Condition("planes meet", False, "the two sets are parallel")])
    trend, plunge = line
    into = (slope.dip_direction + 180.0) % 360.0
    off = angle_between(trend, into)
    steep = 90.0 - slope.dip
    bases = [s for s in others
             if abs(angle_between(s.dip_direction, slope.dip_direction)) <= limit + EPS_DEG
             and s.dip <= slope.dip + EPS_DEG]
    base_names = [s.name for s in bases]
    within = abs(off) <= limit + EPS_DEG
    conds = [
        Condition("plunges into the slope within the lateral limit", within,
                  _off("intersection trend", trend, "the direction into the slope", into,
                       off, limit, within)),
        Condition("steep enough", plunge >= steep - EPS_DEG,
                  f"plunge {_deg(plunge)}° {_vs(plunge, steep)} 90° − slope dip {slope.dip:g}° "
                  f"= {steep:g}°"),
        Condition("base plane", bool(bases),
                  ("base planes " + ", ".join(base_names)) if bases else
                  "no other set dips out of the face within the lateral limit at less than "
                  f"the slope dip {slope.dip:g}°"),
    ]
    ok = all(c.passed for c in conds)
    release = ["sliding" if s.dip > _phi(s, slope) + EPS_DEG else "non-sliding"
               for s in bases]
    oblique = (not conds[0].passed) and conds[1].passed and plunge > EPS_DEG
    return DirectToppling((a.name, b.name), trend, plunge, ok, conds, base_names, release,
                          oblique)


def kinematic_analysis(sets: list[JointSet], slope: SlopeFace,
                       limits: LateralLimits | None = None) -> KinematicResult:
    """Markland tests of every set (planar, flexural toppling) and pair of sets (wedge,
    direct toppling) against the slope face."""
    lim = limits or LateralLimits()
    pairs = list(itertools.combinations(range(len(sets)), 2))
    return KinematicResult(
        slope=slope, sets=list(sets), limits=lim,
        planar=[_planar(s, slope, lim.planar) for s in sets],
        wedge=[_wedge(sets[i], sets[j], slope) for i, j in pairs],
        flexural_toppling=[_flexural(s, slope, lim.flexural_toppling) for s in sets],
        direct_toppling=[
            _direct(sets[i], sets[j], [s for k, s in enumerate(sets) if k not in (i, j)],
                    slope, lim.direct_toppling)
            for i, j in pairs],
    )
