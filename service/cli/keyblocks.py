"""`polydda keyblocks`: the key blocks of a scene's excavations (Goodman & Shi's block
theory, the table Unwedge gives) and, given the run's result, what the DDA did to each."""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

import numpy as np

from engine.analyses.keyblocks import Motion, key_blocks, recorded_motion
from engine.geometry.excavations import EXCAVATION_TAG_BASE
from engine.geometry.polyhedron import FACE_TAG_BOUNDARY
from engine.model import JointMaterial
from service import readable as rd
from service.cli.common import (
    EXIT_OK,
    EXIT_SCENE,
    load_scene,
    open_result_file,
    print_json,
)
from service.documents import AT_REST_SPEED

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


def _release_time(build: Any, excavation: str) -> float:
    """When `excavation` is dug: the start of its stage (0 without stages)."""
    s = _stage_of(build, excavation)
    return build.stages[s - 1].end_time if 0 < s <= len(build.stages) else 0.0


def _radius(poly: Any) -> float:
    """The largest distance of a block's vertex from its centroid (m)."""
    return float(np.max(np.linalg.norm(poly.vertices - poly.centroid, axis=1)))


def _motions(build: Any, result: Any, blocks: list[int], release: float
             ) -> dict[int, Motion]:
    """What the recorded run did to each of `blocks` after `release` (s): its history of
    displacement and speed (a point's: translation plus rotation times the block's radius)
    judged as a strength-reduction trial is judged at its end."""
    out: dict[int, Motion] = {}
    for b in blocks:
        h = result.block_history(b)
        poly = build.model.blocks[b].polyhedron
        v = np.asarray(h["velocity"], float)
        speed = (np.linalg.norm(v[:, :3], axis=1)
                 + np.linalg.norm(v[:, 3:6], axis=1) * _radius(poly))
        out[b] = recorded_motion(h["time"], h["displacement"], speed, release,
                                 MOVED_RATIO * poly.volume ** (1 / 3), AT_REST_SPEED)
    return out


def keyblock_document(build: Any, result: Any = None) -> dict[str, Any]:
    """`{"excavations": [{"name", "blocks": [...]}]}`: per exposed free block (a fixed
    block is the rock mass beyond the model, never a key block) its name, removability,
    mode, sliding planes (joint names), factor of safety, weight (N) and, with a result,
    what the run did to it after the excavation: displacement since then (m), speed at the
    end (m/s) and the verdict ("stayed", "moved, then stopped", "still moving at the
    end")."""
    m = build.model
    dens = np.array([m.materials[b.material].density for b in m.blocks])
    skip = {k for k, o in enumerate(build.excavated) if o is not None}
    fixed = {k for k, b in enumerate(m.blocks) if b.fixed}
    out = []
    for k, name in enumerate(_surface_names(build)):
        jm = _joint_materials(build, name)
        strength = {tag: (math.tan(jm[j].friction_angle_rad), jm[j].cohesion)
                    for tag, j in m.joint_material_of_tag.items()}
        dj = jm[m.default_joint_material]
        table = key_blocks([b.polyhedron for b in m.blocks], dens, m.body_acceleration,
                           {EXCAVATION_TAG_BASE + k}, strength,
                           (math.tan(dj.friction_angle_rad), dj.cohesion), skip,
                           _free_tags(build, name), fixed)
        motion = ({} if result is None else
                  _motions(build, result, [kb.block for kb in table],
                           _release_time(build, name)))
        rows = []
        for kb in table:
            row = {"block": build.block_names[kb.block], "removable": kb.removable,
                   "mode": kb.mode, "planes": [_tag_name(build, t) for t in kb.planes],
                   "factor_of_safety": None if math.isinf(kb.factor_of_safety)
                   else kb.factor_of_safety, "weight": kb.weight}
            if kb.block in motion:
                mo = motion[kb.block]
                row |= {"displacement": mo.displacement, "speed": mo.speed,
                        "peak_speed": mo.peak_speed, "watched_time": mo.watched,
                        "dda": mo.verdict}
            rows.append(row)
        out.append({"name": name, "blocks": rows})
    return {"excavations": out}


def _surface_names(build: Any) -> list[str]:
    """The scene's excavation names in order (index k carries tag EXCAVATION_TAG_BASE + k)."""
    return list(build.excavation_names)


def keyblock_text(doc: dict[str, Any]) -> str:
    """The key-block table as text, one line per block, and the verdict last."""
    lines = []
    for exc in doc["excavations"]:
        lines.append(f"{exc['name']}: {rd.plural(len(exc['blocks']), 'free block')} on its "
                     "surface")
        for r in exc["blocks"]:
            fs = "-" if r["factor_of_safety"] is None else rd.number(r["factor_of_safety"], 3)
            planes = f" on {', '.join(r['planes'])}" if r["planes"] else ""
            dda = ""
            if "dda" in r:
                dda = f"; DDA: {r['dda']} ({rd.length(r['displacement'])}"
                dda += (f", {rd.number(r['speed'], 3)} m/s after "
                        f"{rd.seconds(r['watched_time'])})"
                        if r["dda"] == "still moving at the end" else ")")
            lines.append(f"  {r['block']}: {'removable' if r['removable'] else 'not removable'}"
                         f", {r['mode']}{planes}, FS {fs}, weight {rd.force(r['weight'])}"
                         f"{dda}")
    if lines:
        lines.append(keyblock_verdict(doc))
    return "\n".join(lines)


def keyblock_verdict(doc: dict[str, Any]) -> str:
    """The last line: without a result, the key blocks (removable, FS < 1) and the lowest
    FS it rests on; with one, what the run shows: blocks still moving at the end (not
    stable), or every block stopped (key blocks held by their neighbours)."""
    rows = [(exc["name"], r) for exc in doc["excavations"] for r in exc["blocks"]]
    keys = [(e, r) for e, r in rows if r["removable"] and r["factor_of_safety"] is not None
            and r["factor_of_safety"] < 1.0]
    finite = [(e, r) for e, r in rows if r["removable"] and r["factor_of_safety"] is not None]
    low = min(finite, key=lambda x: x[1]["factor_of_safety"]) if finite else None
    low_text = ("" if low is None else f"lowest FS {rd.number(low[1]['factor_of_safety'], 3)}"
                f" ({low[1]['block']}, {low[0]})")
    names = ", ".join(r["block"] for _, r in keys)
    if any("dda" in r for _, r in rows):  # the run's verdict
        moving = [r["block"] for _, r in rows if r.get("dda") == "still moving at the end"]
        moved = [r["block"] for _, r in rows if r.get("dda") == "moved, then stopped"]
        if moving:
            return (f"Verdict: not stable — the run shows {', '.join(moving)} still moving at "
                    f"the end" + (f"; {low_text}" if low_text else ""))
        fs = "" if low is None else rd.number(low[1]["factor_of_safety"], 3)
        held = (f"; key block{'s' if len(keys) > 1 else ''} {names} (lowest FS {fs} < 1 on "
                "its own) held by the blocks around" if keys
                else f"; {low_text}" if low_text else "")
        return ("Verdict: stable in the run — every block stopped"
                + (f" ({', '.join(moved)} after moving)" if moved else "") + held)
    if keys:
        fs = rd.number(low[1]["factor_of_safety"], 3) if low is not None else "?"
        return (f"Verdict: not stable — {rd.plural(len(keys), 'key block')} ({names}): "
                f"lowest FS {fs} < 1 ({low[1]['block'] if low else '?'}, "
                f"{low[0] if low else '?'})")
    if low is not None:
        return f"Verdict: stable — no key block; {low_text}"
    return "Verdict: stable — no removable block can move under its weight"


def cmd_keyblocks(args: argparse.Namespace) -> int:
    """Print the key-block table of the scene's excavations (with --result, the DDA's
    verdict on each block)."""
    build = load_scene(args.scene, quiet=args.json)
    result = None
    if args.result:
        result = open_result_file("keyblocks --result", args.result)
        if isinstance(result, int):
            return result
        if len((result.summary or {}).get("blocks", [])) != len(build.model.blocks):
            print(f"polydda keyblocks --result: the blocks of {args.result} are not those of "
                  f"{args.scene}", file=sys.stderr)
            result.close()
            return EXIT_SCENE
    try:
        doc = keyblock_document(build, result)
    finally:
        if result is not None:
            result.close()
    if args.json:
        print_json(doc)
    else:
        print(keyblock_text(doc) or "the scene has no excavations")
    return EXIT_OK
