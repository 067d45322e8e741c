"""Scale-out backend: jobs on RQ workers (`polydda worker`) through one Redis queue.

The API commits the job row, then enqueues `service.jobs.execute.run_rq`. A worker writes progress
and the outcome into the Redis hash `polydda:job:<id>` and its files into the shared data
directory, and keeps the job's heartbeat key `polydda:alive:<id>` (TTL `rq_heartbeat_ttl`)
while it runs. The supervisor thread copies those hashes into the job table; a running job
whose heartbeat is gone while Redis has been up for a whole TTL lost its worker (killed,
host gone) and is re-queued, at most `max_attempts` runs (service.jobs.backend.Backend
.requeue_or_fail). It marks jobs whose RQ job failed or was stopped, and delivers cancels:
the cancel key again each tick (Redis may have lost it), RQ's stop-job command for a job
that did not stop within `cancel_grace`, and cancels of queued jobs made while Redis was
away once it is back. While Redis is away nothing is decided; /health says 503.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from typing import Any

from service.jobs.backend import Backend
from service.jobs.execute import alive_key, cancel_key, job_key
from service.jobs.store import (
    ACCEPTED,
    ACTIVE,
    DISMISSED,
    FAILED,
    FINAL,
    RUNNING,
    JobRecord,
)

log = logging.getLogger(__name__)

RQ_FUNCTION = "service.jobs.execute.run_rq"
#: fields copied from a worker's Redis hash into the job table
_SYNCED = ("status", "started", "finished", "updated", "progress", "step", "simulated_time",
           "duration", "message", "error_kind", "worker_pid")


class QueueUnavailable(RuntimeError):
    """Redis could not be reached to enqueue a job."""


class RqBackend(Backend):
    """RQ queue + Redis progress hashes; the job table stays the record the API serves."""

    period = 0.25
    #: s after its submission before an accepted job missing from Redis counts as lost; the
    #: API commits the row before it enqueues, and a tick between the two must not re-enqueue
    #: (the job would then run twice, on two workers, into the same files)
    lost_grace = 30.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        from redis import Redis
        from rq import Queue

        url = self.settings.redis_url
        self.redis = Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5)
        #: for /health: answers within seconds even when Redis hangs
        self.probe = Redis.from_url(url, socket_timeout=2, socket_connect_timeout=2)
        self.queue = Queue(self.settings.rq_queue, connection=self.redis)
        self.probe_queue = Queue(self.settings.rq_queue, connection=self.probe)
        self.stop_sent: set[str] = set()
        #: jobs dismissed before they started whose cancel has not reached Redis yet
        self.undelivered: set[str] = set()
        #: monotonic time since which Redis answered every tick (None: not yet, or not now)
        self.reachable_since: float | None = None
        self.redis_away = False

    def _enqueue(self, job: JobRecord) -> None:
        self.queue.enqueue(RQ_FUNCTION, job.id, job.process, self.store.scene(job.id),
                           job_id=job.id, job_timeout=self.settings.job_timeout,
                           result_ttl=7 * 24 * 3600, failure_ttl=30 * 24 * 3600,
                           description=f"polydda {job.process} {job.id}")

    def submitted(self, job: JobRecord) -> None:
        from redis.exceptions import RedisError

        try:
            self.redis.delete(job_key(job.id), cancel_key(job.id))
            self._enqueue(job)
        except RedisError as exc:
            self.store.update(job.id, only_if=ACTIVE, status=FAILED, finished=time.time(),
                              error_kind="system",
                              message=f"system error: the job queue is unreachable ({exc})")
            raise QueueUnavailable(str(exc)) from exc

    def submitted_again(self, job: JobRecord) -> None:
        """Back to the queue after its worker was lost: RQ's record of the lost run goes
        first (else RQ's clean-up of its abandoned run would fail the new one)."""
        from rq.job import Job

        try:
            old = Job.fetch_many([job.id], connection=self.redis)[0]
            if old is not None:
                old.delete()
            self.submitted(job)
        except Exception as exc:  # QueueUnavailable (recorded), a bad RQ record
            log.warning("could not re-queue job %s: %s", job.id, exc)

    def on_cancel(self, job_id: str, started: bool) -> None:
        from redis.exceptions import RedisError

        try:
            self._deliver_cancel(job_id, started)
        except RedisError as exc:  # the supervisor delivers it when Redis is back
            log.warning("cancel of %s not delivered yet (Redis: %s)", job_id, exc)
            if not started:
                self.undelivered.add(job_id)

    def _deliver_cancel(self, job_id: str, started: bool) -> None:
        """Set the job's cancel key (its worker polls it); a queued job also leaves RQ's
        queue. Raises RedisError."""
        from rq.exceptions import InvalidJobOperation
        from rq.job import Job

        self.redis.set(cancel_key(job_id), b"1", ex=7 * 24 * 3600)
        if not started:
            rq_job = Job.fetch_many([job_id], connection=self.redis)[0]
            if rq_job is not None:
                with contextlib.suppress(InvalidJobOperation):  # already ended
                    rq_job.cancel()

    # ------------------------------------------------------------------ health
    def health(self) -> dict[str, Any]:
        """`unavailable` (503) when Redis does not answer; `degraded` when no worker is
        live (jobs wait); `workers` live (a heartbeat within rq_worker.LIVE s), `busy`."""
        from redis.exceptions import RedisError
        from rq import Worker
        from rq.utils import now

        from service.jobs.rq_worker import LIVE

        try:
            self.probe.ping()
            workers = Worker.all(queue=self.probe_queue)
        except RedisError as exc:
            return {"status": "unavailable", "workers": 0, "busy": 0,
                    "redis": f"unreachable: {exc}"}
        t = now()
        live = [w for w in workers if w.last_heartbeat is not None
                and (t - w.last_heartbeat).total_seconds() < LIVE]
        busy = sum(w.get_state() == "busy" for w in live)
        supervised = self._thread is not None and self._thread.is_alive()
        status = "ok" if live and supervised else "degraded"
        return {"status": status, "workers": len(live), "busy": busy, "redis": "ok"}

    # ------------------------------------------------------------------ supervision
    def tick(self) -> None:
        from redis.exceptions import RedisError

        jobs = self.store.active()
        if not jobs and not self.undelivered:
            return
        try:
            for job_id in list(self.undelivered):
                self._deliver_cancel(job_id, started=False)
                self.undelivered.discard(job_id)
            if jobs:
                self._sync(jobs)
        except RedisError as exc:
            if not self.redis_away:
                log.warning("cannot reach Redis (%s): jobs are not supervised until it is "
                            "back", exc)
            self.redis_away, self.reachable_since = True, None

    def _settled(self, uptime: float, latency: float) -> bool:
        """True when Redis has answered (and run) for a whole heartbeat TTL: a heartbeat
        key missing now means its job's process stopped beating, not that Redis lost it.
        An answer that took over a third of the TTL counts as an outage just ended (Redis
        hung, and the beats were held up with our question)."""
        if self.redis_away:
            log.warning("Redis reachable again")
            self.redis_away = False
        if self.reachable_since is None or latency > self.settings.rq_heartbeat_ttl / 3:
            self.reachable_since = time.monotonic()
        up = min(uptime, time.monotonic() - self.reachable_since)
        return up >= self.settings.rq_heartbeat_ttl

    def _sync(self, jobs: list[JobRecord]) -> None:
        from rq.command import send_stop_job_command
        from rq.job import JobStatus

        pipe = self.redis.pipeline()  # MULTI: the hash and the heartbeat of one instant
        for job in jobs:
            pipe.hgetall(job_key(job.id))
            pipe.exists(alive_key(job.id))
        t0 = time.monotonic()
        replies = pipe.execute()
        latency = time.monotonic() - t0
        settled = self._settled(float(self.redis.info("server")["uptime_in_seconds"]), latency)
        rq_jobs = self._fetch([j.id for j in jobs])
        now = time.time()
        for job, raw, alive, rq_job in zip(jobs, replies[::2], replies[1::2], rq_jobs,
                                           strict=True):
            h = {k.decode(): json.loads(v) for k, v in raw.items()}
            if h and float(h.get("updated") or 0) > job.updated:
                values = {k: h[k] for k in _SYNCED if k in h}
                if values.get("status") not in ("running", *FINAL):
                    values.pop("status", None)
                elif job.status == ACCEPTED:  # a run began: count it, as the embedded claim
                    values = {"message": "", **values, "attempts": job.attempts + 1}
                self.store.update(job.id, only_if=ACTIVE, **values)
                job = self.store.get(job.id) or job
            if h.get("status") in FINAL or job.is_final:
                continue
            status = None if rq_job is None else rq_job.get_status(refresh=False)
            if job.status == RUNNING:
                if job.cancel_requested is not None:  # (again: Redis may have lost it)
                    self.redis.set(cancel_key(job.id), b"1", ex=7 * 24 * 3600)
                if status in (JobStatus.STOPPED, JobStatus.CANCELED):
                    self.store.update(job.id, only_if=ACTIVE, status=DISMISSED, finished=now,
                                      message="cancelled: the worker stopped the job; "
                                              "partial results kept")
                elif status == JobStatus.FAILED:
                    self._failed(job, rq_job, now)
                elif not alive and settled:
                    self.worker_lost(job)
                elif (job.cancel_requested is not None and job.id not in self.stop_sent
                      and now - job.cancel_requested > self.settings.cancel_grace):
                    try:
                        send_stop_job_command(self.redis, job.id)
                        self.stop_sent.add(job.id)
                    except Exception as exc:  # not executing (yet / any more)
                        log.info("stop of %s not sent: %s", job.id, exc)
            elif rq_job is None and not h:  # accepted, and Redis has no trace of it
                if now - job.created > self.lost_grace:
                    self.requeue_lost(job)
            elif status == JobStatus.FAILED:
                self._failed(job, rq_job, now)

    def _fetch(self, ids: list[str]) -> list[Any]:
        """RQ's jobs of these ids (None where Redis has none, or only a broken record:
        after Redis came back empty, a late write can leave a job hash without its data)."""
        from redis.exceptions import RedisError
        from rq.job import Job

        try:
            return Job.fetch_many(ids, connection=self.redis)
        except RedisError:
            raise
        except Exception:  # one broken record: the others one by one
            out: list[Any] = []
            for job_id in ids:
                try:
                    out.append(Job.fetch_many([job_id], connection=self.redis)[0])
                except RedisError:
                    raise
                except Exception:
                    out.append(None)
            return out

    def _failed(self, job: JobRecord, rq_job: Any, now: float) -> None:
        """RQ says the running job's process failed (its function raised, or the process
        was killed while its worker lived): lost, as a killed embedded process is
        (Backend.requeue_or_fail: re-queued until it has run max_attempts times). A job
        that died before it was seen running has no run to count: failed, kind system."""
        why = f"the process running it died ({self._failure(rq_job)})"
        if job.status == RUNNING:
            self.requeue_or_fail(job, why)
            return
        self.store.update(job.id, only_if=ACTIVE, status=FAILED, finished=now,
                          error_kind="system", message=f"system error: {why}")

    def worker_lost(self, job: JobRecord) -> None:
        """A running job whose heartbeat stopped (its worker was killed, or its host
        lost): re-queued (at most max_attempts runs), dismissed if it was cancelled."""
        ttl = self.settings.rq_heartbeat_ttl
        log.warning("job %s: no heartbeat for %g s; its worker is lost", job.id, ttl)
        self.requeue_or_fail(job, f"its worker was lost (no heartbeat for {ttl:g} s)")

    def requeue_lost(self, job: JobRecord) -> None:
        """An accepted job that Redis no longer has (e.g. Redis was emptied): enqueue again."""
        log.warning("job %s is missing from the queue; enqueueing it again", job.id)
        try:
            self._enqueue(job)
        except Exception as exc:
            log.warning("re-enqueue of %s failed: %s", job.id, exc)

    @staticmethod
    def _failure(rq_job: Any) -> str:
        if rq_job is None:
            return "the queue has no record of it"
        try:
            result = rq_job.latest_result()
            text = (getattr(result, "exc_string", None) or "").strip().splitlines()
        except Exception:
            text = []
        return text[-1] if text else f"RQ status {rq_job.get_status(refresh=False)}"
