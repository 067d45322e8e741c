"""All geometric and numerical tolerances of the engine, in one documented object."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tolerances:
    """Tolerances, relative to a length scale unless the name says otherwise.

    Lengths are multiplied by the model's length scale (the largest bounding-box
    edge) by :meth:`length`, so a 1 mm scene and a 1 km scene behave alike.
    """

    #: points closer than this (relative) are the same point
    point_merge: float = 1e-9
    #: a vertex farther than this (relative) from its face plane makes the face non-planar
    planarity: float = 1e-6
    #: a vertex within this (relative) distance of a cutting plane lies on it
    on_plane: float = 1e-9
    #: cells or blocks with volume below this fraction of the domain volume are slivers
    sliver_volume: float = 1e-9
    #: unit normals whose dot product exceeds 1 - this are parallel
    parallel: float = 1e-9
    #: contact features closer than this (relative) to an edge end are at the end (v-v / v-e)
    feature_snap: float = 1e-6
    #: a new contact whose gap is below this (relative) touches and starts closed
    touching: float = 1e-9

    def length(self, name: str, scale: float) -> float:
        """Absolute length tolerance `name` for a model of size `scale` (m)."""
        return float(getattr(self, name)) * max(float(scale), 1e-12)


DEFAULT_TOLERANCES = Tolerances()
