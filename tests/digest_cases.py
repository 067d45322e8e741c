"""Step digests: every example and validation case run for a short time, reduced to the numbers
that a behaviour-preserving change of the engine must keep (to 1e-12).

`python -m tests.digest_cases` records them into `tests/data/step_digests.json`; the test
`tests/test_step_digests.py` runs the cases again and compares. Re-record only for a change
that is meant to change the physics, and say so in its commit (or, for the CHAOTIC cases,
on a new platform: the file says which platform recorded them).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from engine.geometry.shapes import box
from engine.model import AnalysisControls, Block, FixedPoint, JointMaterial, Model
from engine.step.simulation import run

ROOT = Path(__file__).resolve().parents[1]
DIGESTS = ROOT / "tests" / "data" / "step_digests.json"


def _example(name: str, **controls: Any) -> Callable[[], Model]:
    def build() -> Model:
        from schemas.convert import build_model

        model = build_model(ROOT / "examples" / f"{name}.json").model
        model.controls = dataclasses.replace(model.controls, **controls)
        return model
    return build


def _staged(name: str, durations: list[float]) -> Callable[[], Any]:
    """A staged example with its stages shortened to `durations` (s): (model, stages)."""
    def build() -> Any:
        from schemas.convert import build_model

        scene = json.loads((ROOT / "examples" / f"{name}.json").read_text())
        for stage, duration in zip(scene["stages"], durations, strict=True):
            stage["duration"] = duration
        built = build_model(scene, base_dir=ROOT / "examples")
        return built.model, built.stages
    return build


def _incline(phi: float, **controls: Any) -> Callable[[], Model]:
    def build() -> Model:
        from tests.test_simulation import incline_model

        return incline_model(phi, **controls)
    return build


def _cohesion() -> Model:
    from tests.test_simulation import incline_model

    model = incline_model(20.0, duration=0.1)
    model.joint_materials = [JointMaterial(np.radians(20.0), cohesion=12000.0)]
    return model


def _hanging() -> Model:
    return Model(
        blocks=[Block(box([-1, -1, 1], [2, 2, 2]), "roof", fixed=True),
                Block(box([0, 0, 0], [1, 1, 1]), "cube")],
        joint_materials=[JointMaterial(np.radians(30), tensile_strength=30000.0)],
        controls=AnalysisControls(duration=0.1, time_step=1e-3, penalty=1e10))


def _pendulum() -> Model:
    return Model(
        blocks=[Block(box([0, 0, 0], [1, 1, 1]), "cube",
                      velocity=np.array([0.0, 0.05, 0.0, 0.1, 0.0, 0.0]))],
        fixed_points=[FixedPoint(0, np.array([0.5, 0.5, 1.0]))],
        controls=AnalysisControls(duration=0.3, time_step=2e-3))


def _drop() -> Model:
    return Model(
        blocks=[Block(box([-2, -2, -1], [3, 3, 0]), "base", fixed=True),
                Block(box([0, 0, 1.0], [1, 1, 2.0]), "cube")],
        joint_materials=[JointMaterial(np.radians(30.0))],
        controls=AnalysisControls(duration=1.0, time_step=0.1, penalty=1e9))


def _pile() -> Model:
    from benchmarks.pile import pile_model

    return pile_model(100, duration=0.55)


def _rock_mass(spacing: float, steps_time: float) -> Callable[[], Model]:
    def build() -> Model:
        from benchmarks.pile import rock_mass_model

        return rock_mass_model(spacing, duration=steps_time)
    return build


#: name -> model builder (all of them together run in ~6 s)
CASES: dict[str, Callable[[], Model]] = {
    "wedge": _example("wedge", duration=0.3),
    "wedge_trough": _example("wedge_trough", duration=0.2),
    "block_system": _example("block_system", duration=0.02),
    "toppling": _example("toppling", duration=0.05),
    "toppling_goodman_bray": _example("toppling_goodman_bray", duration=0.05),
    "incline": _example("incline", duration=0.5),
    "free_fall": _example("free_fall", duration=0.8),
    "pushed_block": _example("pushed_block", duration=0.3),
    "stack": _example("stack", duration=0.2),
    "incline_stable_35": _incline(35.0, duration=0.3),
    "incline_dt_0.1": _incline(20.0, duration=1.0, dt=0.1),
    "cohesion": _cohesion,
    "hanging": _hanging,
    "pendulum": _pendulum,
    "drop_dt_0.1": _drop,
    "pile_100": _pile,
    "rock_mass_5m": _rock_mass(5.0, 0.02),
    "rock_mass_2.5m": _rock_mass(2.5, 0.005),
    "benched_slope": _example("benched_slope", duration=0.02),
    "terrain_slope": _example("terrain_slope", duration=0.01),
}

#: staged cases: name -> (model, stages) builder
STAGED: dict[str, Callable[[], Any]] = {
    "tunnel_staged": _staged("tunnel_staged", [0.02, 0.04, 0.02]),
}


#: every digest: the runs and a factor-of-safety search
NAMES = [*CASES, *STAGED, "fos_incline"]

#: cases whose path follows round-off: many contacts, the open-close iteration's cycles and
#: Δt cuts decided by a few ulps (a rock mass is chaotic). Their digests hold to 1e-12 on the
#: platform that recorded them (same CPU, numpy, scipy, numba); elsewhere a BLAS kernel or a
#: compiler's instruction choice moves them, and only the other cases are compared
CHAOTIC = frozenset({"block_system", "pile_100", "rock_mass_5m", "rock_mass_2.5m",
                     "benched_slope", "terrain_slope", "tunnel_staged"})


def platform_key() -> dict[str, str]:
    """What decides the engine's round-off: the CPU (numba compiles for it), and the
    versions of numpy (with its BLAS), scipy, numba and llvmlite."""
    import platform

    import llvmlite
    import numba
    import scipy

    cpu = platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((line.split(":", 1)[1].strip() for line in fh
                        if line.startswith("model name")), cpu)
    except OSError:
        pass
    blas = np.show_config(mode="dicts").get("Build Dependencies", {}).get("blas", {})
    return {"cpu": cpu, "numpy": np.__version__, "blas": f"{blas.get('name')} "
            f"{blas.get('version')}", "scipy": scipy.__version__, "numba": numba.__version__,
            "llvmlite": llvmlite.__version__}


class _Digest:
    """A recorder keeping what a digest needs of every step."""

    def __init__(self) -> None:
        self.time: list[float] = []
        self.dt: list[float] = []
        self.iterations: list[int] = []
        self.penetration: list[float] = []
        self.position: list[float] = []
        self.last: Any = None

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        pass

    def record(self, frame: Any) -> None:
        self.time.append(frame.time)
        self.dt.append(frame.dt)
        self.iterations.append(frame.open_close_iterations)
        self.penetration.append(frame.max_penetration)
        self.position.append(float(np.abs(frame.centroids).sum()
                                   + np.abs(frame.rotation).sum()))
        self.last = frame

    def end(self, status: str, message: str = "", summary: Any = None) -> None:
        self.status, self.message = status, message


def _fos_incline() -> dict[str, Any]:
    """Strength reduction of the stable incline (φ 35°), short observation window."""
    from engine.analyses.strength_reduction import StrengthReductionControls, factor_of_safety
    from tests.test_simulation import incline_model

    res = factor_of_safety(incline_model(35.0, dt=0.01), StrengthReductionControls(
        observation_time=0.6, tolerance=0.02))
    return {"factor": res.factor_of_safety, "runs": [
        [r.factor, float(r.failed), r.displacement, r.velocity, r.time] for r in res.runs]}


def digest(name: str) -> dict[str, Any]:
    """The digest of case `name`: status, steps, per-step series, final state."""
    if name == "fos_incline":
        return _fos_incline()
    rec = _Digest()
    if name in STAGED:
        from engine.step.staged_run import run_stages

        model, stages = STAGED[name]()
        model.controls = dataclasses.replace(model.controls, record_interval=1)
        res = run_stages(model, stages, recorder=rec)
    else:
        model = CASES[name]()
        model.controls = dataclasses.replace(model.controls, record_interval=1)
        res = run(model, recorder=rec)
    f = rec.last
    return {
        "status": res.status, "message": res.message, "steps": res.steps,
        "time": rec.time, "dt": rec.dt, "iterations": rec.iterations,
        "penetration": rec.penetration, "position": rec.position,
        "centroids": f.centroids.tolist(), "affine": f.affine.tolist(),
        "velocity": f.velocity.tolist(), "stress": f.stress.tolist(),
        "energies": {k: float(v) for k, v in f.energies.items()},
        "n_contacts": 0 if f.contacts is None else len(f.contacts),
        "normal_force": [] if f.normal_force is None else f.normal_force.tolist(),
    }


def main(argv: list[str]) -> int:
    names = argv or NAMES
    old = json.loads(DIGESTS.read_text()) if DIGESTS.exists() else {}
    old["_platform"] = platform_key()
    for name in names:
        old[name] = digest(name)
        print(f"{name}: {old[name].get('steps', old[name].get('factor'))}", flush=True)
    DIGESTS.write_text(json.dumps(old, indent=0, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
