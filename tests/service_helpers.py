"""Helpers of the service tests: small scenes, a real uvicorn server, polling with deadlines."""

from __future__ import annotations

import copy
import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

from schemas.convert import BOX_FACES, box_vertices

ROOT = Path(__file__).resolve().parents[1]
FINAL = ("successful", "failed", "dismissed")

with warnings.catch_warnings():  # starlette warns when it finds httpx instead of httpx2
    warnings.filterwarnings("ignore", message="Using `httpx` with", category=DeprecationWarning)
    from starlette.testclient import TestClient  # noqa: F401  (re-exported)


def box(name: str, lo: list[float], hi: list[float], **kw: Any) -> dict[str, Any]:
    """An explicit box block as scene JSON."""
    return {"name": name, "vertices": box_vertices(lo, hi).tolist(),
            "faces": copy.deepcopy(BOX_FACES), **kw}


def cube_scene(duration: float = 0.05, record_interval: int = 5, **analysis: Any) -> dict:
    """A 1 m cube resting on a fixed slab: about 5 ms of compute per step."""
    return {"name": "cube", "blocks": [box("cube", [0, 0, 0], [1, 1, 1]),
                                       box("base", [-1, -1, -1], [2, 2, 0], fixed=True)],
            "analysis": {"duration": duration, "time_step": 0.001,
                         "record_interval": record_interval, **analysis}}


def wedge_scene(duration: float) -> dict:
    """examples/wedge.json with a shorter duration."""
    scene = json.loads((ROOT / "examples" / "wedge.json").read_text())
    scene["analysis"]["duration"] = duration
    return scene


def wait_until(check: Callable[[], Any], timeout: float, what: str, every: float = 0.1) -> Any:
    """Call `check` until it returns something truthy; AssertionError after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(every)


def wait_final(client: Any, job_url: str, timeout: float = 60.0) -> dict[str, Any]:
    """Poll a job until it is successful, failed or dismissed; its status document."""
    def done() -> dict[str, Any] | None:
        doc = client.get(job_url).json()
        return doc if doc["status"] in FINAL else None
    return wait_until(done, timeout, f"{job_url} to end", every=0.1)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def pid_alive(pid: int) -> bool:
    """True while `pid` runs (a zombie counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def job_row(data_dir: Path, job_id: str) -> dict[str, Any]:
    """The job table row of a job, read directly (worker pid, attempts)."""
    db = sqlite3.connect(data_dir / "jobs.sqlite")
    try:
        db.row_factory = sqlite3.Row
        row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return dict(row) if row else {}
    finally:
        db.close()


class Server:
    """`service.app.serve` in a subprocess on a free loopback port (what `polydda serve` runs)."""

    def __init__(self, data_dir: Path, **env: str) -> None:
        self.data_dir = data_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "POLYDDA_DATA_DIR": str(data_dir), **env}
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = data_dir.parent / f"server-{self.port}.log"

    def start(self, timeout: float = 30.0) -> Server:
        code = f"from service.app import serve; serve('127.0.0.1', {self.port})"
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-c", code], env=self.env, cwd=ROOT,
                                         stdout=log, stderr=subprocess.STDOUT)

        def up() -> bool:
            assert self.proc is not None and self.proc.poll() is None, self.log.read_text()
            try:
                return httpx.get(self.url + "/health", timeout=1).status_code == 200
            except httpx.TransportError:
                return False
        wait_until(up, timeout, "the server to start", every=0.1)
        return self

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs (a crash)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)

    def __enter__(self) -> Server:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
