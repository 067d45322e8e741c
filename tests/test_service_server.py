"""REST service as deployed: a real uvicorn process (what `polydda serve` runs) on loopback."""

from __future__ import annotations

import json
import statistics
import threading
import time
from pathlib import Path

import httpx
import pytest

from engine.results import open_result
from service import client as svc_client
from tests.service_helpers import (
    Server,
    cube_scene,
    job_row,
    pid_alive,
    wait_final,
    wait_until,
    wedge_scene,
)


def test_wedge_over_http_with_events_and_download(tmp_path: Path) -> None:
    scene = tmp_path / "wedge.json"
    scene.write_text(json.dumps(wedge_scene(0.3)))
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
                assert r.status_code == 200
                with open(out, "wb") as f:
                    for chunk in r.iter_bytes():
                        f.write(chunk)
        with open_result(out) as r5:
            assert r5.status == "completed" and r5.n_steps > 1
            assert r5.block_names == ["B1", "B2"]
            assert json.loads(r5.scene_json)["analysis"]["duration"] == 0.3


def test_cancel_over_http_stops_the_process(tmp_path: Path) -> None:
    with Server(tmp_path / "data", POLYDDA_CANCEL_GRACE="1") as srv, \
            httpx.Client(base_url=srv.url, timeout=30) as c:
        r = c.post("/jobs", json=wedge_scene(60.0))
        assert r.status_code == 201
        url = r.headers["Location"]
        wait_until(lambda: (c.get(url).json()["step"] or 0) >= 10, 60, "the run to go")
        pid = job_row(srv.data_dir, url.rsplit("/", 1)[1])["worker_pid"]
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
        r = httpx.post(srv.url + "/jobs", json=cube_scene(duration=0.4), timeout=30)
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
        assert res["summary"]["simulated_time"] == pytest.approx(0.4)


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
