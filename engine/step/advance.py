"""The update stage of a step: the state after a converged step (exact rotation, velocities,
stresses, energies and works, the bolts, and the contacts' memory for the next step)."""

from __future__ import annotations

import dataclasses

import numpy as np

from engine.contact.constraints import LOCKED, OPEN
from engine.contact.solution import StepResult
from engine.dynamics.block_terms import bolts_now, water_now
from engine.dynamics.motion import bolt_energy, map_point, mass_matrices, mass_properties
from engine.dynamics.state import MEMORY_FIELDS, ContactMemory, Diagnostics, State
from engine.dynamics.system import BlockSystem
from engine.geometry._transform_kernels import advance_blocks
from engine.geometry.transforms import displacement_matrices
from engine.loads import bolts
from engine.step._advance_kernels import deepest_penetrations


def spring_energy(system: BlockSystem, res: StepResult) -> float:
    """Energy (J) the contact springs hold at the end of the step `res`."""
    closed = res.contacts.mode != OPEN
    return (0.5 * system.kn * float(np.sum(res.gap1[closed] ** 2))
            + 0.5 * system.ks * float(np.sum(res.shear ** 2)))


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
        t = displacement_matrices(map_point(system, state, b, p0)[None],
                                      state.centroid[b][None])[0]
        e["external_work"] += float(f @ (t @ d[b]))
    if system.water is not None:
        w = water_now(system, state)
        if len(w.block):
            t = displacement_matrices(w.point, state.centroid[w.block])
            e["external_work"] += float(np.einsum("qi,qij,qj->", w.force, t, d[w.block]))
    e["friction_dissipation"] += res.friction_work
    e["numerical_dissipation"] += res.numerical_dissipation
    e["damping_dissipation"] += res.damping_dissipation
    return e


def _memory(system: BlockSystem, state: State, res: StepResult, still: np.ndarray
            ) -> ContactMemory:
    """What the step's contacts carry to the next step: closed contacts, broken ones (stay
    broken) and open ones pressed in within the open-close hysteresis (their springs start
    the next step unstretched, see :func:`engine.contact.search.plausible_gaps`); and, kept
    as they were, the contacts between blocks that did not move (`still`, asleep or
    fixed)."""
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
    new = ContactMemory(key=cs.key[keep], mode=cs.mode[keep], shear=res.shear[keep],
                        tangent=tangent, broken=broken[keep] | (cs.mode[keep] != LOCKED),
                        gap=res.gap1[keep],
                        force=None if res.force is None else res.force[keep],
                        joint_material=cs.joint_material[keep])
    if state.asleep is None or not np.any(state.asleep):
        return new
    return ContactMemory(**{name: np.concatenate([getattr(new, name),
                                                  getattr(state.memory, name)[still]])
                            for name in MEMORY_FIELDS})


def _penetrations(system: BlockSystem, state: State, res: StepResult
                  ) -> tuple[np.ndarray, Diagnostics]:
    """Each block's deepest contact penetration at the end of the step `(n,)` m (what the
    next step's search must reach), and the diagnostics with the run's deepest
    penetrations, the springs' re-seat loss and the bonds broken updated (a copy: the step
    may be redone)."""
    cs, gap = res.contacts, res.gap1
    deepest = deepest_penetrations(system.n, cs.block_i, cs.block_j, gap)
    d = state.diagnostics
    closed = cs.mode != OPEN
    pen, ratio = d.max_penetration, d.max_penetration_ratio
    pen = max(pen, float(np.max(-gap[closed], initial=0.0)))
    if np.any(closed):
        thin = np.minimum(system.thickness[cs.block_i], system.thickness[cs.block_j])
        ratio = max(ratio, float(np.max(-gap[closed] / thin[closed], initial=0.0)))
    whole, part = res.bond_breaks
    return deepest, dataclasses.replace(
        d, max_penetration=pen, max_penetration_ratio=ratio,
        reseat_dissipation=d.reseat_dissipation + res.reseat_dissipation,
        bonds_broken=d.bonds_broken + whole,
        bonds_broken_progressively=d.bonds_broken_progressively + part)


def _advance_bolts(system: BlockSystem, state: State, after: State, d: np.ndarray) -> None:
    """The bolts' plastic elongation, shear force and state after the step `d`, and the
    energy dissipated in them (implicit springs, yield, rupture) with the integrator's."""
    plastic, shear, status, dissipated = bolts.update(
        system.bolts, bolts_now(system, state), d, system.c0, after.centroid, after.affine,
        state.bolt_plastic, state.bolt_shear, state.bolt_status, bolt_energy(system, state))
    after.bolt_plastic, after.bolt_shear, after.bolt_status = plastic, shear, status
    after.energies["numerical_dissipation"] += dissipated


def advance(system: BlockSystem, state: State, res: StepResult, dt: float) -> State:
    """The state after the converged step `res` of `dt` s: blocks moved with the exact
    rotation, velocities `2 d / Δt − v0` or the ones the contact solve's impact law gave
    (times the dynamic ratio; the kinetic energy that removes counts as the integrator's
    dissipation), stresses, energies, the contacts'
    memory and the time (`dt` and `last_dt` are the caller's). The state `state` is left
    as it was, so a step can be redone from it."""
    d = res.d
    centroid, affine, rotation = state.centroid.copy(), state.affine.copy(), \
        state.rotation.copy()
    v1, vertices = advance_blocks(d, dt, state.velocity, system.fixed, centroid, affine,
                                  rotation, system.vertex_block, system.vertex_rel0)
    if res.velocity is not None:  # the contact solve's impact law gave them
        v1 = res.velocity.copy()
        v1[system.fixed] = 0.0
    stress = state.stress
    if system.elastic:
        stress = stress + np.einsum("nij,nj->ni", system.emat, d[:, 6:])
    deepest, diagnostics = _penetrations(system, state, res)
    still = state.resting_contacts(system.fixed)
    stored = spring_energy(system, res) if res.contact_energy is None else res.contact_energy
    if res.springs and np.any(still):  # sleeping contacts keep what their springs hold
        stored += state.memory.spring_energy(system.kn, system.ks, still)
    after = State(
        centroid=centroid, affine=affine, rotation=rotation, velocity=v1, stress=stress,
        time=state.time + dt, step=state.step + 1, dt=state.dt, last_dt=state.last_dt,
        memory=_memory(system, state, res, still), last_d=d, deepest=deepest,
        energies=_work(system, state, res, dt), contact_energy=stored,
        diagnostics=diagnostics, asleep=state.asleep, quiet=state.quiet, drift=state.drift,
        workspace=state.workspace)
    after.cache["vertices"] = vertices
    if system.bolts is not None:
        _advance_bolts(system, state, after, d)
    ratio = system.controls.dynamic_ratio
    if ratio != 1.0:
        kinetic = 0.5 * float(np.einsum("ni,nij,nj->", v1, mass_matrices(system, after), v1))
        after.energies["numerical_dissipation"] += (1.0 - ratio**2) * kinetic
        after.velocity = ratio * v1
    return after
