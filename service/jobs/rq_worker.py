"""The worker side of the RQ backend: RQ's forking worker, made to ride out Redis outages.

RQ's own worker retries only its idle wait for a job; any other Redis error (a heartbeat
while a job runs, the bookkeeping after it) ends the worker with a traceback, and the job's
work horse, which dies with its worker (service.jobs.execute.die_with_parent), with it. Here those
errors are logged once per outage and the worker goes on: the horse keeps computing (its
own progress writes are skipped and its outcome retried until Redis answers), heartbeats
resume when Redis is back, and a Redis that came back empty gets the worker's registration
again, so the API counts it among the live workers.

Heartbeats come every :data:`HEARTBEAT` s when idle (RQ's dequeue timeout) and every
:data:`MONITOR` s while a job runs; the API counts a worker live while its last heartbeat
is younger than :data:`LIVE`.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any

from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError
from rq import Worker, worker_registration

#: s between an idle worker's heartbeats (RQ's dequeue timeout is its worker_ttl - 15)
HEARTBEAT = 10
#: s between a busy worker's heartbeats (RQ's job monitoring interval)
MONITOR = 5
#: s after its last heartbeat that a worker still counts as live (three idle periods)
LIVE = 3 * HEARTBEAT
#: s, the longest pause between two reconnection attempts
RECONNECT_MAX = 5.0
#: the Redis errors of a lost connection (anything else is a bug and is raised)
LOST = (RedisConnectionError, RedisTimeoutError)


class PolyddaWorker(Worker):
    """An RQ `Worker` that survives Redis going away and coming back (empty or not)."""

    max_connection_wait_time = RECONNECT_MAX

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("worker_ttl", HEARTBEAT + 15)
        kwargs.setdefault("job_monitoring_interval", MONITOR)
        super().__init__(*args, **kwargs)
        self._outage: float | None = None  # monotonic time Redis was first found away

    # ------------------------------------------------------------------ outage bookkeeping
    def _lost(self, exc: Exception) -> None:
        if self._outage is None:
            self._outage = time.monotonic()
            self.log.warning("Worker %s: Redis unreachable (%s); a running job goes on, "
                             "reconnecting", self.name, exc)

    def _back(self) -> None:
        """A heartbeat went through: end the outage (if any), be registered."""
        if self._outage is not None:
            away, self._outage = time.monotonic() - self._outage, None
            self.log.info("Worker %s: Redis reachable again after %.1f s", self.name, away)
        self._register_again()

    def _register_again(self) -> None:
        """Put this worker back into RQ's registry if Redis lost it (restarted empty; RQ's
        wait for a job reconnects by itself, so the outage may have gone unseen here)."""
        if self.connection.sismember(worker_registration.REDIS_WORKER_KEYS, self.key):
            return
        self.log.info("Worker %s: Redis lost this worker's registration; registering again",
                      self.name)
        with self.connection.pipeline() as pipe:
            pipe.hset(self.key, mapping=self.serialize())
            worker_registration.register(self, pipe)
            pipe.expire(self.key, self.worker_ttl + 60)
            pipe.execute()

    # ------------------------------------------------------------------ RQ hooks
    def heartbeat(self, timeout: int | None = None, pipeline: Any = None) -> None:
        try:
            super().heartbeat(timeout, pipeline)
            if pipeline is None:
                self._back()
        except LOST as exc:
            self._lost(exc)

    def maintain_heartbeats(self, job: Any, execution: Any) -> None:
        try:
            super().maintain_heartbeats(job, execution)
            self._back()
        except LOST as exc:
            self._lost(exc)

    def set_state(self, state: str, pipeline: Any = None) -> None:
        try:
            super().set_state(state, pipeline)
        except LOST as exc:
            self._lost(exc)

    def check_for_suspension(self, burst: bool) -> None:
        try:
            super().check_for_suspension(burst)
        except LOST as exc:  # the wait for a job that follows retries with backoff
            self._lost(exc)

    def run_maintenance_tasks(self) -> None:
        try:
            super().run_maintenance_tasks()
        except LOST as exc:
            self._lost(exc)

    def monitor_work_horse(self, job: Any, queue: Any, execution: Any) -> None:
        try:
            super().monitor_work_horse(job, queue, execution)
        except LOST as exc:
            # the horse has ended; RQ's record of how could not be written. The job's own
            # outcome is in its polydda hash (written by the horse, retried until Redis
            # answered); the API decides on the job from that and its heartbeat.
            self._lost(exc)
            self._horse_pid = 0
            self.executions.pop(execution.id, None)
            self.log.warning("Worker %s: RQ's record of job %s not updated (Redis away)",
                             self.name, job.id)

    def _pubsub_exception_handler(self, exc: Exception, pubsub: Any, pubsub_thread: Any) -> None:
        """RQ's handler of the command channel's thread, saying it once per outage."""
        if not isinstance(exc, LOST):
            super()._pubsub_exception_handler(exc, pubsub, pubsub_thread)
            return
        self._lost(exc)
        time.sleep(2.0)  # redis-py subscribes again when the connection is back

    def teardown(self) -> None:
        with contextlib.suppress(*LOST):
            super().teardown()
