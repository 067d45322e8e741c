"""The scene a rock engineer writes: pydantic models, defaults, loading and reference checks.

SI units (m, kg, s, N, Pa), angles in degrees, x = East, y = North, z = Up. Unknown fields
are errors (typos are caught). :func:`load_scene` returns a validated :class:`Scene` or
raises :class:`~schemas.errors.SceneError` listing every problem with its field path;
:func:`schemas.convert.build_model` turns the scene into the engine's ``Model``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    AliasChoices,
    BaseModel,
    BeforeValidator,
    Field,
    ValidationError,
    model_validator,
)

from engine import user_entry
from engine.analyses.sweep import ANALYTIC_QUANTITIES, SWEEP_QUANTITIES, sweep_truncation
from engine.model import (
    DEFAULT_FRICTION_ANGLE_DEG,
    DISPLACEMENT_LIMIT_RATIO,
    AnalysisControls,
    JointMaterial,
    Material,
    SeismicCoefficientControls,
    StrengthReductionControls,
)
from schemas.domains import MeshSpec, SlopeSpec, TerrainSpec
from schemas.errors import (
    Problems,
    SceneError,
    echo,
    fmt_count,
    fmt_num,
    format_loc,
    from_validation_error,
    unicode_problems,
)
from schemas.fields import MULTILINE, Label, Length, Name, Point, StrictModel, Text
from schemas.physical import (
    ACCELERATION,
    RECORD_TIME,
    SWEEP_RANGES,
    BoltCapacity,
    BoltForce,
    BoltStiffness,
    Density,
    Duration,
    Factor,
    Force,
    Gravity,
    MinTimeStep,
    Pressure,
    ShearRatio,
    Spin,
    Strength,
    TimeStep,
    UnitWeight,
    Velocity,
    YoungModulus,
    check_all,
    extent_problems,
    physical,
    unphysical_allowed,
)
from schemas.stages import ExcavationSpec, StageSpec

#: version of the scene format; a scene may state it as ``"schema_version"``
SCHEMA_VERSION = "1.0"

# the engine's defaults are the scene's (one place for each)
_MATERIAL = Material()
_JOINT = JointMaterial()
_CONTROLS = AnalysisControls()
_FOS = StrengthReductionControls()
_KC = SeismicCoefficientControls()


class Limits:
    """Size limits checked before any heavy work (cutting, detection, running)."""

    #: vertices in all explicit blocks, the domain polyhedron and joint polygons
    max_vertices = 200_000
    #: explicit blocks; also the blocks the joints cut the domain into (estimated first)
    max_blocks = 20_000
    #: joint planes after expanding joint sets over the domain
    max_joint_planes = 2_000
    #: time steps: duration / time_step
    max_steps = 10_000_000
    #: rock bolts, listed and from patterns
    max_bolts = 10_000


# --------------------------------------------------------------------------- field types


def _between(lo: float, hi: float, unit: str, *, hi_open: bool = False) -> Any:
    """A float in [lo, hi] (or [lo, hi)) with a message naming both bounds and the unit."""
    suffix = f" {unit}" if unit else ""

    def check(v: float) -> float:
        if not (lo <= v < hi if hi_open else lo <= v <= hi):
            if hi_open and v == hi:
                raise ValueError(f"must be less than {fmt_num(hi)}{suffix}, got {fmt_num(v)}")
            raise ValueError(
                f"must be between {fmt_num(lo)} and {fmt_num(hi)}{suffix}, got {fmt_num(v)}"
            )
        return v

    bound = {"exclusiveMaximum": hi} if hi_open else {"maximum": hi}
    schema = Field(json_schema_extra={"minimum": lo, **bound})
    return Annotated[float, schema, AfterValidator(check)]


Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
#: a direction (its length does not matter): components within ±1e6, so its norm is finite
Direction = Annotated[list[Annotated[float, Field(ge=-1e6, le=1e6)]],
                      Field(min_length=3, max_length=3)]
FrictionAngle = _between(0, 90, "degrees", hi_open=True)
Dip = _between(0, 90, "degrees")
DipDirection = _between(-360, 360, "degrees")
PoissonRatio = _between(0, 0.5, "", hi_open=True)
Ratio01 = _between(0, 1, "")
Azimuth = _between(0, 360, "degrees")
SeismicCoefficient = _between(0, 5, "")
VerticalSeismicCoefficient = _between(-5, 5, "")


def _name_to_selection(value: Any) -> Any:
    """A bare string where a block is expected means ``{"name": value}``."""
    return {"name": value} if isinstance(value, str) else value


class _Model(StrictModel):
    """A part of the scene (strict JSON types: schemas.fields)."""


def _exactly_one(obj: BaseModel, names: tuple[str, ...]) -> None:
    given = [n for n in names if getattr(obj, n) is not None]
    if len(given) != 1:
        quoted = [f"'{n}'" for n in names]
        options = ", ".join(quoted[:-1]) + " or " + quoted[-1]
        got = "none" if not given else " and ".join(f"'{n}'" for n in given)
        raise ValueError(f"give exactly one of {options} (got {got})")


# --------------------------------------------------------------------------- materials


class MaterialSpec(_Model):
    """Intact rock of the blocks."""

    density: Density = Field(_MATERIAL.density, description="kg/m³")
    young_modulus: YoungModulus = Field(_MATERIAL.young_modulus,
                                    description="Pa (unused for rigid blocks)")
    poisson_ratio: PoissonRatio = Field(_MATERIAL.poisson_ratio,
                                        description="0 to 0.5 (unused for rigid blocks)")


class JointMaterialSpec(_Model):
    """Strength of a joint (and of any contact given this joint material)."""

    friction_angle: FrictionAngle = Field(DEFAULT_FRICTION_ANGLE_DEG,
                                          description="degrees, 0 to 90")
    cohesion: Strength = Field(_JOINT.cohesion, description="Pa")
    tensile_strength: Strength = Field(_JOINT.tensile_strength, description="Pa")


# --------------------------------------------------------------------------- geometry


class BoxSpec(_Model):
    """An axis-aligned box from `min` to `max` (m)."""

    min: Point
    max: Point

    @model_validator(mode="after")
    def _ordered(self) -> BoxSpec:
        for axis, lo, hi in zip("xyz", self.min, self.max, strict=True):
            if hi <= lo:
                raise ValueError(
                    f"max must exceed min on every axis ({axis}: min {fmt_num(lo)}, "
                    f"max {fmt_num(hi)})"
                )
        return self


class PolyhedronSpec(_Model):
    """A closed polyhedron: vertices and faces (vertex indices, counter-clockwise from outside)."""

    vertices: list[Point]
    faces: list[list[Annotated[int, Field(ge=0)]]]


class DomainSpec(_Model):
    """The rock mass that the joints cut into blocks: a `box`, a `polyhedron`, a `slope`
    (section profile), a `terrain` (ground surface) or a `mesh` (closed mesh file).

    Cut blocks are named `name_prefix` + 1, 2, ... in order of centroid z, then y, then x
    (lowest first).
    """

    box: BoxSpec | None = None
    polyhedron: PolyhedronSpec | None = None
    slope: SlopeSpec | None = None
    terrain: TerrainSpec | None = None
    mesh: MeshSpec | None = None
    material: Name | None = Field(None, description="material name (default material if omitted)")
    name_prefix: Name = "B"
    min_block_volume: physical(0, 1e15, "m³", "a volume", Field(ge=0)) | None = Field(
        None, description="m³; smaller cut blocks merge into the neighbour they share the "
                          "largest face with (default: 1/1000 of the median block volume; "
                          "0 keeps every block)"
    )
    min_block_width: physical(0, 1e5, "m", "a size", Field(ge=0)) | None = Field(
        None, description="m; thinner cut blocks (slivers: their thinnest extent across "
                          "their own faces) merge into the neighbour they share the largest "
                          "face with (default: 1/10 of the joint sets' median spacing, or of "
                          "the median block width without sets; 0 keeps them)"
    )

    @model_validator(mode="after")
    def _one_shape(self) -> DomainSpec:
        _exactly_one(self, ("box", "polyhedron", "slope", "terrain", "mesh"))
        return self


class DiscSpec(_Model):
    """A circular joint of `radius` (m) about `center` (default: the joint's point)."""

    radius: Length
    center: Point | None = None
    sides: Annotated[int, Field(ge=3, le=256)] = Field(
        24, description="polygon sides used for the disc"
    )


class ExtentSpec(_Model):
    """Where a non-persistent joint exists: a convex `polygon` in its plane or a `disc`."""

    polygon: Annotated[list[Point], Field(min_length=3)] | None = None
    disc: DiscSpec | None = None

    @model_validator(mode="after")
    def _one_shape(self) -> ExtentSpec:
        _exactly_one(self, ("polygon", "disc"))
        return self


class JointSpec(_Model):
    """A joint plane, or a joint set when `spacing` is given (parallel planes `spacing` apart).

    Without `extent` the joint is persistent: it cuts everything it crosses.
    """

    name: Name | None = Field(None, description="default J1, J2, ... by position")
    dip: Dip = Field(description="degrees, 0 to 90")
    dip_direction: DipDirection = Field(description="degrees clockwise from North")
    point: Point = Field(description="a point on the plane (m)")
    spacing: Length | None = Field(None, description="m; makes this a joint set")
    extent: ExtentSpec | None = None
    joint_material: Name | None = Field(None, description="default joint material if omitted")


class VelocitySpec(_Model):
    """Initial velocity: translation (m/s) and spin (rad/s) about the centroid."""

    translation: Velocity = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    spin: Spin = Field(default_factory=lambda: [0.0, 0.0, 0.0])


class BlockSpec(_Model):
    """An explicit block: vertices (m) and faces listed counter-clockwise seen from outside.

    Concave blocks are allowed (decomposed into convex pieces for contact detection).
    """

    name: Name | None = Field(None, description="default block1, block2, ... by position")
    vertices: list[Point]
    faces: list[list[Annotated[int, Field(ge=0)]]]
    material: Name | None = None
    fixed: bool = False
    velocity: VelocitySpec = Field(default_factory=VelocitySpec)


# --------------------------------------------------------------------------- selections


class Selection(_Model):
    """Chooses blocks: by `name`, by a point it `contains`, or all blocks whose centroid is
    in the box `centroid_in`. A bare string means a name."""

    name: Name | None = None
    contains: Point | None = None
    centroid_in: BoxSpec | None = None

    @model_validator(mode="after")
    def _one_rule(self) -> Selection:
        _exactly_one(self, ("name", "contains", "centroid_in"))
        return self


Target = Annotated[
    Selection, BeforeValidator(_name_to_selection, json_schema_input_type=Name | Selection)
]


class BlockPairSpec(_Model):
    """The joint material of every contact between two given blocks (wins over joint tags)."""

    blocks: Annotated[list[Target], Field(min_length=2, max_length=2)]
    joint_material: Name


class FixedPointSpec(_Model):
    """A point of a block held in place by a stiff spring (block default: the one at `point`)."""

    point: Point
    block: Target | None = None


class PointLoadSpec(_Model):
    """A force (N) at a point of a block (block default: the one at `point`)."""

    point: Point
    force: Force
    block: Target | None = None


class BoundarySpec(_Model):
    """Fixed blocks, fixed points and point loads."""

    fixed_blocks: list[Target] = Field(default_factory=list)
    fixed_points: list[FixedPointSpec] = Field(default_factory=list)
    point_loads: list[PointLoadSpec] = Field(default_factory=list)


class _BoltProperties(_Model):
    """What a rock bolt or cable is made of (SI units)."""

    axial_stiffness: BoltStiffness = Field(
        3e7, description="N/m, axial spring of the whole free length (default: a 25 mm steel "
                         "bar 3 m long, EA/L); 0: a constant-force tendon")
    shear_stiffness: BoltStiffness = Field(
        0.0, description="N/m, transverse spring at the head (default 0: a cable)")
    pretension: BoltForce = Field(0.0, description="N, tension at installation")
    capacity: BoltCapacity | None = Field(
        None, description="N, axial yield force (default: unlimited); |force| stays below it "
                          "and the excess becomes plastic elongation")
    shear_capacity: BoltCapacity | None = Field(
        None, description="N, transverse yield force (default: the axial capacity)")
    rupture_displacement: Length | None = Field(
        None, description="m; the bolt breaks (and stops acting) when its two ends have "
                          "moved apart by more since installation (default: never)")

    @model_validator(mode="after")
    def _pretension_below_capacity(self) -> _BoltProperties:
        if self.capacity is not None and self.pretension > self.capacity:
            raise ValueError(f"pretension ({fmt_num(self.pretension)} N) must not exceed "
                             f"capacity ({fmt_num(self.capacity)} N)")
        return self


class BoltSpec(_BoltProperties):
    """A rock bolt or cable from `head` (a point on or in `block`) to `anchor`: a point in
    `anchor_block`, by default the block other than the head's that contains the anchor,
    or the ground (a point that never moves) when no block contains it."""

    name: Name | None = Field(None, description="default bolt1, bolt2, ... by position")
    head: Point = Field(description="m, where the bolt's plate bears on the block")
    anchor: Point = Field(description="m, the anchored end")
    block: Target | None = Field(None, description="the head's block (default: the block "
                                                   "at `head`)")
    anchor_block: Target | None = Field(None, description="the anchor's block (default: "
                                                          "found at `anchor`, else ground)")


class BoltPatternSpec(_BoltProperties):
    """A grid of identical bolts on a face: rows along `row_direction` `spacing` apart
    (`rows` × `columns`, the second direction normal to it in the face), each `length` m
    long, pointing into the rock along `trend` / `plunge` (degrees; plunge positive down).
    Bolts are named `name_prefix` + 1, 2, ..."""

    origin: Point = Field(description="m, the head of the first bolt (on the face)")
    face_normal: Direction = Field(description="outward normal of the face the heads are on")
    row_direction: Direction = Field(description="a direction in the face along which a row runs")
    spacing: Length = Field(description="m between bolts along a row")
    row_spacing: Length | None = Field(None, description="m between rows (default: "
                                                           "spacing)")
    rows: Annotated[int, Field(ge=1, le=1000)] = 1
    columns: Annotated[int, Field(ge=1, le=1000)] = Field(1, description="bolts per row")
    length: Length = Field(description="m, head to anchor")
    trend: Azimuth = Field(description="degrees clockwise from North of the bolt's "
                                       "direction into the rock")
    plunge: _between(-90, 90, "degrees") = Field(description="degrees below horizontal of "
                                                             "the bolt's direction")
    name_prefix: Name = "bolt"


# --------------------------------------------------------------------------- loads


class SeismicSpec(_Model):
    """Pseudo-static seismic load: body forces kh·g·m horizontally toward `azimuth` and
    kv·g·m vertically (positive up) on every block that moves (g = |gravity|)."""

    kh: SeismicCoefficient = Field(0.0, description="horizontal seismic coefficient, "
                                                    "fraction of g, 0 to 5")
    azimuth: Azimuth = Field(0.0, description="degrees clockwise from North, 0 to 360: the "
                                              "direction the horizontal force points")
    kv: VerticalSeismicCoefficient = Field(0.0, description="vertical seismic coefficient, "
                                                            "fraction of g, positive up, "
                                                            "-5 to 5")


class PhreaticSurfaceSpec(_Model):
    """The water table as a plane: below it the joints hold water at hydrostatic pressure
    γw·(depth below the plane, measured vertically)."""

    point: Point = Field(description="m, a point on the water table")
    dip: _between(0, 90, "degrees", hi_open=True) = Field(
        0.0, description="degrees, 0 (horizontal) to less than 90")
    dip_direction: DipDirection = Field(0.0, description="degrees clockwise from North")


class JointPressureSpec(_Model):
    """A uniform water pressure in the joints of one joint material (a joint set or a named
    joint given its own joint material), added to the phreatic surface's."""

    joint_material: Name
    pressure: Pressure = Field(description="Pa")


class WaterSpec(_Model):
    """Water in the joints: pressure normal to the faces where blocks touch (uplift on
    sliding planes, thrust in tension cracks), following the blocks as they move."""

    unit_weight: UnitWeight = Field(9810.0, description="N/m³, unit weight of water")
    phreatic_surface: PhreaticSurfaceSpec | None = None
    joint_pressures: list[JointPressureSpec] = Field(default_factory=list)

    @model_validator(mode="after")
    def _something(self) -> WaterSpec:
        if self.phreatic_surface is None and not self.joint_pressures:
            raise ValueError("give 'phreatic_surface' and/or 'joint_pressures'")
        return self


class GroundMotionSpec(_Model):
    """An acceleration time history of the ground (the fixed blocks), three components in
    m/s²: inline (`time` and `acceleration`) or as `csv` text (rows `t, ax, ay, az`, an
    optional header line). Linear between samples (repeat a time for a jump), zero outside
    them, times `scale`. Applied as the inertial body force −m·a(t) on every block that
    moves: displacements are relative to the ground."""

    time: list[float] | None = Field(None, description="s, non-decreasing")
    acceleration: list[Vec3] | None = Field(None, description="m/s², one (ax, ay, az) per time")
    csv: Annotated[str, Field(pattern=MULTILINE)] | None = Field(
        None, description="CSV text: t, ax, ay, az per row (s, m/s²)")
    scale: float = Field(1.0, description="factor on the accelerations")

    @model_validator(mode="after")
    def _history(self) -> GroundMotionSpec:
        if self.csv is not None:
            if self.time is not None or self.acceleration is not None:
                raise ValueError("give 'csv' or 'time' and 'acceleration', not both")
            rows = []
            for n, line in enumerate(self.csv.strip().splitlines(), 1):
                cells = [c.strip() for c in line.replace(";", ",").split(",") if c.strip()]
                try:
                    rows.append([float(c) for c in cells])
                except ValueError:
                    if n == 1:
                        continue  # a header
                    raise ValueError(f"csv line {n}: not numbers: '{echo(line)}'") from None
                if len(cells) != 4:
                    raise ValueError(f"csv line {n}: expected 4 values (t, ax, ay, az), "
                                     f"got {len(cells)}")
            self.time = [r[0] for r in rows]
            self.acceleration = [r[1:] for r in rows]
            self.csv = None
        if self.time is None or self.acceleration is None:
            raise ValueError("give 'time' and 'acceleration' (or 'csv')")
        if len(self.time) != len(self.acceleration) or len(self.time) < 2:
            raise ValueError(f"'time' and 'acceleration' need the same length, at least 2 "
                             f"(got {len(self.time)} and {len(self.acceleration)})")
        if any(b < a for a, b in zip(self.time, self.time[1:], strict=False)):
            raise ValueError("'time' must not decrease")
        if not all(math.isfinite(x) for x in self.time):
            raise ValueError("'time' must be finite")
        check_all(self.time, RECORD_TIME, "time")
        for k, a in enumerate(self.acceleration):  # as applied: times the scale
            check_all([self.scale * x for x in a], ACCELERATION, f"scale × acceleration[{k}]")
        return self


# --------------------------------------------------------------------------- analysis


#: what the old acceleration criterion's settings say now (accepted, not used)
_OLD_CRITERION = ("no longer used (accepted for old scenes): trials are judged by the watched "
                  "blocks' displacement and velocity (docs/factor-of-safety.md)")


class _TrialSpec(_Model):
    """How a trial of a bisection is judged (engine.analyses.trials): settled under its
    loads with joints that cannot fail, then released for at most `observation_time` s; it
    fails when a watched block moves more than `displacement_limit` or is still moving at
    the end without slowing down, and holds (ending early) once every watched block is at
    rest with every contact stuck."""

    observation_time: Duration = Field(_FOS.observation_time,
                                       description="s simulated per trial at most")
    displacement_limit: Length | None = Field(
        None, description="m; a trial whose watched block moves more fails (default: "
                          f"{DISPLACEMENT_LIMIT_RATIO:g} × the size V^⅓ of the smallest "
                          "watched block)")
    window_start: NonNegative | None = Field(
        None, description=_OLD_CRITERION,
        validation_alias=AliasChoices("window_start", "averaging_start"))
    acceleration_threshold: Positive | None = Field(None, description=_OLD_CRITERION)
    max_runs: Annotated[int, Field(ge=1, le=1000)] = Field(_FOS.max_runs,
                                                            description="trials at most")
    watch: list[Target] = Field(
        default_factory=list, description="blocks whose motion decides (default: all free)"
    )

    def old_criterion(self, loc: str) -> list[str]:
        """Warnings for the settings of the old acceleration criterion given."""
        return [f"{loc}.{name}: {_OLD_CRITERION}"
                for name in ("window_start", "acceleration_threshold")
                if getattr(self, name) is not None]


class FactorOfSafetySpec(_TrialSpec):
    """Strength reduction: bisect on F with tan φ_r = tan φ / F (cohesion and tension / F);
    each trial as :class:`_TrialSpec` says."""

    tolerance: Positive = Field(_FOS.tolerance, description="stop when the F bracket is "
                                                            "this narrow (relative)")
    min_factor: Factor = Field(_FOS.min_factor, description="smallest F tried")
    max_factor: Factor = Field(_FOS.max_factor, description="largest F tried")
    joint_materials: list[Name] | None = Field(
        None, description="joint materials to weaken (default: all)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> FactorOfSafetySpec:
        if self.max_factor <= self.min_factor:
            raise ValueError(
                f"max_factor ({fmt_num(self.max_factor)}) must exceed min_factor "
                f"({fmt_num(self.min_factor)})"
            )
        return self


class CriticalSeismicSpec(_TrialSpec):
    """Critical (yield) seismic coefficient: bisect on kh (the scene's `seismic` azimuth and
    kv kept, full joint strengths) for the kh at which the watched blocks fail (the trials
    of `factor_of_safety`, from the equilibrium at kh = 0)."""

    tolerance: Positive = Field(_KC.tolerance, description="stop when the kh bracket is "
                                                           "this narrow (relative)")
    max_coefficient: SeismicCoefficient = Field(_KC.max_coefficient,
                                                description="largest kh tried, 0 to 5")

    @model_validator(mode="after")
    def _consistent(self) -> CriticalSeismicSpec:
        if self.max_coefficient <= 0:
            raise ValueError("max_coefficient must be positive")
        return self


class AnalysisSpec(_Model):
    """How to run: time, contact penalties, integration mode, block model."""

    type: Literal["simulation", "factor_of_safety", "critical_seismic_coefficient",
                  "limit_equilibrium"] = "simulation"
    duration: Duration = Field(_CONTROLS.duration, description="s simulated")
    time_step: TimeStep = Field(_CONTROLS.time_step, description="s, initial time step")
    min_time_step: MinTimeStep = Field(_CONTROLS.min_time_step,
                                    description="s; the run stops below this")
    penalty: Positive | None = Field(
        _CONTROLS.penalty,
        description="N/m, normal stiffness of one contact spring; default: derived from the "
                    "scene, the larger of E·L (stiffest rock, median block size) and 10 × "
                    "2 m/Δt² (median block mass, time_step), so contacts act as constraints; "
                    "a given one must lie within 4 decades of that")
    shear_penalty_ratio: ShearRatio = Field(_CONTROLS.shear_penalty_ratio,
                                          description="shear / normal spring stiffness")
    fixed_point_penalty: Positive | None = Field(None, description="N/m (default: engine's)")
    record_interval: Annotated[int, Field(ge=1)] = Field(_CONTROLS.record_interval,
                                                         description="steps between records")
    mode: Literal["dynamic", "quasi_static"] = Field(
        "dynamic", description="dynamic keeps velocity between steps; quasi_static drops it"
    )
    dynamic_ratio: Ratio01 | None = Field(
        None, description="velocity kept between steps, 0 to 1 (overrides mode)"
    )
    block_model: Literal["rigid", "elastic"] = _CONTROLS.block_model
    max_displacement_ratio: Annotated[float, Field(gt=0, le=1)] = Field(
        _CONTROLS.max_displacement_ratio,
        description="largest displacement in a step / model size"
    )
    max_penetration_ratio: Annotated[float, Field(gt=0, le=1)] = Field(
        _CONTROLS.max_penetration_ratio,
        description="deepest contact penetration / thickness of the thinner block "
                          "in contact; a deeper step is redone with a smaller time step"
    )
    max_open_close_iterations: Annotated[int, Field(ge=1, le=1000)] = Field(
        _CONTROLS.max_open_close_iterations,
        description="open-close iterations that may change a contact between open and "
                        "closed before the step is redone with a smaller time step"
    )
    open_close_tolerance: Annotated[float, Field(ge=0, le=0.1)] = Field(
        _CONTROLS.open_close_tolerance,
        description="open-close hysteresis / largest displacement in a step (default 0: "
                    "none; a band lets contacts penetrate without force): an open "
                    "contact closes only when it penetrates deeper than this (any "
                    "tension opens a closed one)"
    )
    contact_damping: Annotated[float, Field(ge=0, le=2)] = Field(
        _CONTROLS.contact_damping,
        description="fraction of critical damping of each contact's springs (dashpots "
                    "in compression and in locked shear): impacts and rocking settle "
                    "instead of ringing on the penalty springs; 0 turns them off")
    record_contacts: bool = _CONTROLS.record_contacts
    contact_solver: Literal["open_close", "complementarity", "newton"] = Field(
        _CONTROLS.contact_solver,
        description="how each step's contacts are solved: 'open_close' (the paper's "
                    "open-close iteration on penalty springs), 'newton' (the same springs, "
                    "the step as the minimum of its potential by Newton's method: no mode "
                    "guessing, Δt held where open-close cuts it) or 'complementarity' (one "
                    "solve of the frictional contact problem, no springs: rigid contacts, "
                    "so a block wedged between neighbours can be held by forces springs "
                    "would not give it; docs/contact-solvers.md)")
    contact_tolerance: Annotated[float, Field(gt=0, le=1e-2)] = Field(
        _CONTROLS.contact_tolerance,
        description="complementarity solve: change of the blocks' motion in a sweep, "
                    "relative to the motion the contacts cause, at which it has converged; "
                    "newton: every block's out-of-balance force, relative to the median "
                    "block's weight")
    restitution: Annotated[float, Field(ge=0, le=1)] = Field(
        _CONTROLS.restitution,
        description="complementarity solve: parting / approach normal velocity of an "
                    "impact (0: plastic, the blocks stay together)")
    sleep_velocity: Annotated[float, Field(ge=0)] = Field(
        _CONTROLS.sleep_velocity,
        description="m/s, complementarity solve: a block whose points all move slower than "
                    "this for sleep_time, every contact stuck with a margin, sleeps (leaves "
                    "the solve, contact forces kept) until a contact force on it changes; "
                    "0: never")
    sleep_time: Annotated[float, Field(gt=0)] = Field(
        _CONTROLS.sleep_time, description="s a block must stay quiet before it sleeps")
    factor_of_safety: FactorOfSafetySpec | None = None
    critical_seismic_coefficient: CriticalSeismicSpec | None = None
    allow_unphysical: bool = Field(
        False, description="accept numbers beyond the physical ranges (a density of "
                           "100 to 30,000 kg/m³, gravity up to 100 m/s², a penalty within 4 "
                           "decades of the derived one, a model up to 1e5 m, ...: "
                           "docs/scene.md), up to 1,000 times beyond each end; for scaled "
                           "models (a centrifuge's 100 g) and numerical studies")

    @model_validator(mode="after")
    def _times(self) -> AnalysisSpec:
        if self.time_step > self.duration:
            raise ValueError(
                f"time_step ({fmt_num(self.time_step)} s) must not exceed duration "
                f"({fmt_num(self.duration)} s)"
            )
        if self.min_time_step > self.time_step:
            raise ValueError(
                f"min_time_step ({fmt_num(self.min_time_step)} s) must not exceed time_step "
                f"({fmt_num(self.time_step)} s)"
            )
        return self

    @property
    def dynamic_ratio_value(self) -> float:
        """k01: `dynamic_ratio` if given, else 1 for dynamic and 0 for quasi-static."""
        if self.dynamic_ratio is not None:
            return float(self.dynamic_ratio)
        return 1.0 if self.mode == "dynamic" else 0.0


class SlopeFaceSpec(_Model):
    """The slope face for kinematic screening (`polydda kinematics`): its dip and dip
    direction, and optionally one friction angle for every joint in the tests."""

    dip: Annotated[float, Field(gt=0, le=90)] = Field(
        description="degrees, more than 0 and at most 90 (vertical)")
    dip_direction: DipDirection = Field(description="degrees clockwise from North")
    friction_angle: FrictionAngle | None = Field(
        None, description="degrees; default: each joint's own joint material")


class NormalSpec(_Model):
    """A normally distributed parameter: mean and standard deviation."""

    mean: FrictionAngle
    sd: physical(0, 90, "degrees", "a friction angle's spread", Field(gt=0))


#: quantities that must stay strictly above their lowest bound
_SWEEP_POSITIVE = ("bolt_capacity", "penalty", "time_step")
#: the fields each distribution takes (besides the targets)
_SWEEP_FIELDS = {"normal": ("mean", "sd"), "uniform": ("low", "high"),
                 "lognormal": ("mean", "sd"), "values": ("values",), "fisher": ("kappa",)}
#: the target each quantity may name
_SWEEP_TARGETS = {"friction_angle": "joint_material", "cohesion": "joint_material",
                  "joint_orientation": "joint", "bolt_pretension": "bolt",
                  "bolt_capacity": "bolt"}


class SweepParameterSpec(_Model):
    """One varied parameter of a sweep: what it is (`quantity`, by default the parameter's
    name) and how its value is chosen per realisation (`distribution`).

    Quantities: `friction_angle` (degrees) and `cohesion` (Pa) of every weakened joint
    material (those of `analysis.factor_of_safety.joint_materials`, default all) or of
    `joint_material`; `joint_orientation` of the joint or joint set `joint` (Fisher
    dispersion about its dip / dip direction, concentration `kappa`; the blocks are cut
    again); `water_level` (m, height of the phreatic surface's point); `kh` (the seismic
    coefficient); `bolt_pretension` and `bolt_capacity` (N) of every bolt or of `bolt` (a
    bolt's name or a bolt pattern's name_prefix); `penalty` (N/m) and `time_step` (s) of
    the analysis, for convergence studies.

    Distributions: `normal` (mean, sd; truncated to [low, high] when given and always to
    the quantity's range), `uniform` (low, high), `lognormal` (mean and sd of the value
    itself), `fisher` (kappa; joint_orientation only) or `values`: a fixed list (a study;
    the `values` parameters of a sweep form a grid, the first listed varying fastest, and
    realisation k takes the k-th combination, cycling).
    """

    quantity: Literal[tuple(SWEEP_QUANTITIES)] = Field(  # type: ignore[valid-type]
        description="what varies (default: the parameter's name): friction_angle "
                    "(degrees), cohesion (Pa), joint_orientation (Fisher scatter of a "
                    "joint's dip and dip direction, degrees), water_level (m, height of the "
                    "phreatic surface's point), kh (fraction of g), bolt_pretension or "
                    "bolt_capacity (N), penalty (N/m), time_step (s)")
    distribution: Literal[tuple(_SWEEP_FIELDS)]  # type: ignore[valid-type]
    mean: float | None = Field(None, description="normal or lognormal: the mean (in the "
                                                 "quantity's unit)")
    sd: Positive | None = Field(None, description="normal or lognormal: the standard "
                                                  "deviation (in the quantity's unit)")
    low: float | None = Field(None, description="uniform: the lowest value; normal: "
                                                "truncated below it (optional)")
    high: float | None = Field(None, description="uniform: the highest value; normal: "
                                                 "truncated above it (optional)")
    values: Annotated[list[float], Field(min_length=1, max_length=10_000)] | None = Field(
        None, description="values: the values, in the quantity's unit")
    kappa: Positive | None = Field(None, description="fisher: Fisher's concentration κ "
                                                     "(larger: less scatter)")
    joint_material: Name | None = Field(None, description="friction_angle / cohesion: only "
                                                          "this joint material")
    joint: Name | None = Field(None, description="joint_orientation: the joint or joint set "
                                                 "(by name) whose orientation varies")
    bolt: Name | None = Field(None, description="bolt_*: only this bolt (its name) or bolt "
                                                "pattern (its name_prefix)")

    @model_validator(mode="after")
    def _consistent(self) -> SweepParameterSpec:
        q, d = self.quantity, self.distribution
        lo, hi, unit = SWEEP_QUANTITIES[q]
        if (d == "fisher") != (q == "joint_orientation"):
            raise ValueError("joint_orientation takes the distribution 'fisher' (kappa), "
                             f"and only it does (got {q} with '{d}')")
        for f in ("mean", "sd", "low", "high", "values", "kappa"):
            wanted = f in _SWEEP_FIELDS[d]
            if wanted and getattr(self, f) is None:
                raise ValueError(f"a {d} distribution needs '{f}'")
            if not wanted and getattr(self, f) is not None \
                    and not (d == "normal" and f in ("low", "high")):
                raise ValueError(f"a {d} distribution takes "
                                 f"{' and '.join(_SWEEP_FIELDS[d])}, not '{f}'")
        for f in ("joint_material", "joint", "bolt"):
            if getattr(self, f) is not None and _SWEEP_TARGETS.get(q) != f:
                raise ValueError(f"'{f}' does not apply to {q}")
        if q == "joint_orientation" and self.joint is None:
            raise ValueError("joint_orientation needs 'joint': the name of a joint or set")
        suffix = f" {unit}" if unit else ""

        def inside(v: float, what: str) -> None:
            top = v >= hi if q == "friction_angle" else v > hi
            if v < lo or top or (q in _SWEEP_POSITIVE and v <= lo):
                raise ValueError(f"{what} {fmt_num(v)}{suffix} is outside the range of {q} "
                                 f"({fmt_num(lo)} to {fmt_num(hi)}{suffix})")

        if d == "uniform":
            if not self.high > self.low:
                raise ValueError(f"high ({fmt_num(self.high)}) must exceed low "
                                 f"({fmt_num(self.low)})")
            inside(self.low, "low")
            if not (q == "friction_angle" and self.high == hi):  # drawn below high
                inside(self.high, "high")
        if d == "values":
            for v in self.values:
                inside(v, "value")
        if d == "normal":
            a, b = sweep_truncation(q, self.low, self.high)
            if not b > a:
                raise ValueError(f"the truncation [{fmt_num(a)}, {fmt_num(b)}]{suffix} is "
                                 "empty")
        if d == "lognormal":
            if lo < 0:
                raise ValueError(f"{q} may be negative: give it a normal or uniform "
                                 "distribution, not lognormal")
            if not (self.mean is not None and self.mean > 0):
                raise ValueError("a lognormal distribution needs a positive mean")
        self._physical()
        return self

    def _physical(self) -> None:
        """The values, bounds, mean and spread within the physical range of the quantity
        (schemas.physical; those with a fixed one), or its own range (kh, angles)."""
        q = self.quantity
        rng = SWEEP_RANGES.get(q)
        lo, hi, _ = SWEEP_QUANTITIES[q]
        for name in ("values", "low", "high", "mean"):
            value = getattr(self, name)
            if value is None:
                continue
            values = value if isinstance(value, list) else [value]
            if rng is not None:
                check_all(values, rng, name)
            elif q in ("friction_angle", "kh") and name == "mean" \
                    and not lo <= values[0] <= hi:
                raise ValueError(f"mean {fmt_num(values[0])} is outside the range of {q} "
                                 f"({fmt_num(lo)} to {fmt_num(hi)})")
        width = (rng.hi - rng.lo) if rng is not None else (hi - lo)
        if self.sd is not None and math.isfinite(width) and self.sd > width:
            raise ValueError(f"sd {fmt_num(self.sd)} is wider than the whole range of {q} "
                             f"({fmt_num(width)})")



def _parameter_names(data: Any) -> Any:
    """A parameter's `quantity` defaults to its name in `parameters`."""
    if isinstance(data, dict) and isinstance(data.get("parameters"), dict):
        data = dict(data, parameters={
            name: ({"quantity": name} | spec if isinstance(spec, dict) and "quantity" not in spec
                   else spec)
            for name, spec in data["parameters"].items()})
    return data


class MonteCarloSpec(_Model):
    """A sweep or Monte Carlo analysis (process `sweep`, `polydda sweep`): `n` realisations
    from `seed` of the scene's `parameters` (each from its own random stream, so realisation
    k is the same whatever n and whatever other parameters are added), each evaluated by
    the engine's strength reduction (`dda`) or limit equilibrium (`analytic`: a planar
    block or a two-plane wedge with everything the scene has; every parameter but the DDA's
    penalty and time step). `friction_angle: {mean, sd}` is the short form of the
    parameter `friction_angle` normal on every weakened joint material."""

    n: Annotated[int, Field(ge=1, le=10_000)] = Field(200, description="realisations")
    seed: Annotated[int, Field(ge=0)] = Field(0, description="random seed")
    friction_angle: NormalSpec | None = Field(
        None, description="degrees: φ ~ Normal(mean, sd) truncated to [0°, 90°) on every "
                          "weakened joint material (short form of a parameter)")
    parameters: dict[Name, SweepParameterSpec] = Field(
        default_factory=dict,
        description="the varied parameters by name (their quantity defaults to the name), "
                    "e.g. {\"friction_angle\": {\"distribution\": \"normal\", \"mean\": 40, "
                    "\"sd\": 5}, \"kh\": {\"distribution\": \"values\", \"values\": [0, 0.1]}}")
    mode: Literal["dda", "analytic"] = "dda"
    realisations: list[Annotated[int, Field(ge=0)]] | None = Field(
        None, description="evaluate only these realisations (0 to n - 1; a share of the "
                          "sweep for one job); default all")

    @model_validator(mode="before")
    @classmethod
    def _names(cls, data: Any) -> Any:
        return _parameter_names(data)

    @model_validator(mode="after")
    def _indices(self) -> MonteCarloSpec:
        if self.friction_angle is None and not self.parameters:
            raise ValueError("give 'parameters' (or the short form 'friction_angle': "
                             "{\"mean\", \"sd\"})")
        if self.friction_angle is not None and "friction_angle" in self.parameters:
            raise ValueError("'friction_angle' is given twice: as the short form and in "
                             "'parameters'")
        if self.realisations is not None:
            bad = [k for k in self.realisations if k >= self.n]
            if bad:
                raise ValueError(f"realisations must be below n = {self.n} (got {bad[0]})")
            if len(set(self.realisations)) != len(self.realisations):
                raise ValueError("realisations are listed twice")
        return self


# --------------------------------------------------------------------------- scene

DEFAULT_MATERIAL_NAME = "rock"
DEFAULT_JOINT_MATERIAL_NAME = "joint"


StageSpec.model_rebuild(_types_namespace={
    "BoxSpec": BoxSpec, "WaterSpec": WaterSpec, "JointMaterialSpec": JointMaterialSpec,
    "SeismicSpec": SeismicSpec, "GroundMotionSpec": GroundMotionSpec, "Target": Target,
    "Name": Name})
ExcavationSpec.model_rebuild()


class Scene(_Model):
    """A DDA scene: materials, blocks (cut from a domain by joints, and/or explicit),
    boundary conditions, gravity and the analysis to run."""

    schema_version: Annotated[str, Field(max_length=20)] = Field(
        SCHEMA_VERSION, description="scene format version")
    name: Label = "scene"
    description: Text = ""
    materials: dict[Name, MaterialSpec] = Field(
        default_factory=dict,
        description="by name; none given: one granite-like 'rock' (2600 kg/m³, 10 GPa, 0.25)",
    )
    default_material: Name | None = Field(
        None, description="material of blocks that name none (the only one if just one)"
    )
    joint_materials: dict[Name, JointMaterialSpec] = Field(
        default_factory=dict,
        description="by name; none given: one 'joint' (friction 30°, no cohesion or tension)",
    )
    default_joint_material: Name | None = Field(
        None, description="for contacts on no named joint (the only one if just one)"
    )
    domain: DomainSpec | None = None
    joints: list[JointSpec] = Field(default_factory=list)
    blocks: list[BlockSpec] = Field(default_factory=list)
    block_pairs: list[BlockPairSpec] = Field(default_factory=list)
    boundary: BoundarySpec = Field(default_factory=BoundarySpec)
    gravity: Gravity = Field(default_factory=lambda: [0.0, 0.0, -9.81], description="m/s²")
    seismic: SeismicSpec | None = Field(
        None, description="pseudo-static seismic coefficients (none: no seismic load)")
    water: WaterSpec | None = Field(None, description="water in the joints (none: dry)")
    ground_motion: GroundMotionSpec | None = Field(
        None, description="acceleration time history of the ground (none: none)")
    bolts: list[BoltSpec] = Field(default_factory=list, description="rock bolts and cables")
    bolt_patterns: list[BoltPatternSpec] = Field(
        default_factory=list, description="grids of identical bolts on a face")
    analysis: AnalysisSpec = Field(default_factory=AnalysisSpec)
    slope_face: SlopeFaceSpec | None = Field(
        None, description="the slope face for kinematic screening (not used by runs)")
    sweep: MonteCarloSpec | None = Field(
        None, description="a sweep or Monte Carlo analysis of the scene's parameters "
                          "(process 'sweep'; not used by runs)")
    excavations: list[ExcavationSpec] = Field(
        default_factory=list, description="tunnels, caverns and benches cut from the domain")
    stages: list[StageSpec] = Field(
        default_factory=list, description="a staged run: what changes at each stage's start "
                                          "(analysis.duration is then their sum)")

    @model_validator(mode="wrap")
    @classmethod
    def _ranges(cls, data: Any, handler: Any) -> Scene:
        """Validate with the physical ranges the scene asks for (analysis.allow_unphysical,
        read first: schemas.physical)."""
        analysis = data.get("analysis") if isinstance(data, dict) else None
        allowed = isinstance(analysis, dict) and analysis.get("allow_unphysical") is True
        with unphysical_allowed(allowed):
            return handler(data)

    @model_validator(mode="after")
    def _defaults(self) -> Scene:
        if not self.materials:
            self.materials = {DEFAULT_MATERIAL_NAME: MaterialSpec()}
        if not self.joint_materials:
            self.joint_materials = {DEFAULT_JOINT_MATERIAL_NAME: JointMaterialSpec()}
        if self.default_material is None and len(self.materials) == 1:
            self.default_material = next(iter(self.materials))
        if self.default_joint_material is None and len(self.joint_materials) == 1:
            self.default_joint_material = next(iter(self.joint_materials))
        return self

    def joint_name(self, k: int) -> str:
        """Name of joint `k` (its own or J<k+1>)."""
        return self.joints[k].name or f"J{k + 1}"

    def block_name(self, k: int) -> str:
        """Name of explicit block `k` (its own or block<k+1>)."""
        return self.blocks[k].name or f"block{k + 1}"


# --------------------------------------------------------------------------- checks


def _known(names: Any) -> str:
    return ", ".join(names) if names else "none"


def _count_vertices(scene: Scene) -> int:
    n = sum(len(b.vertices) for b in scene.blocks)
    if scene.domain is not None and scene.domain.polyhedron is not None:
        n += len(scene.domain.polyhedron.vertices)
    for j in scene.joints:
        if j.extent is not None:
            n += len(j.extent.polygon) if j.extent.polygon else j.extent.disc.sides
    return n


def _domain_bounds(scene: Scene) -> tuple[list[float], list[float]] | None:
    """Corners `(lo, hi)` of the domain's bounding box (None without a domain)."""
    d = scene.domain
    if d is None:
        return None
    if d.box is not None:
        return list(d.box.min), list(d.box.max)
    if d.slope is not None:
        return _slope_bounds(d.slope)
    if d.polyhedron is None:
        return None  # a terrain or mesh: known once its file is read
    if d.polyhedron.vertices:
        vs = d.polyhedron.vertices
        return [min(v[i] for v in vs) for i in range(3)], [max(v[i] for v in vs) for i in range(3)]
    return None


def _slope_bounds(sl: Any) -> tuple[list[float], list[float]]:
    """The bounding box of a slope domain, from its profile and extrusion."""
    a = math.radians(sl.dip_direction)
    across = (-math.sin(a), -math.cos(a))
    along = (-across[1], across[0])
    s_vals = [pt[0] for pt in sl.profile]
    xs, ys = [], []
    for sv in (min(s_vals), max(s_vals)):
        for t in (0.0, sl.width):
            xs.append(sl.origin[0] + sv * across[0] + t * along[0])
            ys.append(sl.origin[1] + sv * across[1] + t * along[1])
    zs = [pt[1] for pt in sl.profile] + [sl.base]
    return [min(xs), min(ys), min(zs)], [max(xs), max(ys), max(zs)]


def _domain_diagonal(scene: Scene) -> float | None:
    bounds = _domain_bounds(scene)
    return None if bounds is None else math.dist(*bounds)


def _elementary(values: list[float], k: int) -> float:
    """Elementary symmetric polynomial e_k of `values` (sum of products of k of them)."""
    e = [1.0] + [0.0] * k
    for v in values:
        for j in range(k, 0, -1):
            e[j] += e[j - 1] * v
    return e[k]


#: direction families beyond which pairs and triples are bounded instead of summed
_EXACT_FAMILIES = 60


def estimate_cut_blocks(scene: Scene) -> float:
    """About how many blocks the joints cut the domain into, before any cutting (0 without
    a domain, 1 without joints).

    Planes in general position cut a convex region into 1 + P + L + V pieces: P planes, L
    lines where two of them meet and V points where three meet, counting those that reach
    the region. Over the domain's bounding box (sides a, b, c), a family of parallel planes
    (unit normal n, density ρ per metre: 1 / spacing, summed over parallel sets) gives
    ρ (|n|·(a, b, c)) planes, two families ρ ρ' (|n × n'|·(bc, ac, ab)) lines and three
    ρ ρ' ρ'' |det(n, n', n'')| abc points. Exact for sets normal to a box's sides; joints
    with an extent count as persistent, so it overestimates those.
    """
    bounds = _domain_bounds(scene)
    if bounds is None:
        return 0.0
    a, b, c = (max(hi - lo, 0.0) for lo, hi in zip(*bounds, strict=True))
    families: list[tuple[tuple[float, float, float], float]] = []  # (normal, density)
    for j in scene.joints:
        d, az = math.radians(j.dip), math.radians(j.dip_direction)
        n = (math.sin(d) * math.sin(az), math.sin(d) * math.cos(az), math.cos(d))
        width = abs(n[0]) * a + abs(n[1]) * b + abs(n[2]) * c
        if not width > 0:
            continue
        rho = 1.0 / j.spacing if j.spacing else 1.0 / width  # a single joint: one plane
        for k, (m, r) in enumerate(families):
            if abs(n[0] * m[0] + n[1] * m[1] + n[2] * m[2]) > 1 - 1e-9:
                families[k] = (m, r + rho)
                break
        else:
            families.append((n, rho))
    planes = sum(r * (abs(n[0]) * a + abs(n[1]) * b + abs(n[2]) * c) for n, r in families)
    rhos = [r for _, r in families]
    if len(families) > _EXACT_FAMILIES:  # |n × n'| and |det| are at most 1
        return 1 + planes + _elementary(rhos, 2) * (b * c + a * c + a * b) \
            + _elementary(rhos, 3) * a * b * c

    def cross(u: tuple[float, ...], v: tuple[float, ...]) -> tuple[float, float, float]:
        return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0])

    lines = points = 0.0
    for i, (ni, ri) in enumerate(families):
        for k in range(i + 1, len(families)):
            nk, rk = families[k]
            x = cross(ni, nk)
            lines += ri * rk * (abs(x[0]) * b * c + abs(x[1]) * a * c + abs(x[2]) * a * b)
            for nl, rl in families[k + 1:]:
                det = abs(x[0] * nl[0] + x[1] * nl[1] + x[2] * nl[2])
                points += ri * rk * rl * det * a * b * c
    return 1 + planes + lines + points


def scene_problems(scene: Scene) -> list[dict[str, str]]:
    """Reference and size problems of a validated scene (names, defaults, limits)."""
    p = Problems()
    mats, jmats = list(scene.materials), list(scene.joint_materials)
    major = scene.schema_version.split(".")[0]
    if major != SCHEMA_VERSION.split(".")[0]:
        p.add("schema_version", f"unsupported version '{scene.schema_version}' "
              f"(this PolyDDA reads {SCHEMA_VERSION})")

    if scene.default_material is not None and scene.default_material not in mats:
        p.add("default_material",
              f"unknown material '{scene.default_material}' (known: {_known(mats)})")
    if scene.default_joint_material is None:
        p.add("default_joint_material",
              f"is required when several joint materials are defined (known: {_known(jmats)})")
    elif scene.default_joint_material not in jmats:
        p.add("default_joint_material",
              f"unknown joint material '{scene.default_joint_material}' (known: {_known(jmats)})")

    def material(loc: str, name: str | None) -> None:
        if name is None:
            if scene.default_material is None:
                p.add(loc, "is required when several materials are defined and no "
                      f"default_material is set (known: {_known(mats)})")
        elif name not in mats:
            p.add(loc, f"unknown material '{name}' (known: {_known(mats)})")

    def joint_material(loc: str, name: str | None) -> None:
        if name is not None and name not in jmats:
            p.add(loc, f"unknown joint material '{name}' (known: {_known(jmats)})")

    if scene.domain is not None:
        material("domain.material", scene.domain.material)
    elif scene.joints:
        p.add("joints", "joints cut a domain: give 'domain' (a box or a polyhedron)")
    if scene.domain is None and not scene.blocks:
        p.add("", "the scene has no blocks: give a 'domain' (cut by 'joints') or 'blocks'")

    seen: dict[str, int] = {}
    raw = {"joints": _raw_names(scene.joints), "blocks": _raw_names(scene.blocks)}  # once
    for k, j in enumerate(scene.joints):
        loc = format_loc(("joints", k), raw)
        joint_material(f"{loc}.joint_material", j.joint_material)
        name = scene.joint_name(k)
        if name in seen:
            p.add(f"{loc}.name", f"joint name '{name}' is used twice (also joints[{seen[name]}])")
        seen.setdefault(name, k)

    seen = {}
    for k, b in enumerate(scene.blocks):
        loc = format_loc(("blocks", k), raw)
        material(f"{loc}.material", b.material)
        name = scene.block_name(k)
        if name in seen:
            p.add(f"{loc}.name", f"block name '{name}' is used twice (also blocks[{seen[name]}])")
        seen.setdefault(name, k)

    for k, pair in enumerate(scene.block_pairs):
        joint_material(f"block_pairs[{k}].joint_material", pair.joint_material)
    fos = scene.analysis.factor_of_safety
    if fos is not None and fos.joint_materials is not None:
        for k, name in enumerate(fos.joint_materials):
            joint_material(f"analysis.factor_of_safety.joint_materials[{k}]", name)

    if scene.water is not None:
        for k, jp in enumerate(scene.water.joint_pressures):
            joint_material(f"water.joint_pressures[{k}].joint_material", jp.joint_material)
    if scene.sweep is not None:
        _sweep_problems(scene, p, joint_material)
    if scene.excavations or scene.stages:
        from schemas.stage_checks import stage_problems

        stage_problems(scene, p, joint_material)
    if scene.analysis.type == "critical_seismic_coefficient" and scene.seismic is None:
        p.add("seismic", "the critical_seismic_coefficient analysis needs 'seismic' with the "
              "azimuth the horizontal force points to (and kv, if any)")

    # sizes, before any heavy work
    for problem in _extent_problems(scene):
        p.add(problem["loc"], problem["msg"])
    nv = _count_vertices(scene)
    if nv > Limits.max_vertices:
        p.add("", f"the scene has {nv:,} vertices in all; the limit is {Limits.max_vertices:,}")
    if len(scene.blocks) > Limits.max_blocks:
        p.add("blocks", f"{len(scene.blocks):,} blocks; the limit is {Limits.max_blocks:,}")
    diag = _domain_diagonal(scene)
    if diag is not None:
        planes = sum(diag / j.spacing + 1 if j.spacing else 1 for j in scene.joints)
        if planes > Limits.max_joint_planes:
            p.add("joints", f"the joint sets make about {planes:,.0f} planes across the domain; "
                  f"the limit is {Limits.max_joint_planes:,} (increase the spacings)")
        elif (n := estimate_cut_blocks(scene)) > Limits.max_blocks:
            p.add("joints", f"the joints would cut the domain into about {fmt_count(n)} "
                  f"blocks; the limit is {Limits.max_blocks:,} (increase the spacings)")
    nb = len(scene.bolts) + sum(bp.rows * bp.columns for bp in scene.bolt_patterns)
    if nb > Limits.max_bolts:
        p.add("bolt_patterns" if scene.bolt_patterns else "bolts",
              f"{nb:,} bolts in all; the limit is {Limits.max_bolts:,}")
    a = scene.analysis
    duration = sum(st.duration for st in scene.stages) if scene.stages else a.duration
    steps = duration / a.time_step
    if steps > Limits.max_steps:
        p.add("analysis.time_step",
              f"duration / time_step = {steps:.3g} steps; the limit is {Limits.max_steps:,} "
              "(shorten the duration or enlarge the time step)")
    return p.items


def _extent_problems(scene: Scene) -> list[dict[str, str]]:
    """The explicit blocks and the domain (where its bounds are known before cutting)
    spanning more than a model's physical size (schemas.physical.SIZE)."""
    bounds = [_domain_bounds(scene)] if scene.domain is not None else []
    if scene.blocks:
        xs = [v for b in scene.blocks for v in b.vertices]
        if xs:
            bounds.append(([min(v[i] for v in xs) for i in range(3)],
                           [max(v[i] for v in xs) for i in range(3)]))
    bounds = [b for b in bounds if b is not None]
    if not bounds:
        return []
    lows = [min(b[0][i] for b in bounds) for i in range(3)]
    highs = [max(b[1][i] for b in bounds) for i in range(3)]
    with unphysical_allowed(scene.analysis.allow_unphysical):
        return extent_problems(lows, highs, "blocks" if scene.blocks else "domain")


def _sweep_problems(scene: Scene, p: Problems, joint_material: Any) -> None:
    """What a sweep's parameters name must exist in the scene, and limit equilibrium (mode
    `analytic`) must have them."""
    joints = [scene.joint_name(k) for k in range(len(scene.joints))]
    bolts = [b.name or f"bolt{k + 1}" for k, b in enumerate(scene.bolts)]
    prefixes = [bp.name_prefix for bp in scene.bolt_patterns]
    for name, par in scene.sweep.parameters.items():
        loc, q = f"sweep.parameters.{name}", par.quantity
        joint_material(f"{loc}.joint_material", par.joint_material)
        if par.joint is not None and par.joint not in joints:
            p.add(f"{loc}.joint", f"unknown joint '{par.joint}' (known: {_known(joints)})")
        if q.startswith("bolt_") and not bolts + prefixes:
            p.add(loc, f"{q} varies the bolts, but the scene has none")
        elif par.bolt is not None and par.bolt not in bolts + prefixes:
            p.add(f"{loc}.bolt", f"unknown bolt '{par.bolt}' (known: "
                  f"{_known(bolts + prefixes)})")
        if q == "water_level" and (scene.water is None or scene.water.phreatic_surface is None):
            p.add(loc, "water_level moves the phreatic surface: give 'water': "
                  "{\"phreatic_surface\": ...}")
        if q == "kh" and scene.seismic is None:
            p.add(loc, "kh needs 'seismic' with the azimuth the horizontal force points to")
        if scene.sweep.mode == "analytic" and q not in ANALYTIC_QUANTITIES:
            p.add(loc, f"limit equilibrium (mode 'analytic') has no {q}: it is a setting "
                  "of the DDA; use mode 'dda'")


def explicit_size_problems(data: dict[str, Any]) -> list[dict[str, str]]:
    """The format's limits on the explicit blocks of a raw scene (counts only, before any
    field is validated): a scene over them is refused at once, with the messages
    :func:`scene_problems` gives (which counts the domain and joint polygons too)."""
    blocks = data.get("blocks")
    if not isinstance(blocks, list):
        return []
    nv = sum(len(b["vertices"]) for b in blocks
             if isinstance(b, dict) and isinstance(b.get("vertices"), list))
    problems = []
    if nv > Limits.max_vertices:
        problems.append({"loc": "", "msg": f"the scene has {nv:,} vertices in all; the limit "
                         f"is {Limits.max_vertices:,}"})
    if len(blocks) > Limits.max_blocks:
        problems.append({"loc": "blocks", "msg": f"{len(blocks):,} blocks; the limit is "
                         f"{Limits.max_blocks:,}"})
    return problems


def _raw_names(items: list[Any]) -> list[dict[str, Any]]:
    return [{"name": it.name} if it.name else {} for it in items]


# --------------------------------------------------------------------------- loading


def _parse(source: str | Path | dict[str, Any]) -> Any:
    if isinstance(source, dict):
        return source
    if isinstance(source, Path) or not source.lstrip().startswith(("{", "[")):
        path = Path(source)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise SceneError([{"loc": "", "msg": f"{path}: file not found"}]) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise SceneError([{"loc": "", "msg": f"{path}: cannot read ({exc})"}]) from None
        where = f"{path}: "
    else:
        text, where = source, ""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise SceneError(
            [{"loc": "", "msg": f"{where}not valid JSON: {exc.msg} at line {exc.lineno} "
              f"column {exc.colno}"}]
        ) from None
    except RecursionError:
        raise SceneError([{"loc": "", "msg": f"{where}not valid JSON: nested too deeply"}]
                         ) from None


def read_json(path: str | Path) -> Any:
    """The JSON document in the file at `path`; SceneError naming the file when it is
    missing, unreadable or not JSON."""
    return _parse(Path(path))


@user_entry("polydda.Scene.load")
def load_scene(source: str | Path | dict[str, Any]) -> Scene:
    """Parse and validate a scene from a path, JSON text or a dict; raise SceneError if bad.

    A string that starts with ``{`` is JSON text; any other string is a file path.
    """
    data = _parse(source)
    if not isinstance(data, dict):
        raise SceneError([{"loc": "", "msg": "a scene must be a JSON object {...}"}])
    problems = unicode_problems(data) or explicit_size_problems(data)
    if problems:  # refused at once: validating 25,000 blocks field by field takes seconds
        raise SceneError(problems)
    try:
        scene = Scene.model_validate(data)
    except ValidationError as exc:
        raise from_validation_error(exc, data, Scene) from None
    problems = scene_problems(scene)
    if problems:
        raise SceneError(problems)
    return scene


def scene_json_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of the scene format."""
    schema = Scene.model_json_schema()
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        **schema,
        "title": "PolyDDA scene",
        "x-schema-version": SCHEMA_VERSION,
    }
