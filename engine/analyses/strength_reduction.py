"""Drivers around the simulation: factor of safety by strength reduction (paper 6.1) and the
critical (yield) seismic coefficient.

The joints' strength is divided by a trial factor F (tan φ / F, c / F, σt / F); bisection on
F gives the factor of safety, eq. 52: `F_s = tan φ / tan φ_r`. Each trial starts from the
model settled under its loads and is judged by the watched blocks' displacement and
velocity (:mod:`engine.analyses.trials`): it fails when a block moves beyond the
displacement limit or keeps moving without slowing down, and holds (ending early) when
every watched block is at rest on stuck contacts; every trial starts from the model's
equilibrium at F = 1 when it has one (FLAC's and 3DEC's restore). Bolts, cables and
water act in every trial exactly as in a run. The critical seismic coefficient bisects on
kh with the same trials (from the equilibrium at kh = 0).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.analyses.trials import (
    QuasiStatic,
    Settled,
    TrialRun,
    refuse_quasi_static,
    run_trial,
    settle,
)
from engine.loads.seismic import SeismicLoad
from engine.model import JointMaterial, Model, SeismicCoefficientControls, StrengthReductionControls

__all__ = ["FactorOfSafetyResult", "QuasiStatic", "SeismicCoefficientControls",
           "SeismicCoefficientResult", "StrengthReductionControls", "TrialRun",
           "critical_seismic_coefficient", "factor_of_safety", "reduced_model",
           "seismic_model", "trial"]


@dataclass
class FactorOfSafetyResult:
    """Factor of safety, critical friction angle of each joint material (deg), trials.

    `bound` is "lower" when no trial failed up to the largest factor (the factor of safety
    is at least `factor_of_safety`), "upper" when every trial failed down to the smallest
    (it is below it), None for a bracketed answer."""

    factor_of_safety: float
    critical_friction_angles_deg: list[float]
    runs: list[TrialRun] = field(default_factory=list)
    status: str = "completed"
    message: str = ""
    bound: str | None = None
    displacement_limit: float = 0.0
    settling: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "factor_of_safety": self.factor_of_safety,
            "bound": self.bound,
            "critical_friction_angle": self.critical_friction_angles_deg[0]
            if len(self.critical_friction_angles_deg) == 1 else self.critical_friction_angles_deg,
            "displacement_limit": self.displacement_limit,
            "settling": self.settling,
            "runs": [dataclasses.asdict(r) for r in self.runs],
            "status": self.status,
            "message": self.message,
        }


def reduced_model(model: Model, factor: float, duration: float,
                  which: tuple[int, ...] | None = None) -> Model:
    """A copy of `model` with the strengths of joint materials `which` (None: all) divided
    by `factor`, and the given duration."""
    joints = [
        JointMaterial(
            friction_angle_rad=float(np.arctan(np.tan(j.friction_angle_rad) / factor)),
            cohesion=j.cohesion / factor,
            tensile_strength=j.tensile_strength / factor,
        )
        if which is None or k in which else j
        for k, j in enumerate(model.joint_materials)
    ]
    controls = dataclasses.replace(model.controls, duration=duration, record_contacts=False,
                                   record_interval=1)
    return dataclasses.replace(model, joint_materials=joints, controls=controls)


def start_of_trials(model: Model, controls: StrengthReductionControls) -> Settled:
    """Where the factor of safety's trials start: the model settled under its loads
    (QuasiStatic for a quasi-static model)."""
    refuse_quasi_static(model)
    return settle(model, controls.watch_blocks, controls.displacement_limit,
                  controls.observation_time)


def trial(model: Model, factor: float, controls: StrengthReductionControls,
          start: Settled | None = None) -> TrialRun:
    """One trial with the strengths reduced by `factor`, from `start` (default: the model
    settled afresh)."""
    return _trial(model, factor, controls, start or start_of_trials(model, controls))[0]


def _trial(model: Model, factor: float, controls: StrengthReductionControls,
           start: Settled) -> tuple[TrialRun, Settled | None]:
    m = reduced_model(model, factor, controls.observation_time, controls.joint_materials)
    return run_trial(m, factor, start)


class _Starts:
    """Where a search's trials start: the model's own equilibrium, the end state of the
    trial at `in_situ` (F = 1, the scene's strengths; kh = 0) when it held at rest, as
    FLAC's and 3DEC's strength reduction restore the initial equilibrium for every trial;
    else the model settled with joints that cannot fail. (Continuing each trial from the
    last one that held instead lets a wedge's locked corners ratchet, trial after trial,
    into a wedged state that holds up to 3 % beyond limit equilibrium.)"""

    def __init__(self, settled: Settled | None, in_situ: float, chain: bool = True) -> None:
        self.settled = settled
        self.in_situ = in_situ
        self.best: Settled | None = None
        #: not under a ground-motion history: every trial feels it from its start
        self.chain = chain

    def before(self, value: float) -> Settled | None:
        if self.best is not None and self.best.factor is not None and self.best.factor < value:
            return self.best
        return self.settled

    def held(self, end: Settled | None) -> None:
        if self.chain and end is not None and end.factor == self.in_situ:
            self.best = end


#: a guided trial is placed this fraction of the tolerance from the estimate, either side
GUIDE_OFFSET = 0.4


def failing_rate(r: TrialRun) -> float:
    """How fast a failed trial's block got away: the uniform acceleration that moves it
    `displacement` in the trial's `time` from rest (m/s²)."""
    return 2.0 * r.displacement / max(r.time, 1e-12) ** 2


def estimate(runs: list[TrialRun], x_of: Callable[[float], float],
             f_of: Callable[[float], float]) -> float | None:
    """Where the failed trials' rate of motion extrapolates to zero: the rate is linear in
    `x_of(factor)` for a block sliding on planes (g (sin ψ − cos ψ tan φ / F) in 1 / F;
    linear in kh), fitted through the two failed trials nearest the bracket (None with
    fewer, or when they do not point to a root; the caller keeps it only inside its
    bracket)."""
    failed = sorted((r for r in runs if r.failed and r.status == "completed"
                     and r.time > 0), key=lambda r: x_of(r.factor))
    if len(failed) < 2:
        return None
    a, b = failed[-2], failed[-1]  # the largest x: the failures nearest the answer
    xa, xb, ra, rb = x_of(a.factor), x_of(b.factor), failing_rate(a), failing_rate(b)
    if xa == xb or ra <= rb:  # the rate must fall toward the answer
        return None
    x0 = xb + rb * (xb - xa) / (ra - rb)
    return f_of(x0) if x0 != 0 else None


def bracket(check: Callable[[float], bool], lo: float, hi: float,
            narrow: Callable[[float, float], bool], runs: list[TrialRun], max_runs: int,
            guess: Callable[[], float | None], tolerance: float) -> float:
    """Narrow the bracket [lo (holds), hi (fails)] until `narrow(lo, hi)`; its midpoint.
    Each step tries just below and then just above the `guess()` (the failed trials'
    estimate, `GUIDE_OFFSET × tolerance` away relative: a trial that holds is short, one
    that fails near the answer runs its whole window, so two guided trials close a bracket
    bisection needs four or five for), or bisects when there is no guess or the last
    guided trial disagreed with it. Every answer is a bracket the trials verified."""
    guided = True
    while not narrow(lo, hi) and len(runs) < max_runs:
        g = guess() if guided else None
        margin = 0.01 * (hi - lo)
        if g is not None and lo + margin < g < hi - margin:
            below = max(g * (1.0 - GUIDE_OFFSET * tolerance), lo + margin)
            above = min(g * (1.0 + GUIDE_OFFSET * tolerance), hi - margin)
            if check(below):
                hi, guided = below, False  # the estimate was high: bisect next
                continue
            lo = below
            if narrow(lo, hi) or len(runs) >= max_runs:
                break
            if check(above):
                hi = above
            else:
                lo, guided = above, False
            continue
        guided = True
        mid = 0.5 * (lo + hi)
        if check(mid):
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def factor_of_safety(
    model: Model,
    controls: StrengthReductionControls | None = None,
    progress: Callable[[TrialRun], None] | None = None,
) -> FactorOfSafetyResult:
    """Factor of safety by bisection on the strength-reduction factor F, within
    [min_factor, max_factor] (a bound beyond them); QuasiStatic for a quasi-static model."""
    c = controls or StrengthReductionControls()
    start = start_of_trials(model, c)
    starts = _Starts(start, 1.0, chain=model.ground_motion is None)
    runs: list[TrialRun] = []

    def check(f: float) -> bool:
        r, end = _trial(model, f, c, starts.before(f))
        starts.held(end)
        runs.append(r)
        if progress is not None:
            progress(r)
        return r.failed

    def result(f: float, bound: str | None = None, message: str = "") -> FactorOfSafetyResult:
        crit = [float(np.degrees(np.arctan(np.tan(j.friction_angle_rad) / f)))
                for k, j in enumerate(model.joint_materials)
                if c.joint_materials is None or k in c.joint_materials]
        return FactorOfSafetyResult(float(f), crit, runs, "completed", message, bound,
                                    start.limit, start.note)

    def guess() -> float | None:
        return estimate(runs, lambda f: 1.0 / f, lambda x: 1.0 / x)

    def narrow(lo: float, hi: float) -> FactorOfSafetyResult:
        return result(bracket(check, lo, hi, lambda a, b: (b - a) / a <= c.tolerance, runs,
                              c.max_runs, guess, c.tolerance))

    f = min(max(1.0, c.min_factor), c.max_factor)
    if check(f):
        hi = f
        while True:
            lo = max(0.5 * hi, c.min_factor)
            if not check(lo):
                return narrow(lo, hi)
            if lo <= c.min_factor:
                return result(lo, "upper", f"every trial failed, down to F = {lo:g}: the "
                                           f"factor of safety is below {lo:g}")
            hi = lo
    lo = f
    while True:
        hi = min(2.0 * lo, c.max_factor)
        if hi <= lo:
            return result(lo, "lower", f"no trial failed up to F = {lo:g}: the factor of "
                                       f"safety is at least {lo:g}")
        if check(hi):
            return narrow(lo, hi)
        lo = hi


@dataclass
class SeismicCoefficientResult:
    """Critical (yield) seismic coefficient kh (fraction of g) and its trials (`factor` is
    the kh tried); `bound` "lower" when no kh up to the largest failed."""

    critical_coefficient: float
    azimuth_deg: float
    kv: float
    runs: list[TrialRun] = field(default_factory=list)
    status: str = "completed"
    message: str = ""
    bound: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "critical_seismic_coefficient": self.critical_coefficient,
            "bound": self.bound,
            "azimuth": self.azimuth_deg,
            "kv": self.kv,
            "runs": [{"kh": r.factor, **{k: v for k, v in dataclasses.asdict(r).items()
                                         if k != "factor"}} for r in self.runs],
            "status": self.status,
            "message": self.message,
        }


def seismic_model(model: Model, kh: float, duration: float) -> Model:
    """A copy of `model` with horizontal seismic coefficient `kh` (its azimuth and kv kept)
    and the given duration."""
    seismic = dataclasses.replace(model.seismic or SeismicLoad(), kh=float(kh))
    controls = dataclasses.replace(model.controls, duration=duration, record_contacts=False,
                                   record_interval=1)
    return dataclasses.replace(model, seismic=seismic, controls=controls)


def critical_seismic_coefficient(
    model: Model,
    controls: SeismicCoefficientControls | None = None,
    progress: Callable[[TrialRun], None] | None = None,
) -> SeismicCoefficientResult:
    """The smallest horizontal seismic coefficient kh at which the watched blocks fail, by
    bisection on kh (the model's seismic azimuth and kv, full strengths); each trial starts
    from the equilibrium at kh = 0. QuasiStatic for a quasi-static model."""
    c = controls or SeismicCoefficientControls()
    refuse_quasi_static(model, "the critical seismic coefficient")
    base = model.seismic or SeismicLoad()
    runs: list[TrialRun] = []
    starts = _Starts(None, 0.0, chain=model.ground_motion is None)

    def check(kh: float) -> bool:
        m = seismic_model(model, kh, c.observation_time)
        start = starts.before(kh) or settle(m, c.watch_blocks, c.displacement_limit,
                                            c.observation_time)
        r, end = run_trial(m, kh, start)
        starts.held(end)
        runs.append(r)
        if progress is not None:
            progress(r)
        return r.failed

    def result(kh: float, message: str = "", bound: str | None = None
               ) -> SeismicCoefficientResult:
        return SeismicCoefficientResult(float(kh), float(np.degrees(base.azimuth_rad)),
                                        float(base.kv), runs, "completed", message, bound)

    if check(0.0):
        return result(0.0, "the model fails without seismic load: the critical seismic "
                           "coefficient is 0")
    lo, hi = 0.0, min(0.1, c.max_coefficient)
    while not check(hi):
        lo = hi
        if hi >= c.max_coefficient:
            return result(hi, f"no failure up to kh = {c.max_coefficient:g}; the critical "
                              "coefficient is at least that", "lower")
        hi = min(2.0 * hi, c.max_coefficient)
    return result(bracket(check, lo, hi, lambda a, b: b - a <= c.tolerance * b, runs,
                          c.max_runs, lambda: estimate(runs, lambda k: -k, lambda x: -x),
                          c.tolerance))
