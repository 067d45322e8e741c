"""Embedded backend: each job in its own process on the API host, up to max_workers.

The supervisor thread claims accepted jobs (oldest first), starts their processes, reaps
them, and kills a cancelled one that has not stopped within `cancel_grace`. A job process
is a fresh interpreter (`python -m service.jobs.embedded ...`) started with the
worker environment (`Settings.worker_env`: one OMP/BLAS thread) already set, so numpy
never loads with more threads, whatever the API process imported. It writes its progress
and outcome to the job table itself and stops by itself when the API process that started
it is gone; the next API process re-queues what was left running.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from service.jobs.backend import Backend
from service.jobs.store import ACCEPTED, DISMISSED, FAILED, RUNNING, JobRecord, JobStore
from service.jobs.tasks import TaskContext

log = logging.getLogger(__name__)

#: seconds between SIGTERM and SIGKILL of a job process that was told to stop
KILL_AFTER = 2.0
#: the module a job process runs (`python -m JOB_MODULE ...`); also how a stale one is known
JOB_MODULE = "service.jobs.embedded"


class SqliteContext(TaskContext):
    """Progress into the job table; stop when cancelled or when the parent process died."""

    def __init__(self, store: JobStore, job_id: str, parent_pid: int, interval: float) -> None:
        super().__init__(interval)
        self.store, self.job_id, self.parent_pid = store, job_id, parent_pid
        self.orphaned = False

    def write_progress(self, values: dict[str, Any]) -> None:
        self.store.update(self.job_id, only_if=[RUNNING], **values)

    def cancel_requested(self) -> bool:
        if os.getppid() != self.parent_pid:
            self.orphaned = True
            return True
        job = self.store.get(self.job_id)
        return job is None or job.status != RUNNING or job.cancel_requested is not None


def child_main(db_path: str, job_id: str, process: str, job_dir: str, nice: int,
               interval: float, parent_pid: int) -> None:
    """Body of a job process (its environment set by the parent): run, record the outcome."""
    if nice:
        os.nice(nice)
    from service.jobs.execute import execute

    store = JobStore(Path(db_path))
    ctx = SqliteContext(store, job_id, parent_pid, interval)
    outcome = execute(process, store.scene(job_id), Path(job_dir), ctx)
    if ctx.orphaned:  # the API process is gone: leave the job running for its successor
        return
    store.update(job_id, only_if=[RUNNING], status=outcome.status, message=outcome.message,
                 error_kind=outcome.error_kind, finished=time.time())


def job_command(db_path: Path, job_id: str, process: str, job_dir: Path, nice: int,
                interval: float, parent_pid: int) -> list[str]:
    """The command line of a job process (read back by :func:`main`)."""
    return [sys.executable, "-m", JOB_MODULE, str(db_path), job_id, process, str(job_dir),
            str(nice), repr(interval), str(parent_pid)]


def main(argv: list[str]) -> int:
    """Entry point of a job process: `python -m service.jobs.embedded` + job_command."""
    db_path, job_id, process, job_dir, nice, interval, parent_pid = argv
    child_main(db_path, job_id, process, job_dir, int(nice), float(interval), int(parent_pid))
    return 0


def _exit_text(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"killed by signal {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def _is_job_process(pid: int) -> bool:
    """True if `pid` is alive and is a job process (a stale one of an earlier API process)."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    return JOB_MODULE.encode() in cmdline.split(b"\0")


class EmbeddedBackend(Backend):
    """Job processes of the API host; the job table is their only shared state."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.terminated: dict[str, float] = {}

    def recover(self) -> None:
        for job in self.store.active():
            if job.status != RUNNING:
                continue
            if job.worker_pid and _is_job_process(job.worker_pid):
                log.warning("killing stale job process %s of job %s", job.worker_pid, job.id)
                try:
                    os.kill(job.worker_pid, signal.SIGKILL)
                except OSError:
                    pass
            self.requeue_or_fail(job, "the service stopped while the job was running")

    def tick(self) -> None:
        self._reap()
        self._enforce_cancel()
        self._start_jobs()

    def _start_jobs(self) -> None:
        free = self.settings.max_workers - len(self.procs)
        if free <= 0 or self._stopping.is_set():
            return
        waiting = [j for j in self.store.active() if j.status == ACCEPTED][:free]
        for job in waiting:
            if self.store.claim(job.id):
                self._spawn(job)

    def _spawn(self, job: JobRecord) -> None:
        s = self.settings
        cmd = job_command(s.db_path.resolve(), job.id, job.process, s.job_dir(job.id).resolve(),
                          s.worker_nice, s.progress_interval, os.getpid())
        try:
            # its own session: a Ctrl-C at the API's terminal reaches the API only, whose
            # stop() then ends the job processes and re-queues their jobs
            proc = subprocess.Popen(cmd, env={**os.environ, **s.worker_env()},
                                    stdin=subprocess.DEVNULL, start_new_session=True)
        except Exception as exc:
            log.exception("cannot start a process for job %s", job.id)
            self.store.update(job.id, only_if=[RUNNING], status=FAILED, finished=time.time(),
                              error_kind="system",
                              message=f"system error: cannot start a job process: {exc}")
            return
        self.procs[job.id] = proc
        self.store.update(job.id, only_if=[RUNNING], worker_pid=proc.pid)

    def _reap(self) -> None:
        for job_id, proc in list(self.procs.items()):
            if proc.poll() is None:
                continue
            del self.procs[job_id]
            self.terminated.pop(job_id, None)
            job = self.store.get(job_id)
            if job is None or job.status != RUNNING:
                continue  # the job process recorded its outcome
            now = time.time()
            if job.cancel_requested is not None:
                self.store.update(job_id, only_if=[RUNNING], status=DISMISSED, finished=now,
                                  message="cancelled: the job process was stopped; "
                                          "partial results kept")
            else:
                self.store.update(
                    job_id, only_if=[RUNNING], status=FAILED, finished=now, error_kind="system",
                    message=f"system error: the job process ended unexpectedly "
                            f"({_exit_text(proc.returncode)}); resubmit the job")

    def _enforce_cancel(self) -> None:
        if not self.procs:
            return
        now = time.time()
        for job_id, proc in self.procs.items():
            if job_id in self.terminated:
                if now - self.terminated[job_id] > KILL_AFTER and proc.poll() is None:
                    proc.kill()
                continue
            job = self.store.get(job_id)
            if (job is not None and job.cancel_requested is not None
                    and now - job.cancel_requested > self.settings.cancel_grace):
                proc.terminate()
                self.terminated[job_id] = now

    def on_cancel(self, job_id: str, started: bool) -> None:
        self.wake()

    def health(self) -> dict[str, Any]:
        alive = self._thread is not None and self._thread.is_alive()
        return {"status": "ok" if alive else "unavailable",
                "workers": self.settings.max_workers, "busy": len(self.procs)}

    def stop(self) -> None:
        """Stop supervising; job processes are stopped and their jobs re-queued."""
        super().stop()
        for proc in self.procs.values():
            proc.terminate()
        deadline = time.monotonic() + 5.0
        for job_id, proc in self.procs.items():
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                try:
                    proc.wait(2.0)
                except subprocess.TimeoutExpired:
                    log.error("job process %s of job %s does not die", proc.pid, job_id)
            job = self.store.get(job_id)
            if job is not None and job.status == RUNNING:
                if job.cancel_requested is not None:
                    self.store.update(job_id, only_if=[RUNNING], status=DISMISSED,
                                      finished=time.time(),
                                      message="cancelled; partial results kept")
                else:
                    self.store.update(job_id, only_if=[RUNNING], status=ACCEPTED,
                                      attempts=max(0, job.attempts - 1), worker_pid=None,
                                      message="re-queued: the service was stopped")
        self.procs.clear()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
