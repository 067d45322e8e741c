"""`polydda stereonet MEASUREMENTS.csv`: measured dip / dip direction of joints, as in Dips —
the pole density contoured on the stereonet, the sets picked (k-means on the sphere) with
their Fisher mean and κ, written as a scene's joints and the sweep's Fisher parameters."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from schemas.errors import SceneError
from service.cli.common import EXIT_IO, EXIT_OK, print_json
from service.documents import parse_measurements


def read_measurements(path: Path) -> tuple[list[float], list[float]]:
    """Dips and dip directions (degrees) from a CSV file
    (:func:`service.documents.parse_measurements`: a header naming the columns, or two
    numeric columns). SceneError naming the line of any bad value."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise SceneError([{"loc": "", "msg": f"{path}: file not found"}]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError([{"loc": "", "msg": f"{path}: cannot read ({exc})"}]) from None
    return parse_measurements(text, str(path))


def joints_and_sweep(sets: list[Any], spacing: float | None, point: list[float]
                     ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The fitted sets as a scene's joints (mean dip and dip direction to 0.1°) and as the
    sweep's Fisher parameters of their orientation (κ to 0.1)."""
    joints, sweep = [], {}
    for s in sets:
        joint: dict[str, Any] = {"name": s.name, "dip": round(s.dip, 1),
                                 "dip_direction": round(s.dip_direction, 1) % 360.0,
                                 "point": point}
        if spacing is not None:
            joint["spacing"] = spacing
        joints.append(joint)
        if math.isfinite(s.kappa) and s.kappa > 0:
            sweep[f"{s.name}_orientation"] = {"quantity": "joint_orientation",
                                              "distribution": "fisher",
                                              "kappa": round(s.kappa, 1), "joint": s.name}
    return joints, sweep


def scene_with_sets(scene: dict[str, Any], joints: list[dict[str, Any]],
                    sweep: dict[str, Any] | None) -> dict[str, Any]:
    """`scene` with the measured sets: a joint of the same name takes the set's mean
    orientation (its point, spacing and extent kept), the others are added; with `sweep`,
    the Fisher parameters join the scene's sweep.parameters."""
    out = dict(scene)
    given = [dict(j) for j in scene.get("joints") or []]
    by_name = {j.get("name"): j for j in given}
    for j in joints:
        if j["name"] in by_name:
            by_name[j["name"]].update(dip=j["dip"], dip_direction=j["dip_direction"])
        else:
            given.append(j)
    out["joints"] = given
    if sweep:
        section = dict(scene.get("sweep") or {})
        section["parameters"] = {**(section.get("parameters") or {}), **sweep}
        out["sweep"] = section
    return out


def _domain_centre(scene: dict[str, Any]) -> list[float]:
    """The centre of the scene's domain box (or of its polyhedron's bounding box): where
    the joints added go through. The origin without a domain."""
    domain = scene.get("domain") or {}
    box = domain.get("box")
    if isinstance(box, dict) and "min" in box and "max" in box:
        lo, hi = box["min"], box["max"]
    elif (domain.get("polyhedron") or {}).get("vertices"):
        vs = domain["polyhedron"]["vertices"]
        lo = [min(v[i] for v in vs) for i in range(3)]
        hi = [max(v[i] for v in vs) for i in range(3)]
    else:
        return [0.0, 0.0, 0.0]
    return [round(0.5 * (a + b), 6) for a, b in zip(lo, hi, strict=True)]


def cmd_stereonet(args: argparse.Namespace) -> int:
    """Measured orientations: the sets, their Fisher statistics, the contoured stereonet;
    with --scene / --out, a scene with them as joints (and --sweep: Fisher parameters)."""
    from engine.analyses.orientations import fit_sets, plot_pole_density
    from schemas.scene import load_scene

    source = Path(args.measurements)
    dips, ddirs = read_measurements(source)
    names = [n.strip() for n in args.names.split(",")] if args.names else None
    if names is not None and len(names) != args.sets:
        raise SceneError([{"loc": "--names", "msg": f"{len(names)} names for {args.sets} sets"}])
    if not 1 <= args.sets <= len(dips):
        raise SceneError([{"loc": "--sets", "msg": f"cannot pick {args.sets} sets from "
                           f"{len(dips)} measurements"}])
    if (args.scene is None) != (args.out is None):
        raise SceneError([{"loc": "--scene", "msg": "give --scene and --out together"}])
    sets, labels = fit_sets(dips, ddirs, args.sets, seed=args.seed, names=names)
    scene = None
    if args.scene is not None:
        from schemas.scene import read_json

        scene = read_json(args.scene)
        if not isinstance(scene, dict):
            raise SceneError([{"loc": "--scene", "msg": f"{args.scene}: a scene must be a "
                               "JSON object {...}"}])
    joints, sweep = joints_and_sweep(sets, args.spacing, _domain_centre(scene or {}))
    plot = Path(args.plot) if args.plot else source.with_name(f"{source.stem}_stereonet.png")
    try:
        plot_pole_density(dips, ddirs, sets, labels, plot, title=source.stem)
    except OSError as exc:
        print(f"--plot: cannot write {plot}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_IO
    if scene is not None:
        new = scene_with_sets(scene, joints, sweep if args.sweep else None)
        load_scene(new)  # the scene written must be valid (SceneError: exit 2)
        out = Path(args.out)
        try:
            out.write_text(json.dumps(new, indent=2) + "\n", encoding="utf-8")
        except OSError as exc:
            print(f"--out: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_IO
    doc = {"measurements": len(dips), "sets": [s.as_dict() for s in sets], "joints": joints,
           "sweep_parameters": sweep, "plot": str(plot)}
    if args.json:
        print_json(doc)
        return EXIT_OK
    print(f"{len(dips)} measurements, {len(sets)} sets (k-means on the poles, seed "
          f"{args.seed}):")
    print(f"  {'set':<10} {'dip/dip direction':>17}  {'κ':>7}  {'poles':>5}  α95 (cone)")
    for s in sets:
        print(f"  {s.name:<10} {f'{s.dip:.1f}/{s.dip_direction:05.1f}':>17}  "
              f"{s.kappa:>7.1f}  {s.count:>5}  {s.cone_95:.1f}°")
    print(f"written: {plot}")
    if scene is not None:
        print(f"written: {args.out} (joints {', '.join(j['name'] for j in joints)}"
              + (f"; sweep parameters {', '.join(sweep)})" if args.sweep else ")"))
    return EXIT_OK
