"""REST service in-process (TestClient, embedded backend): jobs, results, errors, limits.

The bad-input catalogue (BAD) goes to a real `polydda serve` instead: its bodies include
one far too large to build in memory, streamed over a socket.
"""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import httpx
import pytest

from engine.results.reader import open_result
from service.settings import Settings
from tests import service_helpers as helpers
from tests.service_helpers import (
    Server,
    TestClient,
    box,
    cube_scene,
    job_row,
    pid_alive,
    post_streamed,
    process_env,
    wait_final,
    wait_until,
    wedge_scene,
)

PROBLEM = "application/problem+json"


def make_client(tmp_path: Path, **settings: Any) -> TestClient:
    return helpers.make_client(tmp_path / "data", **settings)


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with make_client(tmp_path, max_vertices=500, max_body_bytes=64 * 1024) as c:
        yield c


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str]]:
    """One client and the URL of a successful simulation of the cube scene."""
    with make_client(tmp_path_factory.mktemp("finished")) as c:
        r = c.post("/processes/simulation/execution", json=cube_scene())
        assert r.status_code == 201, r.text
        wait_final(c, r.headers["Location"])
        yield c, r.headers["Location"]


def test_processes_are_listed_with_their_input_schema(client: TestClient) -> None:
    r = client.get("/processes")
    assert r.status_code == 200
    assert {p["id"] for p in r.json()["processes"]} == {
        "simulation", "factor-of-safety", "critical-seismic-coefficient", "limit-equilibrium",
        "block-cutting", "kinematics", "sweep"}
    doc = client.get("/processes/simulation").json()
    schema = doc["inputs"]["scene"]["schema"]
    assert schema["title"] == "PolyDDA scene" and "blocks" in schema["properties"]
    assert any(lk["href"].endswith("/processes/simulation/execution") for lk in doc["links"])
    r = client.get("/processes/nope")
    assert r.status_code == 404 and r.headers["content-type"] == PROBLEM


def test_simulation_job_runs_to_success_with_results(finished: tuple[TestClient, str],
                                                     tmp_path: Path) -> None:
    c, url = finished
    status = c.get(url).json()
    assert status["status"] == "successful", status
    assert status["progress"] == 100 and status["step"] == 50
    assert status["simulated_time"] == pytest.approx(0.05)
    assert status["created"] <= status["started"] <= status["finished"]
    res = c.get(url + "/results").json()
    assert res["summary"]["steps"] == 50 and res["partial"] is False
    assert [b["name"] for b in res["summary"]["blocks"]] == ["cube", "base"]
    # the cube settles: it moves by far less than a millimetre
    assert abs(res["summary"]["blocks"][0]["displacement"][2]) < 1e-3
    hrefs = {lk["title"]: lk["href"] for lk in res["links"]}
    h5_url = hrefs["result.h5"]

    whole = c.get(h5_url)
    assert whole.status_code == 200 and whole.headers["accept-ranges"] == "bytes"
    part = c.get(h5_url, headers={"Range": "bytes=100-1123"})
    assert part.status_code == 206
    assert part.headers["content-range"] == f"bytes 100-1123/{len(whole.content)}"
    assert part.content == whole.content[100:1124]
    (tmp_path / "r.h5").write_bytes(whole.content)
    with open_result(tmp_path / "r.h5") as r:
        assert r.status == "completed" and r.n_steps == 11  # step 0 and every 5th


def test_contacts_as_csv_and_json(finished: tuple[TestClient, str]) -> None:
    c, url = finished
    doc = c.get(url + "/results/contacts").json()
    assert doc["step"] == 50 and doc["count"] >= 4
    assert {(k["block_i"], k["block_j"]) for k in doc["contacts"]} <= {
        ("cube", "base"), ("base", "cube")}
    closed = [k for k in doc["contacts"] if k["mode"] != "open"]
    assert closed and sum(k["normal_force"] for k in closed) == pytest.approx(
        2600 * 9.81, rel=0.05)  # the slab carries the cube's weight
    r = c.get(url + "/results/contacts", params={"format": "csv", "step": 25})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    lines = r.text.strip().splitlines()
    assert lines[0].startswith("step,time,block_i,block_j,kind,mode,point_i_x")
    assert len(lines) > 1 and all(line.startswith("25,") for line in lines[1:])
    r = c.get(url + "/results/contacts", params={"step": 3})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == "query.step"


def test_plots_are_made_on_demand(finished: tuple[TestClient, str]) -> None:
    c, url = finished
    plots = c.get(url + "/results/plots").json()["plots"]
    assert {p["name"] for p in plots} >= {"energy.png", "snapshot_final.png"}
    r = c.get(plots[0]["href"])
    assert r.status_code == 200 and r.content.startswith(b"\x89PNG")
    assert c.get(url + "/results/plots/nope.png").status_code == 404


def test_events_stream_ends_with_the_final_status(finished: tuple[TestClient, str]) -> None:
    c, url = finished
    r = c.get(url + "/events")
    assert r.headers["content-type"].startswith("text/event-stream")
    data = [json.loads(line[5:]) for line in r.text.splitlines() if line.startswith("data:")]
    assert data[-1]["status"] == "successful"


def test_jobs_list_filters_and_pages(client: TestClient) -> None:
    urls = [client.post("/jobs", params={"process": "block-cutting"},
                        json=cube_scene()).headers["Location"] for _ in range(3)]
    for u in urls:
        assert wait_final(client, u)["status"] == "successful"
    page = client.get("/jobs", params={"limit": 2}).json()
    assert page["numberMatched"] == 3 and page["numberReturned"] == 2
    nxt = next(lk["href"] for lk in page["links"] if lk["rel"] == "next")
    rest = client.get(nxt).json()
    assert len(rest["jobs"]) == 1
    seen = {j["jobID"] for j in page["jobs"] + rest["jobs"]}
    assert seen == {u.rsplit("/", 1)[1] for u in urls}
    assert client.get("/jobs", params={"status": "running"}).json()["numberMatched"] == 0
    assert client.get("/jobs", params={"status": "bogus"}).status_code == 422
    blocks = client.get(urls[0] + "/results").json()["blocks"]
    assert [b["name"] for b in blocks["blocks"]] == ["cube", "base"]
    assert blocks["blocks"][0]["volume"] == pytest.approx(1.0)


def test_block_cutting_of_the_wedge(client: TestClient) -> None:
    r = client.post("/processes/block-cutting/execution",
                    json={"inputs": {"scene": wedge_scene(2.0)}})
    assert r.status_code == 201, r.text
    assert wait_final(client, r.headers["Location"])["status"] == "successful"
    doc = client.get(r.headers["Location"] + "/results").json()["blocks"]
    assert doc["count"] == 2
    assert min(b["volume"] for b in doc["blocks"]) == pytest.approx(29.7708, rel=1e-4)


def _nothing_created(c: TestClient) -> None:
    assert c.get("/jobs").json()["numberMatched"] == 0
    settings = c.app.state.settings  # type: ignore[attr-defined]
    jobs_dir = settings.data_dir / "jobs"
    assert not jobs_dir.exists() or not any(jobs_dir.iterdir())


def _open_cube() -> dict:
    s = cube_scene()
    del s["blocks"][0]["faces"][1]  # no top face
    return s


def _overlap() -> dict:
    s = cube_scene()
    s["blocks"].append(box("other", [0.5, 0.5, 0.5], [1.5, 1.5, 1.5]))
    return s


def _with(path: str, value: Any) -> dict:
    s = cube_scene()
    node: Any = s
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {}) if not k.isdigit() else node[int(k)]
    node[keys[-1]] = value
    return s


def _huge() -> dict:
    s = cube_scene()
    s["blocks"] = [box(f"b{k}", [2 * k, 0, 0], [2 * k + 1, 1, 1]) for k in range(63)]
    return s


def _joint_bomb() -> dict:
    """Half a kilobyte that cuts into about 4.7 million blocks: a 100 m domain and three
    joint sets 0.6 m apart."""
    s = cube_scene()
    del s["blocks"]
    s["domain"] = {"box": {"min": [0, 0, 0], "max": [100, 100, 100]}}
    s["joints"] = [{"dip": dip, "dip_direction": ddir, "point": [0, 0, 0], "spacing": 0.6}
                   for dip, ddir in [(0, 0), (90, 0), (90, 90)]]
    return s


class Streamed(NamedTuple):
    """A body sent piece by piece, never whole in memory (chunked when `length` is None)."""

    chunks: Callable[[], Iterator[bytes]]
    length: int | None


def _explicit_block_of(n: int, chunked: bool, per_chunk: int = 2_000) -> Streamed:
    """A scene whose one explicit block has `n` vertices (10^7: about 380 MB of JSON)."""
    head = b'{"name": "many vertices", "blocks": [{"name": "b", "vertices": ['
    vertex = b"[0.123456789,0.123456789,0.123456789]"
    tail = b'], "faces": [[0, 1, 2]]}], "analysis": {"duration": 0.01, "time_step": 0.001}}'
    full = (vertex + b",") * per_chunk  # one 76 kB piece, sent again and again

    def chunks() -> Iterator[bytes]:
        yield head
        left = n
        while left > per_chunk:
            yield full
            left -= per_chunk
        yield (vertex + b",") * (left - 1) + vertex
        yield tail

    size = len(head) + n * len(vertex) + (n - 1) + len(tail)
    return Streamed(chunks, None if chunked else size)


def test_streamed_bodies_are_what_they_claim() -> None:
    small = _explicit_block_of(3, chunked=False, per_chunk=2)
    text = b"".join(small.chunks())
    assert len(text) == small.length
    assert len(json.loads(text)["blocks"][0]["vertices"]) == 3
    big = _explicit_block_of(10**7, chunked=False)
    assert big.length is not None and big.length > 350e6
    assert sum(map(len, big.chunks())) == big.length


BAD = {
    "malformed JSON": (b'{"blocks": [', "", "not valid JSON"),
    "not an object": (b"[1, 2]", "", "JSON object"),
    "wrong type": (_with("materials", {"rock": {"density": "heavy"}}),
                   "materials.rock.density", "number"),
    "unknown material": (_with("blocks.0.material", "granit"), "material", "unknown material"),
    "non-closed block": (_open_cube(), "blocks[0]", ""),
    "overlapping blocks": (_overlap(), "blocks", "overlap"),
    "negative density": (_with("materials", {"rock": {"density": -2600}}),
                         "materials.rock.density", "positive"),
    "friction angle 95": (_with("joint_materials", {"j": {"friction_angle": 95}}),
                          "joint_materials.j.friction_angle", "95"),
    "huge scene": (_huge(), "blocks", "at most 500 (POLYDDA_MAX_VERTICES)"),
    "too long": (cube_scene(duration=5000, time_step=0.01), "analysis.duration", "at most"),
    "joint sets cutting 4.7 million blocks": (
        _joint_bomb(), "joints", "about 4.71 million blocks; this service accepts at most "
                                 "5,000 (POLYDDA_MAX_BLOCKS)"),
    "10^7 vertices (Content-Length)": (_explicit_block_of(10**7, chunked=False), "", ""),
    "10^7 vertices (chunked)": (_explicit_block_of(10**7, chunked=True), "", ""),
}
BODY_LIMIT = 64 * 1024


@pytest.fixture(scope="module")
def bad_input_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """`polydda serve` with small limits, for the bad-input catalogue."""
    with Server(tmp_path_factory.mktemp("bad") / "data", POLYDDA_MAX_VERTICES="500",
                POLYDDA_MAX_BODY_BYTES=str(BODY_LIMIT)) as srv:
        yield srv


def _peak_rss(pid: int) -> int:
    """Peak resident memory of process `pid` in bytes."""
    status = Path(f"/proc/{pid}/status").read_text()
    return 1024 * int(status.split("VmHWM:", 1)[1].split()[0])


@pytest.mark.parametrize("name", BAD)
def test_bad_input_is_a_clear_problem_and_creates_nothing(bad_input_server: Server,
                                                          name: str) -> None:
    srv = bad_input_server
    body, loc, text = BAD[name]
    assert srv.proc is not None
    rss0 = _peak_rss(srv.proc.pid)
    t0 = time.monotonic()
    if isinstance(body, Streamed):
        status, headers, raw, sent = post_streamed(srv.url, "/jobs", body.chunks(), body.length,
                                                   wait_first=0 if body.length is None else 2)
        doc = json.loads(raw)
    else:
        r = httpx.post(srv.url + "/jobs", timeout=30, headers={"Content-Type": "application/json"},
                       content=body if isinstance(body, bytes) else json.dumps(body).encode())
        status, headers, raw, doc = r.status_code, dict(r.headers), r.content, r.json()
    elapsed = time.monotonic() - t0
    assert elapsed < 3, f"{name}: answered after {elapsed:.1f} s"
    assert headers["content-type"] == PROBLEM
    assert b"Traceback" not in raw
    if isinstance(body, Streamed):  # refused by size, unread: the rest was never sent
        assert status == 413, doc
        assert doc["type"].endswith("/body-too-large") and "65,536 bytes" in doc["detail"]
        # with a Content-Length: answered on the headers; chunked: soon after the limit
        assert sent == 0 if body.length is not None else sent < 16e6, f"{sent:,} bytes sent"
        grew = _peak_rss(srv.proc.pid) - rss0
        print(f"\n{name}: 413 after {elapsed:.2f} s, {sent:,} of {body.length or 'about 380e6'}"
              f" bytes sent, server peak memory +{grew / 1e6:.1f} MB")
        assert grew < 50e6, f"the server's peak memory grew by {grew / 1e6:.0f} MB"
    else:
        assert status == 422, doc
        assert doc["type"].endswith("/invalid-scene") and doc["status"] == 422
        assert any(loc in e["loc"] and text in e["msg"] for e in doc["errors"]), doc["errors"]
    with httpx.Client(base_url=srv.url, timeout=10) as c:  # still answering; nothing made
        assert c.get("/processes").status_code == 200
        assert c.get("/jobs").json()["numberMatched"] == 0
    jobs_dir = srv.data_dir / "jobs"
    assert not jobs_dir.exists() or not any(jobs_dir.iterdir())


def test_body_over_the_size_limit_is_413(client: TestClient) -> None:
    big = json.dumps(cube_scene() | {"description": "x" * 70_000}).encode()
    r = client.post("/jobs", content=big, headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and r.headers["content-type"] == PROBLEM
    assert "65,536 bytes" in r.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: the streamed size counts
        for k in range(0, len(big), 8192):
            yield big[k:k + 8192]
    r = client.post("/jobs", content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413
    _nothing_created(client)


def test_unknown_job_is_404_everywhere(client: TestClient) -> None:
    for method, path in [("GET", ""), ("DELETE", ""), ("GET", "/results"), ("GET", "/events"),
                         ("GET", "/results/result.h5"), ("GET", "/results/contacts")]:
        r = client.request(method, "/jobs/0000-not-a-job" + path)
        assert r.status_code == 404, (method, path)
        assert r.headers["content-type"] == PROBLEM and r.json()["type"].endswith("no-such-job")


def test_idempotency_key_returns_the_same_job(client: TestClient) -> None:
    h = {"Idempotency-Key": "abc-123"}
    scene = cube_scene()
    a = client.post("/jobs", params={"process": "block-cutting"}, json=scene, headers=h)
    b = client.post("/jobs", params={"process": "block-cutting"}, json=scene, headers=h)
    assert a.status_code == b.status_code == 201
    assert a.json()["jobID"] == b.json()["jobID"]
    assert a.headers["Location"] == b.headers["Location"]
    assert b.headers["Idempotent-Replayed"] == "true"
    other = client.post("/jobs", params={"process": "block-cutting"},
                        json=cube_scene(duration=0.1), headers=h)
    assert other.status_code == 422 and other.json()["type"].endswith("idempotency-key-reused")
    assert client.get("/jobs").json()["numberMatched"] == 1


def test_quota_429_and_cancelling_accepted_jobs(tmp_path: Path) -> None:
    with make_client(tmp_path, client_quota=2, max_workers=1) as c:
        urls = [c.post("/jobs", json=cube_scene(duration=60)).headers["Location"]
                for _ in range(2)]
        r = c.post("/jobs", json=cube_scene())
        assert r.status_code == 429 and r.headers["content-type"] == PROBLEM
        assert "Retry-After" in r.headers and "limit is 2" in r.json()["detail"]
        # one worker: the second job waits; dismissing it is immediate
        assert c.get(urls[1]).json()["status"] == "accepted"
        r = c.get(urls[1] + "/results")
        assert r.status_code == 404 and r.json()["type"].endswith("result-not-ready")
        doc = c.delete(urls[1]).json()
        assert doc["status"] == "dismissed" and doc["message"] == "dismissed before it started"
        assert c.delete(urls[0]).json()["status"] == "dismissed"
        assert c.post("/jobs", json=cube_scene()).status_code == 201


def test_cancel_stops_the_process_and_keeps_partial_results(tmp_path: Path) -> None:
    with make_client(tmp_path, worker_threads=2) as c:
        url = c.post("/jobs", json=cube_scene(duration=60, record_interval=1)).headers[
            "Location"]
        wait_until(lambda: (c.get(url).json()["step"] or 0) > 20, 60, "steps")
        pid = job_row(tmp_path / "data", url.rsplit("/", 1)[1])["worker_pid"]
        assert pid_alive(pid)
        # started with the configured thread count (1 unless configured: test_service_server)
        assert process_env(pid)["OMP_NUM_THREADS"] == "2"
        t0 = time.monotonic()
        r = c.delete(url)
        assert r.status_code == 200 and r.json()["status"] == "dismissed", r.text
        wait_until(lambda: not pid_alive(pid), 5, "the job process to end")
        elapsed = time.monotonic() - t0
        print(f"cancel: process gone {elapsed:.2f} s after DELETE")
        assert elapsed < 5
        res = c.get(url + "/results").json()
        assert res["partial"] is True and res["summary"]["status"] == "cancelled"
        h5 = c.get(url + "/results/result.h5")
        (tmp_path / "p.h5").write_bytes(h5.content)
        with open_result(tmp_path / "p.h5") as r5:
            assert r5.status == "cancelled" and r5.n_steps > 20
        # DELETE of a finished job removes it and its files
        assert c.delete(url).json()["status"] == "dismissed"
        assert c.get(url).status_code == 404


def test_model_failure_says_so(client: TestClient) -> None:
    scene = cube_scene(min_time_step=0.0005)
    scene["blocks"][0]["velocity"] = {"translation": [0, 0, 1000]}
    url = client.post("/jobs", json=scene).headers["Location"]
    doc = wait_final(client, url)
    assert doc["status"] == "failed" and doc["error_kind"] == "model"
    assert doc["message"].startswith("model problem:") and "did not converge" in doc["message"]


def test_a_killed_job_process_is_a_system_error(tmp_path: Path) -> None:
    """With one run allowed (POLYDDA_MAX_ATTEMPTS=1) a killed job process fails the job at
    once, saying why; with more it runs again (test_service_hostile.py)."""
    with make_client(tmp_path, max_attempts=1) as c:
        url = c.post("/jobs", json=cube_scene(duration=60)).headers["Location"]
        wait_until(lambda: c.get(url).json()["status"] == "running"
                   and job_row(tmp_path / "data", url.rsplit("/", 1)[1])["worker_pid"], 30,
                   "the job to start")
        os.kill(job_row(tmp_path / "data", url.rsplit("/", 1)[1])["worker_pid"], signal.SIGKILL)
        doc = wait_final(c, url, 10)
        assert doc["status"] == "failed" and doc["error_kind"] == "system"
        assert "SIGKILL" in doc["message"]


def test_jobs_left_running_are_requeued_on_start(tmp_path: Path) -> None:
    with make_client(tmp_path, max_workers=1) as c:
        url = c.post("/jobs", params={"process": "block-cutting"}, json=cube_scene()).headers[
            "Location"]
        wait_final(c, url)
    job_id = url.rsplit("/", 1)[1]
    from service.jobs.store import JobStore

    store = JobStore(tmp_path / "data" / "jobs.sqlite")  # pretend the API died mid-job
    store.update(job_id, status="running", finished=None, attempts=1, worker_pid=None)
    with make_client(tmp_path, max_workers=1) as c:
        doc = wait_final(c, url)
        assert doc["status"] == "successful"
        assert job_row(tmp_path / "data", job_id)["attempts"] == 2
    store.update(job_id, status="running", finished=None, attempts=2)
    with make_client(tmp_path, max_workers=1, max_attempts=2) as c:
        doc = c.get(url).json()
        assert doc["status"] == "failed" and doc["error_kind"] == "system"
        assert "not retried" in doc["message"]


def test_api_keys(tmp_path: Path) -> None:
    with make_client(tmp_path, api_keys="k1, k2") as c:
        r = c.get("/jobs")
        assert r.status_code == 401 and r.headers["content-type"] == PROBLEM
        assert c.get("/jobs", headers={"X-API-Key": "nope"}).status_code == 401
        assert c.get("/jobs", headers={"X-API-Key": "k2"}).status_code == 200
        assert c.get("/docs").status_code == 200  # documentation stays open


def test_docs_work_offline(client: TestClient) -> None:
    html = client.get("/docs").text
    import re

    refs = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert refs and all(ref.startswith("/static/") for ref in refs), refs
    assert "http://" not in html and "https://" not in html
    for ref in refs + ["/static/docs-init.js"]:
        r = client.get(ref)
        assert r.status_code == 200 and len(r.content) > 0, ref
    assert "openapi.json" in client.get("/static/docs-init.js").text
    spec = client.get("/openapi.json").json()
    assert spec["components"]["schemas"]["Scene"]["title"] == "PolyDDA scene"
    text = json.dumps(spec)
    assert "#/$defs/" not in text


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("POLYDDA_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("POLYDDA_BACKEND", "rq")
    monkeypatch.setenv("POLYDDA_API_KEYS", "a,b")
    monkeypatch.setenv("POLYDDA_MAX_WORKERS", "3")
    s = Settings()
    assert (s.data_dir, s.backend, s.api_keys, s.max_workers) == (tmp_path, "rq",
                                                                  frozenset({"a", "b"}), 3)
    assert s.worker_env()["OMP_NUM_THREADS"] == "1"
