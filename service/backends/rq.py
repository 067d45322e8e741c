"""Scale-out backend: jobs on RQ workers (`polydda worker`) through one Redis queue.

The API commits the job row, then enqueues `service.jobs.run_rq`. A worker writes progress
and the outcome into the Redis hash `polydda:job:<id>` and its files into the shared data
directory; the supervisor thread copies those hashes into the job table, marks jobs whose
RQ job failed, was stopped or vanished, and stops (via RQ's stop-job command) a cancelled
job that did not stop by itself within `cancel_grace`.
"""

from __future__ import annotations

import json
import logging
import time
from typing import Any

from service.backends import Backend
from service.backends.store import ACCEPTED, ACTIVE, DISMISSED, FAILED, FINAL, JobRecord
from service.jobs import cancel_key, job_key

log = logging.getLogger(__name__)

RQ_FUNCTION = "service.jobs.run_rq"
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

        self.redis = Redis.from_url(self.settings.redis_url, socket_timeout=10,
                                    socket_connect_timeout=5)
        self.queue = Queue(self.settings.rq_queue, connection=self.redis)
        self.stop_sent: set[str] = set()

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
        try:
            self.submitted(job)
        except QueueUnavailable:
            log.warning("could not re-queue job %s", job.id)

    def on_cancel(self, job_id: str, started: bool) -> None:
        from redis.exceptions import RedisError
        from rq.job import Job

        try:
            self.redis.set(cancel_key(job_id), b"1", ex=7 * 24 * 3600)
            if not started:
                rq_job = Job.fetch(job_id, connection=self.redis)
                rq_job.cancel()
        except Exception as exc:  # NoSuchJobError, InvalidJobOperation, RedisError
            if isinstance(exc, RedisError):
                log.warning("cancel of %s: Redis error %s", job_id, exc)

    # ------------------------------------------------------------------ supervision
    def tick(self) -> None:
        from redis.exceptions import RedisError

        jobs = self.store.active()
        if not jobs:
            return
        try:
            self._sync(jobs)
        except RedisError as exc:
            log.warning("cannot reach Redis: %s", exc)

    def _sync(self, jobs: list[JobRecord]) -> None:
        from rq.command import send_stop_job_command
        from rq.job import Job, JobStatus

        pipe = self.redis.pipeline()
        for job in jobs:
            pipe.hgetall(job_key(job.id))
        hashes = pipe.execute()
        rq_jobs = Job.fetch_many([j.id for j in jobs], connection=self.redis)
        now = time.time()
        for job, raw, rq_job in zip(jobs, hashes, rq_jobs, strict=True):
            h = {k.decode(): json.loads(v) for k, v in raw.items()}
            if h and float(h.get("updated") or 0) > job.updated:
                values = {k: h[k] for k in _SYNCED if k in h}
                if values.get("status") not in ("running", *FINAL):
                    values.pop("status", None)
                self.store.update(job.id, only_if=ACTIVE, **values)
            if h.get("status") in FINAL:
                continue
            status = None if rq_job is None else rq_job.get_status(refresh=False)
            if rq_job is None and job.status == ACCEPTED and not h:
                if now - job.created > self.lost_grace:
                    self.requeue_lost(job)
            elif rq_job is None or status == JobStatus.FAILED:
                self.store.update(job.id, only_if=ACTIVE, status=FAILED, finished=now,
                                  error_kind="system",
                                  message="system error: the worker running this job died or "
                                          f"lost it ({self._failure(rq_job)}); resubmit the job")
            elif status in (JobStatus.STOPPED, JobStatus.CANCELED):
                self.store.update(job.id, only_if=ACTIVE, status=DISMISSED, finished=now,
                                  message="cancelled: the worker stopped the job; "
                                          "partial results kept")
            elif (job.cancel_requested is not None and job.id not in self.stop_sent
                  and now - job.cancel_requested > self.settings.cancel_grace):
                try:
                    send_stop_job_command(self.redis, job.id)
                    self.stop_sent.add(job.id)
                except Exception as exc:  # not executing (yet / any more)
                    log.info("stop of %s not sent: %s", job.id, exc)

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
