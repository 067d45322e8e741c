"""One trial of a strength-reduction or critical-seismic-coefficient search, judged the way
3DEC and RS2 users judge theirs: by how far the watched blocks move and whether they stop.

1. **Settle.** The model is first brought to rest under its loads (gravity, water, bolts,
   seismic coefficients) with joints that cannot fail (tan φ 1000, cohesion 1e15 Pa; the
   tensile strength as given) in quasi-static steps, so a trial starts from equilibrium: no
   start transient loads a joint beyond what the statics do, and a trial that holds is at
   rest from its first step. A model that does not settle (a block with nothing under it)
   starts its trials from the scene as given, and the trial says so.
2. **Release.** From the settled state the trial model (strengths divided by F, or the
   seismic load of the trial) runs in dynamic steps, for at most `observation_time` s. A
   search starts its trials from the model's own equilibrium, the end of the trial at
   F = 1 (kh = 0) when it held at rest: resistance that builds up with displacement (a
   bolt) is then mobilized by the step from F = 1, not by a drop from full strength.
3. **Verdict**, with its reason:

   - *fails* as soon as a watched block's point has moved more than the displacement limit
     since the release (default 2 % of the smallest watched block's size V^⅓), or the run
     fails (a step that cannot converge), or at the end when the fastest watched point is
     still moving (faster than the rest speed), has not slowed to half its peak speed and
     is not slowing over the window's last tenth;
   - *holds* as soon as every watched block is at rest (speed below the rest speed,
     1e-3 × limit / observation time) with every contact it has stuck (locked) for
     REST_STEPS steps in a row: a rigid block at rest on locked contacts is in static
     equilibrium within its strengths, and nothing will move it; or at the end when it
     moved less than the limit and its speed decayed.

A quasi-static run (velocities dropped every step) cannot tell a failing block from one
creeping to rest, so a search on such a scene is refused (:class:`QuasiStatic`).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from engine.contact.constraints import LOCKED, OPEN
from engine.dynamics.motion import point_displacements
from engine.dynamics.state import State
from engine.geometry._transform_kernels import block_vertices
from engine.model import DISPLACEMENT_LIMIT_RATIO, JointMaterial, Model
from engine.status import STATUS_COMPLETED, STATUS_FAILED, StepFailure
from engine.step import energy, sleep
from engine.step.simulation import Simulation

#: joints that cannot fail while the model settles: tan φ and cohesion (Pa)
SETTLE_TAN_PHI = 1e3
SETTLE_COHESION = 1e15
#: quasi-static settling steps at most, and settled when no point moved more than this
#: fraction of the displacement limit in SETTLED_STEPS steps in a row
MAX_SETTLE_STEPS = 400
SETTLE_TOLERANCE = 1e-7
SETTLED_STEPS = 3
#: a trial holds once its watched blocks are at rest with stuck contacts this many steps
REST_STEPS = 10
#: the rest speed as a fraction of the displacement limit over the observation time
REST_SPEED_RATIO = 1e-3
#: at the end of the window a block that is still faster than this fraction of its peak
#: speed, and no slower than it was LATE_FRACTION of the window earlier, has not slowed down
DECAY_RATIO = 0.5
LATE_FRACTION = 0.1


class QuasiStatic(ValueError):
    """A search on a quasi-static model (the message says why it is refused)."""


@dataclass
class TrialRun:
    """One trial: the factor (or kh) tried, its verdict and why, the largest displacement
    (m) of a watched block's point since the release, the fastest watched point's speed at
    the end and its peak (m/s), the block that decided (-1: none), simulated time (s) and
    steps of the trial, the run's status, the factor of the trial that held whose end
    state this one continued from (None: the settled model), and the face-to-face bonds
    (cohesion, tension over a patch) the trial broke whole and in part (progressively,
    where the stress over the contact is uneven)."""

    factor: float
    failed: bool
    reason: str
    displacement: float
    velocity: float
    peak_velocity: float
    block: int
    time: float
    steps: int
    status: str
    continued_from: float | None = None
    bonds_broken: int = 0
    bonds_broken_progressively: int = 0


@dataclass
class Settled:
    """Where trials start: the settled state (None: the scene as given), the displacement
    limit (m) and rest speed (m/s), the watched blocks, a note on the settling, and the
    factor whose trial held at rest in this state (None: the settled model)."""

    state: State | None
    limit: float
    rest_speed: float
    watch: np.ndarray
    note: str
    factor: float | None = None


def quasi_static_reason(dynamic_ratio: float, what: str = "the factor of safety"
                        ) -> str | None:
    """Why a search is refused for a model that keeps `dynamic_ratio` of its velocity
    between steps (None: it is dynamic)."""
    if dynamic_ratio >= 1.0:
        return None
    return (f"{what} needs analysis.mode 'dynamic' (dynamic_ratio 1; this scene has "
            f"{dynamic_ratio:g}): with velocities dropped every step a failing block only "
            "creeps, and no trial can tell it from one that holds (the trials settle the "
            "model quasi-statically before they start anyway)")


def refuse_quasi_static(model: Model, what: str = "the factor of safety") -> None:
    """QuasiStatic when the model drops (part of) its velocity every step."""
    reason = quasi_static_reason(model.controls.dynamic_ratio, what)
    if reason:
        raise QuasiStatic(reason)


def watched(model: Model, watch: tuple[int, ...] | None) -> np.ndarray:
    """The watched blocks `(k,)`: `watch`, or every block that is not fixed."""
    if watch:
        return np.array(sorted(set(watch)), dtype=np.int64)
    return np.array([k for k, b in enumerate(model.blocks) if not b.fixed], dtype=np.int64)


def displacement_limit(model: Model, watch: np.ndarray, given: float | None) -> float:
    """The trial's displacement limit (m): `given`, or DISPLACEMENT_LIMIT_RATIO × the size
    V^⅓ of the smallest watched block."""
    if given is not None:
        return float(given)
    if not len(watch):
        return DISPLACEMENT_LIMIT_RATIO * model.scale
    size = min(model.blocks[b].polyhedron.volume for b in watch) ** (1.0 / 3.0)
    return DISPLACEMENT_LIMIT_RATIO * float(size)


def strong(model: Model) -> Model:
    """`model` with joints that cannot fail (tan φ SETTLE_TAN_PHI, cohesion SETTLE_COHESION,
    tensile strengths as given), in quasi-static steps, under its static loads (a
    ground-motion history starts with the trials)."""
    joints = [JointMaterial(float(np.arctan(SETTLE_TAN_PHI)), SETTLE_COHESION,
                            j.tensile_strength) for j in model.joint_materials]
    duration = 10.0 * MAX_SETTLE_STEPS * model.controls.time_step
    controls = dataclasses.replace(model.controls, dynamic_ratio=0.0, duration=duration,
                                   record_contacts=False)
    return dataclasses.replace(model, joint_materials=joints, controls=controls,
                               ground_motion=None)


def settle(model: Model, watch: tuple[int, ...] | None, limit: float | None,
           observation_time: float) -> Settled:
    """Bring `model` to rest under its loads with joints that cannot fail (see the
    module's docstring); the start of its trials."""
    w = watched(model, watch)
    lim = displacement_limit(model, w, limit)
    rest = REST_SPEED_RATIO * lim / observation_time
    sim = Simulation(strong(model))
    quiet = 0
    try:
        for _ in range(MAX_SETTLE_STEPS):
            res = sim.step()
            moved = float(point_displacements(sim.system, res.d).max(initial=0.0))
            quiet = quiet + 1 if moved <= SETTLE_TOLERANCE * lim else 0
            if quiet >= SETTLED_STEPS:
                state = sim.state  # the trials' clock starts at 0 (a ground motion's too)
                state.time, state.dt = 0.0, model.controls.time_step
                state.diagnostics.dt_reason = "asked"
                return Settled(state, lim, rest, w, f"settled in {state.step} quasi-static "
                                                    "steps")
    except StepFailure as exc:
        return Settled(None, lim, rest, w, f"the model did not settle ({exc}): trials "
                                           "start from the scene as given")
    return Settled(None, lim, rest, w, f"the model did not settle in {MAX_SETTLE_STEPS} "
                                       "quasi-static steps (a block with nothing under "
                                       "it?): trials start from the scene as given")


class _Watch:
    """What a trial watches: the watched blocks' vertices at the release, their speeds."""

    def __init__(self, sim: Simulation, w: np.ndarray) -> None:
        s = sim.system
        self.blocks = w
        self.rows = np.flatnonzero(np.isin(s.vertex_block, w))
        self.vertex_block = s.vertex_block[self.rows]
        self.rel0 = s.vertex_rel0[self.rows]
        self.radius = s.radius[w]
        self.x0 = self.vertices(sim.state)
        self.mask = np.zeros(s.n, dtype=bool)
        self.mask[w] = True

    def vertices(self, state: State) -> np.ndarray:
        return block_vertices(state.centroid, state.affine, self.vertex_block, self.rel0)

    def displacement(self, state: State) -> tuple[float, int]:
        """The largest point displacement (m) since the release and its block."""
        if not len(self.rows):
            return 0.0, -1
        d = np.linalg.norm(self.vertices(state) - self.x0, axis=1)
        k = int(np.argmax(d))
        return float(d[k]), int(self.vertex_block[k])

    def speed(self, state: State) -> tuple[float, int]:
        """The fastest watched point's speed bound (m/s) and its block."""
        if not len(self.blocks):
            return 0.0, -1
        v = state.velocity[self.blocks]
        s = np.linalg.norm(v[:, :3], axis=1) + np.linalg.norm(v[:, 3:6], axis=1) * self.radius
        k = int(np.argmax(s))
        return float(s[k]), int(self.blocks[k])

    def stuck(self, res: object) -> bool:
        """Whether every closed contact of a watched block is locked."""
        cs = res.contacts  # type: ignore[attr-defined]
        mine = self.mask[cs.block_i] | self.mask[cs.block_j]
        closed = mine & (cs.mode != OPEN)
        return bool(np.all(cs.mode[closed] == LOCKED))


def run_trial(model: Model, value: float, start: Settled) -> tuple[TrialRun, Settled | None]:
    """Run the trial model `model` (its strengths or loads those of the trial `value`) from
    `start` and judge it (see the module's docstring); with the trial's end as a start for
    the next trials when it held at rest (an equilibrium at `value`)."""
    state = copy.deepcopy(start.state) if start.state is not None else None
    t0 = state.time if state is not None else 0.0
    m = dataclasses.replace(model, controls=dataclasses.replace(
        model.controls, duration=t0 + model.controls.duration, record_contacts=False))
    sim = Simulation(m, state=state)
    sleep.wake_all(sim.system, sim.state)  # a trial never starts asleep
    w = _Watch(sim, start.watch)
    end = m.controls.duration - 1e-12 * max(m.controls.duration, 1.0)
    peak, rest, steps = 0.0, 0, 0
    late, late_speed = t0 + (1.0 - LATE_FRACTION) * model.controls.duration, None

    bonds0 = (sim.state.diagnostics.bonds_broken,
              sim.state.diagnostics.bonds_broken_progressively)

    def verdict(failed: bool, reason: str, status: str = STATUS_COMPLETED) -> TrialRun:
        disp, block = w.displacement(sim.state)
        speed, fast = w.speed(sim.state)
        d = sim.state.diagnostics
        return TrialRun(value, failed, reason, disp, speed, max(peak, speed),
                        block if failed and block >= 0 else fast, sim.state.time - t0, steps,
                        status, start.factor, d.bonds_broken - bonds0[0],
                        d.bonds_broken_progressively - bonds0[1])

    while sim.state.time < end:
        try:
            res = sim.step()
        except StepFailure as exc:
            return verdict(True, f"the run failed: {exc}", STATUS_FAILED), None
        steps += 1
        s = sim.state
        finite = np.all(np.isfinite(s.velocity)) and np.all(np.isfinite(s.centroid))
        message = energy.check_run(sim.system, s) if finite else "non-finite state"
        if message:
            return verdict(True, f"the run failed: {message}", STATUS_FAILED), None
        disp, _ = w.displacement(s)
        if disp > start.limit:
            return verdict(True, f"moved {disp:.4g} m, more than the limit "
                                 f"{start.limit:.4g} m, {s.time - t0:.3g} s after release"
                           ), None
        speed, _ = w.speed(s)
        peak = max(peak, speed)
        if late_speed is None and s.time >= late:
            late_speed = speed
        rest = rest + 1 if speed < start.rest_speed and w.stuck(res) else 0
        if rest >= REST_STEPS:
            held = dataclasses.replace(start, state=s, factor=value)
            return verdict(False, f"at rest with every contact stuck {s.time - t0:.3g} s "
                                  f"after release (moved {disp:.3g} m)"), held
    return _at_end(verdict, w.speed(sim.state)[0], peak, late_speed, start), None


def still_moving(speed: float, peak: float, late: float | None, rest_speed: float) -> bool:
    """Whether a block at the end of a run is still moving (the trials' rule at the end of
    their window, and key blocks' judgement of a recorded run): faster than `rest_speed`,
    at least DECAY_RATIO of its `peak` speed, and not slower than it was LATE_FRACTION of
    the window before the end (`late`; None: not known)."""
    slowing = late is not None and speed < late
    return speed > rest_speed and speed >= DECAY_RATIO * peak and not slowing


def _at_end(verdict: Callable[[bool, str], TrialRun], speed: float, peak: float,
            late: float | None, start: Settled) -> TrialRun:
    """The verdict of a trial that reached the end of its window without a certain one
    (`late`: the speed LATE_FRACTION of the window before its end)."""
    if still_moving(speed, peak, late, start.rest_speed):
        return verdict(True, f"still moving at the end ({speed:.3g} m/s, peak "
                             f"{peak:.3g} m/s): the velocity does not decay")
    return verdict(False, f"moved less than the limit {start.limit:.4g} m and its speed "
                          f"decays ({speed:.3g} m/s at the end, peak {peak:.3g} m/s)")
