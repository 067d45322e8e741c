"""What a run reports: the energies of a state, the frame a recorder receives, and the run's
summary with its warnings."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from engine import assembly as asm
from engine.block_terms import kinetic_energy
from engine.contacts import OPEN
from engine.frame import Frame
from engine.motion import mass_properties
from engine.state import State, StepResult
from engine.system import BlockSystem

#: a run whose contacts penetrated deeper than this fraction of the thinner block's
#: thickness says so in its summary: the penalty is soft for the loads, and the motion
#: carries an error of that order
SOFT_PENALTY_WARNING_RATIO = 0.01


def energies(system: BlockSystem, state: State, res: StepResult | None) -> dict[str, float]:
    """Kinetic, elastic and contact-spring energies (J) of the state after the step `res`,
    with the accumulated works and dissipations."""
    vol, second = mass_properties(system, state)
    mass = asm.mass_matrices(system.density, vol, second)
    kinetic = kinetic_energy(state.velocity, mass)
    contact = 0.0
    if res is not None and len(res.contacts):
        closed = res.contacts.mode != OPEN
        contact = 0.5 * system.kn * float(np.sum(res.gap1[closed] ** 2))
        contact += 0.5 * system.ks * float(np.sum(res.shear**2))
    elastic = 0.0
    if system.elastic:
        comp = np.linalg.solve(system.emat, state.stress[:, :, None])[:, :, 0]
        elastic = 0.5 * float(np.sum(vol * np.einsum("ij,ij->i", state.stress, comp)))
    return {"kinetic": kinetic, "elastic": elastic, "contact": contact, **state.energies}


def frame(system: BlockSystem, state: State, res: StepResult | None) -> Frame:
    """The recorder's frame of `state`, reached by the step `res` (None: the start)."""
    rv = Rotation.from_matrix(state.rotation).as_rotvec().reshape(system.n, 3)
    f = Frame(
        step=state.step, time=state.time, dt=state.last_dt,
        open_close_iterations=res.iterations if res else 0,
        max_penetration=float(np.max(-res.gap1[res.contacts.mode != OPEN], initial=0.0))
        if res is not None and len(res.contacts) else 0.0,
        centroids=state.centroid.copy(), affine=state.affine.copy(), rotation=rv,
        velocity=state.velocity.copy(), stress=state.stress.copy(),
        energies=energies(system, state, res),
    )
    if res is not None and system.controls.record_contacts:
        f.contacts = res.contacts
        f.normal_force = res.normal_force
        f.shear_force = res.shear_force
    return f


def warnings(system: BlockSystem, state: State) -> list[str]:
    """What the user should know about a run that did complete (soft penalty...)."""
    out = []
    d = state.diagnostics
    if d.max_penetration_ratio > SOFT_PENALTY_WARNING_RATIO:
        out.append(
            f"contacts penetrated up to {d.max_penetration:.3g} m "
            f"({d.max_penetration_ratio:.1%} of the thinner block): the penalty "
            f"{system.kn:.3g} N/m is soft for these loads and displacements carry an "
            "error of that order; raise analysis.penalty")
    return out


def summary(system: BlockSystem, state: State, status: str, message: str,
            wall: float) -> dict[str, Any]:
    """The run's summary: how it ended, its warnings and diagnostics, and every block's
    final centroid, rotation vector, displacement and velocity."""
    rv = Rotation.from_matrix(state.rotation).as_rotvec().reshape(system.n, 3)
    blocks = [{
        "name": blk.name or f"block{b}",
        "centroid": state.centroid[b].tolist(),
        "rotation": rv[b].tolist(),
        "displacement": (state.centroid[b] - system.c0[b]).tolist(),
        "velocity": state.velocity[b, :6].tolist(),
    } for b, blk in enumerate(system.model.blocks)]
    d = state.diagnostics
    return {
        "status": status, "message": message, "steps": state.step,
        "simulated_time": state.time, "wall_time": wall,
        "max_penetration": d.max_penetration, "warnings": warnings(system, state),
        "blocks": blocks, "timings": dict(d.timings),
        "relaxed_contacts": d.relaxed_contacts, "time_step_cuts": dict(d.cuts),
    }
