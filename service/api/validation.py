"""The heavy half of a scene's validation (cutting, closed surfaces, overlaps:
schemas.convert.build_model) in worker processes apart from the API, with a time limit.

The API process checks a scene's structure itself (field types, names, the service's size
limits: milliseconds); building the model can take a minute for thousands of blocks, so it
runs in a small pool of `python -m service.api.validation` processes. A check that takes
longer than its time limit has its process killed (a new one takes its place), and every
check's time is charged to the client that asked (:class:`ValidationBudget`), so no client
can keep the pool busy and the API itself stays free to answer.

Protocol: one JSON line per request on the worker's stdin (`{"scene": <scene JSON text>}`),
one JSON line per answer on its stdout (`{"ok": true}`, `{"problems": [...]}` or
`{"error": "..."}`); the worker ends when its stdin closes (its API process is gone).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import logging
import os
import queue
import select
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import IO, Any

log = logging.getLogger("service.api")

MODULE = "service.api.validation"


class CheckTimeout(Exception):
    """The scene's check took longer than its time limit (its process was killed)."""


class CheckUnavailable(Exception):
    """No worker could check the scene (it died, or none could be started)."""


@dataclass
class Verdict:
    """A checked scene: `problems` (empty: valid) and the seconds the check took; for a
    preview (the builder's), the blocks cut (service.api.preview.preview_document)."""

    problems: list[dict[str, str]]
    seconds: float
    preview: dict[str, Any] | None = None


class _Worker:
    """One checking process and its pipes."""

    def __init__(self, env: dict[str, str], nice: int) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", MODULE, str(nice)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, env={**os.environ, **env}, start_new_session=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.kill()
        with contextlib.suppress(Exception):
            self.proc.wait(5)
        for f in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(Exception):
                f.close()  # type: ignore[union-attr]

    def ask(self, scene_text: str, timeout: float, preview: bool = False) -> dict[str, Any]:
        """Send one scene, wait up to `timeout` s for the answer (CheckTimeout, or
        CheckUnavailable when the process died)."""
        stdin, stdout = self.proc.stdin, self.proc.stdout
        assert stdin is not None and stdout is not None
        request = {"scene": scene_text, "preview": True} if preview else {"scene": scene_text}
        try:
            stdin.write(json.dumps(request).encode() + b"\n")
            stdin.flush()
        except OSError as exc:
            raise CheckUnavailable(f"the checking process is gone ({exc})") from None
        ready, _, _ = select.select([stdout], [], [], timeout)
        if not ready:
            raise CheckTimeout(timeout)
        line = stdout.readline()
        if not line:
            raise CheckUnavailable(f"the checking process ended (exit code "
                                   f"{self.proc.poll()})")
        return dict(json.loads(line))


class ValidationPool:
    """Up to `size` checking processes, started on first use and reused."""

    def __init__(self, size: int, env: dict[str, str], nice: int = 0) -> None:
        self.size, self.env, self.nice = size, env, nice
        self._idle: queue.SimpleQueue[_Worker | None] = queue.SimpleQueue()
        for _ in range(size):
            self._idle.put(None)  # a slot whose process is started when first used
        self._all: set[_Worker] = set()
        self._lock = threading.Lock()

    def warm(self) -> None:
        """Start the processes of the slots that have none, in the background (a process
        takes seconds to load the engine; the first scene then need not wait for that)."""
        def start() -> None:
            for _ in range(self.size):
                worker = self._idle.get()
                if worker is None or not worker.alive():
                    self._drop(worker)
                    try:
                        worker = self._start()
                    except OSError as exc:
                        log.warning("scene-checking process not started: %s", exc)
                        worker = None
                self._idle.put(worker)
        threading.Thread(target=start, name="polydda-validation-warm", daemon=True).start()

    def check(self, scene_text: str, timeout: float, preview: bool = False) -> Verdict:
        """Check a scene (blocking: call from a thread); CheckTimeout, CheckUnavailable.
        With `preview`, the answer also holds the builder's preview of its blocks."""
        worker = self._idle.get()
        start = time.monotonic()
        try:
            if worker is None or not worker.alive():
                worker = self._start()
            answer = worker.ask(scene_text, timeout, preview)
        except (CheckTimeout, CheckUnavailable, OSError) as exc:
            if worker is not None:
                self._drop(worker)
            self._idle.put(None)
            if isinstance(exc, CheckTimeout):
                raise
            raise CheckUnavailable(str(exc)) from None
        except BaseException:
            self._drop(worker)
            self._idle.put(None)
            raise
        self._idle.put(worker)
        seconds = time.monotonic() - start
        if "error" in answer:
            raise CheckUnavailable(str(answer["error"]))
        return Verdict(list(answer.get("problems") or []), seconds, answer.get("preview"))

    def _start(self) -> _Worker:
        worker = _Worker(self.env, self.nice)
        with self._lock:
            self._all.add(worker)
        return worker

    def _drop(self, worker: _Worker | None) -> None:
        if worker is None:
            return
        worker.kill()
        with self._lock:
            self._all.discard(worker)

    def close(self) -> None:
        """Kill every checking process (idle ones and any still checking)."""
        with self._lock:
            workers, self._all = list(self._all), set()
        for w in workers:
            w.kill()


_pools: dict[tuple[int, int], ValidationPool] = {}
_pools_lock = threading.Lock()


def shared_pool(size: int, env: dict[str, str], nice: int) -> ValidationPool:
    """The process-wide pool of `size` workers (apps of one process share it: the
    workers are stateless); killed when the process exits."""
    with _pools_lock:
        pool = _pools.get((size, nice))
        if pool is None:
            pool = _pools[(size, nice)] = ValidationPool(size, env, nice)
            pool.warm()
        return pool


@atexit.register
def _close_pools() -> None:
    for pool in list(_pools.values()):
        pool.close()


class ValidationBudget:
    """Seconds of scene checking per client: a bucket of `seconds` refilled at `seconds`
    per minute; a check may start while the client's bucket is not empty and its time
    is taken from it afterwards."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._left: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def _now_left(self, client: str, now: float) -> float:
        left, last = self._left.get(client, (self.seconds, now))
        return min(self.seconds, left + (now - last) * self.seconds / 60.0)

    def wait_for(self, client: str) -> float:
        """0 if the client may start a check now, else the seconds until it may."""
        now = time.monotonic()
        with self._lock:
            left = self._now_left(client, now)
            return 0.0 if left > 0 else (-left + 1e-3) * 60.0 / self.seconds

    def charge(self, client: str, seconds: float) -> None:
        now = time.monotonic()
        with self._lock:
            self._left[client] = (self._now_left(client, now) - seconds, now)
            if len(self._left) > 100_000:  # forget clients whose buckets are full again
                self._left = {k: v for k, v in self._left.items()
                              if self._now_left(k, now) < self.seconds}


# --------------------------------------------------------------------------- the worker


def _answer(scene_text: str, preview: bool = False) -> dict[str, Any]:
    from schemas.convert import build_model
    from schemas.errors import SceneError
    from schemas.scene import Scene

    try:
        if preview:
            from service.api.preview import preview_document

            return {"ok": True, "preview": preview_document(scene_text)}
        build_model(Scene.model_validate(json.loads(scene_text)))
    except SceneError as exc:
        return {"problems": exc.problems}
    except RecursionError:
        return {"problems": [{"loc": "", "msg": "the scene is nested too deeply"}]}
    except Exception as exc:  # the scene passed the API's checks: say what broke
        log.exception("scene check failed")
        return {"error": f"{type(exc).__name__}: {exc}"}
    return {"ok": True}


def worker_main(out: IO[bytes], inp: IO[bytes]) -> None:
    """Answer checks until `inp` ends."""
    import schemas.convert  # noqa: F401  (loaded before the first scene arrives)

    for line in inp:
        try:
            request = json.loads(line)
            text = request["scene"]
        except (ValueError, KeyError, TypeError):
            answer: dict[str, Any] = {"error": "malformed request"}
        else:
            answer = _answer(text, bool(request.get("preview")))
        out.write(json.dumps(answer).encode() + b"\n")
        out.flush()


if __name__ == "__main__":
    if len(sys.argv) > 1 and int(sys.argv[1]):
        os.nice(int(sys.argv[1]))
    # the answers' channel is the real stdout; anything the engine prints goes to stderr
    channel = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    worker_main(channel, sys.stdin.buffer)
