"""Shi's block terms of a step (docs/theory.md): inertia of the constant-acceleration scheme,
elasticity, initial stress, gravity and ground motion, point loads, fixed points, rock bolts
and water, on the
blocks' own unknowns; and the energy the implicit block springs dissipate in a step."""

from __future__ import annotations

import numpy as np

from engine.dynamics import assembly as asm
from engine.dynamics.motion import current_polyhedra, map_point, mass_matrices, mass_properties
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.loads.bolts import BoltStep, bolt_step
from engine.loads.water import WaterLoads, water_loads


def kinetic_energy(velocity: np.ndarray, mass: np.ndarray) -> float:
    """½ Σ vᵀ M v (J) of block velocities `(n, 12)` and masses `(n, 12, 12)`."""
    return 0.5 * float(np.sum(velocity * (mass @ velocity[:, :, None])[:, :, 0]))


def block_terms(system: BlockSystem, state: State, dt: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block stiffness `(n, d, d)` and block forces `(n, 12)` on the d = 6 (rigid) or 12
    (elastic) unknowns of each block for a step of `dt` s, and the mass `(n, 12, 12)`."""
    nd = system.ndof
    vol, _ = mass_properties(system, state)
    mass = mass_matrices(system, state)
    kb = mass[:, :nd, :nd] * (2.0 / dt**2)
    fb = (mass @ state.velocity[:, :, None])[:, :, 0]
    fb *= 2.0 / dt
    fb[:, :3] += (system.density * vol)[:, None] * system.gravity[None]
    gm = system.model.ground_motion
    if gm is not None:  # the ground's frame: inertial body force −m a(t), its step mean
        fb[:, :3] -= (system.density * vol)[:, None] * gm.mean(state.time, state.time + dt)
    if system.elastic:
        kb[:, 6:, 6:] += vol[:, None, None] * system.emat
        fb[:, 6:] -= vol[:, None] * state.stress
    for b, p0, f in system.loads:
        t = asm.displacement_matrices(map_point(system, state, b, p0)[None],
                                      state.centroid[b][None])[0]
        fb[b] += t.T @ f
    for b, p0 in system.fixed_points:
        p = map_point(system, state, b, p0)
        t = asm.displacement_matrices(p[None], state.centroid[b][None])[0]
        kb[b] += system.kf * (t.T @ t)[:nd, :nd]
        fb[b] -= system.kf * t.T @ (p - p0)
    if system.bolts is not None:
        _add_bolts(system, bolts_now(system, state), kb, fb)
    if system.water is not None:
        w = water_now(system, state)
        if len(w.block):
            t = asm.displacement_matrices(w.point, state.centroid[w.block])
            np.add.at(fb, w.block, np.einsum("qij,qi->qj", t, w.force))
    return kb, fb, mass


def water_now(system: BlockSystem, state: State) -> WaterLoads:
    """The water forces of the state (computed once per state)."""
    hit = state.cache.get("water")
    if hit is None:
        m = system.model
        hit = state.cache["water"] = water_loads(
            system.water, current_polyhedra(system, state), system.fixed, system.scale,
            m.pair_joint_material, m.joint_material_of_tag, m.default_joint_material)
    return hit


def bolts_now(system: BlockSystem, state: State) -> BoltStep:
    """The bolts at the start of a step from `state` (computed once per state)."""
    hit = state.cache.get("bolts")
    if hit is None:
        hit = state.cache["bolts"] = bolt_step(
            system.bolts, system.c0, state.centroid, state.affine, state.bolt_plastic,
            state.bolt_shear, state.bolt_status)
    return hit


def bolt_links(system: BlockSystem, state: State) -> tuple[np.ndarray, ...] | None:
    """The bolts between two free blocks as two-point springs for the global K: blocks
    `bi`, `bj`, T `ti`, `tj (k, 3, d)`, axes `(k, 3)`, axial and shear stiffness `(k,)`
    (None when there are none; the others are block terms, :func:`block_terms`)."""
    if system.bolts is None:
        return None
    bs, st, nd = system.bolts, bolts_now(system, state), system.ndof
    free = ~system.fixed
    link = st.acting & (bs.anchor_block >= 0) & free[bs.block] & free[
        np.maximum(bs.anchor_block, 0)]
    if not np.any(link):
        return None
    return (bs.block[link], bs.anchor_block[link],
            np.ascontiguousarray(st.ti[link][:, :, :nd]),
            np.ascontiguousarray(st.tj[link][:, :, :nd]), st.axis[link], st.ka[link],
            st.ks[link])


def _add_bolts(system: BlockSystem, st: BoltStep, kb: np.ndarray, fb: np.ndarray) -> None:
    """Bolt forces at the step's start as point loads on both ends, and the stiffness of
    bolts with one end on a fixed block or the ground on the free end's block."""
    bs, nd = system.bolts, system.ndof
    for k in np.flatnonzero(st.acting):
        i, j = int(bs.block[k]), int(bs.anchor_block[k])
        fb[i] += st.ti[k].T @ st.f[k]
        if j >= 0:
            fb[j] -= st.tj[k].T @ st.f[k]
        free_i = not system.fixed[i]
        free_j = j >= 0 and not system.fixed[j]
        if free_i and free_j:
            continue  # coupled: in the global K (bolt_links)
        if free_i:
            kb[i] += (st.ti[k].T @ st.p[k] @ st.ti[k])[:nd, :nd]
        if free_j:
            kb[j] += (st.tj[k].T @ st.p[k] @ st.tj[k])[:nd, :nd]


def block_dissipation(system: BlockSystem, state: State, d: np.ndarray) -> float:
    """½ dᵀ K d (J) of the implicit elastic and fixed-point springs in a step of block
    displacements `d (n, 12)`."""
    out = 0.0
    if system.elastic:
        vol, _ = mass_properties(system, state)
        out += 0.5 * float(np.einsum("ni,nij,nj->", d[:, 6:],
                                     vol[:, None, None] * system.emat, d[:, 6:]))
    for b, p0 in system.fixed_points:
        t = asm.displacement_matrices(map_point(system, state, b, p0)[None],
                                      state.centroid[b][None])[0]
        r = t @ d[b]
        out += 0.5 * system.kf * float(r @ r)
    return out
