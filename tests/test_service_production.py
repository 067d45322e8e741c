"""Issue 15 in-process (TestClient, embedded backend): ownership, idempotency after our own
failure, killed runs' HDF5 files, no 500s, the small HTTP defects, retention, disk guard,
metrics, CORS, rate limits."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests import service_helpers as helpers
from tests.service_helpers import TestClient, cube_scene, job_row, wait_final, wait_until

PROBLEM = "application/problem+json"
ALICE, BOB, ADMIN = ({"X-API-Key": k} for k in ("alice-key", "bob-key", "admin-key"))


def make_client(tmp_path: Path, **settings: Any) -> TestClient:
    return helpers.make_client(tmp_path / "data", **({"min_free_bytes": 0} | settings))


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with make_client(tmp_path) as c:
        yield c


def _blocks_job(c: TestClient, headers: dict[str, str] | None = None) -> str:
    r = c.post("/jobs", params={"process": "block-cutting"}, json=cube_scene(),
               headers=headers or {})
    assert r.status_code == 201, r.text
    return r.headers["Location"]


# ----------------------------------------------------------------------- 1 ownership


def test_jobs_belong_to_the_key_that_made_them(tmp_path: Path) -> None:
    with make_client(tmp_path, api_keys="alice-key,bob-key", admin_keys="admin-key") as c:
        url = _blocks_job(c, ALICE)
        assert wait_final(_As(c, ALICE), url)["status"] == "successful"
        for method, path in [("GET", ""), ("GET", "/results"), ("GET", "/events"),
                             ("GET", "/results/blocks.json"), ("DELETE", "")]:
            r = c.request(method, url + path, headers=BOB)
            assert r.status_code == 404, (method, path, r.status_code)
            assert r.headers["content-type"] == PROBLEM
            assert r.json()["type"].endswith("/no-such-job")
        assert c.get("/jobs", headers=BOB).json()["numberMatched"] == 0
        assert c.get("/jobs", headers=ALICE).json()["numberMatched"] == 1
        assert c.get(url, headers=ALICE).status_code == 200  # bob's DELETE did nothing
        # the admin key sees and removes everyone's jobs
        assert c.get("/jobs", headers=ADMIN).json()["numberMatched"] == 1
        assert c.get(url + "/results", headers=ADMIN).status_code == 200
        assert c.delete(url, headers=ADMIN).json()["status"] == "dismissed"
        assert c.get(url, headers=ALICE).status_code == 404
        # the same Idempotency-Key of two keys: two jobs
        h = {"Idempotency-Key": "same"}
        a = c.post("/jobs", params={"process": "block-cutting"}, json=cube_scene(),
                   headers=ALICE | h)
        b = c.post("/jobs", params={"process": "block-cutting"}, json=cube_scene(),
                   headers=BOB | h)
        assert a.json()["jobID"] != b.json()["jobID"]


class _As:
    """A client that sends one API key with every GET (for wait_final)."""

    def __init__(self, c: TestClient, headers: dict[str, str]) -> None:
        self.c, self.headers = c, headers

    def get(self, url: str) -> Any:
        return self.c.get(url, headers=self.headers)


# ----------------------------------------------------------------------- 5 idempotency


def test_a_key_whose_job_failed_for_our_cause_may_be_retried(tmp_path: Path) -> None:
    """Redis unreachable: 503, the job recorded as failed (system); the retry the 503
    invites makes a new attempt instead of replaying the failure."""
    with make_client(tmp_path, backend="rq", redis_url="redis://127.0.0.1:1/0") as c:
        h = {"Idempotency-Key": "retry-me"}
        first = c.post("/jobs", json=cube_scene(), headers=h)
        assert first.status_code == 503 and first.headers["Retry-After"] == "30"
        assert first.headers["content-type"] == PROBLEM
        again = c.post("/jobs", json=cube_scene(), headers=h)
        assert again.status_code == 503, again.text  # tried again, not replayed
        jobs = c.get("/jobs").json()["jobs"]
        assert [j["status"] for j in jobs] == ["failed", "failed"]
        assert all(j["error_kind"] == "system" for j in jobs)
        # a job that failed for the model's cause keeps its key (a replay)
        from service.jobs.store import JobStore

        store = JobStore(tmp_path / "data" / "jobs.sqlite")
        job, created = store.submit(process="simulation", scene="{}", client="c", quota=4,
                                    idempotency_key="k", request_hash="h")
        store.update(job.id, status="failed", error_kind="model")
        assert store.submit(process="simulation", scene="{}", client="c", quota=4,
                            idempotency_key="k", request_hash="h") == (store.get(job.id), False)


# ----------------------------------------------------------------------- 6 killed run's h5


def test_a_killed_runs_result_is_served_as_a_file_any_hdf5_reader_opens(tmp_path: Path) -> None:
    """One run allowed (POLYDDA_MAX_ATTEMPTS=1): the killed run is not retried, its steps
    are what the job keeps."""
    with make_client(tmp_path, max_attempts=1) as c:
        url = c.post("/jobs", json=cube_scene(duration=60, record_interval=1)).headers[
            "Location"]
        job_id = url.rsplit("/", 1)[1]
        wait_until(lambda: (c.get(url).json()["step"] or 0) > 30, 60, "steps")
        time.sleep(2.5)  # the writer flushes its steps at least every second
        os.kill(job_row(tmp_path / "data", job_id)["worker_pid"], signal.SIGKILL)
        assert wait_final(c, url, 10)["status"] == "failed"
        raw = tmp_path / "data" / "jobs" / job_id / "result.h5"
        with pytest.raises(OSError):  # marked open by its killed writer
            h5py.File(raw, "r").close()
        doc = c.get(url + "/results").json()
        link = next(lk for lk in doc["links"] if lk["href"].endswith("/result.h5"))
        assert "any HDF5 reader" in link["title"]
        r = c.get(url + "/results/result.h5")
        assert r.status_code == 200 and r.headers["x-polydda-recovered"] == "true"
        (tmp_path / "got.h5").write_bytes(r.content)
        with h5py.File(tmp_path / "got.h5", "r") as f:  # no SWMR, no h5clear
            assert f.attrs["status"] == "running" and len(f["steps/step"]) > 10
        part = c.get(url + "/results/result.h5", headers={"Range": "bytes=0-99"})
        assert part.status_code == 206 and part.content == r.content[:100]


# ----------------------------------------------------------------------- 7 no 500s


def test_numbers_python_refuses_and_huge_offsets_are_4xx(client: TestClient) -> None:
    body = b'{"name": "x", "gravity": [0, 0, ' + b"9" * 5000 + b"]}"
    r = client.post("/jobs", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    assert "4300 digits" in r.json()["errors"][0]["msg"]
    r = client.get("/jobs", params={"offset": "9" * 30})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == "query.offset"
    r = client.get("/jobs", params={"offset": 2**63 - 1})
    assert r.status_code == 200 and r.json()["numberReturned"] == 0


# ----------------------------------------------------------------------- 10 smaller


def test_405_names_the_allowed_methods(client: TestClient) -> None:
    # every GET route answers HEAD too (service.api.middleware.HeadAsGet)
    for method, path, allow in [("PUT", "/jobs", "GET, HEAD, POST"),
                                ("PATCH", "/jobs/x", "DELETE, GET, HEAD"),
                                ("POST", "/processes/simulation", "GET, HEAD"),
                                ("PUT", "/jobs/x/results/result.h5", "GET, HEAD"),
                                ("PUT", "/static/swagger-ui.css", "GET, HEAD")]:
        r = client.request(method, path)
        assert r.status_code == 405 and r.headers["allow"] == allow, (method, path)
        assert r.headers["content-type"] == PROBLEM


def test_text_bodies_are_415_and_bad_ranges_problem_documents(client: TestClient) -> None:
    import json

    r = client.post("/jobs", content=json.dumps(cube_scene()).encode(),
                    headers={"Content-Type": "text/plain"})
    assert r.status_code == 415 and r.headers["content-type"] == PROBLEM
    assert "application/json" in r.json()["detail"]
    ok = client.post("/jobs", params={"process": "block-cutting"},
                     content=json.dumps(cube_scene()).encode(),
                     headers={"Content-Type": "application/json; charset=utf-8"})
    assert ok.status_code == 201
    url = ok.headers["Location"]
    wait_final(client, url)
    r = client.get(url + "/results/blocks.json", headers={"Range": "bytes=999999-"})
    assert r.status_code == 416 and r.headers["content-type"] == PROBLEM
    assert r.headers["content-range"].startswith("bytes */")
    r = client.get(url + "/results/blocks.json", headers={"Range": "pages=1-2"})
    assert r.status_code == 400 and r.headers["content-type"] == PROBLEM


def test_status_shows_attempts(tmp_path: Path) -> None:
    with make_client(tmp_path, max_workers=1) as c:
        url = _blocks_job(c)
        assert wait_final(c, url)["attempts"] == 1
    from service.jobs.store import JobStore

    job_id = url.rsplit("/", 1)[1]
    JobStore(tmp_path / "data" / "jobs.sqlite").update(job_id, status="running", finished=None,
                                                       worker_pid=None)
    with make_client(tmp_path, max_workers=1) as c:  # the API died mid-job: re-queued
        doc = wait_final(c, url)
        assert doc["status"] == "successful" and doc["attempts"] == 2
        assert c.get("/openapi.json").json()["components"]["schemas"]["StatusInfo"][
            "properties"]["attempts"]


# ----------------------------------------------------------------------- retention, disk


def test_finished_jobs_expire_after_the_retention(tmp_path: Path) -> None:
    with make_client(tmp_path, retention=3600) as c:
        old, new = _blocks_job(c), _blocks_job(c)
        running = c.post("/jobs", json=cube_scene(duration=60)).headers["Location"]
        for u in (old, new):
            wait_final(c, u)
        backend = c.app.state.backend  # type: ignore[attr-defined]
        store = c.app.state.store  # type: ignore[attr-defined]
        old_id = old.rsplit("/", 1)[1]
        store.update(old_id, finished=time.time() - 7200)
        assert backend.housekeeping() == [old_id]
        assert c.get(old).status_code == 404
        assert not (tmp_path / "data" / "jobs" / old_id).exists()
        assert c.get(new).json()["status"] == "successful"
        assert c.get(running).json()["status"] in ("accepted", "running")  # never expires
        assert backend.housekeeping(now=time.time() + 10**6) == [new.rsplit("/", 1)[1]]
        c.delete(running)


def test_new_jobs_are_refused_with_507_before_the_disk_fills(tmp_path: Path) -> None:
    with make_client(tmp_path, min_free_bytes=2**62) as c:
        r = c.post("/jobs", json=cube_scene())
        assert r.status_code == 507 and r.headers["content-type"] == PROBLEM
        assert "POLYDDA_MIN_FREE_BYTES" in r.json()["detail"] and "Retry-After" in r.headers
        assert c.get("/jobs").json()["numberMatched"] == 0


# ----------------------------------------------------------------------- metrics, CORS, rate


def test_metrics_in_prometheus_format(client: TestClient) -> None:
    for _ in range(2):
        wait_final(client, _blocks_job(client))
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    families = {f.name: f for f in text_string_to_metric_families(r.text)}
    states = {s.labels["state"]: s.value for s in families["polydda_jobs"].samples}
    assert states["successful"] == 2 and states["running"] == 0
    wait = {s.name: s.value for s in families["polydda_job_queue_wait_seconds"].samples
            if s.labels.get("le") in (None, "+Inf")}
    assert wait["polydda_job_queue_wait_seconds_count"] == 2
    run = {s.name: s.value for s in families["polydda_job_run_seconds"].samples}
    assert run["polydda_job_run_seconds_count"] == 2 and run["polydda_job_run_seconds_sum"] > 0
    assert families["polydda_workers"].samples[0].value == 2


def test_cors_for_configured_origins(tmp_path: Path) -> None:
    with make_client(tmp_path, cors_origins="https://app.example") as c:
        pre = c.options("/jobs", headers={"Origin": "https://app.example",
                                          "Access-Control-Request-Method": "POST",
                                          "Access-Control-Request-Headers": "x-api-key"})
        assert pre.status_code == 200
        assert pre.headers["access-control-allow-origin"] == "https://app.example"
        r = c.get("/jobs", headers={"Origin": "https://app.example"})
        assert r.headers["access-control-allow-origin"] == "https://app.example"
        assert "location" in r.headers["access-control-expose-headers"].lower()
        other = c.get("/jobs", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers
    with make_client(tmp_path) as c:  # off by default
        r = c.get("/jobs", headers={"Origin": "https://app.example"})
        assert "access-control-allow-origin" not in r.headers


def test_rate_limit_per_key(tmp_path: Path) -> None:
    with make_client(tmp_path, api_keys="alice-key,bob-key", rate_limit=1, rate_burst=3) as c:
        codes = [c.get("/jobs", headers=ALICE).status_code for _ in range(4)]
        assert codes == [200, 200, 200, 429]
        r = c.get("/jobs", headers=ALICE)
        assert r.status_code == 429 and r.headers["content-type"] == PROBLEM
        assert int(r.headers["Retry-After"]) >= 1
        assert c.get("/jobs", headers=BOB).status_code == 200  # bob has his own bucket
        assert c.get("/health").status_code == 200  # health and metrics are not limited
        time.sleep(1.1)
        assert c.get("/jobs", headers=ALICE).status_code == 200
