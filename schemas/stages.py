"""Excavations (tunnels, caverns, benches) and stages of a scene: the pydantic models.

An excavation is cut from the rock mass after the joints (`cut: "after_joints"`, the
default: its rock is blocks that a stage removes) or before them (`"before_joints"`: the
domain never had that rock). A stage states what changes when it starts; `stages` run in
order, each for its `duration`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from schemas.domains import _exactly_one, _Model
from schemas.fields import Length, Name, Point, Point2
from schemas.physical import Duration

# BoxSpec, GroundMotionSpec, JointMaterialSpec, SeismicSpec, Target and WaterSpec are the
# scene's own: scene.py resolves them (`model_rebuild`) once it has defined them
Positive = Annotated[float, Field(gt=0)]
Azimuth = Annotated[float, Field(ge=0, le=360)]
Plunge = Annotated[float, Field(ge=-90, le=90)]
DipDirection = Annotated[float, Field(ge=-360, le=360)]


class TunnelSpec(_Model):
    """A tunnel: its cross-section and its axis (the invert's centre line), straight from
    `start` along `trend` / `plunge` over `length`, or the polyline `axis`."""

    shape: Literal["circular", "horseshoe", "d_shaped"] = "circular"
    width: Length = Field(description="m: the diameter of a circular tunnel, the span of "
                                        "the others")
    height: Length | None = Field(None, description="m, D-shaped: floor to crown "
                                                      "(default: the width)")
    sides: Annotated[int, Field(ge=6, le=128)] = Field(
        16, description="vertices of a circular section (arcs get about half as many)")
    start: Point | None = Field(None, description="m, the invert's centre at the portal")
    trend: Azimuth | None = Field(None, description="degrees clockwise from North")
    plunge: Plunge = Field(0.0, description="degrees below "
                                                                  "horizontal")
    length: Length | None = Field(None, description="m along the axis")
    axis: Annotated[list[Point], Field(min_length=2, max_length=1000)] | None = Field(
        None, description="m, the invert's centre line as a polyline (instead of start, "
                          "trend, plunge, length)")

    @model_validator(mode="after")
    def _one_axis(self) -> TunnelSpec:
        straight = (self.start, self.trend, self.length)
        if self.axis is None and any(v is None for v in straight):
            raise ValueError("give the axis as 'start', 'trend' (and 'plunge') and 'length', "
                             "or as the polyline 'axis'")
        if self.axis is not None and any(v is not None for v in straight):
            raise ValueError("give either 'axis' or 'start' / 'trend' / 'length', not both")
        return self


class CavernSpec(_Model):
    """A box-shaped cavern or chamber: `size` = length along `trend`, width, height (m)."""

    center: Point
    size: Annotated[list[Length], Field(min_length=3, max_length=3)]
    trend: Azimuth = 0.0


class BenchSpec(_Model):
    """A prism of a vertical section (an open-pit bench or cut): the closed polygon
    `section` of `[s, z]` points (as a slope profile's: s m horizontal against
    `dip_direction`, z the elevation), extruded over `width` m along the strike from
    `origin` (x, y of s = 0)."""

    section: Annotated[list[Point2], Field(min_length=3, max_length=1000)]
    dip_direction: DipDirection
    width: Length
    origin: Point2 = Field(default_factory=lambda: [0.0, 0.0])


class ExcavationSpec(_Model):
    """An opening cut from the rock mass: one of `tunnel`, `cavern` or `bench`."""

    name: Name
    tunnel: TunnelSpec | None = None
    cavern: CavernSpec | None = None
    bench: BenchSpec | None = None
    cut: Literal["after_joints", "before_joints"] = Field(
        "after_joints", description="after the joints: its rock is blocks a stage removes; "
                                    "before: the domain never had that rock")

    @model_validator(mode="after")
    def _one_shape(self) -> ExcavationSpec:
        _exactly_one(self, ("tunnel", "cavern", "bench"))
        return self


class StageSpec(_Model):
    """One stage: its name, how long it runs, and what changes as it starts (everything
    else stays as the stage before left it)."""

    name: Name
    duration: Duration = Field(description="s simulated in this stage")
    excavate: list[Name] = Field(default_factory=list,
                                 description="excavations (names) dug out as it starts")
    excavate_region: BoxSpec | None = Field(  # noqa: F821
        None, description="also remove every block whose centroid lies in this box")
    add_bolts: list[Name] = Field(default_factory=list, description="bolts or bolt patterns "
                                  "(names, prefixes) installed as it starts")
    remove_bolts: list[Name] = Field(default_factory=list)
    water: WaterSpec | None = Field(None, description="the water from now on")  # noqa: F821
    drain: bool = Field(False, description="no water from now on")
    joint_materials: dict[Name, JointMaterialSpec] = Field(  # noqa: F821
        default_factory=dict, description="joint materials (by name) given new strengths")
    seismic: SeismicSpec | None = Field(  # noqa: F821
        None, description="pseudo-static load from now on")
    ground_motion: GroundMotionSpec | None = Field(  # noqa: F821
        None, description="acceleration record of the ground from now on (its time starts "
                          "with the stage)")
    quiet: bool = Field(False, description="no seismic load and no ground motion from now on")
    fix: list[Target] = Field(default_factory=list)  # noqa: F821
    free: list[Target] = Field(default_factory=list)  # noqa: F821

    @model_validator(mode="after")
    def _consistent(self) -> StageSpec:
        if self.drain and self.water is not None:
            raise ValueError("give 'water' or 'drain', not both")
        if self.quiet and (self.seismic is not None or self.ground_motion is not None):
            raise ValueError("'quiet' removes the seismic load: give it without "
                             "'seismic' or 'ground_motion'")
        return self
