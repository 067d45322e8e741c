"""DDA time stepping: the orchestrator of a run.

A step is the paper's pipeline (docs/theory.md "One step"): find contacts → the contact solution
(the open-close iteration of Tables 1 and 2, or the complementarity solve) → checks
(displacement limit, penetration) → wake sleeping blocks whose loads changed → advance
(exact rotation) → settle rings and rebounds → put quiet blocks to sleep → energy watchdog →
record. Each stage is a module of its own: :mod:`engine.contact.search`,
:mod:`engine.contact.solvers`, :mod:`engine.step.stepping`, :mod:`engine.step.advance`,
:mod:`engine.step.energy`, :mod:`engine.step.output`. When an attempt fails, Δt is cut and
the step redone; below the smallest allowed time step the run stops with a clear status and
keeps what was recorded. Constants live in a :class:`BlockSystem`, everything that changes
in a :class:`State`, so a run can be checkpointed and resumed.
"""

from __future__ import annotations

import os
import time as _time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.contact.search import find_contacts
from engine.contact.solution import StepResult
from engine.contact.solvers import settle_contacts, solve_contacts
from engine.dynamics.state import State, initial_state, load_state, save_state
from engine.dynamics.system import BlockSystem, build_system
from engine.model import Model
from engine.status import STATUS_CANCELLED, STATUS_COMPLETED, STATUS_FAILED, StepFailure
from engine.step import energy, output, sleep, stepping
from engine.step.advance import advance
from engine.step.frame import Frame, Recorder

__all__ = ["STATUS_CANCELLED", "STATUS_COMPLETED", "STATUS_FAILED", "Progress", "RunResult",
           "Simulation", "StepFailure", "run"]


@dataclass
class Progress:
    """Progress of a run, for callbacks: step, simulated time (s), duration (s), Δt (s)."""

    step: int
    time: float
    duration: float
    dt: float

    @property
    def fraction(self) -> float:
        return min(1.0, self.time / self.duration) if self.duration > 0 else 1.0


@dataclass
class RunResult:
    """How a run ended and the final state."""

    status: str
    message: str
    state: State
    steps: int
    wall_time: float
    max_penetration: float
    summary: dict[str, Any]


def _start_state(system: BlockSystem) -> State:
    """The state at t = 0: blocks where the model puts them, free ones at their velocity."""
    v0 = np.zeros((system.n, 12))
    for b, blk in enumerate(system.model.blocks):
        if not system.fixed[b]:
            v0[b, :6] = np.asarray(blk.velocity, float)[:6]
    state = initial_state(system.c0, v0, float(system.controls.time_step))
    if system.bolts is not None:
        nb = len(system.bolts)
        state.bolt_plastic, state.bolt_shear = np.zeros(nb), np.zeros((nb, 3))
        state.bolt_status = np.zeros(nb, dtype=np.int8)
    return state


class Simulation:
    """A DDA run of one model: its constants (`system`), its `state`, one step at a time."""

    def __init__(self, model: Model, adaptive_search: bool = True,
                 state: State | None = None) -> None:
        self.system = build_system(model, adaptive_search)
        self.state = _start_state(self.system) if state is None else state
        if state is not None:  # another model's state (a trial, a stage) wakes what it must
            sleep.reconcile(self.system, self.state)

    def step(self) -> StepResult:
        """Advance one step, cutting Δt as needed (StepFailure below the smallest Δt)."""
        system, state = self.system, self.state
        attempt = stepping.first_attempt(system, state)
        contacts, patches = find_contacts(system, state, stepping.reach(system, state, attempt))
        res = None
        while True:
            try:
                if res is None:
                    res = solve_contacts(system, state, contacts, patches, attempt.dt)
                stepping.check(system, res, attempt)
                drift = sleep.check_wake(system, state, res)
                clock = _time.perf_counter()
                after = advance(system, state, res, attempt.dt)
                clock = state.diagnostics.tick("update", clock)
                after = settle_contacts(system, state, res, after, attempt.dt)
                clock = state.diagnostics.tick("damping", clock)
                sleep.update(system, res, after, attempt.dt, drift)
                energy.check_step(system, state, after)
                break
            except sleep.Wake:  # blocks woke: the step again with them in it
                contacts, patches = find_contacts(system, state,
                                                  stepping.reach(system, state, attempt))
                res = None
            except stepping.SearchWider:
                wider, patches_wider = find_contacts(system, state,
                                                     stepping.reach(system, state, attempt))
                if not wider.same_as(contacts):  # the same contacts give the same step
                    contacts, patches, res = wider, patches_wider, None
            except StepFailure as exc:
                attempt = stepping.cut(system, state, attempt, exc)
                res = None
        self.state = after
        self.state.dt, self.state.diagnostics.dt_reason = stepping.next_time_step(
            system, state, res, attempt.dt)
        self.state.last_dt = attempt.dt
        stepping.count_limit(self.state, attempt)
        self.state.diagnostics.tick("update", clock)
        return res

    def frame(self, res: StepResult | None = None) -> Frame:
        """What a recorder receives of the current state (reached by the step `res`)."""
        return output.frame(self.system, self.state, res)

    def checkpoint(self, path: str | os.PathLike[str]) -> None:
        """Save the run's state to `path`; :meth:`resume` continues it bit for bit."""
        save_state(self.state, path)

    @classmethod
    def resume(cls, model: Model, path: str | os.PathLike[str]) -> Simulation:
        """The simulation of `model` continuing from the state saved at `path`."""
        return cls(model, state=load_state(path))


def run(
    model: Model,
    recorder: Recorder | None = None,
    progress: Callable[[Progress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    scene_json: str | None = None,
    resume_from: State | None = None,
) -> RunResult:
    """Run `model` to its duration (from its start, or continuing the state `resume_from`);
    record frames; never return NaN or silently wrong results.

    Status is `completed`, `cancelled` (should_stop returned True) or `failed` (a step
    could not converge at the smallest time step, or the state became non-finite).
    """
    start = _time.perf_counter()
    sim = Simulation(model, state=resume_from)
    c = model.controls
    if recorder is not None:
        recorder.begin(model, scene_json)
        if resume_from is None:
            recorder.record(sim.frame())
    status, message = STATUS_COMPLETED, ""
    eps = 1e-12 * max(c.duration, 1.0)
    try:
        while sim.state.time < c.duration - eps:
            if should_stop is not None and should_stop():
                status, message = STATUS_CANCELLED, "cancelled by request"
                break
            try:
                res = sim.step()
            except StepFailure as exc:
                status, message = STATUS_FAILED, str(exc)
                break
            s = sim.state
            if not (np.all(np.isfinite(s.centroid)) and np.all(np.isfinite(s.velocity))):
                status = STATUS_FAILED
                message = f"non-finite state at step {s.step}; stopped"
                break
            message = energy.check_run(sim.system, s)
            if message:
                status = STATUS_FAILED
                break
            last = s.time >= c.duration - eps
            if recorder is not None and (s.step % c.record_interval == 0 or last):
                clock = _time.perf_counter()
                recorder.record(sim.frame(res))
                s.diagnostics.tick("output", clock)
            if progress is not None:
                progress(Progress(s.step, s.time, c.duration, s.last_dt))
    finally:
        wall = _time.perf_counter() - start
        summary = output.summary(sim.system, sim.state, status, message, wall)
        if recorder is not None:
            recorder.end(status, message, summary)
    return RunResult(status, message, sim.state, sim.state.step, wall,
                     sim.state.diagnostics.max_penetration, summary)
