"""Helpers of the service tests: small scenes, a real uvicorn server, polling with deadlines."""

from __future__ import annotations

import copy
import http.client
import json
import os
import select
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterable
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


def polydda(*args: str) -> list[str]:
    """The installed `polydda` command with `args`: what docker/Dockerfile and compose run."""
    exe = Path(sys.executable).with_name("polydda")
    found = str(exe) if exe.is_file() else shutil.which("polydda")
    if found is None:
        raise RuntimeError("the `polydda` command is not installed (pip install -e .)")
    return [found, *args]


def serve_command(host: str, port: int) -> list[str]:
    """`polydda serve` as the image runs it (docker/Dockerfile CMD), on `host`:`port`."""
    return polydda("serve", "--host", host, "--port", str(port))


def worker_command(*options: str) -> list[str]:
    """`polydda worker` as compose runs it, plus `options`."""
    return polydda("worker", *options)


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


def process_env(pid: int) -> dict[str, str]:
    """The environment process `pid` was started (exec'd) with."""
    raw = Path(f"/proc/{pid}/environ").read_bytes()
    return dict(item.decode().split("=", 1) for item in raw.split(b"\0") if b"=" in item)


def process_threads(pid: int) -> int:
    """Threads of process `pid` now."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(status.split("Threads:", 1)[1].split()[0])


def post_streamed(url: str, path: str, chunks: Iterable[bytes], length: int | None,
                  wait_first: float = 0.0, timeout: float = 30.0,
                  ) -> tuple[int, dict[str, str], bytes, int]:
    """POST a JSON body piece by piece (chunked when `length` is None), stopping as soon as
    the server answers; `(status, headers, body, bytes of the body sent)`.

    For bodies too large to build in memory: only what is sent is made. `wait_first` s are
    given to the server to answer on the headers alone, before the first piece.
    """
    host, port = url.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=timeout)
    try:
        conn.putrequest("POST", path)
        conn.putheader("Content-Type", "application/json")
        if length is None:
            conn.putheader("Transfer-Encoding", "chunked")
        else:
            conn.putheader("Content-Length", str(length))
        conn.endheaders()
        assert conn.sock is not None
        sent = 0
        for k, chunk in enumerate(chunks):
            if select.select([conn.sock], [], [], wait_first if k == 0 else 0)[0]:
                break  # the server answered (or closed): stop sending
            data = chunk if length is not None else b"%x\r\n%s\r\n" % (len(chunk), chunk)
            try:
                conn.sock.sendall(data)
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += len(chunk)
        else:
            if length is None:
                conn.sock.sendall(b"0\r\n\r\n")
        resp = conn.getresponse()
        return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read(), sent
    finally:
        conn.close()


def job_row(data_dir: Path, job_id: str) -> dict[str, Any]:
    """The job table row of a job, read directly (worker pid, attempts)."""
    db = sqlite3.connect(data_dir / "jobs.sqlite")
    try:
        db.row_factory = sqlite3.Row
        row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return dict(row) if row else {}
    finally:
        db.close()


class RedisServer:
    """A throw-away redis-server on a free loopback port that can crash and come back.

    Nothing is persisted unless `persist` (append-only file in `workdir`): a restart after
    `kill` then comes back empty, like a crashed Redis without a volume.
    """

    def __init__(self, workdir: Path, persist: bool = False) -> None:
        self.workdir, self.persist = workdir, persist
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 10.0) -> RedisServer:
        exe = shutil.which("redis-server")
        if exe is None:
            raise RuntimeError("redis-server is not installed")
        self.proc = subprocess.Popen(
            [exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
             "--appendonly", "yes" if self.persist else "no", "--dir", str(self.workdir)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        from redis import Redis

        with Redis(port=self.port, socket_connect_timeout=1) as conn:
            def up() -> bool:
                try:
                    return bool(conn.ping())
                except Exception:
                    return False
            wait_until(up, timeout, "redis-server to answer")
        return self

    def kill(self) -> None:
        """SIGKILL: a crash (nothing saved on the way out)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def pause(self) -> None:
        """SIGSTOP: Redis hangs (connections stay open, nothing answers)."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.resume()
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()

    def __enter__(self) -> RedisServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Server:
    """`polydda serve` (the image's command) in a subprocess on a free loopback port."""

    def __init__(self, data_dir: Path, log_dir: Path | None = None, **env: str) -> None:
        self.data_dir = data_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "POLYDDA_DATA_DIR": str(data_dir), **env}
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = (log_dir or data_dir.parent) / f"server-{self.port}.log"

    def start(self, timeout: float = 30.0) -> Server:
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(serve_command("127.0.0.1", self.port), env=self.env,
                                         cwd=self.data_dir.parent, stdout=log,
                                         stderr=subprocess.STDOUT)

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


def synthetic_job(data_dir: Path, n_blocks: int = 1000, n_steps: int = 100,
                  contacts: bool = True, client: str = "ip:testclient") -> tuple[str, Path]:
    """A successful simulation job of `n_blocks` moving cubes and `n_steps` recorded steps
    (made-up frames of benchmarks.bench_results, ~6 contacts per block unless not
    `contacts`, written by the engine's ResultWriter), put straight into the job table of
    `data_dir`, owned by `client` (without keys a client is its address: `ip:testclient`
    for a TestClient, `ip:127.0.0.1` for a real server); `(job id, its result.h5)`."""
    from benchmarks.bench_results import FrameSource, grid_model
    from engine.results.writer import ResultWriter
    from service.jobs.store import JobStore
    from service.settings import Settings

    settings = Settings(data_dir=data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    store = JobStore(settings.db_path)
    job, _ = store.submit(process="simulation", scene='{"name": "synthetic"}',
                          client=client, quota=10**6)
    path = settings.job_dir(job.id) / "result.h5"
    path.parent.mkdir(parents=True)
    model = grid_model(n_blocks)
    src = FrameSource(model)
    w = ResultWriter(path, record_contacts=contacts)
    w.begin(model, '{"name": "synthetic"}')
    for k in range(n_steps):
        w.record(src.frame(k, 0.01 * k))
    w.end("completed", "", {"steps": n_steps})
    now = time.time()
    store.update(job.id, status="successful", started=now, finished=now, progress=100.0,
                 message=f"synthetic: {n_blocks} blocks, {n_steps} steps")
    return job.id, path


def make_client(data_dir: Path, peer: tuple[str, int] = ("testclient", 50000),
                **settings: Any) -> Any:
    """An in-process client of a fresh app on `data_dir` (two workers, a short cancel
    grace), connecting from `peer`; `settings` override."""
    from service.api.app import create_app
    from service.settings import Settings

    kw: dict[str, Any] = {"data_dir": data_dir, "max_workers": 2, "cancel_grace": 0.5}
    return TestClient(create_app(Settings(**(kw | settings)), listen="127.0.0.1"), client=peer)
