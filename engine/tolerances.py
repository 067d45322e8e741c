"""All geometric and numerical tolerances of the engine, in one documented object."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Lengths:
    """The length tolerances of :class:`Tolerances` in metres, for one model size."""

    point_merge: float
    planarity: float
    on_plane: float
    feature_snap: float
    touching: float
    bonding: float


@dataclass(frozen=True)
class Tolerances:
    """Tolerances, relative to a length scale unless the name says otherwise.

    Lengths become metres by :meth:`lengths` (times the model's length scale, the largest
    bounding-box edge), so a 1 mm scene and a 1 km scene behave alike.
    """

    #: points closer than this (relative) are the same point
    point_merge: float = 1e-9
    #: a vertex farther than this (relative) from its face plane makes the face non-planar
    planarity: float = 1e-6
    #: a vertex within this (relative) distance of a cutting plane lies on it
    on_plane: float = 1e-9
    #: contact features closer than this (relative) to an edge end are at the end (v-v / v-e)
    feature_snap: float = 1e-6
    #: a new contact whose gap is below this (relative) touches and starts closed
    touching: float = 1e-9
    #: joint faces of a cohesive or tensile joint closer than this (relative) at the start of
    #: a run are bonded: the resolution of coordinates a user writes (a block given "on" a
    #: plane to 5 decimals sits up to 1e-5 m above it); a contact that forms later is not
    bonding: float = 1e-6
    #: a contact force below this fraction of the lighter block's weight is round-off: the
    #: open-close iteration neither opens a closed contact nor closes an open one on it
    #: (a fraction of the weight, not a length, so that it means the same at any penalty). A
    #: cut rock mass's faces touch exactly (gap 0.0) and carry no force; at 5,272 blocks
    #: ~54,000 of 130,000 flipped each step on forces of a median 1e-11 of a block's weight,
    #: and the cascade that followed held Δt at 2.4 µs (benchmarks/TIMESTEP-FINDINGS.md)
    contact_round_off: float = 1e-9
    #: cells or blocks with volume below this fraction of the domain volume are slivers
    sliver_volume: float = 1e-9
    #: unit normals whose dot product exceeds 1 - this are parallel
    parallel: float = 1e-9
    #: sine of the angle a cone edge may dip through a contact plane and still count as
    #: entering / not overlapping: a block tilted by up to ~3 degrees in a step (paper
    #: section 5.2, theta = 1-3 deg) keeps its face-to-face contacts
    entrance: float = 0.05

    def lengths(self, scale: float) -> Lengths:
        """The length tolerances in metres for a model of size `scale` (m)."""
        s = max(float(scale), 1e-12)
        return Lengths(self.point_merge * s, self.planarity * s, self.on_plane * s,
                       self.feature_snap * s, self.touching * s, self.bonding * s)


DEFAULT_TOLERANCES = Tolerances()
