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


#: the sidewall block: a prism on one joint dipping PSI towards the cavern (west) out of its
#: east wall (x = 3), released by a vertical back crack (x = 5), two vertical sides
#: (y = ±2) and a horizontal top (z = -0.5); the base through (3, 0, -2.5)
PSI = 30.0


def _rect(points: list[list[float]], grow: float = 1.3) -> list[list[float]]:
    p = np.asarray(points, float)
    return (p.mean(axis=0) + grow * (p - p.mean(axis=0))).tolist()


def sidewall_scene(friction: float, fall: float = 0.5) -> dict[str, Any]:
    """The sidewall block in the 6 m wide cavern of :func:`roof_wedge_scene` (no wedge);
    the base joint's friction angle `friction`, the release joints frictionless."""
    t = math.tan(math.radians(PSI))
    z3, z5 = -2.5, -2.5 + 2 * t  # the base at the wall and at the back crack
    base = _rect([[3, -2, z3], [5, -2, z5], [5, 2, z5], [3, 2, z3]])
    crack = _rect([[5, -2, z5], [5, 2, z5], [5, 2, -0.5], [5, -2, -0.5]])
    top = _rect([[3, -2, -0.5], [5, -2, -0.5], [5, 2, -0.5], [3, 2, -0.5]])
    sides = [_rect([[3, y, z3], [5, y, z5], [5, y, -0.5], [3, y, -0.5]]) for y in (-2, 2)]
    rel = {"joint_material": "release"}
    joints = [
        {"name": "base", "dip": PSI, "dip_direction": 270, "point": [3, 0, z3],
         "extent": {"polygon": base}, "joint_material": "slide"},
        {"name": "crack", "dip": 90, "dip_direction": 90, "point": [5, 0, -1],
         "extent": {"polygon": crack}, **rel},
        {"name": "top", "dip": 0, "dip_direction": 0, "point": [4, 0, -0.5],
         "extent": {"polygon": top}, **rel},
        {"name": "south", "dip": 90, "dip_direction": 180, "point": [4, -2, -1],
         "extent": {"polygon": sides[0]}, **rel},
        {"name": "north", "dip": 90, "dip_direction": 0, "point": [4, 2, -1],
         "extent": {"polygon": sides[1]}, **rel},
        {"name": "floor", "dip": 0, "dip_direction": 0, "point": [0, 0, -3]},
    ]
    return {
        "name": "sidewall block",
        "joint_materials": {"slide": {"friction_angle": friction},
                            "release": {"friction_angle": 0.0},
                            "rock": {"friction_angle": 45.0}},
        "default_joint_material": "rock",
        "domain": {"box": {"min": [-6, -6, -8], "max": [8, 6, 6]}},
        "joints": joints,
        "excavations": [{"name": "cavern",
                         "cavern": {"center": [0, 0, -1.5], "size": [14, 6, 3]}}],
        "boundary": {"fixed_blocks": [{"contains": [0, 0, -5]}]},
        "analysis": {"time_step": 2e-3, "record_interval": 10},
        "stages": [{"name": "settle", "duration": 0.05},
                   {"name": "excavate", "duration": fall, "excavate": ["cavern"]}],
    }
