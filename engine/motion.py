"""Block motion: where the blocks' points are, how far a step moves them, and the update
of the state after a converged step (exact rotation, velocities, stresses, energies and the
contacts' memory for the next step)."""

from __future__ import annotations

import dataclasses

import numpy as np

from engine import assembly as asm
from engine import bolts
from engine._motion_kernels import block_vertices, move_blocks
from engine.contacts import LOCKED, OPEN
from engine.geometry import Polyhedron
from engine.state import ContactMemory, Diagnostics, State, StepResult
from engine.system import BlockSystem


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


def spring_energy(system: BlockSystem, res: StepResult) -> float:
    """Energy (J) the contact springs hold at the end of the step `res`."""
    closed = res.contacts.mode != OPEN
    return (0.5 * system.kn * float(np.sum(res.gap1[closed] ** 2))
            + 0.5 * system.ks * float(np.sum(res.shear ** 2)))


def current_vertices(system: BlockSystem, state: State) -> np.ndarray:
    """Current positions `(V, 3)` of all blocks' vertices, stacked in block order."""
    return block_vertices(state.centroid, state.affine, system.vertex_block,
                          system.vertex_rel0)


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


def _work(system: BlockSystem, state: State, res: StepResult, dt: float) -> dict[str, float]:
    """The energies after the step: works of gravity and loads, and the dissipations."""
    d = res.d
    vol, _ = mass_properties(system, state)
    weight = (system.density * vol)[:, None] * system.gravity[None]
    e = dict(state.energies)
    e["gravity_work"] += float(np.sum(weight * d[:, :3]))
    gm = system.model.ground_motion
    if gm is not None:
        inertial = -(system.density * vol)[:, None] * gm.mean(state.time, state.time + dt)
        e["external_work"] += float(np.sum(inertial[~system.fixed] * d[~system.fixed, :3]))
    for b, p0, f in system.loads:
        t = asm.displacement_matrices(map_point(system, state, b, p0)[None],
                                      state.centroid[b][None])[0]
        e["external_work"] += float(f @ (t @ d[b]))
    if system.water is not None:
        from engine.block_terms import water_now

        w = water_now(system, state)
        if len(w.block):
            t = asm.displacement_matrices(w.point, state.centroid[w.block])
            e["external_work"] += float(np.einsum("qi,qij,qj->", w.force, t, d[w.block]))
    e["friction_dissipation"] += res.friction_work
    e["numerical_dissipation"] += res.numerical_dissipation
    e["damping_dissipation"] += res.damping_dissipation
    return e


def _memory(system: BlockSystem, res: StepResult) -> ContactMemory:
    """What the step's contacts carry to the next step: closed contacts, broken ones (stay
    broken) and open ones pressed in within the open-close hysteresis (their springs start
    the next step unstretched, see :func:`engine.contact_step.plausible_gaps`)."""
    cs = res.contacts
    broken = res.broken if res.broken is not None else np.zeros(len(cs), dtype=bool)
    keep = (cs.mode != OPEN) | broken | (res.gap1 < 0)
    slip = res.slip[keep]
    slip_norm = np.linalg.norm(slip, axis=1)
    # sliding direction for the next step: this step's slip (paper eq. 7)
    big = slip_norm > 1e-14 * system.scale
    tangent = np.where(big[:, None], slip / np.maximum(slip_norm, 1e-300)[:, None],
                       cs.tangent[keep])
    # a contact that slid or ended open has lost its bond (cohesion, tensile strength)
    return ContactMemory(key=cs.key[keep], mode=cs.mode[keep], shear=res.shear[keep],
                         tangent=tangent, broken=broken[keep] | (cs.mode[keep] != LOCKED),
                         gap=res.gap1[keep])


def _penetrations(system: BlockSystem, state: State, res: StepResult
                  ) -> tuple[np.ndarray, Diagnostics]:
    """Each block's deepest contact penetration at the end of the step `(n,)` m (what the
    next step's search must reach), and the diagnostics with the run's deepest
    penetrations and the springs' re-seat loss updated (a copy: the step may be redone)."""
    cs, gap = res.contacts, res.gap1
    deepest = np.zeros(system.n)
    if len(gap):
        depth = np.maximum(-gap, 0.0)
        np.maximum.at(deepest, cs.block_i, depth)
        np.maximum.at(deepest, cs.block_j, depth)
    d = state.diagnostics
    closed = cs.mode != OPEN
    pen, ratio = d.max_penetration, d.max_penetration_ratio
    pen = max(pen, float(np.max(-gap[closed], initial=0.0)))
    if np.any(closed):
        thin = np.minimum(system.thickness[cs.block_i], system.thickness[cs.block_j])
        ratio = max(ratio, float(np.max(-gap[closed] / thin[closed], initial=0.0)))
    return deepest, dataclasses.replace(
        d, max_penetration=pen, max_penetration_ratio=ratio,
        reseat_dissipation=d.reseat_dissipation + res.reseat_dissipation)


def bolt_energy(system: BlockSystem, state: State) -> float:
    """Energy (J) the rock bolts of the state hold (0 without bolts)."""
    if system.bolts is None:
        return 0.0
    head, anchor = bolts.bolt_ends(system.bolts, system.c0, state.centroid, state.affine)
    return bolts.stored_energy(system.bolts, head, anchor, state.bolt_plastic,
                               state.bolt_shear, state.bolt_status)


def _advance_bolts(system: BlockSystem, state: State, after: State, d: np.ndarray) -> None:
    """The bolts' plastic elongation, shear force and state after the step `d`, and the
    energy dissipated in them (implicit springs, yield, rupture) with the integrator's."""
    from engine.block_terms import bolts_now

    plastic, shear, status, dissipated = bolts.update(
        system.bolts, bolts_now(system, state), d, system.c0, after.centroid, after.affine,
        state.bolt_plastic, state.bolt_shear, state.bolt_status, bolt_energy(system, state))
    after.bolt_plastic, after.bolt_shear, after.bolt_status = plastic, shear, status
    after.energies["numerical_dissipation"] += dissipated


def advance(system: BlockSystem, state: State, res: StepResult, dt: float) -> State:
    """The state after the converged step `res` of `dt` s: blocks moved with the exact
    rotation, velocities `2 d / Δt − v0` (times the dynamic ratio; the kinetic energy that
    removes counts as the integrator's dissipation), stresses, energies, the contacts'
    memory and the time (`dt` and `last_dt` are the caller's). The state `state` is left
    as it was, so a step can be redone from it."""
    d = res.d
    centroid, affine, rotation = state.centroid.copy(), state.affine.copy(), \
        state.rotation.copy()
    move_blocks(d, centroid, affine, rotation)
    v1 = 2.0 * d / dt - state.velocity
    v1[system.fixed] = 0.0
    stress = state.stress
    if system.elastic:
        stress = stress + np.einsum("nij,nj->ni", system.emat, d[:, 6:])
    deepest, diagnostics = _penetrations(system, state, res)
    after = State(
        centroid=centroid, affine=affine, rotation=rotation, velocity=v1, stress=stress,
        time=state.time + dt, step=state.step + 1, dt=state.dt, last_dt=state.last_dt,
        memory=_memory(system, res), last_d=d, deepest=deepest,
        energies=_work(system, state, res, dt), contact_energy=spring_energy(system, res),
        diagnostics=diagnostics)
    if system.bolts is not None:
        _advance_bolts(system, state, after, d)
    ratio = system.controls.dynamic_ratio
    if ratio != 1.0:
        kinetic = 0.5 * float(np.einsum("ni,nij,nj->", v1, mass_matrices(system, after), v1))
        after.energies["numerical_dissipation"] += (1.0 - ratio**2) * kinetic
        after.velocity = ratio * v1
    return after
