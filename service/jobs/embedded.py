"""Embedded backend: each job in its own process on the API host, up to max_workers.

The supervisor thread claims accepted jobs (oldest first), starts their processes, reaps
them, and kills a cancelled one that has not stopped within `cancel_grace`. A job process
is a fresh interpreter (`python -m service.jobs.embedded ...`) started with the
worker environment (`Settings.worker_env`: one OMP/BLAS thread) already set, so numpy
never loads with more threads, whatever the API process imported. It writes its progress
and outcome to the job table itself and stops by itself when the API process that started
it is gone; the next API process re-queues what was left running.

A job whose process ended without an outcome (killed, crashed) is lost as a job is when
the API process stops under it: one policy for both (Backend.requeue_or_fail), back to the
queue until it has run `max_attempts` times, then failed, kind `system`. Only a process
that died while the data disk was full fails at once (no retry cures that).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from service.jobs.backend import Backend
from service.jobs.store import (
    ACCEPTED,
    DISMISSED,
    FAILED,
    RUNNING,
    JobRecord,
    JobStore,
    disk_full,
)
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
        try:
            self.store.update(self.job_id, only_if=[RUNNING], **values)
        except sqlite3.Error as exc:  # a full disk: the next write carries the news
            if not disk_full(exc):
                raise
            log.warning("progress of job %s not written: %s", self.job_id, exc)

    def cancel_requested(self) -> bool:
        if os.getppid() != self.parent_pid:
            self.orphaned = True
            return True
        job = self.store.get(self.job_id)
        return job is None or job.status != RUNNING or job.cancel_requested is not None


def child_main(db_path: str, job_id: str, process: str, job_dir: str, nice: int,
               interval: float, parent_pid: int, outcome_fd: int = -1,
               min_free_bytes: int = 0) -> None:
    """Body of a job process (its environment set by the parent): run, record the outcome.

    The outcome also goes to the parent through `outcome_fd` before it is written to the
    job table: when that write fails (a full disk), the parent retries it.
    """
    if nice:
        os.nice(nice)
    from service.jobs.execute import execute

    def send(values: dict[str, Any]) -> None:
        if outcome_fd >= 0:
            with contextlib.suppress(OSError):
                os.write(outcome_fd, json.dumps(values).encode()[:60_000])
                os.close(outcome_fd)

    try:
        store = JobStore(Path(db_path))
        scene_text = store.scene(job_id)
    except sqlite3.Error as exc:  # e.g. a disk so full that the table cannot be opened
        send({"status": FAILED, "error_kind": "system", "finished": time.time(),
              "message": f"system error: the job table could not be read ({exc}"
                         f"{': the disk is full' if disk_full(exc) else ''})"})
        raise
    ctx = SqliteContext(store, job_id, parent_pid, interval)
    ctx.guard_disk(Path(db_path).parent, min_free_bytes)
    outcome = execute(process, scene_text, Path(job_dir), ctx)
    if ctx.orphaned:  # the API process is gone: leave the job running for its successor
        return
    values = {"status": outcome.status, "message": outcome.message,
              "error_kind": outcome.error_kind, "finished": time.time()}
    send(values)
    try:
        store.update(job_id, only_if=[RUNNING], **values)
    except sqlite3.Error as exc:
        if not disk_full(exc):
            raise
        log.error("outcome of job %s not written (%s); the service retries it", job_id, exc)


def job_command(db_path: Path, job_id: str, process: str, job_dir: Path, nice: int,
                interval: float, parent_pid: int, outcome_fd: int = -1,
                min_free_bytes: int = 0) -> list[str]:
    """The command line of a job process (read back by :func:`main`)."""
    return [sys.executable, "-m", JOB_MODULE, str(db_path), job_id, process, str(job_dir),
            str(nice), repr(interval), str(parent_pid), str(outcome_fd), str(min_free_bytes)]


def main(argv: list[str]) -> int:
    """Entry point of a job process: `python -m service.jobs.embedded` + job_command."""
    db_path, job_id, process, job_dir, nice, interval, parent_pid, fd, free = argv
    child_main(db_path, job_id, process, job_dir, int(nice), float(interval), int(parent_pid),
               int(fd), int(free))
    return 0


def _read_outcome(fd: int) -> dict[str, Any] | None:
    """The outcome a job process sent through its pipe (None if it sent none); closes fd."""
    chunks = []
    try:
        while True:
            chunk = os.read(fd, 65536)
            if not chunk:
                break
            chunks.append(chunk)
    except BlockingIOError:
        pass
    except OSError:
        return None
    finally:
        with contextlib.suppress(OSError):
            os.close(fd)
    try:
        values = json.loads(b"".join(chunks)) if chunks else None
    except ValueError:
        return None
    return values if isinstance(values, dict) and "status" in values else None


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
        #: job id -> read end of the pipe its process sends its outcome through
        self.outcome_pipes: dict[str, int] = {}
        #: outcomes of ended job processes not yet written to the job table (a full
        #: disk): retried every tick until they are; `{"lost": why}` for a process that
        #: ended without one (its job is re-queued or failed: Backend.requeue_or_fail)
        self.pending: dict[str, dict[str, Any]] = {}

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
        self._write_pending()
        self._enforce_cancel()
        self._start_jobs()

    def _start_jobs(self) -> None:
        free = self.settings.max_workers - len(self.procs) - len(self.pending)
        if free <= 0 or self._stopping.is_set() or self.low_disk():
            return
        waiting = [j for j in self.store.active() if j.status == ACCEPTED][:free]
        for job in waiting:
            if self.store.claim(job.id):
                self._spawn(job)

    def _spawn(self, job: JobRecord) -> None:
        s = self.settings
        read_fd, write_fd = os.pipe()
        os.set_blocking(read_fd, False)
        cmd = job_command(s.db_path.resolve(), job.id, job.process, s.job_dir(job.id).resolve(),
                          s.worker_nice, s.progress_interval, os.getpid(), write_fd,
                          s.min_free_bytes)
        try:
            # its own session: a Ctrl-C at the API's terminal reaches the API only, whose
            # stop() then ends the job processes and re-queues their jobs
            proc = subprocess.Popen(cmd, env={**os.environ, **s.worker_env()},
                                    stdin=subprocess.DEVNULL, start_new_session=True,
                                    pass_fds=(write_fd,))
        except Exception as exc:
            os.close(read_fd)
            log.exception("cannot start a process for job %s", job.id)
            self.store.update(job.id, only_if=[RUNNING], status=FAILED, finished=time.time(),
                              error_kind="system",
                              message=f"system error: cannot start a job process: {exc}")
            return
        finally:
            os.close(write_fd)
        self.procs[job.id] = proc
        self.outcome_pipes[job.id] = read_fd
        self.store.update(job.id, only_if=[RUNNING], worker_pid=proc.pid)

    def _reap(self) -> None:
        """Settle the jobs whose processes ended: the outcome each sent (if the job table
        does not have it yet), else why it ended. A write that fails (a full disk) is kept
        in `pending` and retried; the process leaves the table only once it is decided."""
        for job_id, proc in list(self.procs.items()):
            if proc.poll() is None:
                continue
            sent = _read_outcome(self.outcome_pipes.pop(job_id, -1))
            self.pending[job_id] = self._final_values(job_id, proc, sent)
            del self.procs[job_id]  # only now: its outcome is kept in `pending`
            self.terminated.pop(job_id, None)

    def _final_values(self, job_id: str, proc: subprocess.Popen[bytes],
                      sent: dict[str, Any] | None) -> dict[str, Any]:
        """The final fields of a job whose process ended (`sent`: its own outcome)."""
        now = time.time()
        if sent is not None:
            return {"status": sent["status"], "message": str(sent.get("message") or ""),
                    "error_kind": sent.get("error_kind"),
                    "finished": float(sent.get("finished") or now)}
        try:
            job = self.store.get(job_id)
        except sqlite3.Error:  # unreadable now (a full disk): not cancelled, as far as known
            job = None
        if job is not None and job.cancel_requested is not None:
            return {"status": DISMISSED, "finished": now,
                    "message": "cancelled: the job process was stopped; partial results kept"}
        why = f"its job process ended unexpectedly ({_exit_text(proc.returncode)})"
        if self._disk_full_now():  # a cause no retry cures: failed, as a full disk is
            return {"status": FAILED, "finished": now, "error_kind": "system",
                    "message": f"system error: {why} while the data directory's disk was "
                               "full; not retried"}
        return {"lost": why}

    def _disk_full_now(self) -> bool:
        try:
            return shutil.disk_usage(self.settings.data_dir).free < (1 << 20)
        except OSError:
            return False

    def _write_pending(self) -> None:
        """Write the outcomes of ended job processes to the job table (only over `running`:
        a job that recorded its own outcome keeps it); keep those that fail for later."""
        for job_id, values in list(self.pending.items()):
            try:
                if "lost" in values:  # no outcome: the policy of a lost job
                    job = self.store.get(job_id)
                    if job is not None and job.status == RUNNING:
                        self.requeue_or_fail(job, values["lost"])
                else:
                    self.store.update(job_id, only_if=[RUNNING], **values)
            except sqlite3.Error as exc:
                log.warning("outcome of job %s not written yet (%s); retrying", job_id, exc)
                continue
            del self.pending[job_id]

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

    def _stopped(self, job_id: str) -> None:
        """A job whose process the stopping service ended: dismissed if it was being
        cancelled, else back to the queue (its attempt not counted)."""
        job = self.store.get(job_id)
        if job is None or job.status != RUNNING:
            return
        if job.cancel_requested is not None:
            self.store.update(job_id, only_if=[RUNNING], status=DISMISSED, finished=time.time(),
                              message="cancelled; partial results kept")
        else:
            self.store.update(job_id, only_if=[RUNNING], status=ACCEPTED,
                              attempts=max(0, job.attempts - 1), worker_pid=None,
                              message="re-queued: the service was stopped")

    def on_cancel(self, job_id: str, started: bool) -> None:
        self.wake()

    def health(self) -> dict[str, Any]:
        alive = self._thread is not None and self._thread.is_alive()
        doc = {"status": "ok" if alive else "unavailable",
               "workers": self.settings.max_workers, "busy": len(self.procs)}
        if self.pending:  # ended jobs whose outcome could not be written yet (disk full)
            doc |= {"status": "degraded" if alive else "unavailable",
                    "unrecorded": len(self.pending)}
        return doc

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
            try:
                self._stopped(job_id)
            except sqlite3.Error as exc:  # the next server's recovery settles the job
                log.error("job %s not re-queued: %s", job_id, exc)
        self.procs.clear()
        for fd in self.outcome_pipes.values():
            with contextlib.suppress(OSError):
                os.close(fd)
        self.outcome_pipes.clear()
        self._write_pending()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
