"""Sweeps and Monte Carlo analyses of a scene: realisations from a seed, one factor of
safety each.

A :class:`SweepSpec` varies the scene's parameters (:class:`Parameter`: joint friction angle
and cohesion, a joint set's orientation with Fisher dispersion, water level, kh, bolt
pretension and capacity, penalty, time step), each given as a distribution or as a fixed
list of values (a study: the value parameters form a grid). Each random parameter draws from
its own stream of (seed, parameter name) (`friction_angle` from the seed itself, as the
friction-only sweeps always did), so realisation k is the same whatever N and adding a
parameter leaves the others' draws as they were. A realisation is the scene with its values
written in (:func:`realisation_scene`; an orientation re-cuts the blocks), evaluated by the
engine's strength reduction (`dda`:
:func:`engine.analyses.strength_reduction.factor_of_safety`) or by limit equilibrium
(`analytic`: :mod:`engine.analyses.limit_equilibrium`, a planar block or a two-plane wedge
with everything the scene has, or refused saying why), and written
to `OUT/realisations/NNNNN.json` (or, for the service's jobs, to a folder shared by every
job of the same sweep) as soon as it is done; a re-run with the same scene and spec skips
those already there. A spec may cover a share of the N (`only`): jobs run shares and
:func:`merge_documents` joins them. The aggregate (probability of failure, histogram, CDF,
sensitivity to each parameter; engine.analyses.reliability) goes to `OUT/sweep.json`, beside
limit equilibrium's of the same realisations when it applies to every one (in mode `dda`
its strength-reduction factor, the engine's definition). """

from __future__ import annotations

import copy
import hashlib
import json
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np

from engine.analyses.jointstats import scatter_about
from engine.analyses.kinematics import normal
from engine.analyses.sweep import (
    LEGACY_NAME,
    Parameter,
    SweepSpec,
    sweep_document,
)
from schemas.scene import SweepParameterSpec
from service.documents import finite, write_json_atomic


def parameter_of(name: str, spec: SweepParameterSpec | Mapping[str, Any]) -> Parameter:
    """The parameter `name` of a scene's (or a document's) spec, validated (a ValueError
    names what is wrong); the quantity defaults to the name."""
    if not isinstance(spec, SweepParameterSpec):
        spec = SweepParameterSpec.model_validate(
            {"quantity": name} | {k: v for k, v in spec.items() if k != "name"})
    d = spec.model_dump(exclude_none=True)
    if "values" in d:
        d["values"] = tuple(float(v) for v in d["values"])
    return Parameter(name=name, **d)


def _rotate_about(points: Any, centre: Any, a: np.ndarray, b: np.ndarray) -> list[list[float]]:
    """`points` turned about `centre` by the rotation taking unit vector `a` to `b`
    (Rodrigues), so a joint's extent follows its plane."""
    pts = np.asarray(points, float) - np.asarray(centre, float)
    axis, c = np.cross(a, b), float(a @ b)
    s = float(np.linalg.norm(axis))
    if s < 1e-15:
        return (pts + centre).tolist()
    k = axis / s
    rot = pts * c + np.cross(k, pts) * s + np.outer(pts @ k, k) * (1.0 - c)
    return (rot + np.asarray(centre, float)).tolist()


def _orient(joint: dict[str, Any], theta: float, psi: float) -> dict[str, float]:
    """Turn the joint (or set) `theta` radians from its normal at azimuth `psi`, its
    extent with it; its new dip and dip direction."""
    dip0, dd0 = float(joint["dip"]), float(joint["dip_direction"])
    dips, dds = scatter_about(dip0, dd0, theta, psi)
    joint["dip"], joint["dip_direction"] = float(dips[0]), float(dds[0])
    a, b = normal(dip0, dd0), normal(joint["dip"], joint["dip_direction"])
    extent = joint.get("extent") or {}
    if extent.get("polygon") is not None:
        extent["polygon"] = _rotate_about(extent["polygon"], joint["point"], a, b)
    if (extent.get("disc") or {}).get("center") is not None:
        extent["disc"]["center"] = _rotate_about([extent["disc"]["center"]], joint["point"],
                                                 a, b)[0]
    return {"dip": joint["dip"], "dip_direction": joint["dip_direction"]}


def _apply(scene: dict[str, Any], parameters: Sequence[Parameter],
           values: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """A copy of the scene with each parameter's value written in, and the values as
    recorded (an orientation as its dip and dip direction)."""
    out = copy.deepcopy(scene)
    recorded: dict[str, Any] = {}
    for p in parameters:
        v = values[p.name]
        q = p.quantity
        if q in ("friction_angle", "cohesion"):
            mats = out.setdefault("joint_materials", {}) or {"joint": {}}
            out["joint_materials"] = mats
            fos = (out.get("analysis") or {}).get("factor_of_safety") or {}
            names = [p.joint_material] if p.joint_material else (
                fos.get("joint_materials") or list(mats))
            for name in names:
                mats[name] = dict(mats.get(name, {}), **{q: float(v)})
        elif q == "joint_orientation":
            joints = out["joints"]
            (k,) = [k for k, j in enumerate(joints) if (j.get("name") or f"J{k + 1}") == p.joint]
            recorded[p.name] = _orient(joints[k], float(v[0]), float(v[1]))
            continue
        elif q == "water_level":
            out["water"]["phreatic_surface"]["point"][2] = float(v)
        elif q == "kh":
            out["seismic"]["kh"] = float(v)
        elif q.startswith("bolt_"):
            field = q.removeprefix("bolt_")
            for k, b in enumerate(out.get("bolts") or []):
                if p.bolt in (None, b.get("name") or f"bolt{k + 1}"):
                    b[field] = float(v)
            for bp in out.get("bolt_patterns") or []:
                if p.bolt in (None, bp.get("name_prefix", "bolt")):
                    bp[field] = float(v)
        else:  # penalty, time_step
            out.setdefault("analysis", {})[q] = float(v)
        recorded[p.name] = float(v)
    return out, recorded


def realisation_scene(scene: dict[str, Any], values: float | Mapping[str, Any],
                      parameters: Sequence[Parameter] | None = None) -> dict[str, Any]:
    """A copy of the scene with a realisation's values written in: `values` by parameter
    name (a row of :meth:`SweepSpec.draws`) of the `parameters`, or one friction angle for
    every weakened joint material (those of the factor of safety when it names them)."""
    if not isinstance(values, Mapping):
        values = {LEGACY_NAME: values}
        parameters = (Parameter(LEGACY_NAME, "friction_angle", "values", values=(0.0,)),)
    return _apply(scene, parameters or (), values)[0]


def _with_friction(scene: dict[str, Any], friction_angle: float) -> dict[str, Any]:
    """The scene with `friction_angle` (degrees) on every weakened joint material."""
    return realisation_scene(scene, friction_angle)


def limit_equilibrium_of(build: Any) -> tuple[float | None, float | None, str | None]:
    """The limit-equilibrium factor of safety (Hoek & Bray's convention) and
    strength-reduction factor of a built realisation, or (None, None, why it does not
    apply); an unbounded factor (nothing drives the block) is None with its note."""
    from schemas.errors import SceneError
    from service.documents import le_result

    try:
        r = le_result(build)
    except SceneError as exc:
        return None, None, "; ".join(p["msg"] for p in exc.problems)
    if not np.isfinite(r.factor_of_safety):
        return None, None, "no force drives the block: its factor of safety is unbounded"
    srf = r.strength_reduction_factor
    return float(r.factor_of_safety), float(srf) if np.isfinite(srf) else None, None


def analytic_fs(scene: dict[str, Any], friction_angle: float | None = None) -> float | None:
    """The limit-equilibrium factor of safety of a scene (engine.analyses.limit_equilibrium:
    the vector method with everything the scene has: cohesion, water, bolts, seismic load,
    point loads), with `friction_angle` (degrees) on every weakened joint material when
    given; None when limit equilibrium does not apply or the scene is invalid."""
    from schemas.convert import build_model
    from schemas.errors import SceneError

    if friction_angle is not None:
        scene = _with_friction(scene, friction_angle)
    try:
        build = build_model(scene)
    except SceneError:
        return None
    return limit_equilibrium_of(build)[0]


class Stopped(Exception):
    """A stop was asked for in the middle of a realisation."""


def spec_of_scene(scene: dict[str, Any]) -> SweepSpec:
    """The SweepSpec of a scene's `sweep` (SceneError when it has none or it is invalid)."""
    from schemas.errors import SceneError
    from schemas.scene import load_scene

    s = load_scene(scene).sweep
    if s is None:
        raise SceneError([{"loc": "sweep", "msg": "a sweep needs 'sweep': {\"n\", \"seed\", "
                           "\"parameters\": {...} (or \"friction_angle\": {\"mean\", "
                           "\"sd\"}), \"mode\"}"}])
    only = None if s.realisations is None else tuple(s.realisations)
    short = s.friction_angle
    return SweepSpec(s.n, s.seed, None if short is None else short.mean,
                     None if short is None else short.sd, s.mode, only,
                     tuple(parameter_of(name, p) for name, p in s.parameters.items()))


def dda_fs(build: Any, should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """The engine's factor of safety of a realisation's built scene (strength reduction);
    Stopped between trials once `should_stop()`."""
    from engine.analyses.strength_reduction import QuasiStatic, TrialRun, factor_of_safety
    from service.documents import fos_controls

    def check(_: TrialRun) -> None:
        if should_stop is not None and should_stop():
            raise Stopped

    start = time.perf_counter()
    try:
        res = factor_of_safety(build.model, fos_controls(build), progress=check)
    except QuasiStatic as exc:
        return {"factor_of_safety": None, "status": "refused", "message": str(exc),
                "trials": 0, "wall_time": time.perf_counter() - start}
    return {"factor_of_safety": res.factor_of_safety, "status": res.status,
            "bound": res.bound, "trials": len(res.runs), "message": res.message,
            "wall_time": time.perf_counter() - start}


def evaluate(scene: dict[str, Any], spec: SweepSpec, index: int, values: Mapping[str, Any],
             should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """One realisation's record: index, its parameters' values (and φ as before when the
    sweep has `friction_angle`), its factor of safety by the spec's mode, and limit
    equilibrium's (`analytic_fs`, everything the scene has counted; in mode `dda` the
    strength-reduction factor, the same definition as the engine's; None with
    `analytic_note` saying why when limit equilibrium does not apply). A realisation whose
    values make the scene invalid (e.g. a pretension above the capacity) is recorded with
    the problem, no FS."""
    from schemas.convert import build_model
    from schemas.errors import SceneError

    scene_k, recorded = _apply(scene, spec.all_parameters(), values)
    rec: dict[str, Any] = {"index": index, "parameters": recorded}
    if LEGACY_NAME in recorded:
        rec["friction_angle"] = recorded[LEGACY_NAME]
    start = time.perf_counter()
    try:
        build = build_model(scene_k)
    except SceneError as exc:
        return rec | {"analytic_fs": None, "factor_of_safety": None,
                      "status": "invalid scene", "message": "; ".join(exc.lines()),
                      "trials": 0, "wall_time": time.perf_counter() - start}
    fs, srf, why = limit_equilibrium_of(build)
    rec["analytic_fs"] = fs if spec.mode == "analytic" else srf
    if why is not None:
        rec["analytic_note"] = why
    if spec.mode == "analytic":
        return rec | {"factor_of_safety": fs,
                      "status": "completed" if fs is not None else
                      f"limit equilibrium does not apply: {why}"}
    return rec | dda_fs(build, should_stop)


def _row(draws: Mapping[str, np.ndarray], k: int) -> dict[str, Any]:
    """Realisation k's values by parameter name (plain floats, or a pair for Fisher)."""
    return {name: (v[k].tolist() if v.ndim > 1 else float(v[k])) for name, v in draws.items()}


def _digest(scene: dict[str, Any], spec: SweepSpec) -> str:
    """Identity of the realisations' population: the scene and spec but not the share."""
    scene = copy.deepcopy(scene)
    if isinstance(scene.get("sweep"), dict):
        scene["sweep"].pop("realisations", None)
    text = json.dumps({"scene": scene, "spec": spec.population()}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def run_sweep(scene: dict[str, Any], spec: SweepSpec, out: Path, workers: int = 1,
              progress: Callable[[int, int, int], None] | None = None,
              should_stop: Callable[[], bool] | None = None,
              limit: int | None = None, shared: Path | None = None) -> dict[str, Any]:
    """Evaluate the realisations not yet in `out` (at most `limit` of them, in `workers`
    processes), then aggregate every one done. `progress(done, n, evaluated_now)` after
    each; `should_stop` ends the sweep early (the aggregate covers the realisations done).
    With `shared`, the realisation files live in `shared/<population digest>/` instead,
    where every job of the same sweep finds those any other job already did."""
    out = Path(out)
    digest = _digest(scene, spec)
    rdir = out / "realisations" if shared is None else Path(shared) / digest
    rdir.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    stamp = out / "sweep.id"
    if stamp.exists() and stamp.read_text().strip() != digest:
        raise ValueError(f"{out} holds a sweep of another scene or spec; use another folder")
    stamp.write_text(digest + "\n")
    draws = spec.draws()
    records: dict[int, dict[str, Any]] = {}
    for k in spec.indices():
        path = rdir / f"{k:05d}.json"
        if path.is_file():
            records[k] = json.loads(path.read_text())
    todo = [k for k in spec.indices() if k not in records][:limit]
    evaluated = 0

    def done(rec: dict[str, Any]) -> None:
        nonlocal evaluated
        write_json_atomic(rdir / f"{rec['index']:05d}.json", finite(rec))
        records[rec["index"]] = rec
        evaluated += 1
        if progress is not None:
            progress(len(records), len(spec.indices()), evaluated)

    stop = should_stop or (lambda: False)
    if workers <= 1:
        for k in todo:
            if stop():
                break
            try:
                done(evaluate(scene, spec, k, _row(draws, k), stop))
            except Stopped:
                break
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            pending: set[Future] = set()
            queue = list(todo)
            while queue or pending:
                while queue and len(pending) < workers and not stop():
                    k = queue.pop(0)
                    pending.add(pool.submit(evaluate, scene, spec, k, _row(draws, k)))
                if not pending:
                    break
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    done(f.result())
    doc = sweep_document(spec, [records[k] for k in sorted(records)])
    write_json_atomic(out / "sweep.json", doc)
    return doc


#: times a share whose job failed for a system reason (its worker died) is submitted again
RESUBMIT = 1


def share_scene(scene: Mapping[str, Any], part: Sequence[int]) -> dict[str, Any]:
    """The scene of the job that evaluates the realisations `part` of the scene's sweep."""
    child = copy.deepcopy(dict(scene))
    child["sweep"] = dict(child["sweep"], realisations=list(part))
    return child


def should_resubmit(status: str, error_kind: str | None, tries: int,
                    resubmit: int = RESUBMIT) -> bool:
    """Whether a share's job is submitted again: it failed for a system reason (its worker
    or job process died, the queue was away) and the share ran fewer than 1 + `resubmit`
    times; it redoes none of the realisations recorded before (they are kept by sweep)."""
    return status == "failed" and error_kind == "system" and tries < 1 + resubmit


def document_so_far(scene: dict[str, Any], shared: Path) -> dict[str, Any]:
    """The aggregate of the scene's realisations recorded so far in `shared` (the folder
    of every job's records, by population), whichever job evaluated them."""
    spec = spec_of_scene(scene)
    rdir = Path(shared) / _digest(scene, spec)
    records = [json.loads(p.read_text()) for k in spec.indices()
               if (p := rdir / f"{k:05d}.json").is_file()]
    return sweep_document(spec, records)


