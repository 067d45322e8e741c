"""Writes the planar-sliding scenes of docs/factor-of-safety.md (hand-worked in
tests/test_limit_equilibrium.py): `python examples/planar_cases.py`.

A 2 × 2 × 1 m block (2 m down-dip, 2 m along strike, 1 m thick; 2600 kg/m³, W = 102 024 N)
on a fixed slab dipping 35° to the east, with:

- planar_tendon: φ 38°, 10 kPa of water on the plane, a 70 kN constant-force tendon normal to
  the plane (issue 30's case: FS = (W cos α − U + T) tan φ / (W sin α) = 1.5163);
- planar_cohesion: φ 38°, c = 5 kPa over the 4 m² base (FS 1.4576);
- planar_tendon_angle: φ 30°, an active 25 kN constant-force tendon plunging 20° into the
  slope (55° to the plane; FS 1.3598);
- planar_bolt_passive: φ 30°, an untensioned bolt (3e7 N/m) of capacity 30 kN plunging 20°
  into the slope (Hoek & Bray's passive FS 1.3610; strength reduction's 1.5114);
- planar_seismic: φ 45°, kh 0.1 out of the slope and kv 0.1 upward (FS 1.1367);

and planar_crack_cohesion: examples/planar_tension_crack.json (Hoek & Bray's slope with a
water-filled tension crack) with c = 10 kPa on the sliding plane and none in the crack
(FS 1.4897).
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
DIP = math.radians(35.0)
DOWN = (math.cos(DIP), 0.0, -math.sin(DIP))   # down-dip (east, down)
ALONG = (0.0, 1.0, 0.0)                       # strike (north)
UP = (math.sin(DIP), 0.0, math.cos(DIP))      # normal to the plane, out of the slab
FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _point(a: float, b: float, c: float) -> list[float]:
    """The point a m down-dip, b m along strike and c m above the plane from the origin."""
    return [round(a * DOWN[k] + b * ALONG[k] + c * UP[k], 6) + 0.0 for k in range(3)]


def _box(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]
         ) -> list[list[float]]:
    """The 8 corners of a box in plane coordinates (order of FACES)."""
    return [_point(*p) for p in ((a[0], b[0], c[0]), (a[1], b[0], c[0]), (a[1], b[1], c[0]),
                                 (a[0], b[1], c[0]), (a[0], b[0], c[1]), (a[1], b[0], c[1]),
                                 (a[1], b[1], c[1]), (a[0], b[1], c[1]))]


def _tendon_direction(plunge_deg: float) -> list[float]:
    """A unit vector pointing west (into the slope) and `plunge_deg` below horizontal."""
    p = math.radians(plunge_deg)
    return [-math.cos(p), 0.0, -math.sin(p)]


def _bolt(name: str, direction: list[float], **props: Any) -> dict[str, Any]:
    """A bolt from the centre of the block's top face, 20 m along `direction`."""
    head = _point(1.0, 1.0, 1.0)
    anchor = [round(head[k] + 20.0 * direction[k], 6) for k in range(3)]
    return {"name": name, "head": head, "anchor": anchor, "block": "block", **props}


def block_on_plane(description: str, phi: float, **extra: Any) -> dict[str, Any]:
    """The block on the 35° slab with friction angle `phi` and the `extra` sections."""
    scene: dict[str, Any] = {
        "name": "", "description": description,
        "joint_materials": {"joint": {"friction_angle": phi}},
        "blocks": [
            {"name": "block", "vertices": _box((0, 2), (0, 2), (0, 1)), "faces": FACES},
            {"name": "slab", "vertices": _box((-2, 12), (-1, 3), (-2, 0)), "faces": FACES,
             "fixed": True},
        ],
        "analysis": {"type": "factor_of_safety", "duration": 1.0, "time_step": 0.002,
                     "factor_of_safety": {"observation_time": 1.0, "tolerance": 0.01}},
    }
    scene.update(extra)
    return scene


def crack_with_cohesion() -> dict[str, Any]:
    """examples/planar_tension_crack.json with c = 10 kPa on the sliding plane; the tension
    crack (the block pair slide-back) is a joint of its own with none."""
    scene = copy.deepcopy(json.loads((HERE / "planar_tension_crack.json").read_text()))
    scene["description"] = (
        "Hoek & Bray planar failure with a water-filled tension crack and cohesion: "
        "examples/planar_tension_crack.json (H 10 m, face 60 deg, plane 30 deg, crack 4 m "
        "deep with 3 m of water, phi 45 deg; 2 m wide) with c = 10 kPa on the sliding plane "
        "(A = 24 m2) and none in the crack. FS = (c A + (W cos psi - U - V sin psi) tan phi) "
        "/ (W sin psi + V cos psi) = 1.4897 (1.2890 with c = 0).")
    scene["joint_materials"] = {"joint": {"friction_angle": 45.0, "cohesion": 10000.0},
                                "crack": {"friction_angle": 45.0}}
    scene["default_joint_material"] = "joint"
    scene["block_pairs"] = [{"blocks": ["slide", "back"], "joint_material": "crack"}]
    return scene


def scenes() -> dict[str, dict[str, Any]]:
    """Every scene this writes, by file name."""
    down_west_20 = _tendon_direction(20.0)
    normal_in = [-x for x in UP]
    out = {
        "planar_tendon": block_on_plane(
            "Issue 30's tendon case: a 2 x 2 x 1 m block on a 35 deg plane, phi 38 deg, 10 kPa "
            "of water on the plane (U = 40 kN), a 70 kN constant-force tendon (axial_stiffness "
            "0) normal to the plane. FS = (W cos a - U + T) tan phi / (W sin a) = 1.5163.",
            38.0, water={"joint_pressures": [{"joint_material": "joint",
                                              "pressure": 10000.0}]},
            bolts=[_bolt("T1", normal_in, axial_stiffness=0.0, pretension=70000.0)]),
        "planar_cohesion": block_on_plane(
            "A 2 x 2 x 1 m block on a 35 deg plane, phi 38 deg, c 5 kPa over its 4 m2 base. "
            "FS = (c A + W cos a tan phi) / (W sin a) = 1.4576 (1.1158 with c = 0).",
            38.0, joint_materials={"joint": {"friction_angle": 38.0, "cohesion": 5000.0}}),
        "planar_tendon_angle": block_on_plane(
            "A 2 x 2 x 1 m block on a 35 deg plane, phi 30 deg (FS 0.8245 alone), held by an "
            "active 25 kN constant-force tendon plunging 20 deg into the slope (55 deg to the "
            "plane). FS = (W cos a + T sin 55) tan phi / (W sin a - T cos 55) = 1.3598.",
            30.0, bolts=[_bolt("T1", down_west_20, axial_stiffness=0.0, pretension=25000.0)]),
        "planar_bolt_passive": block_on_plane(
            "A 2 x 2 x 1 m block on a 35 deg plane, phi 30 deg, held by an untensioned bolt "
            "(3e7 N/m) of capacity 30 kN plunging 20 deg into the slope (55 deg to the plane). "
            "Passive (Hoek & Bray, Wyllie & Mah): FS = ((W cos a + C sin 55) tan phi + C cos "
            "55) / (W sin a) = 1.3610; strength reduction divides only the joint: F = (W cos a "
            "+ C sin 55) tan phi / (W sin a - C cos 55) = 1.5114.",
            30.0, bolts=[_bolt("B1", down_west_20, axial_stiffness=3e7, capacity=30000.0)]),
        "planar_seismic": block_on_plane(
            "A 2 x 2 x 1 m block on a 35 deg plane, phi 45 deg, pseudo-static kh 0.1 out of the "
            "slope (east) and kv 0.1 upward. FS = ((1 - kv) cos a - kh sin a) tan phi / "
            "((1 - kv) sin a + kh cos a) = 1.1367.",
            45.0, seismic={"kh": 0.1, "azimuth": 90.0, "kv": 0.1}),
        "planar_crack_cohesion": crack_with_cohesion(),
    }
    for name, scene in out.items():
        scene["name"] = name
    return out


def main() -> None:
    for name, scene in scenes().items():
        (HERE / f"{name}.json").write_text(json.dumps(scene, indent=2) + "\n")
        print(f"wrote examples/{name}.json")


if __name__ == "__main__":
    main()
