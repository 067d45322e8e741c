"""A sweep fanned out over the queue by the server (issue 17): `POST /jobs?process=sweep&
shares=K` is a parent job of K child `sweep` jobs; its progress, status, cancel and merged
results are those of the whole (in-process embedded backend, eq. 51 sweeps of the wedge)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from service.jobs.store import JobStore
from service.sweep import run_sweep, spec_of_scene
from tests.service_helpers import job_row, make_client, wait_final, wait_until

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def sweep_scene(n: int = 50, **sweep: Any) -> dict[str, Any]:
    scene = json.loads((EXAMPLES / "wedge.json").read_text())
    scene["sweep"] = {"n": n, "seed": 2026, "friction_angle": {"mean": 25, "sd": 5},
                      "mode": "analytic"} | sweep
    return scene


def links(doc: dict[str, Any], rel: str) -> list[str]:
    return [lk["href"] for lk in doc["links"] if lk["rel"] == rel]


def post_parent(c: Any, scene: dict[str, Any], shares: int) -> Any:
    return c.post("/jobs", params={"process": "sweep", "shares": shares}, json=scene)


def test_parent_fans_out_in_shares_and_merges_them(tmp_path: Path) -> None:
    """K = 3: three child jobs, each its share (together 0..n-1 once), linked both ways;
    the parent ends successful at 100 % with the realisations of all three, and its
    results are the numbers of the sweep run as one job."""
    scene = sweep_scene()
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    data = tmp_path / "data"
    with make_client(data) as c:
        r = post_parent(c, scene, 3)
        assert r.status_code == 201, r.text
        url = r.headers["Location"]
        parent = r.json()
        children = links(parent, "item")
        assert len(children) == 3 and parent["status"] == "accepted"
        store = JobStore(data / "jobs.sqlite")
        shares = [json.loads(store.scene(u.rsplit("/", 1)[1]))["sweep"]["realisations"]
                  for u in children]
        assert sorted(k for s in shares for k in s) == list(range(50))
        assert [len(s) for s in shares] == [17, 17, 16]
        for u in children:
            assert links(c.get(u).json(), "up") == [url]
        job = wait_final(c, url)
        assert job["status"] == "successful", job
        assert job["progress"] == 100 and job["step"] == 50
        assert job["message"].startswith("analytic: probability of failure")
        for u in children:
            assert c.get(u).json()["status"] == "successful"
        res = c.get(url + "/results").json()
        assert res["status"] == "successful" and res["partial"] is False
        doc = res["sweep"]
        assert doc["done"] == 50 and doc["analytic"] == local["analytic"]
        assert [(r["index"], r["factor_of_safety"]) for r in doc["realisations"]] == \
            [(r["index"], r["factor_of_safety"]) for r in local["realisations"]]
        assert [j["realisations"] for j in doc["jobs"]] == [17, 17, 16]
        assert c.get(url + "/report").status_code == 200
        assert c.get(url + "/results/sweep.json").json()["analytic"] == doc["analytic"]
        # one job of the whole sweep gives the same numbers
        one = c.post("/jobs", params={"process": "sweep"}, json=scene)
        assert links(one.json(), "item") == []
        assert wait_final(c, one.headers["Location"])["status"] == "successful"
        whole = c.get(one.headers["Location"] + "/results").json()["sweep"]
        assert whole["analytic"] == doc["analytic"]
        # removing the finished parent removes its children
        assert c.delete(url).status_code == 200
        assert all(c.get(u).status_code == 404 for u in [url, *children])


def test_shares_are_checked(tmp_path: Path) -> None:
    """More shares than realisations, or shares of a process other than sweep: 422 naming
    `shares`; shares=1 is a plain job; the OpenAPI document describes the option."""
    with make_client(tmp_path / "data") as c:
        r = post_parent(c, sweep_scene(n=4), 5)
        assert r.status_code == 422 and "shares" in r.text and "at most 4" in r.text
        r = post_parent(c, sweep_scene(n=50, realisations=[1, 2]), 3)
        assert r.status_code == 422 and "at most 2" in r.text
        r = c.post("/jobs", params={"process": "kinematics", "shares": 2},
                   json=sweep_scene())
        assert r.status_code == 422 and "shares" in r.text
        assert c.get("/jobs").json()["numberMatched"] == 0
        r = post_parent(c, sweep_scene(n=4), 1)
        assert r.status_code == 201 and links(r.json(), "item") == []
        wait_final(c, r.headers["Location"])
        api = c.get("/openapi.json").json()
        for path in ("/jobs", "/processes/{process_id}/execution"):
            (p,) = [p for p in api["paths"][path]["post"]["parameters"]
                    if p["name"] == "shares"]
            assert p["in"] == "query" and "parent" in p["description"]
            assert p["schema"]["minimum"] == 1


def test_running_parent_shows_progress_and_cancel_reaches_every_child(tmp_path: Path) -> None:
    """One worker, three shares of a long sweep: while the first child runs, the parent is
    running with the realisations done so far and its results aggregate them; DELETE of the
    parent stops the running child and dismisses the waiting ones, and the parent ends
    dismissed with its partial aggregate."""
    n = 10000
    with make_client(tmp_path / "data", max_workers=1) as c:
        r = post_parent(c, sweep_scene(n=n), 3)
        url = r.headers["Location"]
        children = links(r.json(), "item")
        job = wait_until(lambda: (d := c.get(url).json())["step"] and d, 120,
                         "realisations to be done")
        assert job["status"] == "running" and 0 < job["step"] < n
        assert f"of {n} realisations done" in job["message"]
        res = c.get(url + "/results").json()
        assert res["status"] == "running" and res["partial"] is True
        assert 0 < res["sweep"]["done"] < n
        r = c.delete(url)
        assert r.status_code in (200, 202)
        job = wait_final(c, url)
        assert job["status"] == "dismissed" and job["cancel_requested"], job
        kids = [c.get(u).json() for u in children]
        assert [k["status"] for k in kids] == ["dismissed"] * 3, kids
        assert [k["started"] is not None for k in kids] == [True, False, False]
        done = c.get(url + "/results").json()
        assert done["partial"] is True and 0 < done["sweep"]["done"] < n


def test_a_share_whose_process_died_is_submitted_again(tmp_path: Path) -> None:
    """The job process of one child is SIGKILLed mid-share, with one run allowed: the child
    is lost as any job is (Backend.requeue_or_fail; with runs left it would run again in
    place, tests/test_service_hostile.py) and fails for a system reason; the parent
    submits the share again as a new child (linked in its place) and ends successful with
    every realisation."""
    n = 3000
    scene = sweep_scene(n=n)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    data = tmp_path / "data"
    with make_client(data, max_workers=2, max_attempts=1) as c:
        r = post_parent(c, scene, 2)
        url = r.headers["Location"]
        first = links(r.json(), "item")[0]
        wait_until(lambda: (c.get(first).json()["step"] or 0) > 50, 120, "a share to run")
        os.kill(job_row(data, first.rsplit("/", 1)[1])["worker_pid"], signal.SIGKILL)
        job = wait_final(c, url, timeout=120)
        assert job["status"] == "successful", job
        assert c.get(first).json()["status"] == "failed"
        again = links(job, "item")[0]
        assert again != first and links(c.get(again).json(), "up") == [url]
        doc = c.get(url + "/results").json()["sweep"]
        assert doc["done"] == n and doc["analytic"] == local["analytic"]


def test_cli_sweep_on_a_server_is_one_parent_job(tmp_path: Path) -> None:
    """`polydda sweep --server URL --jobs K` (service.cli.client.sweep_parent): one parent job
    with K shares, followed to its end; sweep.json has the local numbers and the jobs;
    a re-run submits nothing new."""
    from service.cli.client import sweep_parent

    scene = sweep_scene(n=60)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    seen: list[int] = []
    with make_client(tmp_path / "data") as c:
        doc = sweep_parent(c, scene, 3, tmp_path / "out",
                           on_progress=lambda done, n, st: seen.append(done), poll=0.1)
        jobs = c.get("/jobs").json()
        assert jobs["numberMatched"] == 4  # the parent and its three children
        assert doc["analytic"] == local["analytic"] and doc["done"] == 60
        assert [j["status"] for j in doc["jobs"]] == ["successful"] * 3
        assert doc["job"]["status"] == "successful"
        assert seen[-1] == 60 and seen == sorted(seen)
        saved = json.loads((tmp_path / "out" / "sweep.json").read_text())
        assert saved["analytic"] == doc["analytic"]
        again = sweep_parent(c, scene, 3, tmp_path / "out")
        assert again["job"] == doc["job"]
        assert c.get("/jobs").json()["numberMatched"] == 4


def test_an_older_job_table_gains_the_parent_columns(tmp_path: Path) -> None:
    """A job table written before parents existed is given their columns on first use;
    its jobs read as plain jobs."""
    path = tmp_path / "jobs.sqlite"
    db = sqlite3.connect(path)
    db.executescript("""CREATE TABLE jobs (id TEXT PRIMARY KEY, process TEXT NOT NULL,
        status TEXT NOT NULL, client TEXT NOT NULL, idempotency_key TEXT, request_hash TEXT,
        scene TEXT NOT NULL, created REAL NOT NULL, started REAL, finished REAL,
        updated REAL NOT NULL, progress REAL NOT NULL DEFAULT 0, step INTEGER,
        simulated_time REAL, duration REAL, message TEXT NOT NULL DEFAULT '',
        error_kind TEXT, cancel_requested REAL, attempts INTEGER NOT NULL DEFAULT 0,
        worker_pid INTEGER);
        INSERT INTO jobs (id, process, status, client, scene, created, updated)
        VALUES ('old', 'sweep', 'accepted', 'ip:x', '{}', 1, 1);""")
    db.commit()
    db.close()
    store = JobStore(path)
    job = store.get("old")
    assert job is not None and not job.is_parent and job.parent is None
    assert [j.id for j in store.active()] == ["old"] and store.active_parents() == []


@pytest.mark.parametrize("shares,sizes", [(1, [7]), (3, [3, 2, 2]), (7, [1] * 7),
                                          (9, [1] * 7)])
def test_share_parts_cover_every_index_once(shares: int, sizes: list[int]) -> None:
    from engine.analyses.sweep import share_parts

    parts = share_parts(list(range(7)), shares)
    assert [len(p) for p in parts] == sizes
    assert sorted(k for p in parts for k in p) == list(range(7))


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="redis-server is not "
                    "installed")
def test_parent_job_on_rq_workers(tmp_path: Path) -> None:
    """The same parent job on the RQ backend: its children run on two `polydda worker`s,
    the merged results are the local sweep's; DELETE of a running parent stops the
    children on the workers."""
    import httpx

    from tests.service_helpers import RedisServer, Server
    from tests.test_service_rq import start_worker, stop_workers

    scene = sweep_scene(n=200)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    data = tmp_path / "shared"
    env = {"POLYDDA_RQ_HEARTBEAT_TTL": "2"}
    with RedisServer(tmp_path) as redis:
        workers = [start_worker(data, redis.url, f"p{k}-{os.getpid()}", tmp_path / f"w{k}.log",
                                **env) for k in range(2)]
        try:
            with Server(data, POLYDDA_BACKEND="rq", POLYDDA_REDIS_URL=redis.url,
                        POLYDDA_CANCEL_GRACE="1", **env) as srv, \
                    httpx.Client(base_url=srv.url, timeout=60) as c:
                r = post_parent(c, scene, 2)
                url = r.headers["Location"]
                job = wait_final(c, url, 180)
                assert job["status"] == "successful", job
                doc = c.get(url + "/results").json()["sweep"]
                assert doc["analytic"] == local["analytic"] and doc["done"] == 200
                assert [j["status"] for j in doc["jobs"]] == ["successful"] * 2
                r = post_parent(c, sweep_scene(n=10000), 2)
                url, children = r.headers["Location"], links(r.json(), "item")
                wait_until(lambda: (c.get(url).json()["step"] or 0) > 0, 120,
                           "realisations to be done")
                c.delete(url)
                job = wait_final(c, url, 60)
                assert job["status"] == "dismissed", job
                assert [wait_final(c, u, 30)["status"] for u in children] == \
                    ["dismissed"] * 2
                assert 0 < c.get(url + "/results").json()["sweep"]["done"] < 10000
        finally:
            stop_workers(workers)
