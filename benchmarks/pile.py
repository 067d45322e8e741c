"""Many-block scenes: the piles shared with other engines (benchmarks/scenes/pile_N.json.gz,
copied into the repository byte for byte) and a cut rock mass."""

from __future__ import annotations

import gzip
import json
from pathlib import Path
from typing import Any

import numpy as np

from engine.geometry.cutting.cut import cut_blocks
from engine.geometry.joints import joint_set_planes
from engine.geometry.polyhedron import dip_normal
from engine.geometry.shapes import box, convex_hull
from engine.model import AnalysisControls, Block, JointMaterial, Material, Model

#: joint sets of the rock mass, (dip, dip direction) in degrees (as bench_cutting.py)
JOINT_SETS = [(45.0, 135.0), (45.0, 315.0), (75.0, 45.0)]


#: the shared scenes, kept in the repository (their README has the peers' numbers)
SCENES = Path(__file__).resolve().parent / "scenes"


def pile_path(n: int) -> Path:
    """Path of the shared pile scene with `n` blocks (gzip-compressed JSON)."""
    return SCENES / f"pile_{n}.json.gz"


def pile_scene(n: int) -> dict[str, Any]:
    """The shared pile scene with `n` blocks, as its JSON (bodies, walls, rho, seed, N)."""
    with gzip.open(pile_path(n), "rt", encoding="utf-8") as f:
        return json.load(f)


def pile_model(n: int, dt: float = 1e-3, penalty: float = 1e10, duration: float = 1.0,
               **kw: object) -> Model:
    """The shared pile: fixed walls first (5 boxes), then the N convex hulls; φ = 30°."""
    scene = pile_scene(n)
    blocks = []
    for k, (c, e) in enumerate(scene["walls"]):
        c, e = np.asarray(c, float), np.asarray(e, float)
        blocks.append(Block(box(c - e, c + e), f"wall{k}", fixed=True))
    for k, b in enumerate(scene["bodies"]):
        pts = np.asarray(b["pos"], float) + np.asarray(b["verts"], float)
        blocks.append(Block(convex_hull(pts), f"b{k}"))
    return Model(blocks=blocks, materials=[Material(float(scene["rho"]))],
                 joint_materials=[JointMaterial(np.radians(30.0))],
                 controls=AnalysisControls(duration=duration, time_step=dt, penalty=penalty,
                                           **kw))


def rock_mass_model(spacing: float, size: float = 10.0, dt: float = 1e-3,
                    penalty: float = 1e10, duration: float = 1.0, **kw: object) -> Model:
    """A `size` m cube cut by three joint sets at `spacing` m, resting on a fixed base
    slab (blocks touching the base are free too); φ = 30°. Block 0 is the base."""
    domain = box([0, 0, 0], [size, size, size])
    joints = []
    for tag, (dip, ddir) in enumerate(JOINT_SETS):
        joints += joint_set_planes(dip_normal(dip, ddir), [size / 2] * 3, spacing, domain, tag)
    pieces = cut_blocks(domain, joints).blocks
    base = box([-1, -1, -1], [size + 1, size + 1, 0])
    blocks = [Block(base, "base", fixed=True)] + [Block(p, f"r{k}") for k, p in enumerate(pieces)]
    return Model(blocks=blocks, joint_materials=[JointMaterial(np.radians(30.0))],
                 controls=AnalysisControls(duration=duration, time_step=dt, penalty=penalty,
                                           **kw))
