"""`polydda keyblocks`: the key blocks of a scene's excavations (Goodman & Shi's block
theory, the table Unwedge gives) and, given the run's result, what the DDA did to each."""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

import numpy as np

from engine.analyses.keyblocks import key_blocks
from engine.geometry.excavations import EXCAVATION_TAG_BASE
from engine.geometry.polyhedron import FACE_TAG_BOUNDARY
from engine.model import JointMaterial
from service.cli.common import EXIT_IO, EXIT_OK, EXIT_SCENE, load_scene, print_json

#: the DDA says a block moved when its final displacement exceeds this fraction of its
#: size (the cube root of its volume)
MOVED_RATIO = 0.01


def _stage_of(build: Any, excavation: str) -> int:
    """The stage that digs `excavation` (0 without stages; len(stages): never)."""
    dug = {k for k, o in enumerate(build.excavated) if o == excavation}
    return next((s for s, st in enumerate(build.stages) if dug & st.removed),
                len(build.stages) if build.stages else 0)


def _joint_materials(build: Any, excavation: str) -> list[JointMaterial]:
    """The joint materials in force when `excavation` is dug (its stage's, else the
    scene's)."""
    s = _stage_of(build, excavation)
    if s < len(build.stages):
        return list(build.stages[s].joint_materials or build.model.joint_materials)
    return list(build.model.joint_materials)


def _free_tags(build: Any, excavation: str) -> set[int]:
    """Faces that touch nothing when `excavation` is dug: the domain's outer surface and
    the surfaces of the openings dug by then."""
    s = _stage_of(build, excavation)
    return {FACE_TAG_BOUNDARY} | {EXCAVATION_TAG_BASE + k for k, e in
                                  enumerate(build.excavation_names) if _stage_of(build, e) <= s}


def _tag_name(build: Any, tag: int) -> str:
    """A face tag as the scene names it."""
    if 0 <= tag < len(build.joint_names):
        return build.joint_names[tag]
    if tag >= EXCAVATION_TAG_BASE and tag - EXCAVATION_TAG_BASE < len(build.excavation_names):
        return f"the surface of {build.excavation_names[tag - EXCAVATION_TAG_BASE]}"
    return "the domain's surface" if tag < 0 else f"tag {tag}"


def keyblock_document(build: Any, result: Any = None) -> dict[str, Any]:
    """`{"excavations": [{"name", "blocks": [...]}]}`: per exposed block its name,
    removability, mode, sliding planes (joint names), factor of safety, weight (N) and,
    with a result, its final displacement (m) and whether the DDA moved it."""
    m = build.model
    final = None if result is None else result.summary.get("blocks")
    dens = np.array([m.materials[b.material].density for b in m.blocks])
    skip = {k for k, o in enumerate(build.excavated) if o is not None}
    out = []
    for k, name in enumerate(_surface_names(build)):
        jm = _joint_materials(build, name)
        strength = {tag: (math.tan(jm[j].friction_angle_rad), jm[j].cohesion)
                    for tag, j in m.joint_material_of_tag.items()}
        dj = jm[m.default_joint_material]
        table = key_blocks([b.polyhedron for b in m.blocks], dens, m.body_acceleration,
                           {EXCAVATION_TAG_BASE + k}, strength,
                           (math.tan(dj.friction_angle_rad), dj.cohesion), skip,
                           _free_tags(build, name))
        rows = []
        for kb in table:
            row = {"block": build.block_names[kb.block], "removable": kb.removable,
                   "mode": kb.mode, "planes": [_tag_name(build, t) for t in kb.planes],
                   "factor_of_safety": None if math.isinf(kb.factor_of_safety)
                   else kb.factor_of_safety, "weight": kb.weight}
            if final is not None:
                d = float(np.linalg.norm(final[kb.block]["displacement"]))
                size = m.blocks[kb.block].polyhedron.volume ** (1 / 3)
                row |= {"displacement": d, "dda": "moved" if d > MOVED_RATIO * size
                        else "stayed"}
            rows.append(row)
        out.append({"name": name, "blocks": rows})
    return {"excavations": out}


def _surface_names(build: Any) -> list[str]:
    """The scene's excavation names in order (index k carries tag EXCAVATION_TAG_BASE + k)."""
    return list(build.excavation_names)


def keyblock_text(doc: dict[str, Any]) -> str:
    """The key-block table as text, one line per block."""
    lines = []
    for exc in doc["excavations"]:
        lines.append(f"{exc['name']}: {len(exc['blocks'])} block(s) on its surface")
        for r in exc["blocks"]:
            fs = "-" if r["factor_of_safety"] is None else f"{r['factor_of_safety']:.3g}"
            planes = f" on {', '.join(r['planes'])}" if r["planes"] else ""
            dda = (f"; DDA: {r['dda']} ({r['displacement']:.3g} m)" if "dda" in r else "")
            lines.append(f"  {r['block']}: {'removable' if r['removable'] else 'not removable'}"
                         f", {r['mode']}{planes}, FS {fs}, weight {r['weight'] / 1e3:.4g} kN"
                         f"{dda}")
    return "\n".join(lines)


def cmd_keyblocks(args: argparse.Namespace) -> int:
    """Print the key-block table of the scene's excavations (with --result, the DDA's
    verdict on each block)."""
    build = load_scene(args.scene, quiet=args.json)
    result = None
    if args.result:
        from engine.results.reader import open_result

        try:
            result = open_result(args.result)
        except (OSError, ValueError) as exc:
            print(f"--result: cannot read {args.result}: {exc}", file=sys.stderr)
            return EXIT_IO
        if len(result.summary.get("blocks", [])) != len(build.model.blocks):
            print("--result: the result's blocks are not this scene's", file=sys.stderr)
            return EXIT_SCENE
    doc = keyblock_document(build, result)
    if args.json:
        print_json(doc)
    else:
        print(keyblock_text(doc) or "the scene has no excavations")
    return EXIT_OK
