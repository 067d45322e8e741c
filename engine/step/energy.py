"""Energy of a run and its watchdog.

What is stored (kinetic, elastic strain, contact and fixed-point springs), the work done on
the blocks (gravity, point loads) and what was dissipated (friction, the integrator's
implicit springs and velocity reduction, contact dashpots) must balance: DDA's integrator
satisfies the balance exactly within a step, so any energy a run creates comes from how
contacts are re-seated between steps or from the linearized rotation within a step. The
watchdog measures it every step: a step that creates more than a small fraction of the
energy in play is redone with a smaller Δt, and a run whose created energy exceeds
RUN_RTOL of its energy scale stops `failed`, naming the step and the blocks.
"""

from __future__ import annotations

import numpy as np

from engine.dynamics.block_terms import kinetic_energy
from engine.dynamics.motion import bolt_energy, map_point, mass_matrices, mass_properties
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.status import StepFailure
from engine.step.frame import energy_created

#: a step may create at most this fraction of the energy in play in it (kinetic and
#: stored energy at its start, plus the work done and the energy dissipated in it) ...
STEP_RTOL = 1e-3
#: ... and a run at most this fraction of its energy scale (the largest of the work done
#: on it and the kinetic and stored energy it reached)
RUN_RTOL = 5e-3


def fixed_point_energy(system: BlockSystem, state: State) -> float:
    """Energy (J) the fixed points' penalty springs hold."""
    out = 0.0
    for b, p0 in system.fixed_points:
        r = map_point(system, state, b, p0) - p0
        out += 0.5 * system.kf * float(r @ r)
    return out


def stored_energies(system: BlockSystem, state: State) -> dict[str, float]:
    """Kinetic, elastic-strain and spring energies (J) of the state (contact springs as they
    ended the last step, `state.contact_energy`, with the fixed points' and the bolts')."""
    vol, _ = mass_properties(system, state)
    elastic = 0.0
    if system.elastic:
        comp = np.linalg.solve(system.emat, state.stress[:, :, None])[:, :, 0]
        elastic = 0.5 * float(np.sum(vol * np.einsum("ij,ij->i", state.stress, comp)))
    return {"kinetic": kinetic_energy(state.velocity, mass_matrices(system, state)),
            "elastic": elastic,
            "contact": state.contact_energy + fixed_point_energy(system, state)
            + bolt_energy(system, state)}


def check_step(system: BlockSystem, before: State, after: State) -> None:
    """The watchdog for one step: StepFailure ("energy") when the step from `before` to
    `after` created more than STEP_RTOL of the energy in play, naming the blocks that gained
    most kinetic energy beyond the work of gravity on them. Updates the run's created
    energy and energy scale in `after.diagnostics`."""
    e0 = {**stored_energies(system, before), **before.energies}
    e1 = {**stored_energies(system, after), **after.energies}
    gain = float(energy_created(e1) - energy_created(e0))
    moved = {k: abs(e1[k] - e0[k]) for k in e1 if k not in ("kinetic", "elastic", "contact")}
    # stored spring energy is >= 0 but for pretensioned bolts (T0 x may be negative)
    in_play = e0["kinetic"] + e0["elastic"] + abs(e0["contact"]) + sum(moved.values())
    scale = max(e1["kinetic"] + e1["elastic"] + abs(e1["contact"]),
                abs(e1["gravity_work"]) + abs(e1["external_work"]))
    d = after.diagnostics
    d.energy_scale = max(d.energy_scale, scale)
    if gain > STEP_RTOL * in_play + system.energy_round_off:
        raise StepFailure(f"the step created {gain:.3g} J of energy "
                          f"({_blocks(system, before, after)})", "energy")
    d.energy_created += gain  # from the start: a run may begin moving, with stored energy
    d.max_energy_created = max(d.max_energy_created, d.energy_created)


def check_run(system: BlockSystem, state: State) -> str:
    """Why the run must stop (its created energy exceeds RUN_RTOL of its energy scale), or
    an empty string."""
    d = state.diagnostics
    if d.energy_created > RUN_RTOL * d.energy_scale + system.energy_round_off:
        return (f"the run created {d.energy_created:.3g} J of energy by step {state.step} "
                f"(t = {state.time:.6g} s), more than {RUN_RTOL:.1%} of its energy scale "
                f"{d.energy_scale:.3g} J")
    return ""


def _blocks(system: BlockSystem, before: State, after: State) -> str:
    """The blocks that gained most kinetic energy beyond the work of gravity on them."""
    m0, m1 = mass_matrices(system, before), mass_matrices(system, after)
    ke0 = 0.5 * np.einsum("ni,nij,nj->n", before.velocity, m0, before.velocity)
    ke1 = 0.5 * np.einsum("ni,nij,nj->n", after.velocity, m1, after.velocity)
    vol, _ = mass_properties(system, before)
    work = (system.density * vol) * ((after.centroid - before.centroid) @ system.gravity)
    excess = ke1 - ke0 - work
    top = np.argsort(-excess)[:3]
    names = [system.model.blocks[b].name or f"block{b}" for b in top if excess[b] > 0]
    return "blocks " + ", ".join(names) if names else "no block gained kinetic energy"
