"""The job function: run one process on a scene into a job directory, whatever the backend.

A backend hands :func:`execute` a :class:`~service.jobs.tasks.TaskContext` that reports progress
(throttled) and says when to stop; the process's runner (service.jobs.processes) writes the
artifacts (`result.h5` + `summary.json`, `fos.json`, `seismic.json` or `blocks.json`) and
returns an :class:`~service.jobs.tasks.Outcome`. JSON artifacts are written to a temporary file
and renamed, so a reader never sees half a file; the HDF5 writer flushes as it goes.

The RQ entry point (:func:`run_rq`) runs in RQ's work horse: it keeps a heartbeat key in
Redis while it runs (the API re-queues a job whose heartbeat stopped), dies with the worker
that forked it (a SIGKILLed worker leaves no orphan running the job), and rides out a Redis
outage (progress is skipped, the final status is retried until Redis answers).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import signal
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from service.documents import write_json_atomic
from service.jobs.processes import MAIN_ARTIFACTS, PROCESSES, RESULT_FILE
from service.jobs.tasks import MODEL, SYSTEM, Cancelled, Outcome, TaskContext

__all__ = ["MAIN_ARTIFACTS", "MODEL", "PROCESSES", "RESULT_FILE", "SYSTEM", "Cancelled",
           "Outcome", "RedisContext", "TaskContext", "execute", "run_rq", "write_json_atomic"]

log = logging.getLogger(__name__)


def execute(process: str, scene_text: str, job_dir: Path, ctx: TaskContext) -> Outcome:
    """Run `process` on the scene JSON text into `job_dir`; never raises for model problems.

    Scene problems and runs that cannot go on are `failed` with kind `model`; anything else
    (disk full, out of memory, a bug) is `failed` with kind `system`.
    """

    try:
        job_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return Outcome("failed", f"system error: cannot make the job's directory: {exc}",
                       SYSTEM)
    outcome = _execute(process, scene_text, job_dir, ctx)
    if ctx.stop_reason is not None and outcome.status == "dismissed":
        # stopped by the disk guard, not by its owner: a failure of the service's
        kept = "" if outcome.message.startswith("cancelled before") else \
            "; partial results kept"
        return Outcome("failed", f"system error: {ctx.stop_reason}{kept}", SYSTEM)
    return outcome


def _execute(process: str, scene_text: str, job_dir: Path, ctx: TaskContext) -> Outcome:
    from schemas.convert import build_model
    from schemas.errors import SceneError
    from service.jobs.store import disk_full

    if ctx.should_stop():
        return Outcome("dismissed", "cancelled before it started")
    try:
        p = PROCESSES[process]
        build = build_model(json.loads(scene_text)) if p.needs_model else None
        return p.run(build, scene_text, job_dir, ctx)
    except SceneError as exc:
        return Outcome("failed", "model problem: the scene is invalid: "
                       + "; ".join(exc.lines()), MODEL)
    except MemoryError:
        log.exception("job in %s ran out of memory", job_dir)
        return Outcome("failed", "system error: the job ran out of memory", SYSTEM)
    except Exception as exc:
        if _caused_by(exc, disk_full):
            log.error("job in %s stopped: the disk is full (%s)", job_dir, exc)
            return Outcome("failed", f"system error: the disk is full ({exc}); partial "
                                     "results kept", SYSTEM)
        log.exception("job in %s failed", job_dir)
        return Outcome("failed", f"system error: {type(exc).__name__}: {exc}", SYSTEM)


def _caused_by(exc: BaseException, test: Any) -> bool:
    """True if `exc` or an exception it was raised from or during passes `test`."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if test(e):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


# --------------------------------------------------------------------------- RQ entry point


def job_key(job_id: str) -> str:
    """Redis hash of a job's progress and outcome (JSON values), written by the worker."""
    return f"polydda:job:{job_id}"


def cancel_key(job_id: str) -> str:
    """Redis key whose existence asks the job to stop."""
    return f"polydda:cancel:{job_id}"


def alive_key(job_id: str) -> str:
    """Redis key (with a TTL) that the process running the job keeps refreshing."""
    return f"polydda:alive:{job_id}"


class RedisContext(TaskContext):
    """Progress and cancellation through Redis, tolerant of Redis outages.

    Progress writes that fail are skipped (the next one carries the news); a cancel check
    that fails says "go on"; a heartbeat thread refreshes `alive_key` every third of
    `heartbeat_ttl` s; the job stops by itself when its parent (the worker) is gone, or
    when the job's hash names another run (`run`: this one was given up for lost, e.g. its
    host was cut off longer than the TTL, and the job was re-queued and started again).
    """

    def __init__(self, connection: Any, job_id: str, interval: float = 0.25,
                 heartbeat_ttl: float = 10.0, parent_pid: int | None = None) -> None:
        super().__init__(interval)
        self.redis, self.job_id = connection, job_id
        self.key, self.cancel_key = job_key(job_id), cancel_key(job_id)
        self.heartbeat_ttl, self.parent_pid = heartbeat_ttl, parent_pid
        self.orphaned = False
        self.run = uuid.uuid4().hex  # this run's token in the job's hash
        self.progress_lost = False  # progress writes fail (said once, until one succeeds)
        self._beating = threading.Event()
        self._thread: threading.Thread | None = None

    def write_progress(self, values: dict[str, Any]) -> None:
        from redis.exceptions import RedisError

        try:
            self.set(values | {"updated": time.time()})
        except RedisError as exc:
            if not self.progress_lost:
                log.warning("progress of job %s not written (%s); the job goes on, progress "
                            "is skipped until Redis answers", self.job_id, exc)
            self.progress_lost = True
            return
        if self.progress_lost:
            log.info("progress of job %s written again", self.job_id)
            self.progress_lost = False

    def set(self, values: dict[str, Any]) -> None:
        """Write fields of the job's hash (raises RedisError)."""
        pipe = self.redis.pipeline()
        pipe.hset(self.key, mapping={k: json.dumps(v) for k, v in values.items()})
        pipe.expire(self.key, 30 * 24 * 3600)
        pipe.execute()

    def set_final(self, values: dict[str, Any], patience: float = 600.0) -> bool:
        """Write the outcome, retrying with backoff while Redis is away (up to `patience`
        s); True once written."""
        from redis.exceptions import RedisError

        deadline, pause = time.monotonic() + patience, 0.5
        while True:
            try:
                self.set(values)
                return True
            except RedisError as exc:
                if time.monotonic() > deadline:
                    log.error("outcome of job %s lost: Redis unreachable for %.0f s (%s)",
                              self.job_id, patience, exc)
                    return False
                log.warning("outcome of job %s not written yet (%s); retrying in %.1f s",
                            self.job_id, exc, pause)
                time.sleep(pause)
                pause = min(2 * pause, 10.0)

    def cancel_requested(self) -> bool:
        from redis.exceptions import RedisError

        if self.parent_pid is not None and os.getppid() != self.parent_pid:
            self.orphaned = True
            return True
        try:
            pipe = self.redis.pipeline()
            pipe.exists(self.cancel_key)
            pipe.hget(self.key, "run")
            cancelled, run = pipe.execute()
        except RedisError:
            return False
        if run is not None and json.loads(run) != self.run:
            log.warning("job %s runs again elsewhere (it was given up for lost); this run "
                        "stops", self.job_id)
            self.orphaned = True
            return True
        return bool(cancelled)

    # heartbeat
    def beat(self) -> None:
        """Refresh the heartbeat key once (errors ignored: Redis may be away)."""
        from redis.exceptions import RedisError

        with contextlib.suppress(RedisError):
            self.redis.set(alive_key(self.job_id), os.getpid(),
                           px=max(1, int(1000 * self.heartbeat_ttl)))

    def start_heartbeat(self) -> None:
        self.beat()

        def loop() -> None:
            while not self._beating.wait(self.heartbeat_ttl / 3):
                self.beat()
        self._thread = threading.Thread(target=loop, name="polydda-heartbeat", daemon=True)
        self._thread.start()

    def stop_heartbeat(self) -> None:
        from redis.exceptions import RedisError

        self._beating.set()
        if self._thread is not None:
            self._thread.join(5)
        with contextlib.suppress(RedisError):
            self.redis.delete(alive_key(self.job_id))


def store_results(settings: Any, job_id: str, outcome: Outcome) -> Outcome:
    """Upload the job's files to the object store, when one is configured (before its
    outcome is recorded, so an ended job's results are there to serve); a failed upload
    fails the job (kind system), its files kept in this worker's data directory."""
    from service.jobs.objectstore import ResultStore

    store = ResultStore.of(settings)
    if store is None:
        return outcome
    try:
        store.upload_job(job_id, settings.job_dir(job_id))
    except Exception as exc:
        log.exception("results of job %s not stored", job_id)
        return Outcome("failed", f"system error: the results could not be stored in the "
                                 f"object store ({type(exc).__name__}: {exc}); "
                                 f"{outcome.status} before that: {outcome.message}", SYSTEM)
    return outcome


def die_with_parent() -> int:
    """Ask Linux to SIGKILL this process when its parent dies (prctl PR_SET_PDEATHSIG);
    returns the parent's pid. Exits at once if the parent is already gone."""
    parent = os.getppid()
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent died before the request was in place
        os._exit(1)
    return parent


def run_rq(job_id: str, process: str, scene_text: str) -> str:
    """RQ job function: run the job on this worker, results under POLYDDA_DATA_DIR."""
    from rq import get_current_job

    from service.settings import Settings

    settings = Settings()
    current = get_current_job()
    if current is None:
        raise RuntimeError("run_rq runs inside an RQ worker")
    parent = die_with_parent()  # the work horse must not outlive its worker
    ctx = RedisContext(current.connection, job_id, settings.progress_interval,
                       heartbeat_ttl=settings.rq_heartbeat_ttl, parent_pid=parent)
    ctx.guard_disk(settings.data_dir, settings.min_free_bytes)
    ctx.start_heartbeat()
    try:
        now = time.time()
        ctx.set_final({"status": "running", "started": now, "updated": now, "progress": 0.0,
                       "worker_pid": os.getpid(),  # the work horse, on the worker's host
                       "run": ctx.run})
        outcome = execute(process, scene_text, settings.job_dir(job_id), ctx)
        if not ctx.orphaned:
            outcome = store_results(settings, job_id, outcome)
        if ctx.orphaned:  # the worker is gone (the API re-queues the job), or the job
            # runs again elsewhere: leave the job's records to the run that owns it (exit
            # 0: a live worker would otherwise mark the job's RQ record failed)
            os._exit(0)
        ctx.set_final({"status": outcome.status, "message": outcome.message,
                       "error_kind": outcome.error_kind, "finished": time.time(),
                       "updated": time.time()})
    finally:
        ctx.stop_heartbeat()
    return outcome.status
