"""What a running job sees, whatever the backend: progress reporting, cancellation, outcome.

A backend hands a process runner (service.jobs.processes) a :class:`TaskContext`; the runner
reports progress (throttled), asks `should_stop()` and returns an :class:`Outcome`.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: who is to blame for a failed job: the scene (`model`) or the service (`system`)
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
        #: the disk guard: the job stops when `guard_dir`'s disk has less than
        #: `min_free_bytes` free (0: no guard)
        self.guard_dir: Path | None = None
        self.min_free_bytes = 0
        #: why the job was stopped by the service itself (the disk guard), if it was
        self.stop_reason: str | None = None

    def guard_disk(self, directory: Path, min_free_bytes: int) -> None:
        """Stop the job when `directory`'s disk has less than `min_free_bytes` free."""
        self.guard_dir, self.min_free_bytes = directory, min_free_bytes

    def low_disk(self) -> bool:
        """True (and `stop_reason` set) when the guarded disk has too little free space."""
        if self.guard_dir is None or self.min_free_bytes <= 0:
            return False
        try:
            free = shutil.disk_usage(self.guard_dir).free
        except OSError:
            return False
        if free >= self.min_free_bytes:
            return False
        self.stop_reason = (f"stopped by the service: the data directory's disk has "
                            f"{free / 2**20:,.0f} MiB free, less than the "
                            f"{self.min_free_bytes / 2**20:,.0f} MiB it keeps free "
                            "(POLYDDA_MIN_FREE_BYTES)")
        return True

    # hooks
    def write_progress(self, values: dict[str, Any]) -> None:
        """Store progress fields (`progress` percent, `step`, `simulated_time`, ...)."""

    def cancel_requested(self) -> bool:
        """True when someone asked this job to stop."""
        return False

    # API used by the job function
    def report(self, percent: float, *, force: bool = False, **fields: Any) -> None:
        """Record progress (`percent` 0-100 plus fields), throttled unless `force`."""
        now = time.monotonic()
        if not force and now - self._last_report < self.interval:
            return
        self._last_report = now
        self.write_progress({"progress": round(max(0.0, min(100.0, percent)), 2), **fields})

    def should_stop(self) -> bool:
        """True once a stop was asked for (the backend is polled every `poll` s)."""
        if self._stop:
            return True
        now = time.monotonic()
        if now - self._last_poll >= self.poll:
            self._last_poll = now
            self._stop = self.low_disk() or bool(self.cancel_requested())
        return self._stop
