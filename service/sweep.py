"""Monte Carlo sweeps of a scene: realisations from a seed, one factor of safety each.

A :class:`SweepSpec` draws the joints' friction angle φ ~ Normal(mean, sd) (truncated to
[0°, 90°)), one value per realisation applied to every weakened joint material; realisation
k is the same whatever N. Each realisation is evaluated by the engine's strength reduction
(`dda`: the scene with that φ through :func:`engine.analyses.factor_of_safety`) or by the
analytic wedge (`analytic`: eq. 51 on the scene's two joints), and written to
`OUT/realisations/NNNNN.json` (or, for the service's jobs, to a folder shared by every job
of the same sweep) as soon as it is done; a re-run with the same scene and spec skips
those already there. A spec may cover a share of the N (`only`): jobs run shares and
:func:`merge_documents` joins them. The aggregate (probability of failure, histogram, CDF,
sensitivity; engine.reliability) goes to `OUT/sweep.json`, beside the analytic sweep of
the same realisations when the scene is a two-joint wedge.
"""

from __future__ import annotations

import copy
import hashlib
import json
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.reliability import (
    aggregate,
    truncated_normal,
    wedge_factor_of_safety,
    wedge_geometry,
)
from service.documents import finite, write_json_atomic

MODES = ("dda", "analytic")


@dataclass(frozen=True)
class SweepSpec:
    """N realisations from `seed` of φ ~ Normal(friction_mean, friction_sd) in degrees."""

    n: int
    seed: int
    friction_mean: float
    friction_sd: float
    mode: str = "dda"
    #: the realisations this sweep evaluates (a share of the N; None: all)
    only: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.n < 1:
            raise ValueError(f"n must be at least 1, got {self.n}")
        if not self.friction_sd > 0:
            raise ValueError(f"friction sd must be positive, got {self.friction_sd:g}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got '{self.mode}'")

    def friction_angles(self) -> np.ndarray:
        """φ of each realisation (degrees)."""
        return truncated_normal(self.friction_mean, self.friction_sd, self.n, self.seed)

    def indices(self) -> list[int]:
        """The realisations to evaluate, in order."""
        return list(range(self.n)) if self.only is None else sorted(self.only)

    def population(self) -> dict[str, Any]:
        """What makes realisation k what it is (every field but `only`; 40 and 40.0 alike)."""
        return {"n": int(self.n), "seed": int(self.seed),
                "friction_mean": float(self.friction_mean),
                "friction_sd": float(self.friction_sd), "mode": self.mode}


def realisation_scene(scene: dict[str, Any], friction_angle: float) -> dict[str, Any]:
    """A copy of the scene whose joint materials (all, or the factor-of-safety's weakened
    ones when it names them) have this friction angle."""
    out = copy.deepcopy(scene)
    mats = out.setdefault("joint_materials", {}) or {"joint": {}}
    out["joint_materials"] = mats
    fos = (out.get("analysis") or {}).get("factor_of_safety") or {}
    names = fos.get("joint_materials") or list(mats)
    for name in names:
        mats[name] = dict(mats.get(name, {}), friction_angle=float(friction_angle))
    return out


def analytic_fs(scene: dict[str, Any], friction_angle: float) -> float | None:
    """Eq. 51 for a scene of exactly two joints (the wedge on their intersection), else
    None; cohesion is ignored (as in eq. 51)."""
    joints = scene.get("joints") or []
    if len(joints) != 2:
        return None
    a, b = joints
    try:
        g = wedge_geometry(a["dip"], a["dip_direction"], b["dip"], b["dip_direction"])
    except ValueError:  # parallel planes
        return None
    if not 0 < g.plunge < 90 or min(g.n_a, g.n_b) < 0:
        return None  # a horizontal intersection, or a wedge that lifts off a plane
    return float(wedge_factor_of_safety(g, friction_angle))


class Stopped(Exception):
    """A stop was asked for in the middle of a realisation."""


def spec_of_scene(scene: dict[str, Any]) -> SweepSpec:
    """The SweepSpec of a scene's `sweep` (SceneError when it has none or it is invalid)."""
    from schemas.errors import SceneError
    from schemas.scene import load_scene

    s = load_scene(scene).sweep
    if s is None:
        raise SceneError([{"loc": "sweep", "msg": "a sweep needs 'sweep': {\"n\", \"seed\", "
                           "\"friction_angle\": {\"mean\", \"sd\"}, \"mode\"}"}])
    only = None if s.realisations is None else tuple(s.realisations)
    return SweepSpec(s.n, s.seed, s.friction_angle.mean, s.friction_angle.sd, s.mode, only)


def dda_fs(scene: dict[str, Any], friction_angle: float,
           should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """The engine's factor of safety of the scene with this φ (strength reduction);
    Stopped between trials once `should_stop()`."""
    from engine.analyses import TrialRun, factor_of_safety
    from schemas.convert import build_model
    from service.documents import fos_controls

    def check(_: TrialRun) -> None:
        if should_stop is not None and should_stop():
            raise Stopped

    start = time.perf_counter()
    build = build_model(realisation_scene(scene, friction_angle))
    res = factor_of_safety(build.model, fos_controls(build), progress=check)
    return {"factor_of_safety": res.factor_of_safety, "status": res.status,
            "trials": len(res.runs), "message": res.message,
            "wall_time": time.perf_counter() - start}


def evaluate(scene: dict[str, Any], mode: str, index: int, friction_angle: float,
             should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """One realisation's record: index, φ, its factor of safety (by `mode`) and eq. 51's."""
    rec: dict[str, Any] = {"index": index, "friction_angle": float(friction_angle),
                           "analytic_fs": analytic_fs(scene, friction_angle)}
    if mode == "analytic":
        rec |= {"factor_of_safety": rec["analytic_fs"],
                "status": "completed" if rec["analytic_fs"] is not None
                else "not a two-joint wedge (eq. 51 does not apply)"}
    else:
        rec |= dda_fs(scene, friction_angle, should_stop)
    return rec


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
    phis = spec.friction_angles()
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
                done(evaluate(scene, spec.mode, k, phis[k], stop))
            except Stopped:
                break
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            pending: set[Future] = set()
            queue = list(todo)
            while queue or pending:
                while queue and len(pending) < workers and not stop():
                    k = queue.pop(0)
                    pending.add(pool.submit(evaluate, scene, spec.mode, k, float(phis[k])))
                if not pending:
                    break
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    done(f.result())
    doc = sweep_document(spec, [records[k] for k in sorted(records)])
    write_json_atomic(out / "sweep.json", doc)
    return doc


def merge_documents(docs: list[dict[str, Any]]) -> dict[str, Any]:
    """One sweep document from those of jobs that each evaluated a share of the same sweep
    (same population; a realisation in several shares counts once)."""
    specs = [SweepSpec(**d["spec"]) for d in docs]
    if not specs or any(s.population() != specs[0].population() for s in specs):
        raise ValueError("the documents are not shares of one sweep (n, seed, φ, mode differ)")
    records = {r["index"]: r for d in docs for r in d["realisations"]}
    whole = SweepSpec(**specs[0].population())
    return sweep_document(whole, [records[k] for k in sorted(records)])


def sweep_document(spec: SweepSpec, records: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate of the realisations done: by `spec.mode`, and by eq. 51 over the same
    realisations when the scene is a two-joint wedge; their PoF difference."""
    phi = [r["friction_angle"] for r in records]
    fs = [r["factor_of_safety"] if r.get("status") == "completed" else None for r in records]
    fs_arr = np.array([np.nan if f is None else f for f in fs], float)
    doc: dict[str, Any] = {
        "spec": asdict(spec),
        "parameters": {"friction_angle": {"distribution": "normal", "mean": spec.friction_mean,
                                          "sd": spec.friction_sd, "truncated_to": [0, 90]}},
        "done": len(records),
        spec.mode: aggregate(fs_arr, {"friction_angle": phi}),
    }
    ana = [r.get("analytic_fs") for r in records]
    if spec.mode != "analytic" and records and all(a is not None for a in ana):
        doc["analytic"] = aggregate(np.array(ana, float), {"friction_angle": phi})
        p, q = doc[spec.mode]["probability_of_failure"], doc["analytic"]["probability_of_failure"]
        doc["pof_difference"] = None if p is None or q is None else p - q
        rel = fs_arr / np.array(ana, float) - 1.0
        ok = np.isfinite(rel)
        doc["fs_relative_difference"] = {
            "mean": float(rel[ok].mean()) if ok.any() else None,
            "max_abs": float(np.abs(rel[ok]).max()) if ok.any() else None}
    doc["realisations"] = records
    return finite(doc)
