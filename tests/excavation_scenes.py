"""Scenes of the excavation and stage tests, with the numbers derived by hand."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: the roof wedge: three joints dipping DELTA towards 0°, 120° and 240° through the apex
#: H m above a flat roof at z = 0. Each meets the roof on a line r = H / tan(DELTA) from
#: the axis, so the base is the equilateral triangle of inradius r (circumradius 2 r,
#: area 3√3 r²) and the volume is area × H / 3 = √3 r² H
H, DELTA = 2.0, 60.0
R_IN = H / math.tan(math.radians(DELTA))
WEDGE_VOLUME = math.sqrt(3.0) * R_IN**2 * H  # 8/√3 = 4.6188 m³ for H = 2, δ = 60°


def _az(a: float, r: float) -> list[float]:
    """The point at azimuth `a` degrees, `r` m from the axis, on the roof (z = 0)."""
    return [r * math.sin(math.radians(a)), r * math.cos(math.radians(a)), 0.0]


def roof_wedge_scene(friction: float = 30.0, settle: float = 0.1, fall: float = 0.5
                     ) -> dict[str, Any]:
    """A 12 m block of rock on a fixed base (joint at z = -3), a box cavern 6 m wide and
    3 m high along y (roof z = 0), and the tetrahedral roof wedge; stages: settle, then
    excavate."""
    apex = np.array([0.0, 0.0, H])
    joints = []
    for k, dd in enumerate((0.0, 120.0, 240.0)):
        tri = np.array([apex, _az(dd - 60, 2 * R_IN), _az(dd + 60, 2 * R_IN)])
        big = tri.mean(axis=0) + 1.3 * (tri - tri.mean(axis=0))
        joints.append({"name": f"W{k + 1}", "dip": DELTA, "dip_direction": dd,
                       "point": apex.tolist(), "extent": {"polygon": big.tolist()}})
    joints.append({"name": "floor", "dip": 0.0, "dip_direction": 0.0, "point": [0, 0, -3]})
    return {
        "name": "roof wedge",
        "joint_materials": {"joint": {"friction_angle": friction}},
        "domain": {"box": {"min": [-6, -6, -8], "max": [6, 6, 6]}},
        "joints": joints,
        "excavations": [{"name": "cavern",
                         "cavern": {"center": [0, 0, -1.5], "size": [14, 6, 3]}}],
        "boundary": {"fixed_blocks": [{"contains": [0, 0, -5]}]},
        "analysis": {"time_step": 2e-3, "record_interval": 5},
        "stages": [{"name": "settle", "duration": settle},
                   {"name": "excavate", "duration": fall, "excavate": ["cavern"]}],
    }
