"""Physical ranges of the scene's numbers: what a rock engineer would defend, checked on
every scene (CLI and API alike) as the field's own validation, naming the field and the
range. Beyond them lies physical nonsense (a density of 1e200 kg/m³, gravity of 1e300 m/s²)
that ran to `successful`, to "singular system" or to infinite displacements.

`analysis.allow_unphysical: true` accepts values up to OVERRIDE_FACTOR times beyond each
end of a range (a centrifuge model's 100 g, a lab model's soft infill), never more: the
arithmetic stays finite either way. The format's own bounds (coordinates within ±1e8 m,
positive where a quantity must be) hold with or without it.

The contact penalty has no fixed range: it must lie within PENALTY_DECADES decades of the
one the scene would derive (engine.model.default_penalty), checked once the blocks are
built (:func:`penalty_problems`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import AfterValidator, Field

if TYPE_CHECKING:
    from engine.model import Model

#: how far beyond each end of a physical range `analysis.allow_unphysical` accepts
OVERRIDE_FACTOR = 1000.0
#: decades either side of the derived contact penalty a given one may lie
PENALTY_DECADES = 4
#: the field that accepts values beyond the physical ranges
OVERRIDE = "analysis.allow_unphysical"

_ALLOWED: ContextVar[bool] = ContextVar("allow_unphysical", default=False)


@contextlib.contextmanager
def unphysical_allowed(allowed: bool) -> Iterator[None]:
    """Check the ranges of the models validated inside as `allowed` says (the scene's
    `analysis.allow_unphysical`, read before its fields are validated)."""
    token = _ALLOWED.set(allowed)
    try:
        yield
    finally:
        _ALLOWED.reset(token)


def _num(value: float) -> str:
    """A number as a person writes it: 100, 30,000, 0.001, 1e+12, 1.234567e+07."""
    if value != 0 and (abs(value) >= 1e6 or abs(value) < 1e-3):
        mantissa, exponent = f"{value:.6e}".split("e")
        return f"{mantissa.rstrip('0').rstrip('.')}e{exponent}"
    return f"{value:,.10g}"


@dataclass(frozen=True)
class Range:
    """A physical range `[lo, hi]` in `unit` (what it is: `what`, for the message)."""

    lo: float
    hi: float
    unit: str
    what: str

    def widened(self) -> tuple[float, float]:
        """The range `analysis.allow_unphysical` accepts: OVERRIDE_FACTOR times beyond
        each end (an end at 0 stays there)."""
        f = OVERRIDE_FACTOR
        lo = self.lo / f if self.lo > 0 else self.lo * f
        hi = self.hi * f if self.hi > 0 else self.hi / f
        return lo, hi

    def text(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        return f"{_num(self.lo)} to {_num(self.hi)}{unit}"

    def outside(self, value: float) -> str | None:
        """Where `value` lies if it is refused ("outside the physical range of ..."), None
        if it is accepted (see the module: `analysis.allow_unphysical` widens the range)."""
        allowed = _ALLOWED.get()
        lo, hi = self.widened() if allowed else (self.lo, self.hi)
        if lo <= value <= hi:
            return None
        unit = f" {self.unit}" if self.unit else ""
        if allowed:
            return (f"beyond even what {OVERRIDE} accepts for {self.what}, {_num(lo)} to "
                    f"{_num(hi)}{unit} ({OVERRIDE_FACTOR:,.0f} times beyond the physical "
                    f"range {self.text()})")
        return (f"outside the physical range of {self.what}, {self.text()} (a scene that "
                f"needs more sets {OVERRIDE}: true)")

    def problem(self, value: float) -> str | None:
        """Why `value` is refused (None if it is accepted), as a field's message."""
        if not math.isfinite(value):
            return "must be a finite number"
        where = self.outside(value)
        unit = f" {self.unit}" if self.unit else ""
        return None if where is None else f"{_num(value)}{unit} is {where}"

    def schema(self) -> dict[str, Any]:
        return {"x-physical-range": [self.lo, self.hi], "x-unit": self.unit}


def physical(lo: float, hi: float, unit: str, what: str, *base: Any) -> Any:
    """A number within the physical range `[lo, hi]` of `what` (see the module), after
    the format's own constraints `base` (e.g. `Field(gt=0)`: "must be positive" first)."""
    rng = Range(lo, hi, unit, what)

    def check(value: float) -> float:
        why = rng.problem(value)
        if why is not None:
            raise ValueError(why)
        return value

    return Annotated[float, *base, Field(json_schema_extra=rng.schema()),
                     AfterValidator(check)]


def magnitude(hi: float, unit: str, what: str) -> Any:
    """A vector [x, y, z] whose magnitude (its length) is at most `hi` (see the module)."""
    rng = Range(0.0, hi, unit, f"{what}'s magnitude")

    def check(value: list[float]) -> list[float]:
        why = rng.problem(math.hypot(*value))
        if why is not None:
            raise ValueError(why)
        return value

    return Annotated[list[float], Field(min_length=3, max_length=3,
                                        json_schema_extra=rng.schema()),
                     AfterValidator(check)]


def check_all(values: Sequence[float], rng: Range, what: str) -> None:
    """ValueError naming the first of `values` (`what`, e.g. "acceleration[3]") outside
    `rng`."""
    for k, v in enumerate(values):
        why = rng.problem(v)
        if why is not None:
            raise ValueError(f"{what}[{k}]: {why}")


# ----------------------------------------------------------------------- the ranges

_POSITIVE, _NONNEGATIVE = Field(gt=0), Field(ge=0)
#: kg/m³: from a porous pumice or a coal to the densest ore
Density = physical(100, 30_000, "kg/m³", "a rock's density", _POSITIVE)
#: Pa: from a soft soil (1 MPa) to beyond any rock or steel (1,000 GPa)
YoungModulus = physical(1e6, 1e12, "Pa", "Young's modulus", _POSITIVE)
#: Pa: up to 100 MPa, the cohesion or tensile strength of the strongest intact rock
Strength = physical(0, 1e8, "Pa", "a strength", _NONNEGATIVE)
#: Pa: up to 100 MPa, the water pressure of 10 km of head
Pressure = physical(0, 1e8, "Pa", "a water pressure", _NONNEGATIVE)
#: N/m³: from fresh water to a dense brine or mud
UnitWeight = physical(5_000, 20_000, "N/m³", "water's unit weight", _POSITIVE)
#: m/s²: up to about 10 g
Gravity = magnitude(100, "m/s²", "gravity")
#: m/s², a ground acceleration: up to about 10 g (the strongest records reach 4 g)
ACCELERATION = Range(-100, 100, "m/s²", "a ground acceleration")
#: s, a record's time
RECORD_TIME = Range(-1e6, 1e6, "s", "a record's time")
#: m/s: faster than any rock fall
Velocity = magnitude(1_000, "m/s", "a velocity")
#: rad/s
Spin = magnitude(1_000, "rad/s", "a spin")
#: N: about 40 times the weight of a 100 m cube of rock
Force = magnitude(1e12, "N", "a force")
#: N/m: a bolt's spring
BoltStiffness = physical(0, 1e12, "N/m", "a bolt's stiffness", _NONNEGATIVE)
#: N: up to 100 MN, beyond the largest ground anchors
BoltForce = physical(0, 1e8, "N", "a bolt's force", _NONNEGATIVE)
#: N, a bolt's yield force (positive)
BoltCapacity = physical(0, 1e8, "N", "a bolt's force", _POSITIVE)
#: s simulated
Duration = physical(1e-6, 1e6, "s", "a simulated duration", _POSITIVE)
#: s, a time step
TimeStep = physical(1e-7, 10, "s", "a time step", _POSITIVE)
#: s, the smallest time step before a run stops
MinTimeStep = physical(1e-12, 10, "s", "the smallest time step", _POSITIVE)
#: shear over normal contact stiffness
ShearRatio = physical(1e-3, 10, "", "the shear / normal stiffness ratio", _POSITIVE)
#: a factor of safety
Factor = physical(0.01, 100, "", "a factor of safety", _POSITIVE)
#: m: the largest size of a model, and of any length in it
SIZE = Range(0, 1e5, "m", "a model's size")
#: the physical range of a sweep's quantity (those with a fixed one)
SWEEP_RANGES = {"cohesion": Range(0, 1e8, "Pa", "a strength"),
                "bolt_pretension": Range(0, 1e8, "N", "a bolt's force"),
                "bolt_capacity": Range(0, 1e8, "N", "a bolt's force"),
                "time_step": Range(1e-7, 10, "s", "a time step"),
                "water_level": Range(-1e7, 1e7, "m", "a coordinate")}


def penalty_problems(model: Model, penalty: float | None,
                     fixed_point_penalty: float | None) -> list[dict[str, str]]:
    """The given contact and fixed-point penalties (N/m) that lie more than
    PENALTY_DECADES decades from the ones the scene derives (fixed points: 10 × the
    contact penalty), unless the scene allows the unphysical."""
    from engine.model import default_penalty

    if penalty is None and fixed_point_penalty is None:
        return []
    derived = default_penalty(model)
    problems = []
    for loc, value, base in (("analysis.penalty", penalty, derived),
                             ("analysis.fixed_point_penalty", fixed_point_penalty,
                              10 * (penalty or derived))):
        if value is None:
            continue
        decades = PENALTY_DECADES + (math.log10(OVERRIDE_FACTOR) if _ALLOWED.get() else 0)
        lo, hi = base / 10**decades, base * 10**decades
        if not lo <= value <= hi:
            more = (f"beyond even what {OVERRIDE} accepts" if _ALLOWED.get() else
                    f"a scene that needs it sets {OVERRIDE}: true")
            problems.append({"loc": loc, "msg": (
                f"{_num(value)} N/m is more than {decades:g} decades from the "
                f"{_num(base)} N/m this scene derives ({_num(lo)} to {_num(hi)} N/m; "
                f"{more}); leave it out to use the derived one")})
    return problems


def extent_problems(lows: Sequence[float], highs: Sequence[float], loc: str
                    ) -> list[dict[str, str]]:
    """The model's size along x, y and z (its bounding box `lows` to `highs`) beyond
    SIZE."""
    for axis, lo, hi in zip("xyz", lows, highs, strict=True):
        where = SIZE.outside(hi - lo)
        if where is not None:
            return [{"loc": loc, "msg": f"the model spans {_num(hi - lo)} m along {axis}, "
                                        f"{where}"}]
    return []
