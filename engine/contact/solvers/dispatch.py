"""The contact solution of a step behind one call, whichever solver the scene asks for
(`analysis.contact_solver`): the paper's open-close iteration on penalty springs
(:mod:`.open_close`), the step as one minimisation of the same springs' potential by
Newton's method (:mod:`.newton`), both followed by dashpots against rings and rebounds
(:mod:`.damping`); or the complementarity solve without springs (:mod:`.complementarity`,
whose impact law takes the dashpots' place)."""

from __future__ import annotations

from engine.contact.constraints import ContactSet
from engine.contact.patches import ContactPatches
from engine.contact.solution import StepResult
from engine.contact.solvers.complementarity import complementarity_step
from engine.contact.solvers.damping import damp_contacts
from engine.contact.solvers.newton import newton_step
from engine.contact.solvers.open_close import initial_modes, open_close_iteration
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem


def solve_contacts(system: BlockSystem, state: State, contacts: ContactSet,
                   patches: ContactPatches, dt: float) -> StepResult:
    """The converged step of `dt` s from `state` with its `contacts` (and their bonded
    `patches`); StepFailure when it does not converge."""
    solver = system.controls.contact_solver
    if solver == "complementarity":
        return complementarity_step(system, state, contacts, patches, dt)
    if solver == "newton":
        return newton_step(system, state, contacts, patches, dt)
    start = initial_modes(system, state, contacts, dt)
    return open_close_iteration(system, state, contacts, patches, start, dt)


def settle_contacts(system: BlockSystem, before: State, res: StepResult, after: State,
                    dt: float) -> State:
    """The state after the step with rings and rebounds damped at its closed contacts (the
    open-close iteration's dashpots); a solve that applied an impact law already did."""
    if res.velocity is not None:
        return after
    return damp_contacts(system, before, res, after, dt)
