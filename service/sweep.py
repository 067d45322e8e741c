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
:func:`engine.analyses.strength_reduction.factor_of_safety`) or by the analytic wedge
(`analytic`: eq. 51 on the scene's two joints; friction and orientation only), and written
to `OUT/realisations/NNNNN.json` (or, for the service's jobs, to a folder shared by every
job of the same sweep) as soon as it is done; a re-run with the same scene and spec skips
those already there. A spec may cover a share of the N (`only`): jobs run shares and
:func:`merge_documents` joins them. The aggregate (probability of failure, histogram, CDF,
sensitivity to each parameter; engine.analyses.reliability) goes to `OUT/sweep.json`, beside
the analytic sweep of the same realisations when the scene is a two-joint wedge and every
parameter is one eq. 51 takes. """

from __future__ import annotations

import copy
import hashlib
import json
import math
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from engine.analyses.jointstats import Distribution, fisher_angles_of, scatter_about
from engine.analyses.kinematics import normal
from engine.analyses.reliability import (
    aggregate,
    truncated_normal,
    wedge_factor_of_safety,
    wedge_geometry,
)
from engine.model import DEFAULT_FRICTION_ANGLE_DEG
from schemas.scene import ANALYTIC_QUANTITIES, SweepParameterSpec, sweep_truncation
from service.documents import finite, write_json_atomic

MODES = ("dda", "analytic")
#: the parameter drawn from the seed itself (the friction-only sweeps' stream)
LEGACY_NAME = "friction_angle"


@dataclass(frozen=True)
class Parameter:
    """One varied parameter of a sweep (validated as
    :class:`schemas.scene.SweepParameterSpec`): its name, quantity, distribution and
    what it applies to."""

    name: str
    quantity: str
    distribution: str
    mean: float | None = None
    sd: float | None = None
    low: float | None = None
    high: float | None = None
    values: tuple[float, ...] | None = None
    kappa: float | None = None
    joint_material: str | None = None
    joint: str | None = None
    bolt: str | None = None

    @classmethod
    def of(cls, name: str, spec: SweepParameterSpec | Mapping[str, Any]) -> Parameter:
        """The parameter `name` of a scene's (or a document's) spec, validated (a
        ValueError names what is wrong); the quantity defaults to the name."""
        if not isinstance(spec, SweepParameterSpec):
            spec = SweepParameterSpec.model_validate(
                {"quantity": name} | {k: v for k, v in spec.items() if k != "name"})
        d = spec.model_dump(exclude_none=True)
        if "values" in d:
            d["values"] = tuple(float(v) for v in d["values"])
        return cls(name=name, **d)

    def as_dict(self) -> dict[str, Any]:
        """The fields given (numbers as floats, so 40 and 40.0 are alike)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if f.name == "values":
                v = [float(x) for x in v]
            elif isinstance(v, int | float):
                v = float(v)
            out[f.name] = v
        return out

    def entropy(self, seed: int) -> int | list[int]:
        """The seed of this parameter's own random stream: (seed, CRC-32 of its name);
        `friction_angle` draws from the seed itself."""
        if self.name == LEGACY_NAME:
            return int(seed)
        return [int(seed), zlib.crc32(self.name.encode())]

    def draw(self, n: int, seed: int) -> np.ndarray:
        """Realisations 0 .. n-1 of a random parameter, `(n,)`, or `(n, 2)` angles θ, ψ
        (radians) from the joint's mean normal for `fisher`; row k does not depend on n."""
        if self.distribution == "normal":
            lo, hi = sweep_truncation(self.quantity, self.low, self.high)
            return truncated_normal(self.mean, self.sd, n, self.entropy(seed), lo, hi)
        rng = np.random.default_rng(self.entropy(seed))
        if self.distribution == "fisher":
            u = rng.random((n, 2))  # row k: one pair per realisation
            return np.column_stack([fisher_angles_of(self.kappa, u[:, 0]),
                                    2.0 * math.pi * u[:, 1]])
        u = rng.random(n)
        if self.distribution == "uniform":
            return self.low + u * (self.high - self.low)
        if self.distribution == "lognormal":
            lo, hi = sweep_truncation(self.quantity)
            dist = Distribution("lognormal", self.mean, self.sd).frozen()
            a, b = dist.cdf(lo), dist.cdf(hi)
            return np.minimum(dist.ppf(a + u * (b - a)), np.nextafter(hi, lo))
        raise ValueError(f"{self.name}: '{self.distribution}' is not drawn at random")

    def describe(self) -> dict[str, Any]:
        """The parameter for the sweep document: its spec, and the range a normal or
        lognormal draw is truncated to."""
        out = {k: v for k, v in self.as_dict().items() if k != "name"}
        if self.distribution in ("normal", "lognormal"):
            lo, hi = sweep_truncation(self.quantity, self.low, self.high)
            out["truncated_to"] = [finite_or_none(lo), finite_or_none(hi)]
        return out


def finite_or_none(x: float) -> float | None:
    """`x`, or None for an infinite bound (JSON has no infinity)."""
    return float(x) if math.isfinite(x) else None


@dataclass(frozen=True)
class SweepSpec:
    """N realisations from `seed` of the `parameters`; `friction_mean` and `friction_sd`
    (degrees) are the short form of φ ~ Normal on every weakened joint material."""

    n: int
    seed: int
    friction_mean: float | None = None
    friction_sd: float | None = None
    mode: str = "dda"
    #: the realisations this sweep evaluates (a share of the N; None: all)
    only: tuple[int, ...] | None = None
    parameters: tuple[Parameter, ...] = ()

    def __post_init__(self) -> None:
        if self.n < 1:
            raise ValueError(f"n must be at least 1, got {self.n}")
        if (self.friction_mean is None) != (self.friction_sd is None):
            raise ValueError("give both the friction mean and sd, or neither")
        if self.friction_sd is not None and not self.friction_sd > 0:
            raise ValueError(f"friction sd must be positive, got {self.friction_sd:g}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got '{self.mode}'")
        names = [p.name for p in self.all_parameters()]
        if not names:
            raise ValueError("a sweep needs a parameter (or the friction mean and sd)")
        if len(set(names)) != len(names):
            raise ValueError(f"a parameter is given twice: {', '.join(names)}")
        if self.mode == "analytic":
            bad = [p.name for p in self.parameters if p.quantity not in ANALYTIC_QUANTITIES]
            if bad:
                raise ValueError(f"eq. 51 (mode 'analytic') covers only "
                                 f"{' and '.join(ANALYTIC_QUANTITIES)}, not {', '.join(bad)}")

    def all_parameters(self) -> tuple[Parameter, ...]:
        """The short-form friction angle (if given) and then the parameters, in order."""
        short = () if self.friction_mean is None else (Parameter(
            LEGACY_NAME, "friction_angle", "normal", self.friction_mean, self.friction_sd),)
        return short + tuple(self.parameters)

    def draws(self) -> dict[str, np.ndarray]:
        """Every parameter's value per realisation (rows; see :meth:`Parameter.draw`); the
        `values` parameters form a grid, the first listed varying fastest, cycling."""
        out: dict[str, np.ndarray] = {}
        k = np.arange(self.n)
        stride = 1
        for p in self.all_parameters():
            if p.distribution == "values":
                out[p.name] = np.asarray(p.values, float)[(k // stride) % len(p.values)]
                stride *= len(p.values)
            else:
                out[p.name] = p.draw(self.n, self.seed)
        return out

    def friction_angles(self) -> np.ndarray:
        """φ of each realisation (degrees) of the parameter `friction_angle`."""
        return self.draws()[LEGACY_NAME]

    def analytic_applies(self) -> bool:
        """Whether eq. 51 takes every parameter into account."""
        return all(p.quantity in ANALYTIC_QUANTITIES for p in self.all_parameters())

    def indices(self) -> list[int]:
        """The realisations to evaluate, in order."""
        return list(range(self.n)) if self.only is None else sorted(self.only)

    def population(self) -> dict[str, Any]:
        """What makes realisation k what it is (every field but `only`; 40 and 40.0
        alike); a friction-only sweep's is what it was before parameters existed, so its
        realisation files are found again."""
        out: dict[str, Any] = {"n": int(self.n), "seed": int(self.seed)}
        if self.friction_mean is not None:
            out |= {"friction_mean": float(self.friction_mean),
                    "friction_sd": float(self.friction_sd)}
        out["mode"] = self.mode
        if self.parameters:
            out["parameters"] = [p.as_dict() for p in self.parameters]
        return out

    def as_dict(self) -> dict[str, Any]:
        """The spec for the sweep document (:meth:`from_dict` reads it back)."""
        return {"n": self.n, "seed": self.seed, "friction_mean": self.friction_mean,
                "friction_sd": self.friction_sd, "mode": self.mode,
                "only": None if self.only is None else list(self.only),
                "parameters": [p.as_dict() for p in self.parameters]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SweepSpec:
        """The spec of :meth:`as_dict` or :meth:`population` (or of a document written
        before parameters existed)."""
        only = d.get("only")
        return cls(int(d["n"]), int(d["seed"]), d.get("friction_mean"), d.get("friction_sd"),
                   d.get("mode", "dda"), None if only is None else tuple(only),
                   tuple(Parameter.of(p["name"], p) for p in d.get("parameters") or ()))

    def scene_sweep(self) -> dict[str, Any]:
        """The scene's `sweep` section of this spec (without the share)."""
        out: dict[str, Any] = {"n": self.n, "seed": self.seed, "mode": self.mode}
        if self.friction_mean is not None:
            out["friction_angle"] = {"mean": self.friction_mean, "sd": self.friction_sd}
        if self.parameters:
            out["parameters"] = {p.name: {k: v for k, v in p.as_dict().items() if k != "name"}
                                 for p in self.parameters}
        return out


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


def _joint_friction(scene: dict[str, Any], joint: dict[str, Any]) -> float:
    """The friction angle (degrees) of a joint's joint material in a scene dict."""
    mats = scene.get("joint_materials") or {}
    name = joint.get("joint_material") or scene.get("default_joint_material") or (
        next(iter(mats)) if len(mats) == 1 else None)
    return float((mats.get(name) or {}).get("friction_angle", DEFAULT_FRICTION_ANGLE_DEG))


def analytic_fs(scene: dict[str, Any], friction_angle: float | None = None) -> float | None:
    """Eq. 51 for a scene of exactly two joints (the wedge on their intersection), else
    None; with `friction_angle` on both planes, else each plane's own; cohesion, water and
    loads are ignored (as in eq. 51)."""
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
    if friction_angle is not None:
        return float(wedge_factor_of_safety(g, friction_angle))
    return float(wedge_factor_of_safety(g, _joint_friction(scene, a), _joint_friction(scene, b)))


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
                     tuple(Parameter.of(name, p) for name, p in s.parameters.items()))


def dda_fs(scene: dict[str, Any],
           should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """The engine's factor of safety of a realisation's scene (strength reduction);
    Stopped between trials once `should_stop()`. A realisation whose values make the scene
    invalid (e.g. a pretension above the capacity) is recorded with the problem, no FS."""
    from engine.analyses.strength_reduction import TrialRun, factor_of_safety
    from schemas.convert import build_model
    from schemas.errors import SceneError
    from service.documents import fos_controls

    def check(_: TrialRun) -> None:
        if should_stop is not None and should_stop():
            raise Stopped

    start = time.perf_counter()
    try:
        build = build_model(scene)
    except SceneError as exc:
        return {"factor_of_safety": None, "status": "invalid scene",
                "message": "; ".join(exc.lines()), "trials": 0,
                "wall_time": time.perf_counter() - start}
    res = factor_of_safety(build.model, fos_controls(build), progress=check)
    return {"factor_of_safety": res.factor_of_safety, "status": res.status,
            "trials": len(res.runs), "message": res.message,
            "wall_time": time.perf_counter() - start}


def evaluate(scene: dict[str, Any], spec: SweepSpec, index: int, values: Mapping[str, Any],
             should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """One realisation's record: index, its parameters' values (and φ as before when the
    sweep has `friction_angle`), its factor of safety (by the spec's mode) and eq. 51's
    (None when eq. 51 does not take every parameter into account)."""
    scene_k, recorded = _apply(scene, spec.all_parameters(), values)
    rec: dict[str, Any] = {"index": index, "parameters": recorded}
    if LEGACY_NAME in recorded:
        rec["friction_angle"] = recorded[LEGACY_NAME]
    rec["analytic_fs"] = analytic_fs(scene_k) if spec.analytic_applies() else None
    if spec.mode == "analytic":
        rec |= {"factor_of_safety": rec["analytic_fs"],
                "status": "completed" if rec["analytic_fs"] is not None
                else "not a two-joint wedge (eq. 51 does not apply)"}
    else:
        rec |= dda_fs(scene_k, should_stop)
    return rec


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


def share_parts(indices: Sequence[int], shares: int) -> list[list[int]]:
    """The realisations of each of `shares` jobs (every `shares`-th index, so the shares
    take alike long); empty shares (more shares than indices) are left out."""
    k = max(1, shares)
    return [p for p in (list(indices[i::k]) for i in range(k)) if p]


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


def merge_documents(docs: list[dict[str, Any]]) -> dict[str, Any]:
    """One sweep document from those of jobs that each evaluated a share of the same sweep
    (same population; a realisation in several shares counts once)."""
    specs = [SweepSpec.from_dict(d["spec"]) for d in docs]
    if not specs or any(s.population() != specs[0].population() for s in specs):
        raise ValueError("the documents are not shares of one sweep (n, seed, parameters "
                         "or mode differ)")
    records = {r["index"]: r for d in docs for r in d["realisations"]}
    whole = SweepSpec.from_dict(specs[0].population())
    return sweep_document(whole, [records[k] for k in sorted(records)])


def _recorded(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A record's parameter values (a friction-only record written before parameters
    existed has only `friction_angle`)."""
    return rec.get("parameters") or {LEGACY_NAME: rec["friction_angle"]}


def sensitivity_inputs(records: Sequence[Mapping[str, Any]]) -> dict[str, list[float]]:
    """Each parameter's values over the records as numbers for the sensitivity: an
    orientation as `NAME.dip` and `NAME.dip_direction` (unwrapped about the circular mean,
    so 359° and 1° are 2° apart)."""
    out: dict[str, list[float]] = {}
    for name in (_recorded(records[0]) if records else {}):
        vals = [_recorded(r)[name] for r in records]
        if not isinstance(vals[0], dict):
            out[name] = [float(v) for v in vals]
            continue
        out[f"{name}.dip"] = [float(v["dip"]) for v in vals]
        dd = np.radians([float(v["dip_direction"]) for v in vals])
        mean = math.atan2(float(np.sin(dd).sum()), float(np.cos(dd).sum()))
        out[f"{name}.dip_direction"] = np.degrees(
            mean + (dd - mean + math.pi) % (2 * math.pi) - math.pi).tolist()
    return out


def sweep_document(spec: SweepSpec, records: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate of the realisations done: by `spec.mode`, and by eq. 51 over the same
    realisations when the scene is a two-joint wedge (and eq. 51 takes every parameter);
    their PoF difference. The sensitivity is Spearman's ρ of FS and each parameter."""
    inputs = sensitivity_inputs(records)
    fs = [r["factor_of_safety"] if r.get("status") == "completed" else None for r in records]
    fs_arr = np.array([np.nan if f is None else f for f in fs], float)
    doc: dict[str, Any] = {
        "spec": spec.as_dict(),
        "parameters": {p.name: p.describe() for p in spec.all_parameters()},
        "done": len(records),
        spec.mode: aggregate(fs_arr, inputs),
    }
    ana = [r.get("analytic_fs") for r in records]
    if spec.mode != "analytic" and records and all(a is not None for a in ana):
        doc["analytic"] = aggregate(np.array(ana, float), inputs)
        p, q = doc[spec.mode]["probability_of_failure"], doc["analytic"]["probability_of_failure"]
        doc["pof_difference"] = None if p is None or q is None else p - q
        rel = fs_arr / np.array(ana, float) - 1.0
        ok = np.isfinite(rel)
        doc["fs_relative_difference"] = {
            "mean": float(rel[ok].mean()) if ok.any() else None,
            "max_abs": float(np.abs(rel[ok]).max()) if ok.any() else None}
    doc["realisations"] = records
    return finite(doc)
