"""Queue backends: where jobs run. Both keep the SQLite job table as the record of every job.

- `embedded` (default): a supervisor thread in the API process starts each job in its own
  process (multiprocessing, spawn) up to `max_workers`.
- `rq`: jobs go to a Redis queue worked by `polydda worker` processes on any machine; a
  thread in the API copies their progress from Redis into the job table.

A parent job (a sweep fanned out in shares, service.jobs.fanout) runs nothing: backends see
only its children (`JobStore.active` leaves parents out) and the supervisor refreshes the
parent from them every tick.

A backend gets `submitted(job)` after the job's row was committed and `cancel(job_id)` on
DELETE; the job function itself (service.jobs.execute.execute) is the same for both.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from typing import Any

from service.jobs.fanout import refresh_all
from service.jobs.store import ACCEPTED, DISMISSED, RUNNING, JobRecord, JobStore, disk_full
from service.settings import Settings

log = logging.getLogger(__name__)


class Backend:
    """Supervisor thread (`tick` every `period` s, or sooner after `wake`) and job hooks."""

    period = 0.2
    #: s between housekeeping rounds (retention)
    housekeeping_period = 60.0

    def __init__(self, settings: Settings, store: JobStore) -> None:
        self.settings, self.store = settings, store
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._quiet_until = 0.0

    def low_disk(self) -> bool:
        """True when the data directory's disk has less free space than `min_free_bytes`
        (no job is started then: it would fail at once)."""
        if self.settings.min_free_bytes <= 0:
            return False
        try:
            return shutil.disk_usage(self.settings.data_dir).free < self.settings.min_free_bytes
        except OSError:
            return False

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self.recover()
        self._thread = threading.Thread(target=self._loop, name="polydda-supervisor",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def wake(self) -> None:
        self._wake.set()

    def _loop(self) -> None:
        next_housekeeping = time.monotonic()
        while not self._stopping.is_set():
            try:
                self.tick()
                self.refresh_parents()
                if time.monotonic() >= next_housekeeping:
                    next_housekeeping = time.monotonic() + self.housekeeping_period
                    self.housekeeping()
            except Exception as exc:  # the supervisor must outlive any one bad tick
                if disk_full(exc):  # said once a minute, not 5 tracebacks a second
                    if time.monotonic() >= self._quiet_until:
                        log.error("supervisor: the disk is full (%s); retrying", exc)
                        self._quiet_until = time.monotonic() + 60.0
                else:
                    log.exception("supervisor tick failed")
            self._wake.wait(self.period)
            self._wake.clear()

    def housekeeping(self, now: float | None = None) -> list[str]:
        """Remove the finished jobs (rows and files) older than `retention`; their ids."""
        if self.settings.retention <= 0:
            return []
        now = time.time() if now is None else now
        gone = []
        from service.jobs.objectstore import ResultStore

        objects = ResultStore.of(self.settings)
        for job in self.store.expired(now - self.settings.retention):
            shutil.rmtree(self.settings.job_dir(job.id), ignore_errors=True)
            if objects is not None:
                try:
                    objects.delete_job(job.id)
                except Exception as exc:
                    log.warning("objects of job %s not deleted: %s", job.id, exc)
                    continue
            if self.store.delete(job.id):
                gone.append(job.id)
        if gone:
            log.info("retention: removed %d finished jobs older than %.0f s", len(gone),
                     self.settings.retention)
        return gone

    def refresh_parents(self) -> None:
        """Bring the parent jobs of fanned-out sweeps up to date with their children
        (service.jobs.fanout): the same on every backend, all state in the job table."""
        refresh_all(self.store, self)

    def health(self) -> dict[str, Any]:
        """`status` (`ok`, `degraded`: jobs wait for a worker, `unavailable`: jobs cannot
        be queued), `workers` that can run jobs and how many are `busy`."""
        return {"status": "ok", "workers": 0, "busy": 0}

    # ------------------------------------------------------------------ hooks
    def recover(self) -> None:
        """Called once at start: settle jobs left `running` by an earlier API process."""

    def tick(self) -> None:
        """One round of supervision (start, reap, enforce cancellation, sync)."""

    def submitted(self, job: JobRecord) -> None:
        """A new accepted job was committed."""
        self.wake()

    def on_cancel(self, job_id: str, started: bool) -> None:
        """A job was dismissed before it started (`started` False) or asked to stop."""

    # ------------------------------------------------------------------ shared
    def cancel(self, job_id: str) -> None:
        """Dismiss an accepted job at once; ask a running one to stop (killed after grace)."""
        now = time.time()
        if self.store.update(job_id, only_if=[ACCEPTED], status=DISMISSED, finished=now,
                             message="dismissed before it started"):
            self.on_cancel(job_id, started=False)
            return
        job = self.store.get(job_id)
        if job is not None and job.status == RUNNING and job.cancel_requested is None:
            self.store.update(job_id, only_if=[RUNNING], cancel_requested=now)
        self.on_cancel(job_id, started=True)
        self.wake()

    def requeue_or_fail(self, job: JobRecord, why: str) -> None:
        """A running job was lost (its process or worker killed, the service stopped under
        it): back to the queue, or failed (kind system) once it has run `max_attempts`
        times; dismissed if it was being cancelled. The one retry policy of every backend."""
        now = time.time()
        if job.cancel_requested is not None:
            self.store.update(job.id, only_if=[RUNNING], status=DISMISSED, finished=now,
                              message=f"cancelled ({why}); partial results kept")
        elif job.attempts >= self.settings.max_attempts:
            self.store.update(
                job.id, only_if=[RUNNING], status="failed", finished=now, error_kind="system",
                message=f"system error: {why}, {job.attempts} time"
                        f"{'s' if job.attempts != 1 else ''}; not retried again")
        else:
            self.store.update(job.id, only_if=[RUNNING], status=ACCEPTED, worker_pid=None,
                              message=f"re-queued: {why} (attempt {job.attempts} of "
                                      f"{self.settings.max_attempts})")
            self.submitted_again(job)

    def submitted_again(self, job: JobRecord) -> None:
        """A job went back to `accepted` after its worker was lost."""
        self.wake()
