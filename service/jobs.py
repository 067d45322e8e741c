"""The job function: run one process on a scene into a job directory, whatever the backend.

A backend hands :func:`execute` a :class:`TaskContext` that reports progress (throttled) and
says when to stop; :func:`execute` writes the artifacts (`result.h5` + `summary.json`,
`fos.json` or `blocks.json`) and returns an :class:`Outcome`. JSON artifacts are written to a
temporary file and renamed, so a reader never sees half a file; the HDF5 writer flushes
every recorded step.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: process id -> (title, description, artifact file names)
PROCESSES: dict[str, dict[str, Any]] = {
    "simulation": {
        "title": "DDA simulation",
        "description": "Run the scene's blocks through time (3-D DDA) and record every "
                       "recorded step in an HDF5 result file (VTKHDF for ParaView).",
        "artifacts": ["summary.json", "result.h5"],
    },
    "factor-of-safety": {
        "title": "Factor of safety (strength reduction)",
        "description": "Divide the joints' strength by trial factors and find by bisection "
                       "the factor at which the moving blocks start to accelerate.",
        "artifacts": ["fos.json"],
    },
    "block-cutting": {
        "title": "Block cutting",
        "description": "Cut the domain by the joints and list the blocks (volume, centroid, "
                       "vertices, faces); nothing is run.",
        "artifacts": ["blocks.json"],
    },
}
#: the main JSON artifact of each process
MAIN_ARTIFACT = {"simulation": "summary.json", "factor-of-safety": "fos.json",
                 "block-cutting": "blocks.json"}
RESULT_FILE = "result.h5"

MODEL, SYSTEM = "model", "system"


@dataclass
class Outcome:
    """How a job ended: `successful`, `failed` or `dismissed`, a message and for failures
    whether the model (`model`) or the service (`system`) is to blame."""

    status: str
    message: str = ""
    error_kind: str | None = None


class Cancelled(Exception):
    """Raised inside a job function when the job was asked to stop."""


class TaskContext:
    """Progress reporting and cancellation for one job; backends override the two hooks.

    `report` writes at most once per `interval` seconds (the last call always wins when
    `force` is set); `should_stop` asks the backend at most every `poll` seconds.
    """

    def __init__(self, interval: float = 0.25, poll: float = 0.2) -> None:
        self.interval, self.poll = interval, poll
        self._last_report = -1e300
        self._last_poll = -1e300
        self._stop = False

    # hooks
    def write_progress(self, values: dict[str, Any]) -> None:
        """Store progress fields (`progress` percent, `step`, `simulated_time`, ...)."""

    def cancel_requested(self) -> bool:
        """True when someone asked this job to stop."""
        return False

    # API used by the job function
    def report(self, percent: float, *, force: bool = False, **fields: Any) -> None:
        now = time.monotonic()
        if not force and now - self._last_report < self.interval:
            return
        self._last_report = now
        self.write_progress({"progress": round(max(0.0, min(100.0, percent)), 2), **fields})

    def should_stop(self) -> bool:
        if self._stop:
            return True
        now = time.monotonic()
        if now - self._last_poll >= self.poll:
            self._last_poll = now
            self._stop = bool(self.cancel_requested())
        return self._stop


def write_json_atomic(path: Path, doc: Any) -> None:
    """Write `doc` as JSON to `path` via a temporary file, fsync and rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2, allow_nan=False, default=_json_default)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def _finite(value: Any) -> Any:
    """`value` with NaN and infinities replaced by None (strict JSON)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


# --------------------------------------------------------------------------- processes


def blocks_document(build: Any) -> dict[str, Any]:
    """`{"blocks": [...]}`: name, volume, centroid, concave, fixed, surface vertices, faces."""
    import numpy as np

    docs = []
    for name, b in zip(build.block_names, build.model.blocks, strict=True):
        poly = b.polyhedron
        used = poly.surface_vertex_ids
        remap = np.full(len(poly.vertices), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        docs.append({
            "name": name,
            "volume": float(poly.volume),
            "centroid": (np.round(poly.centroid, 9) + 0.0).tolist(),
            "concave": not poly.is_convex,
            "fixed": bool(b.fixed),
            "vertices": (np.round(poly.vertices[used], 9) + 0.0).tolist(),
            "faces": [remap[f].tolist() for f in poly.faces],
        })
    return {"blocks": docs, "count": len(docs),
            "total_volume": float(sum(d["volume"] for d in docs)), "warnings": build.warnings}


def _simulation(build: Any, scene_text: str, job_dir: Path, ctx: TaskContext) -> Outcome:
    from engine.results import ResultWriter
    from engine.simulation import STATUS_CANCELLED, STATUS_COMPLETED, Progress, run
    from schemas.scene import SCHEMA_VERSION

    def progress(p: Progress) -> None:
        ctx.report(100.0 * p.fraction, step=p.step, simulated_time=p.time,
                   duration=p.duration)

    ctx.report(0.0, force=True, step=0, simulated_time=0.0,
               duration=build.model.controls.duration)
    writer = ResultWriter(job_dir / RESULT_FILE, overwrite=True, schema_version=SCHEMA_VERSION)
    res = run(build.model, recorder=writer, progress=progress, should_stop=ctx.should_stop,
              scene_json=scene_text)
    summary = _finite({**res.summary, "block_names": build.block_names,
                       "warnings": build.warnings})
    write_json_atomic(job_dir / "summary.json", summary)
    s = res.summary
    ctx.report(100.0 * min(1.0, s["simulated_time"] / build.model.controls.duration),
               force=True, step=s["steps"], simulated_time=s["simulated_time"])
    if res.status == STATUS_COMPLETED:
        return Outcome("successful", f"completed {res.steps} steps")
    if res.status == STATUS_CANCELLED:
        return Outcome("dismissed", f"cancelled at t = {s['simulated_time']:.6g} s after "
                                    f"{res.steps} steps; partial results kept")
    return Outcome("failed", f"model problem: {res.message}", MODEL)


def _factor_of_safety(build: Any, scene_text: str, job_dir: Path,
                      ctx: TaskContext) -> Outcome:
    from engine.analyses import StrengthReductionControls, TrialRun, factor_of_safety

    controls = build.factor_of_safety or StrengthReductionControls()
    runs: list[TrialRun] = []

    def progress(r: TrialRun) -> None:
        runs.append(r)
        verdict = "fails" if r.failed else "holds"
        ctx.report(100.0 * len(runs) / controls.max_runs, force=True, step=len(runs),
                   message=f"trial {len(runs)}: reduction factor {r.factor:.4g} {verdict}")
        if ctx.should_stop():
            raise Cancelled

    ctx.report(0.0, force=True, message="first trial running")
    try:
        result = factor_of_safety(build.model, controls, progress=progress)
    except Cancelled:
        write_json_atomic(job_dir / "fos.json", _finite({
            "status": "cancelled", "runs": [r.__dict__ for r in runs],
            "message": f"cancelled after {len(runs)} trials"}))
        return Outcome("dismissed", f"cancelled after {len(runs)} trials; partial results kept")
    doc = _finite(result.as_dict())
    write_json_atomic(job_dir / "fos.json", doc)
    ctx.report(100.0, force=True, step=len(result.runs))
    if result.status == "completed":
        return Outcome("successful", f"factor of safety {result.factor_of_safety:.4g}"
                       + (f" ({result.message})" if result.message else ""))
    return Outcome("failed", f"model problem: {result.message}", MODEL)


def _block_cutting(build: Any, scene_text: str, job_dir: Path, ctx: TaskContext) -> Outcome:
    write_json_atomic(job_dir / "blocks.json", blocks_document(build))
    ctx.report(100.0, force=True)
    n = len(build.model.blocks)
    return Outcome("successful", f"{n} block{'s' if n != 1 else ''}")


_RUNNERS: dict[str, Callable[[Any, str, Path, TaskContext], Outcome]] = {
    "simulation": _simulation, "factor-of-safety": _factor_of_safety,
    "block-cutting": _block_cutting,
}


def execute(process: str, scene_text: str, job_dir: Path, ctx: TaskContext) -> Outcome:
    """Run `process` on the scene JSON text into `job_dir`; never raises for model problems.

    Scene problems and runs that cannot go on are `failed` with kind `model`; anything else
    (disk full, out of memory, a bug) is `failed` with kind `system`.
    """
    from schemas.convert import build_model
    from schemas.errors import SceneError

    job_dir.mkdir(parents=True, exist_ok=True)
    if ctx.should_stop():
        return Outcome("dismissed", "cancelled before it started")
    try:
        build = build_model(json.loads(scene_text))
        return _RUNNERS[process](build, scene_text, job_dir, ctx)
    except SceneError as exc:
        return Outcome("failed", "model problem: the scene is invalid: "
                       + "; ".join(exc.lines()), MODEL)
    except MemoryError:
        log.exception("job in %s ran out of memory", job_dir)
        return Outcome("failed", "system error: the job ran out of memory", SYSTEM)
    except Exception as exc:
        log.exception("job in %s failed", job_dir)
        return Outcome("failed", f"system error: {type(exc).__name__}: {exc}", SYSTEM)


# --------------------------------------------------------------------------- RQ entry point


class RedisContext(TaskContext):
    """Progress and cancellation through Redis: hash `polydda:job:<id>`, key `...:cancel`."""

    def __init__(self, connection: Any, job_id: str, interval: float = 0.25) -> None:
        super().__init__(interval)
        self.redis, self.key = connection, job_key(job_id)
        self.cancel_key = cancel_key(job_id)

    def write_progress(self, values: dict[str, Any]) -> None:
        self.set(values | {"updated": time.time()})

    def set(self, values: dict[str, Any]) -> None:
        self.redis.hset(self.key, mapping={k: json.dumps(v) for k, v in values.items()})
        self.redis.expire(self.key, 30 * 24 * 3600)

    def cancel_requested(self) -> bool:
        return bool(self.redis.exists(self.cancel_key))


def job_key(job_id: str) -> str:
    return f"polydda:job:{job_id}"


def cancel_key(job_id: str) -> str:
    return f"polydda:cancel:{job_id}"


def run_rq(job_id: str, process: str, scene_text: str) -> str:
    """RQ job function: run the job on this worker, results under POLYDDA_DATA_DIR."""
    from rq import get_current_job

    from service.settings import Settings

    settings = Settings()
    current = get_current_job()
    if current is None:
        raise RuntimeError("run_rq runs inside an RQ worker")
    ctx = RedisContext(current.connection, job_id, settings.progress_interval)
    now = time.time()
    ctx.set({"status": "running", "started": now, "updated": now, "progress": 0.0,
             "worker_pid": os.getpid()})  # the work horse, on the worker's host
    outcome = execute(process, scene_text, settings.job_dir(job_id), ctx)
    ctx.set({"status": outcome.status, "message": outcome.message,
             "error_kind": outcome.error_kind, "finished": time.time(),
             "updated": time.time()})
    return outcome.status
