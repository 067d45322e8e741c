"""Planar sliding scenes as a new user writes them (scene JSON): a 2 × 2 × 1 m block on a
fixed slab dipping `dip` degrees to the east, with a friction angle, cohesion, pseudo-static
seismic coefficients, water and a removable prop, for any contact solver. Their hand-worked
answers (Hoek & Bray) are in :func:`planar_fs` and :func:`critical_kh`."""

from __future__ import annotations

import math
from typing import Any

from schemas.convert import build_model

#: 2600 kg/m³ × 4 m³ × 9.81 m/s² (N): the block's weight
WEIGHT = 2600.0 * 4.0 * 9.81
#: the base's area (m²)
AREA = 4.0
FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _frame(dip: float) -> tuple[tuple[float, ...], ...]:
    """Down-dip, along-strike and out-of-plane unit vectors of a plane dipping east."""
    a = math.radians(dip)
    return ((math.cos(a), 0.0, -math.sin(a)), (0.0, 1.0, 0.0), (math.sin(a), 0.0, math.cos(a)))


def _box(dip: float, a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]
         ) -> list[list[float]]:
    """The 8 corners of a box in plane coordinates (down-dip, strike, normal), in the
    order of FACES."""
    down, along, up = _frame(dip)

    def point(x: float, y: float, z: float) -> list[float]:
        return [round(x * down[k] + y * along[k] + z * up[k], 9) + 0.0 for k in range(3)]

    return [point(*p) for p in ((a[0], b[0], c[0]), (a[1], b[0], c[0]), (a[1], b[1], c[0]),
                                (a[0], b[1], c[0]), (a[0], b[0], c[1]), (a[1], b[0], c[1]),
                                (a[1], b[1], c[1]), (a[0], b[1], c[1]))]


def planar_block(dip: float, phi: float, solver: str, cohesion: float = 0.0,
                 kh: float = 0.0, kv: float = 0.0, time_step: float = 0.01,
                 prop: bool = False, **extra: Any) -> dict[str, Any]:
    """The scene: the block on the slab (a factor-of-safety analysis by default); with
    `prop`, a fixed prop against its down-dip face that a stage can excavate."""
    joint: dict[str, Any] = {"friction_angle": phi}
    if cohesion:
        joint["cohesion"] = cohesion
    blocks = [
        {"name": "block", "vertices": _box(dip, (0, 2), (0, 2), (0, 1)), "faces": FACES},
        {"name": "slab", "vertices": _box(dip, (-2, 14), (-1, 3), (-2, 0)), "faces": FACES,
         "fixed": True},
    ]
    if prop:
        blocks.append({"name": "prop", "vertices": _box(dip, (2, 3), (0, 2), (0, 1)),
                       "faces": FACES, "fixed": True})
    scene: dict[str, Any] = {
        "name": f"planar {dip:g}/{phi:g}", "joint_materials": {"joint": joint},
        "blocks": blocks,
        "analysis": {"type": "factor_of_safety", "duration": 1.0, "time_step": time_step,
                     "contact_solver": solver,
                     "factor_of_safety": {"observation_time": 1.0, "tolerance": 0.005}},
    }
    if kh or kv:
        scene["seismic"] = {"kh": kh, "kv": kv, "azimuth": 90.0}
    scene.update(extra)
    return scene


def planar_fs(dip: float, phi: float, cohesion: float = 0.0, kh: float = 0.0,
              kv: float = 0.0) -> float:
    """Hoek & Bray's factor of safety of the block: (c A + W' cos − kh W sin) tan φ over
    (W' sin + kh W cos), W' = (1 − kv) W; kh out of the slope, kv upward."""
    a, t = math.radians(dip), math.tan(math.radians(phi))
    w = (1.0 - kv) * WEIGHT
    normal = w * math.cos(a) - kh * WEIGHT * math.sin(a)
    return (cohesion * AREA + normal * t) / (w * math.sin(a) + kh * WEIGHT * math.cos(a))


def critical_kh(dip: float, phi: float) -> float:
    """The horizontal seismic coefficient at which the dry, cohesionless block slides:
    tan(φ − α)."""
    return math.tan(math.radians(phi - dip))


def sliding_acceleration(dip: float, phi: float) -> float:
    """The down-dip acceleration (m/s²) of the block sliding on its base: g (sin α − cos α
    tan φ)."""
    a = math.radians(dip)
    return 9.81 * (math.sin(a) - math.cos(a) * math.tan(math.radians(phi)))


def model_of(scene: dict[str, Any]) -> Any:
    """The engine model of a scene (:func:`schemas.convert.build_model`)."""
    return build_model(scene).model
