"""REST service as deployed: `polydda serve` (the docker image's command) on loopback."""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from engine.results.reader import open_result
from service.cli import client as svc_client
from service.jobs.worker import build_parser as worker_parser
from service.settings import Settings
from tests.service_helpers import (
    ROOT,
    Server,
    cube_scene,
    job_row,
    pid_alive,
    polydda,
    process_env,
    process_threads,
    serve_command,
    wait_final,
    wait_until,
    wedge_scene,
)


def test_wedge_over_http_with_events_and_download(tmp_path: Path) -> None:
    scene = tmp_path / "wedge.json"
    scene.write_text(json.dumps(wedge_scene(0.3)))
    cli_h5 = tmp_path / "cli.h5"
    # the same scene through `polydda run`, meanwhile
    cli = subprocess.Popen(polydda("run", str(scene), "--out", str(cli_h5), "--quiet"),
                           cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    seen: list[dict] = []
    with Server(tmp_path / "data") as srv:
        doc = svc_client.submit(srv.url, scene, wait=True, on_status=seen.append)
        assert doc["status"] == "successful", doc
        assert seen[0]["status"] == "accepted" and seen[-1]["status"] == "successful"
        running = [d["progress"] for d in seen if d["status"] == "running"]
        assert running == sorted(running)  # progress only grows
        job_url = f"{srv.url}/jobs/{doc['jobID']}"
        with httpx.Client(timeout=30) as c:
            res = c.get(job_url + "/results").json()
            assert res["summary"]["simulated_time"] == pytest.approx(0.3)
            # the wedge slides out of the slope (J1/J2 intersection plunges towards -y)
            wedge = next(b for b in res["summary"]["blocks"] if b["name"] == "B2")
            assert wedge["displacement"][1] < 0 and wedge["displacement"][2] < 0
            out = tmp_path / "wedge.h5"
            with c.stream("GET", job_url + "/results/result.h5") as r:
                assert r.status_code == 200 and r.headers["accept-ranges"] == "bytes"
                with open(out, "wb") as f:
                    for chunk in r.iter_bytes():
                        f.write(chunk)
            whole = out.read_bytes()
            assert int(r.headers["content-length"]) == len(whole)
            for ask, lo, hi in [("bytes=100-1123", 100, 1123),
                                ("bytes=-500", len(whole) - 500, len(whole) - 1),
                                (f"bytes={len(whole) - 10}-", len(whole) - 10, len(whole) - 1)]:
                part = c.get(job_url + "/results/result.h5", headers={"Range": ask})
                assert part.status_code == 206, (ask, part.status_code)
                assert part.headers["content-range"] == f"bytes {lo}-{hi}/{len(whole)}", ask
                assert part.content == whole[lo:hi + 1], ask
    with open_result(out) as r5:
        assert r5.status == "completed" and r5.n_steps > 1
        assert r5.block_names == ["B1", "B2"]
        assert json.loads(r5.scene_json)["analysis"]["duration"] == 0.3
        http_run = _final_state(r5)
    cli_log = cli.communicate(timeout=120)[0].decode()
    assert cli.returncode == 0, cli_log
    with open_result(cli_h5) as r5:
        cli_run = _final_state(r5)
    # the engine is deterministic: the service computes what the command line computes
    assert http_run["steps"].tolist() == cli_run["steps"].tolist()
    for key in ("times", "centroids", "rotations", "vertices"):
        np.testing.assert_allclose(http_run[key], cli_run[key], rtol=0, atol=1e-9,
                                   err_msg=key)
    moved = np.abs(http_run["centroids"][1] - http_run["initial"][1]).max()
    assert moved > 1e-6  # far more than the tolerance: the comparison is not trivial


def _final_state(r: object) -> dict[str, np.ndarray]:
    """Recorded steps and times, and the blocks at the last step: centroids, rotations,
    vertices (and the initial centroids)."""
    from engine.results.reader import Result

    assert isinstance(r, Result)
    return {"steps": r.steps, "times": r.times, "centroids": r.centroids(-1),
            "initial": r.centroids(0),
            "rotations": np.array([r.block_history(b)["rotation"][-1]
                                   for b in range(r.n_blocks)]),
            "vertices": r.all_vertices(-1)}


def test_cancel_over_http_stops_the_process(tmp_path: Path) -> None:
    with Server(tmp_path / "data", POLYDDA_CANCEL_GRACE="1") as srv, \
            httpx.Client(base_url=srv.url, timeout=30) as c:
        r = c.post("/jobs", json=wedge_scene(60.0))
        assert r.status_code == 201
        url = r.headers["Location"]
        wait_until(lambda: (c.get(url).json()["step"] or 0) >= 10, 60, "the run to go")
        pid = job_row(srv.data_dir, url.rsplit("/", 1)[1])["worker_pid"]
        # the job process started with one OMP/BLAS/numba thread (POLYDDA_WORKER_THREADS)
        # and runs single-threaded, whatever the API process had loaded
        env = process_env(pid)
        keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")
        assert {k: env.get(k) for k in keys} == dict.fromkeys(keys, "1")
        assert process_threads(pid) == 1
        t0 = time.monotonic()
        doc = c.delete(url).json()
        wait_until(lambda: not pid_alive(pid), 5, "the job process to stop")
        gone = time.monotonic() - t0
        print(f"\ncancel over HTTP: job process gone {gone:.2f} s after DELETE")
        assert doc["status"] == "dismissed" and gone < 5
        res = c.get(url + "/results").json()
        assert res["partial"] is True and res["summary"]["steps"] >= 10
        h5 = tmp_path / "partial.h5"
        h5.write_bytes(c.get(url + "/results/result.h5").content)
        with open_result(h5) as r5:
            assert r5.n_steps >= 1


def test_killed_server_requeues_its_running_job(tmp_path: Path) -> None:
    data = tmp_path / "data"
    srv = Server(data).start()
    try:
        # long enough (1000 steps) that the orphaned job process cannot finish the run in
        # the fraction of a second it takes to notice that the server is gone
        r = httpx.post(srv.url + "/jobs", json=cube_scene(duration=1.0), timeout=30)
        url = srv.url + r.headers["Location"]
        wait_until(lambda: (httpx.get(url).json()["step"] or 0) >= 5, 60, "the job to run")
        job_id = url.rsplit("/", 1)[1]
        old_pid = job_row(data, job_id)["worker_pid"]
        srv.kill()
        assert job_row(data, job_id)["status"] == "running"  # as the crash left it
        # the orphaned job process notices that its parent is gone and stops by itself
        wait_until(lambda: not pid_alive(old_pid), 10, "the orphaned job process to stop")
    finally:
        srv.kill()
    with Server(data) as again:
        url = f"{again.url}/jobs/{job_id}"
        doc = wait_final(httpx, url, 60)
        assert doc["status"] == "successful", doc
        assert job_row(data, job_id)["attempts"] == 2
        res = httpx.get(url + "/results").json()
        assert res["summary"]["simulated_time"] == pytest.approx(1.0)


@pytest.mark.parametrize("n_jobs", [
    20, pytest.param(50, marks=[pytest.mark.slow, pytest.mark.ci])])
def test_many_jobs_finish_and_status_stays_fast(tmp_path: Path, n_jobs: int) -> None:
    """Jobs submitted at once all finish; status answers stay under 100 ms (p95)."""
    with Server(tmp_path / "data", POLYDDA_CLIENT_QUOTA="100") as srv, \
            httpx.Client(base_url=srv.url, timeout=30) as c:
        def submit(k: int, out: list[str]) -> None:
            r = httpx.post(srv.url + "/jobs", json=cube_scene(duration=0.02 + 0.001 * k),
                           timeout=60)
            assert r.status_code == 201, r.text
            out.append(r.headers["Location"])
        urls: list[str] = []
        threads = [threading.Thread(target=submit, args=(k, urls)) for k in range(n_jobs)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert len(urls) == n_jobs
        latencies = []
        deadline = time.monotonic() + 60 + 6 * n_jobs
        while time.monotonic() < deadline:
            states = []
            for u in urls:
                t0 = time.perf_counter()
                r = c.get(u)
                latencies.append(time.perf_counter() - t0)
                states.append(r.json()["status"])
            if all(s == "successful" for s in states):
                break
            assert "failed" not in states and "dismissed" not in states
            time.sleep(0.2)
        assert all(c.get(u).json()["status"] == "successful" for u in urls)
        p95 = statistics.quantiles(latencies, n=20)[-1]
        print(f"\nload: {n_jobs} jobs, {len(latencies)} status requests while they ran, "
              f"p50 {1e3 * statistics.median(latencies):.1f} ms, p95 {1e3 * p95:.1f} ms, "
              f"max {1e3 * max(latencies):.1f} ms")
        assert p95 < 0.1


def test_docker_files_run_the_commands_these_tests_run() -> None:
    """The image's API command is `serve_command` (all server tests run it) with the
    container's address; compose's worker command is what test_service_rq runs."""
    yaml = pytest.importorskip("yaml")
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    lines = [ln.strip() for ln in dockerfile.splitlines()]
    cmd = json.loads(next(ln for ln in lines if ln.startswith("CMD ["))[4:])
    assert cmd == ["polydda", *serve_command("0.0.0.0", 8000)[1:]]
    port = cmd[cmd.index("--port") + 1]
    assert f"EXPOSE {port}" in lines
    assert f"http://127.0.0.1:{port}/health" in dockerfile
    assert "POLYDDA_DATA_DIR=/data" in dockerfile and 'VOLUME ["/data"]' in lines

    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    services = compose["services"]
    assert services["api"]["command"] == cmd
    assert services["api"]["ports"] == [f"{port}:{port}"]
    worker = services["worker"]["command"]
    assert worker[:2] == ["polydda", "worker"]
    worker_parser().parse_args(worker[2:])  # options `polydda worker` accepts
    settings = set(Settings.model_fields)
    for name in ("api", "worker"):
        variables = services[name]["environment"]
        ours = {k.removeprefix("POLYDDA_").lower() for k in variables if k.startswith("POLYDDA_")}
        assert ours <= settings, variables
        assert set(variables) - {f"POLYDDA_{k.upper()}" for k in ours} <= {
            "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION"}, variables
        assert variables["POLYDDA_BACKEND"] == "rq"
        assert variables["POLYDDA_REDIS_URL"].startswith("redis://redis:")
        assert variables["POLYDDA_DATA_DIR"] == "/data"
    # the job table on the API's volume; workers keep a job's files until it is uploaded
    assert services["api"]["volumes"] == ["api:/data"]
    assert services["worker"]["volumes"] == ["/data"]


def test_a_second_server_on_the_same_data_directory_is_refused(tmp_path: Path) -> None:
    """The second `polydda serve` on a data directory exits at once with one line; the
    first's running job goes on undisturbed (it used to be killed as stale and run again)."""
    data = tmp_path / "data"
    with Server(data) as first, httpx.Client(base_url=first.url, timeout=30) as c:
        url = c.post("/jobs", json=cube_scene(duration=60)).headers["Location"]
        wait_until(lambda: (c.get(url).json()["step"] or 0) >= 5, 60, "the job to run")
        job_id = url.rsplit("/", 1)[1]
        pid = job_row(data, job_id)["worker_pid"]
        second = Server(data)
        done = subprocess.run(serve_command("127.0.0.1", second.port), env=second.env,
                              cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert done.returncode == 1, done.stderr
        lines = done.stderr.strip().splitlines()
        assert lines == [f"polydda serve: the data directory {data} is in use by another "
                         f"PolyDDA server (pid {first.proc.pid} on {os.uname().nodename}); "
                         "stop it first, or give this one its own POLYDDA_DATA_DIR"], lines
        step = c.get(url).json()["step"]
        wait_until(lambda: c.get(url).json()["step"] > step, 10, "the job to go on")
        doc = c.get(url).json()
        assert doc["status"] == "running" and doc["attempts"] == 1, doc
        assert pid_alive(pid) and job_row(data, job_id)["worker_pid"] == pid
        assert c.delete(url).json()["status"] == "dismissed"
    with Server(data) as again:  # the lock goes with its server
        assert httpx.get(f"{again.url}/jobs/{job_id}").json()["status"] == "dismissed"


def test_an_idle_connection_outlives_retry_after(tmp_path: Path) -> None:
    """A client that waits the 429's Retry-After reuses its connection: the server keeps
    idle connections 75 s (uvicorn's default 5 s equalled Retry-After: 5, and the reuse
    raced the close)."""
    import http.client

    with Server(tmp_path / "data", POLYDDA_CLIENT_QUOTA="1") as srv:
        conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=30)
        body = json.dumps(cube_scene(duration=60))
        headers = {"Content-Type": "application/json"}
        conn.request("POST", "/jobs", body, headers)
        first = conn.getresponse()
        url = first.getheader("Location")
        first.read()
        conn.request("POST", "/jobs", body, headers)
        refused = conn.getresponse()
        refused.read()
        assert refused.status == 429
        wait = float(refused.getheader("Retry-After"))
        sock = conn.sock
        time.sleep(wait + 0.5)
        conn.request("DELETE", url)  # the same connection, after the advised wait
        r = conn.getresponse()
        r.read()
        assert r.status in (200, 202) and conn.sock is sock
        conn.close()


def test_a_client_that_disconnects_mid_body_is_no_internal_error(tmp_path: Path) -> None:
    import socket

    with Server(tmp_path / "data") as srv:
        with socket.create_connection(("127.0.0.1", srv.port)) as s:
            s.sendall(b"POST /jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                      b"Content-Length: 100000\r\n\r\n" + b'{"blocks": [' + b" " * 1000)
            time.sleep(0.3)
        time.sleep(0.5)
        assert httpx.get(srv.url + "/health", timeout=10).status_code == 200
        log = srv.log.read_text(errors="replace")
        assert "client disconnected during POST /jobs" in log
        assert "Traceback" not in log and "internal error" not in log, log[-3000:]
