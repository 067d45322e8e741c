"""Drivers around the simulation: factor of safety by strength reduction (paper 6.1).

The joints' strength is divided by a trial factor F (tan φ / F, c / F, T / F) and the
model is run for an observation time; F fails when the moving blocks keep accelerating
over the observation window. Bisection on F gives the factor of safety, eq. 52:
`F_s = tan φ / tan φ_r`. The criterion is sustained acceleration, not a displacement
threshold, which would bias the answer with the observation time (VALIDATION.md 2.3).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from engine.loads.seismic import SeismicLoad
from engine.model import JointMaterial, Model, SeismicCoefficientControls, StrengthReductionControls
from engine.step.frame import Frame
from engine.step.simulation import STATUS_CANCELLED, STATUS_FAILED, run

__all__ = ["FactorOfSafetyResult", "SeismicCoefficientControls", "SeismicCoefficientResult",
           "StrengthReductionControls", "TrialRun", "critical_seismic_coefficient",
           "factor_of_safety", "reduced_model", "seismic_model", "trial"]


@dataclass
class TrialRun:
    """One strength-reduction trial: factor, verdict, measured mean acceleration (m/s²)."""

    factor: float
    failed: bool
    mean_acceleration: float
    status: str


@dataclass
class FactorOfSafetyResult:
    """Factor of safety, critical friction angle of each joint material (deg), trials."""

    factor_of_safety: float
    critical_friction_angles_deg: list[float]
    runs: list[TrialRun] = field(default_factory=list)
    status: str = "completed"
    message: str = ""

    def as_dict(self) -> dict:
        return {
            "factor_of_safety": self.factor_of_safety,
            "critical_friction_angle": self.critical_friction_angles_deg[0]
            if len(self.critical_friction_angles_deg) == 1 else self.critical_friction_angles_deg,
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


class _SpeedProbe:
    """A recorder that keeps the fastest point speed (m/s) of the moving blocks per step."""

    def __init__(self, radius: np.ndarray, moving: np.ndarray) -> None:
        self.radius, self.moving = radius, moving
        self.time: list[float] = []
        self.speed: list[float] = []

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        pass

    def record(self, frame: Frame) -> None:
        v = frame.velocity[self.moving]
        s = np.linalg.norm(v[:, :3], axis=1) + np.linalg.norm(v[:, 3:6], axis=1) * self.radius
        self.time.append(frame.time)
        self.speed.append(float(s.max(initial=0.0)))

    def end(self, status: str, message: str = "", summary: dict | None = None) -> None:
        pass

    def mean_acceleration(self, t0: float, t1: float) -> float:
        t, s = np.array(self.time), np.array(self.speed)
        if len(t) < 2:
            return 0.0
        v0 = np.interp(t0, t, s)
        v1 = np.interp(min(t1, t[-1]), t, s)
        return float((v1 - v0) / max(min(t1, t[-1]) - t0, 1e-12))


def trial(model: Model, factor: float, controls: StrengthReductionControls) -> TrialRun:
    """Run the model with strengths reduced by `factor`; failed = sustained acceleration."""
    m = reduced_model(model, factor, controls.observation_time, controls.joint_materials)
    return _observe(m, factor, controls)


def _observe(m: Model, factor: float,
             controls: StrengthReductionControls | SeismicCoefficientControls) -> TrialRun:
    """Run the trial model `m`; failed = sustained acceleration of the watched blocks."""
    radius = np.array([
        np.linalg.norm(b.polyhedron.vertices[b.polyhedron.surface_vertex_ids]
                       - b.polyhedron.centroid, axis=1).max() for b in m.blocks
    ])
    moving = np.array([not b.fixed for b in m.blocks])
    if controls.watch_blocks:
        watch = np.zeros(len(m.blocks), dtype=bool)
        watch[list(controls.watch_blocks)] = True
        moving &= watch
    probe = _SpeedProbe(radius[moving], moving)
    res = run(m, recorder=probe)
    if res.status == STATUS_CANCELLED:
        return TrialRun(factor, False, 0.0, res.status)
    acc = probe.mean_acceleration(controls.window_start, controls.observation_time)
    failed = res.status == STATUS_FAILED or acc > controls.acceleration_threshold
    return TrialRun(factor, bool(failed), acc, res.status)


def factor_of_safety(
    model: Model,
    controls: StrengthReductionControls | None = None,
    progress: Callable[[TrialRun], None] | None = None,
) -> FactorOfSafetyResult:
    """Factor of safety by bisection on the strength-reduction factor F."""
    c = controls or StrengthReductionControls()
    runs: list[TrialRun] = []

    def check(f: float) -> bool:
        r = trial(model, f, c)
        runs.append(r)
        if progress is not None:
            progress(r)
        return r.failed

    lo, hi = 1.0, 1.0
    if check(1.0):
        hi = 1.0
        lo = 0.5
        while check(lo):
            hi = lo
            lo *= 0.5
            if lo < c.min_factor:
                return _result(model, lo, runs, "failed",
                               f"the model fails even with strengths multiplied by {1 / lo:g}",
                               c.joint_materials)
    else:
        hi = 2.0
        while not check(hi):
            lo = hi
            hi *= 2.0
            if hi > c.max_factor:
                return _result(model, hi, runs, "completed",
                               f"no failure up to a reduction factor of {c.max_factor:g}; "
                               f"the factor of safety is at least that", c.joint_materials)
    while (hi - lo) / lo > c.tolerance and len(runs) < c.max_runs:
        mid = 0.5 * (lo + hi)
        if check(mid):
            hi = mid
        else:
            lo = mid
    return _result(model, 0.5 * (lo + hi), runs, "completed", "", c.joint_materials)


def _result(model: Model, factor: float, runs: list[TrialRun], status: str,
            message: str, which: tuple[int, ...] | None = None) -> FactorOfSafetyResult:
    crit = [float(np.degrees(np.arctan(np.tan(j.friction_angle_rad) / factor)))
            for k, j in enumerate(model.joint_materials) if which is None or k in which]
    return FactorOfSafetyResult(float(factor), crit, runs, status, message)


@dataclass
class SeismicCoefficientResult:
    """Critical (yield) seismic coefficient kh (fraction of g) and its trials (`factor` is
    the kh tried)."""

    critical_coefficient: float
    azimuth_deg: float
    kv: float
    runs: list[TrialRun] = field(default_factory=list)
    status: str = "completed"
    message: str = ""

    def as_dict(self) -> dict:
        return {
            "critical_seismic_coefficient": self.critical_coefficient,
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
    """The smallest horizontal seismic coefficient kh at which the watched blocks start to
    accelerate, by bisection on kh (the model's seismic azimuth and kv, full strengths)."""
    c = controls or SeismicCoefficientControls()
    base = model.seismic or SeismicLoad()
    runs: list[TrialRun] = []

    def check(kh: float) -> bool:
        r = _observe(seismic_model(model, kh, c.observation_time), kh, c)
        runs.append(r)
        if progress is not None:
            progress(r)
        return r.failed

    def result(kh: float, status: str = "completed", message: str = ""
               ) -> SeismicCoefficientResult:
        return SeismicCoefficientResult(float(kh), float(np.degrees(base.azimuth_rad)),
                                        float(base.kv), runs, status, message)

    if check(0.0):
        return result(0.0, "completed", "the model fails without seismic load: the critical "
                                        "seismic coefficient is 0")
    lo, hi = 0.0, min(0.1, c.max_coefficient)
    while not check(hi):
        lo = hi
        if hi >= c.max_coefficient:
            return result(hi, "completed", f"no failure up to kh = {c.max_coefficient:g}; "
                                           "the critical coefficient is at least that")
        hi = min(2.0 * hi, c.max_coefficient)
    while hi - lo > c.tolerance * hi and len(runs) < c.max_runs:
        mid = 0.5 * (lo + hi)
        if check(mid):
            hi = mid
        else:
            lo = mid
    return result(0.5 * (lo + hi))
