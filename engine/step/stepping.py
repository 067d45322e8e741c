"""Time-step control (docs/theory.md "One step", 3): the Δt and displacement limits of a step's
attempts, the checks of a converged step (displacement limit, penetration), the cut of Δt
when an attempt fails, and its growth after easy steps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.contact.constraints import OPEN
from engine.contact.search import SEARCH_SAFETY, step_limit, step_search
from engine.contact.solution import StepResult
from engine.dynamics.motion import point_displacements
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.status import StepFailure

#: time-step cut factor when a step fails, and growth factor after easy steps
DT_CUT = 0.3
DT_GROW = 1.5

#: what limits a step's Δt (counted per step in `Diagnostics.limited_by`): the asked Δt;
#: the run's end; a cut in the step itself ("cut:" and the failure's reason, e.g.
#: "cut:open_close"); a cut kept from the step before; regrowth by DT_GROW after a cut,
#: still below the asked Δt; held because the step before had more than half the allowed
#: open/closed changes
LIMITS = ("asked", "end_of_run", "cut:<reason>", "kept_cut", "regrowth", "mode_changes")


class SearchWider(Exception):
    """Blocks moved further than their limit predicted: detect again, wider, same Δt."""


@dataclass
class Attempt:
    """One attempt at a step: its time step `dt` s, each block's displacement limit
    `limit (n,)` m (what its contact search covers) and what limits `dt` (:data:`LIMITS`)."""

    dt: float
    limit: np.ndarray
    reason: str = "asked"


def _allowed(system: BlockSystem, state: State, dt: float, reason: str) -> None:
    """StepFailure when `dt` is below the smallest allowed time step."""
    if dt < system.controls.min_time_step:
        raise StepFailure(
            f"step {state.step + 1} at t = {state.time:.6g} s did not converge even at the "
            f"smallest time step {system.controls.min_time_step:g} s: {reason}", "time_step")


def first_attempt(system: BlockSystem, state: State) -> Attempt:
    """The step's first attempt: the state's Δt (the rest of the run at most), limited by
    what the step before decided (`Diagnostics.dt_reason`) or by the run's end."""
    remaining = system.controls.duration - state.time
    dt = min(state.dt, remaining) if remaining > 0 else state.dt
    _allowed(system, state, dt, "")
    reason = "end_of_run" if dt < state.dt else state.diagnostics.dt_reason
    return Attempt(dt, step_limit(system, state, dt), reason)


def reach(system: BlockSystem, state: State, attempt: Attempt) -> np.ndarray:
    """Each block's contact search reach `(n,)` m for the attempt."""
    return step_search(system, state, attempt.limit)


def check(system: BlockSystem, res: StepResult, attempt: Attempt) -> None:
    """The converged step keeps its limits: blocks that moved further than predicted (but
    within the model's step limit) raise SearchWider after widening `attempt.limit`; beyond
    the model's limit, or a contact deeper than its share of the thinner block, StepFailure."""
    disp = point_displacements(system, res.d)
    limit = attempt.limit
    over = disp > limit
    wider = over & (limit < system.max_step_displacement)
    if np.any(wider):
        attempt.limit = np.where(wider, np.minimum(np.maximum(SEARCH_SAFETY * disp, 2.0 * limit),
                                                   system.max_step_displacement), limit)
        raise SearchWider
    if np.any(over):
        b = int(np.argmax(disp - limit))
        raise StepFailure(f"largest displacement {disp[b]:.3g} m (block {b}) exceeds the step "
                          f"limit {limit[b]:.3g} m", "displacement")
    check_penetration(system, res)


def check_penetration(system: BlockSystem, res: StepResult) -> None:
    """StepFailure if a closed contact penetrates deeper than its allowed share
    (`max_penetration_ratio`) of the thinner of its two blocks: nothing tunnels."""
    cs = res.contacts
    if not len(cs):
        return
    limit = system.controls.max_penetration_ratio * np.minimum(
        system.thickness[cs.block_i], system.thickness[cs.block_j])
    excess = np.where(cs.mode != OPEN, -res.gap1 - limit, -np.inf)
    k = int(np.argmax(excess))
    if excess[k] > 0:
        raise StepFailure(
            f"penetration {-res.gap1[k]:.3g} m between blocks {cs.block_i[k]} and "
            f"{cs.block_j[k]} exceeds the limit {limit[k]:.3g} m", "penetration")


def cut(system: BlockSystem, state: State, attempt: Attempt, exc: StepFailure) -> Attempt:
    """The next attempt after `exc`: Δt × DT_CUT with the same limits (the contacts found
    for the larger step cover it); counted by reason in the state's diagnostics.
    StepFailure below the smallest allowed time step."""
    cuts = state.diagnostics.cuts
    cuts[exc.reason] = cuts.get(exc.reason, 0) + 1
    dt = attempt.dt * DT_CUT
    _allowed(system, state, dt, str(exc))
    return Attempt(dt, attempt.limit, f"cut:{exc.reason}")


def next_time_step(system: BlockSystem, before: State, res: StepResult,
                   dt: float) -> tuple[float, str]:
    """The Δt the next step tries after a step of `dt` s from `before`, and what limits it
    (:data:`LIMITS`): a cut is kept (unless it only shortened the run's last step), and Δt
    grows back by DT_GROW after easy steps (at most half the allowed open/closed changes)."""
    c = system.controls
    remaining = c.duration - before.time
    if dt < before.dt and dt < remaining:
        return dt, "kept_cut"
    if res.mode_changes <= c.max_open_close_iterations // 2:
        grown = min(c.time_step, before.dt * DT_GROW)
        return grown, "asked" if grown >= c.time_step else "regrowth"
    return before.dt, "asked" if before.dt >= c.time_step else "mode_changes"


def count_limit(state: State, attempt: Attempt) -> None:
    """Count the step's Δt under what limited it (`Diagnostics.limited_by`)."""
    limited = state.diagnostics.limited_by
    limited[attempt.reason] = limited.get(attempt.reason, 0) + 1
