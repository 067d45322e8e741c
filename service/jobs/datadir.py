"""One owner per data directory: an exclusive lock (flock) on `<data dir>/.polydda.lock`.

Two API servers on one data directory would each supervise the same job table: the second's
recovery would take the first's running jobs for stale and run them again. The lock is held
for the server's lifetime and released by the kernel when its process dies (even by
SIGKILL), so a crashed server never blocks its successor; job processes do not inherit it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from pathlib import Path


class DataDirBusy(RuntimeError):
    """Another live process owns the data directory."""


class DataDirLock:
    """The exclusive lock of one data directory (acquire / release, or a `with` block)."""

    def __init__(self, data_dir: Path) -> None:
        self.path = Path(data_dir) / ".polydda.lock"
        self._fd: int | None = None

    def acquire(self) -> DataDirLock:
        """Take the lock now or raise DataDirBusy naming the owner."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise DataDirBusy(f"the data directory {self.path.parent} is in use by another "
                              f"PolyDDA server ({owner}); stop it first, or give this one its "
                              "own POLYDDA_DATA_DIR") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> DataDirLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
