"""The builder's preview of a scene: its blocks cut as `polydda blocks` cuts them, as
meshes for the browser, each with its key-block verdict and kinematic mode (block theory,
engine.analyses.keyblocks) before anything runs.

Which faces are free: with excavations, their surfaces (every opening dug; the domain's
outer faces are rock that goes on); without, the ground: the domain's outer faces that face
upwards (a slope's face, benches and crest, a terrain's surface, a box's top). Fixed and
excavated blocks are not analysed. Runs in the API's scene-checking processes
(service.api.validation), within their time limit.
"""

from __future__ import annotations

import base64
import math
import time
from typing import Any

import numpy as np

#: a free face of the ground faces upwards more than this (the z of its outward normal)
UP = 0.05
#: a free face's tag for the key-block analysis (no joint or excavation has it)
_FREE = -1_000

#: verdicts, in the legend's order
VERDICTS = ("key block", "potential key block", "not removable", "interior", "fixed",
            "excavated")
#: kinematic modes, in the legend's order
MODES = ("falling", "sliding on two planes", "sliding on one plane", "stable", "interior",
         "fixed", "excavated")


def _free_faces(build: Any, st: Any) -> list[Any]:
    """The blocks' polyhedra with their free faces tagged `_FREE` (the others as they
    are); `st` is the model's flattened surface (engine.results.layout.flatten_model), whose
    faces' normals are worked out here in one pass (Newell's method)."""
    from engine.geometry.excavations import EXCAVATION_TAG_BASE
    from engine.geometry.polyhedron import FACE_TAG_BOUNDARY, Polyhedron

    tags = np.asarray(st.face_tags)
    if build.excavation_names:
        free = tags >= EXCAVATION_TAG_BASE
    else:
        x, off, conn = st.vertices, st.face_offsets, st.face_connectivity
        nxt = np.arange(len(conn)) + 1
        nxt[off[1:] - 1] = off[:-1]
        cross = np.cross(x[conn], x[conn[nxt]])
        normal = np.add.reduceat(cross, off[:-1], axis=0) if len(conn) else cross
        up = normal[:, 2] > UP * np.linalg.norm(normal, axis=1)
        free = (tags == FACE_TAG_BOUNDARY) & up
    out = []
    fb = st.face_block_offsets
    for k, block in enumerate(build.model.blocks):
        p = block.polyhedron
        mask = free[fb[k]:fb[k + 1]]
        if not mask.any():
            out.append(p)  # nothing of it is free: as it is
            continue
        q = Polyhedron(p.vertices, p.face_indptr, p.face_indices,
                       np.where(mask, _FREE, p.face_tags), p.pieces)
        # the same shape: what it has worked out already (normals, mass) holds for the copy
        q.__dict__.update({k: v for k, v in p.__dict__.items() if k.startswith("_")})
        out.append(q)
    return out


def key_block_table(build: Any, st: Any = None) -> tuple[list[str], list[str],
                                                         list[float | None]]:
    """Each block's verdict, mode and factor of safety (None: none) in the preview (`st`:
    the model's flattened surface, made here when not given)."""
    from engine.analyses.keyblocks import key_blocks
    from engine.results.layout import flatten_model

    st = flatten_model(build.model) if st is None else st

    m = build.model
    n = len(m.blocks)
    verdict, mode = ["interior"] * n, ["interior"] * n
    fs: list[float | None] = [None] * n
    skip = set()
    for k, b in enumerate(m.blocks):
        if build.excavated[k] is not None:
            verdict[k] = mode[k] = "excavated"
            skip.add(k)
        elif b.fixed:
            verdict[k] = mode[k] = "fixed"
            skip.add(k)
    jm = m.joint_materials
    strength = {tag: (math.tan(jm[j].friction_angle_rad), jm[j].cohesion)
                for tag, j in m.joint_material_of_tag.items()}
    dj = jm[m.default_joint_material]
    density = np.array([m.materials[b.material].density for b in m.blocks])
    for kb in key_blocks(_free_faces(build, st), density, m.body_acceleration, {_FREE},
                         strength, (math.tan(dj.friction_angle_rad), dj.cohesion), skip):
        k = kb.block
        mode[k] = kb.mode
        finite = math.isfinite(kb.factor_of_safety)
        fs[k] = float(kb.factor_of_safety) if finite else None
        if not kb.removable:
            verdict[k] = "not removable"
        elif kb.mode != "stable" and finite and kb.factor_of_safety < 1.0:
            verdict[k] = "key block"
        else:
            verdict[k] = "potential key block"
    return verdict, mode, fs


def preview_document(scene_text: str) -> dict[str, Any]:
    """The preview of a scene (JSON text): `blocks` (name, fixed, volume, verdict, mode,
    factor of safety), the `mesh` (`vertices` relative to `origin`, `vertex_offsets`,
    `triangles`, `triangle_block`, `edges`: each `{dtype, data}`, little-endian arrays in
    base64), `extent`, `warnings`, `timings` (s). SceneError when the scene does not
    build."""
    import json

    from engine.results.layout import flatten_model
    from schemas.convert import build_model
    from schemas.scene import Scene
    from service.api.frames import triangulate

    t0 = time.perf_counter()
    build = build_model(Scene.model_validate(json.loads(scene_text)))
    t1 = time.perf_counter()
    st = flatten_model(build.model)
    verdict, mode, fs = key_block_table(build, st)
    t2 = time.perf_counter()
    mesh = {"vertices": st.vertices, "face_offsets": st.face_offsets,
            "face_connectivity": st.face_connectivity,
            "face_block_offsets": st.face_block_offsets}
    tris, tri_block, edges = triangulate(mesh, len(build.model.blocks))
    x = st.vertices
    lo, hi = (x.min(axis=0), x.max(axis=0)) if len(x) else (np.zeros(3), np.zeros(3))
    origin = (lo + hi) / 2
    blocks = [{"name": name, "fixed": bool(b.fixed), "volume": round(float(
                   b.polyhedron.volume), 6), "verdict": verdict[k], "mode": mode[k],
               "factor_of_safety": None if fs[k] is None else round(fs[k], 4),
               "excavation": build.excavated[k]}
              for k, (name, b) in enumerate(zip(build.block_names, build.model.blocks,
                                                strict=True))]
    mesh_arrays = {"vertices": (x - origin).astype("<f4"),
                   "vertex_offsets": st.vertex_offsets.astype("<u4"),
                   "triangles": tris.astype("<u4"), "triangle_block": tri_block.astype("<u4"),
                   "edges": edges.astype("<u4")}
    t3 = time.perf_counter()
    return {"count": len(blocks), "blocks": blocks, "origin": origin.tolist(),
            "extent": (hi - lo).tolist(),
            # little-endian float32 / uint32 arrays, base64: a tenth of the time of JSON lists
            "mesh": {k: {"dtype": str(a.dtype.name), "data": base64.b64encode(
                a.tobytes()).decode()} for k, a in mesh_arrays.items()},
            "warnings": list(build.warnings),
            "verdicts": list(VERDICTS), "modes": list(MODES),
            "timings": {"cut": round(t1 - t0, 3), "key_blocks": round(t2 - t1, 3),
                        "mesh": round(t3 - t2, 3)}}
