"""What a run reports: the energies of a state, the frame a recorder receives, and the run's
summary with its warnings."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from engine.contact.constraints import OPEN
from engine.contact.solution import StepResult
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem, default_penalty
from engine.loads.bolts import STATUS_NAMES, recorded_forces
from engine.step.energy import stored_energies
from engine.step.frame import Frame

#: a run whose contacts penetrated deeper than this fraction of the thinner block's
#: thickness says so in its summary: the penalty is soft for the loads, and the motion
#: carries an error of that order
SOFT_PENALTY_WARNING_RATIO = 0.01


def energies(system: BlockSystem, state: State) -> dict[str, float]:
    """Kinetic, elastic and spring energies (J) of the state, with the accumulated works and
    dissipations."""
    return {**stored_energies(system, state), **state.energies}


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
        energies=energies(system, state),
    )
    if system.bolts is not None:
        f.bolt_axial_force, f.bolt_shear_force = recorded_forces(
            system.bolts, system.c0, state.centroid, state.affine, state.bolt_plastic,
            state.bolt_shear, state.bolt_status)
        f.bolt_status = state.bolt_status.copy()
    if system.water is not None:
        from engine.dynamics.block_terms import water_now

        f.water_force = water_now(system, state).resultant.copy()
    if res is not None and system.controls.record_contacts:
        f.contacts = res.contacts
        f.normal_force = res.normal_force
        f.shear_force = res.shear_force
    return f


def warnings(system: BlockSystem, state: State) -> list[str]:
    """What the user should know about a run that did complete (soft penalty...), with
    advice that helps: raise the penalty only where it is below the scene's default;
    otherwise the steps are too long for the speeds reached."""
    out = []
    d = state.diagnostics
    if d.max_penetration_ratio > SOFT_PENALTY_WARNING_RATIO:
        suggested = default_penalty(system.model)
        advice = (f"set analysis.penalty to the scene's default {suggested:.3g} N/m "
                  "(or leave it out)" if system.kn < suggested else
                  "the penalty is not below the scene's default: reduce analysis.time_step")
        out.append(
            f"contacts penetrated up to {d.max_penetration:.3g} m "
            f"({d.max_penetration_ratio:.1%} of the thinner block) with the penalty "
            f"{system.kn:.3g} N/m, and displacements carry an error of that order; {advice}")
    if d.bonds_broken_progressively:
        out.append(
            f"{d.bonds_broken_progressively} time(s) a joint's bond (cohesion, tensile "
            "strength over a face-to-face contact) broke in part and held the rest: the "
            "stress over the contact is uneven (bending, toppling, a load off its centre), "
            "so it fails progressively, from the edge in; limit equilibrium, which counts "
            "c·A over the whole face, overestimates such a joint")
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
        "penalty": {"normal": system.kn, "shear": system.ks,
                    "derived": system.controls.penalty is None},
        "max_penetration": d.max_penetration, "warnings": warnings(system, state),
        "blocks": blocks, **_bolt_summary(system, state), "timings": dict(d.timings),
        "relaxed_contacts": d.relaxed_contacts,
        "bonds_broken": {"whole": d.bonds_broken,
                         "progressively": d.bonds_broken_progressively},
        "reseat_dissipation": d.reseat_dissipation, "time_step_cuts": dict(d.cuts),
        "time_step_limited_by": dict(d.limited_by),
        "solves": {"solves": d.solves, "factorizations": d.factorizations},
        "initial_overlap": {"largest": d.initial_overlap, "contacts": d.initial_overlaps},
        "energy": {"created": d.max_energy_created, "scale": d.energy_scale,
                   "created_ratio": d.max_energy_created / d.energy_scale
                   if d.energy_scale > 0 else 0.0},
    }


def _bolt_summary(system: BlockSystem, state: State) -> dict[str, Any]:
    """`{"bolts": [...]}` with each bolt's name, final axial and shear force (N) and state
    (nothing without bolts)."""
    if system.bolts is None:
        return {}
    axial, shear = recorded_forces(system.bolts, system.c0, state.centroid, state.affine,
                                   state.bolt_plastic, state.bolt_shear, state.bolt_status)
    return {"bolts": [{"name": b.name or f"bolt{k + 1}", "axial_force": float(axial[k]),
                       "shear_force": float(shear[k]),
                       "state": STATUS_NAMES[int(state.bolt_status[k])]}
                      for k, b in enumerate(system.bolts.bolts)]}
