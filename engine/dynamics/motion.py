"""Block motion: where the blocks' points are, their current mass properties, how far a step
moves them, and the energy the bolts hold (the update after a step is
:mod:`engine.step.advance`)."""

from __future__ import annotations

import numpy as np

from engine.dynamics import assembly as asm
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.geometry._transform_kernels import block_vertices
from engine.geometry.polyhedron import Polyhedron
from engine.loads import bolts


def mass_properties(system: BlockSystem, state: State) -> tuple[np.ndarray, np.ndarray]:
    """Current volume `(n,)` m³ and second moments `(n, 3, 3)` m⁵ (affine images of the
    initial ones; computed once per state)."""
    hit = state.cache.get("mass_properties")
    if hit is not None:
        return hit
    a = state.affine
    det = np.linalg.det(a)
    vol = system.volume0 * det
    second = det[:, None, None] * (a @ system.second0 @ np.transpose(a, (0, 2, 1)))
    state.cache["mass_properties"] = (vol, second)
    return vol, second


def mass_matrices(system: BlockSystem, state: State) -> np.ndarray:
    """Block mass matrices `(n, 12, 12)` of the state (computed once per state)."""
    hit = state.cache.get("mass")
    if hit is None:
        vol, second = mass_properties(system, state)
        hit = state.cache["mass"] = asm.mass_matrices(system.density, vol, second)
    return hit


def current_vertices(system: BlockSystem, state: State) -> np.ndarray:
    """Current positions `(V, 3)` of all blocks' vertices, stacked in block order (once per
    state: the update that made the state computed them)."""
    hit = state.cache.get("vertices")
    if hit is None:
        hit = state.cache["vertices"] = block_vertices(state.centroid, state.affine,
                                                       system.vertex_block, system.vertex_rel0)
    return hit


def current_polyhedra(system: BlockSystem, state: State) -> list[Polyhedron]:
    """The blocks as polyhedra at the current state."""
    pts = np.split(current_vertices(system, state), system.vertex_start[1:])
    return [p.moved(x) for p, x in zip(system.polys0, pts, strict=True)]


def map_point(system: BlockSystem, state: State, b: int, point0: np.ndarray) -> np.ndarray:
    """Current position `(3,)` of the material point of block `b` given at its initial
    position `point0 (3,)`."""
    rel0 = (np.asarray(point0, float) - system.c0[b])[None]
    return block_vertices(state.centroid, state.affine, np.array([b], dtype=np.int64),
                          rel0)[0]


def point_displacements(system: BlockSystem, d: np.ndarray) -> np.ndarray:
    """Bound `(n,)` m on the largest displacement of any point of each block in a step of
    block displacements `d (n, 12)`."""
    trans = np.linalg.norm(d[:, :3], axis=1)
    rot = np.linalg.norm(d[:, 3:6], axis=1) * system.radius
    strain = np.abs(d[:, 6:]).max(axis=1) * 2.0 * system.radius
    return trans + rot + strain


def bolt_energy(system: BlockSystem, state: State) -> float:
    """Energy (J) the rock bolts of the state hold (0 without bolts)."""
    if system.bolts is None:
        return 0.0
    head, anchor = bolts.bolt_ends(system.bolts, system.c0, state.centroid, state.affine)
    return bolts.stored_energy(system.bolts, head, anchor, state.bolt_plastic,
                               state.bolt_shear, state.bolt_status)
