"""Probability of failure of the paper's wedge (issue 17): realisations from a seed, eq. 51
over them, the sweep's skip-done re-run, and the DDA sweep against eq. 51 (slow)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from engine.analyses.sweep import SweepSpec, merge_documents
from service.cli.main import main
from service.sweep import analytic_fs, realisation_scene, run_sweep

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCENE = json.loads((EXAMPLES / "wedge.json").read_text())
K, PLUNGE = 1.437213, 28.7499  # docs/validation.md
PHI_C = math.degrees(math.atan(math.tan(math.radians(PLUNGE)) / K))  # 20.893°
SEED = 2026


def test_realisations_are_reproducible_from_the_seed() -> None:
    """Realisation k is the same for N = 10 and N = 200; the sample's mean and sd match
    Normal(40, 5) within 3 standard errors."""
    phi = SweepSpec(200, SEED, 40, 5).friction_angles()
    assert np.array_equal(phi[:10], SweepSpec(10, SEED, 40, 5).friction_angles())
    assert not np.array_equal(phi, SweepSpec(200, SEED + 1, 40, 5).friction_angles())
    assert abs(phi.mean() - 40) < 3 * 5 / math.sqrt(200)
    assert abs(phi.std(ddof=1) - 5) < 3 * 5 / math.sqrt(2 * 199)


def test_eq51_of_the_realisation_scene() -> None:
    """The realisation scene carries φ; eq. 51 of it is K tan φ / tan ψ (2.19819 at 40°)."""
    s = realisation_scene(SCENE, 33.3)
    assert s["joint_materials"]["joint"]["friction_angle"] == 33.3
    assert SCENE["joint_materials"]["joint"]["friction_angle"] == 40  # not modified
    assert analytic_fs(SCENE, 40) == pytest.approx(2.19819, abs=1e-5)
    assert analytic_fs(s, 33.3) == pytest.approx(
        K * math.tan(math.radians(33.3)) / math.tan(math.radians(PLUNGE)), rel=1e-6)
    assert PHI_C == pytest.approx(20.893, abs=1e-3)


@pytest.mark.parametrize("mean", [40.0, 25.0])
def test_analytic_pof_of_the_paper_wedge(tmp_path: Path, mean: float) -> None:
    """PoF by eq. 51 over N = 200 realisations is the fraction with φ < φ_c = 20.893°; it is
    within 3 binomial standard errors of Φ((φ_c − mean) / 5): 6.7e-5 for mean 40° (so no
    failure among 200: the acceptance comparison is 0 against 0), 0.206 for mean 25°."""
    spec = SweepSpec(200, SEED, mean, 5, mode="analytic")
    doc = run_sweep(SCENE, spec, tmp_path)
    a = doc["analytic"]
    phi = spec.friction_angles()
    assert a["n"] == 200 and a["failures"] == int((phi < PHI_C).sum())
    exact = stats.norm.cdf((PHI_C - mean) / 5)
    assert abs(a["probability_of_failure"] - exact) < 3 * math.sqrt(exact * (1 - exact) / 200)
    if mean == 40:
        assert a["failures"] == 0 and a["pof_interval_95"][1] == pytest.approx(0.0188, abs=1e-4)
    assert a["sensitivity"]["friction_angle"] == pytest.approx(1.0)  # F grows with φ only
    assert a["min"] == pytest.approx(K * math.tan(math.radians(phi.min()))
                                     / math.tan(math.radians(PLUNGE)), rel=1e-6)
    assert sum(a["histogram"]["counts"]) == 200 and a["cdf"]["p"][-1] == 1.0


def test_rerun_skips_done_realisations(tmp_path: Path) -> None:
    """A second run evaluates only the realisations whose files are missing and aggregates
    the same numbers; a stop request ends a run early; another spec in the folder is
    refused; 2 worker processes give the same records as 1."""
    spec = SweepSpec(30, SEED, 30, 5, mode="analytic")
    first = run_sweep(SCENE, spec, tmp_path / "a")
    for k in (3, 7, 11, 29):
        (tmp_path / "a" / "realisations" / f"{k:05d}.json").unlink()
    evaluated: list[int] = []
    again = run_sweep(SCENE, spec, tmp_path / "a",
                      progress=lambda done, n, now: evaluated.append(now))
    assert evaluated == [1, 2, 3, 4]
    assert again == first
    calls = iter(range(100))
    part = run_sweep(SCENE, spec, tmp_path / "b", should_stop=lambda: next(calls) >= 5)
    assert part["done"] == 5 and part["analytic"]["n"] == 5
    same = SweepSpec(30, SEED, 30.0, 5.0, mode="analytic")  # as the CLI parses it
    assert run_sweep(SCENE, same, tmp_path / "a") == first
    with pytest.raises(ValueError, match="another scene or spec"):
        run_sweep(SCENE, SweepSpec(30, SEED + 1, 30, 5, mode="analytic"), tmp_path / "a")
    two = run_sweep(SCENE, spec, tmp_path / "c", workers=2)
    assert two["realisations"] == first["realisations"]


def test_cli_sweep(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["sweep", str(EXAMPLES / "wedge.json"), "--n", "200", "--seed", str(SEED),
            "--friction-mean", "25", "--friction-sd", "5", "--mode", "analytic",
            "--out", str(tmp_path), "--quiet"]
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    phi = SweepSpec(200, SEED, 25, 5).friction_angles()
    assert doc["analytic"]["probability_of_failure"] == pytest.approx((phi < PHI_C).mean())
    assert (tmp_path / "sweep.json").is_file()
    assert main(args) == 0
    assert "probability of failure" in capsys.readouterr().out
    assert main(args[:-1] + ["--friction-sd", "0"]) == 2


# --------------------------------------------------------------------------- DDA (slow)


@pytest.mark.slow
@pytest.mark.parametrize("n", [200])
def test_dda_sweep_pof_matches_eq51(tmp_path: Path, n: int) -> None:
    """Acceptance (issue 17): φ ~ Normal(40°, 5°) on both joints, N = 200, seed 2026: the
    PoF of the engine's strength reduction per realisation is within 2 percentage points of
    eq. 51 over the same realisations, and each factor of safety within 2 % of eq. 51
    (docs/validation.md). About 40-80 s per realisation on one core."""
    doc = run_sweep(SCENE, SweepSpec(n, SEED, 40, 5), tmp_path, workers=2)
    assert doc["dda"]["n"] == n
    assert abs(doc["pof_difference"]) <= 0.02
    assert doc["fs_relative_difference"]["max_abs"] < 0.02


# --------------------------------------------------------------------------- API


def sweep_scene(**sweep: object) -> dict:
    scene = json.loads(json.dumps(SCENE))
    scene["sweep"] = {"n": 50, "seed": SEED, "friction_angle": {"mean": 25, "sd": 5},
                      "mode": "analytic"} | sweep
    return scene


def test_api_sweep_process_equals_the_cli(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """POST /jobs?process=sweep (embedded backend) gives the numbers `polydda sweep` gives
    for the same scene; a scene without `sweep` is refused with 422."""
    from service.api.app import create_app
    from service.settings import Settings
    from tests.service_helpers import TestClient, wait_final

    scene = sweep_scene()
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    assert main(["sweep", str(path), "--out", str(tmp_path / "cli"), "--json", "--quiet"]) == 0
    cli = json.loads(capsys.readouterr().out)
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", max_workers=1),
                               listen="127.0.0.1")) as c:
        r = c.post("/jobs", params={"process": "sweep"}, json=scene)
        assert r.status_code == 201, r.text
        job = wait_final(c, r.headers["Location"])
        assert job["status"] == "successful", job
        assert job["progress"] == 100 and job["message"].startswith("analytic: probability")
        doc = c.get(r.headers["Location"] + "/results").json()["sweep"]
        assert doc["analytic"] == cli["analytic"] and doc["done"] == 50
        bad = dict(scene)
        del bad["sweep"]
        r = c.post("/jobs", params={"process": "sweep"}, json=bad)
        assert r.status_code == 422 and "sweep" in r.text
        r = c.post("/jobs", params={"process": "sweep"}, json=sweep_scene(realisations=[50]))
        assert r.status_code == 422 and "below n = 50" in r.text


def test_shares_of_a_sweep_merge_into_the_whole(tmp_path: Path) -> None:
    """Two shares of one sweep (even and odd realisations, as two jobs would run them)
    merge into the numbers of the whole sweep; shares of different sweeps do not merge."""
    from service.sweep import spec_of_scene

    whole = run_sweep(SCENE, spec_of_scene(sweep_scene()), tmp_path / "whole")
    parts = [sweep_scene(realisations=list(range(first, 50, 2))) for first in (0, 1)]
    shares = [run_sweep(s, spec_of_scene(s), tmp_path / f"share{k}")
              for k, s in enumerate(parts)]
    assert [d["done"] for d in shares] == [25, 25]
    merged = merge_documents(shares)
    assert merged["analytic"] == whole["analytic"] and merged["done"] == 50
    assert merged["realisations"] == whole["realisations"]
    other = run_sweep(SCENE, spec_of_scene(sweep_scene(seed=SEED + 1, n=4)), tmp_path / "x")
    with pytest.raises(ValueError, match="not shares of one sweep"):
        merge_documents([shares[0], other])


@pytest.mark.slow
def test_api_jobs_of_shares_merge_into_the_whole(tmp_path: Path) -> None:
    """The same sweep as two jobs of the service (embedded backend), each a share of the
    realisations: merged, the numbers of one job running them all."""
    from service.api.app import create_app
    from service.settings import Settings
    from tests.service_helpers import TestClient, wait_final

    docs = []
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", max_workers=2),
                               listen="127.0.0.1")) as c:
        urls = [c.post("/jobs", params={"process": "sweep"}, json=scene).headers["Location"]
                for scene in (sweep_scene(), sweep_scene(realisations=list(range(0, 50, 2))),
                              sweep_scene(realisations=list(range(1, 50, 2))))]
        for url in urls:
            assert wait_final(c, url)["status"] == "successful"
            docs.append(c.get(url + "/results").json()["sweep"])
    merged = merge_documents(docs[1:])
    assert merged["analytic"] == docs[0]["analytic"]
    assert merged["realisations"] == docs[0]["realisations"]


@pytest.mark.slow
def test_stop_reaches_inside_a_dda_realisation(tmp_path: Path) -> None:
    """A stop asked for during the first realisation ends it after its current trial (one
    3 s observation, not a whole bisection); nothing half-done is written, and the re-run
    evaluates it in full."""
    asked: list[float] = []

    def stop() -> bool:
        asked.append(time.monotonic())
        return len(asked) > 1  # the loop's check passes, the first trial's check stops

    spec = SweepSpec(2, SEED, 40, 5)
    t0 = time.monotonic()
    doc = run_sweep(SCENE, spec, tmp_path, should_stop=stop)
    assert doc["done"] == 0 and not list((tmp_path / "realisations").iterdir())
    assert len(asked) == 2 and asked[1] - t0 < 60
    rest = run_sweep(SCENE, spec, tmp_path, limit=1)
    assert rest["done"] == 1 and rest["realisations"][0]["trials"] >= 8


@pytest.mark.slow
def test_requeued_sweep_job_redoes_no_realisation(tmp_path: Path) -> None:
    """The API stops mid-sweep (its job process is terminated and the job re-queued); the
    next API process runs the job again in the same folder: it ends with every realisation
    and rewrites none of those written before the stop."""
    from service.api.app import create_app
    from service.settings import Settings
    from tests.service_helpers import TestClient, wait_final, wait_until

    settings = Settings(data_dir=tmp_path / "data", max_workers=1)
    scene = sweep_scene(n=2000)
    with TestClient(create_app(settings, listen="127.0.0.1")) as c:
        url = c.post("/jobs", params={"process": "sweep"}, json=scene).headers["Location"]
        sweeps = settings.data_dir / "sweeps"
        wait_until(lambda: len(list(sweeps.glob("*/*.json"))) > 100, 120, "realisations")
        (folder,) = sweeps.iterdir()
    before = {p.name: p.stat().st_mtime_ns for p in folder.glob("*.json")}
    assert 100 < len(before) < 2000
    with TestClient(create_app(settings, listen="127.0.0.1")) as c:
        job = wait_final(c, url, timeout=600)
        assert job["status"] == "successful", job
        assert c.get(url + "/results").json()["sweep"]["done"] == 2000
    after = {p.name: p.stat().st_mtime_ns for p in folder.glob("*.json")}
    assert len(after) == 2000
    assert all(after[name] == t for name, t in before.items())


# --------------------------------------------------------------------------- sweep as jobs


@pytest.mark.slow
def test_sweep_jobs_on_the_embedded_backend(tmp_path: Path) -> None:
    """`sweep_jobs` (`polydda sweep --server URL --jobs 2`): two jobs, each a share, give
    the numbers of the sweep run locally; a re-run submits nothing new."""
    from service.api.app import create_app
    from service.cli.client import sweep_jobs
    from service.settings import Settings
    from service.sweep import spec_of_scene
    from tests.service_helpers import TestClient

    scene = sweep_scene(n=100)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    seen: list[int] = []
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", max_workers=2),
                               listen="127.0.0.1")) as c:
        doc = sweep_jobs(c, scene, 2, tmp_path / "out",
                         on_progress=lambda done, n, st: seen.append(done))
        assert [j["status"] for j in doc["jobs"]] == ["successful", "successful"]
        assert doc["analytic"] == local["analytic"]
        assert doc["realisations"] == local["realisations"]
        assert seen[-1] == 100 and seen == sorted(seen)
        jobs = c.get("/jobs").json()["jobs"]
        again = sweep_jobs(c, scene, 2, tmp_path / "out")
        assert again["jobs"] == doc["jobs"] and len(c.get("/jobs").json()["jobs"]) == len(jobs)


REDIS = shutil.which("redis-server")


@pytest.mark.slow
@pytest.mark.skipif(REDIS is None, reason="redis-server is not installed")
def test_sweep_jobs_on_rq_workers(tmp_path: Path) -> None:
    """Two `polydda worker`s each take one job of a sweep fanned out in two shares; merged,
    the numbers are those of the sweep run locally (and so of the embedded backend)."""
    import os

    import httpx

    from service.cli.client import sweep_jobs
    from service.sweep import spec_of_scene
    from tests.service_helpers import Server, free_port, wait_until
    from tests.test_service_rq import start_worker

    port = free_port()
    redis = subprocess.Popen(
        [str(REDIS), "--port", str(port), "--bind", "127.0.0.1", "--save", "",
         "--appendonly", "no", "--dir", str(tmp_path)], stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)
    url = f"redis://127.0.0.1:{port}/0"
    data = tmp_path / "shared"
    scene = sweep_scene(n=1200)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    workers = []
    try:
        from redis import Redis

        conn = Redis(port=port)

        def up() -> bool:
            try:
                return bool(conn.ping())
            except Exception:
                return False
        wait_until(up, 10, "redis-server to answer")
        conn.close()
        workers = [start_worker(data, url, f"s{k}-{os.getpid()}", tmp_path / f"w{k}.log")
                   for k in range(2)]
        server = Server(data, POLYDDA_BACKEND="rq", POLYDDA_REDIS_URL=url,
                        POLYDDA_RQ_HEARTBEAT_TTL="2")
        server.start(timeout=180)  # slow on a loaded machine
        try:
            with httpx.Client(base_url=server.url, timeout=60) as c:
                doc = sweep_jobs(c, scene, 2, tmp_path / "out")
        finally:
            server.stop()
        assert [j["status"] for j in doc["jobs"]] == ["successful", "successful"]
        assert doc["analytic"] == local["analytic"] and doc["done"] == 1200
        assert doc["realisations"] == local["realisations"]
        ran = [(tmp_path / f"w{k}.log").read_text().count("Job OK") for k in range(2)]
        assert ran == [1, 1], ran  # one share on each worker
    finally:
        for w in workers:
            if w.poll() is None:
                w.terminate()
                w.wait(20)
        redis.terminate()
        redis.wait(10)


@pytest.mark.slow
@pytest.mark.ci
@pytest.mark.skipif(REDIS is None, reason="redis-server is not installed")
def test_killing_one_rq_worker_mid_sweep_loses_no_realisation(tmp_path: Path) -> None:
    """A sweep in two shares on two `polydda worker`s; the worker running the first share
    is SIGKILLed a fifth of the way through it. Its job is re-queued (the same job, attempt
    2), the surviving worker finishes it, redoing none of the realisations written before
    the kill; the merged numbers are those of the sweep run locally (and so of the
    embedded backend)."""
    import os

    import httpx

    from service.cli.client import sweep_jobs
    from service.sweep import spec_of_scene
    from tests.service_helpers import RedisServer, Server, job_row
    from tests.test_service_rq import parent_pid, start_worker, stop_workers

    n = 10000  # the most a sweep has; eq. 51 takes ~1 ms a realisation: seconds a share
    scene = sweep_scene(n=n)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    data = tmp_path / "shared"
    env = {"POLYDDA_RQ_HEARTBEAT_TTL": "2"}
    before: dict[Path, int] = {}
    killed: list[tuple[str, int, float]] = []
    with RedisServer(tmp_path) as redis:
        workers = [start_worker(data, redis.url, f"m{k}-{os.getpid()}", tmp_path / f"w{k}.log",
                                **env) for k in range(2)]

        seen: list[tuple[object, float]] = []  # (the shares' states, when they last changed)

        def kill_first(done: int, total: int, statuses: list[dict]) -> None:
            st = statuses[0]
            if killed:  # sweep_jobs would wait for ever on a job left `running`: one whose
                # state and progress stop changing (on a loaded machine the survivor may
                # finish its own share first and redo the rest slowly: that is progress)
                now = [(s["status"], s["step"], s["attempts"]) for s in statuses]
                if not seen or seen[-1][0] != now:
                    seen.append((now, time.monotonic()))
                assert time.monotonic() - seen[-1][1] < 120, f"stuck: {statuses}"
                return
            if st["status"] != "running" or (st["step"] or 0) < n // 10:
                return
            horse = job_row(data, st["jobID"])["worker_pid"]
            (victim,) = [w for w in workers if w.pid == parent_pid(horse)]
            victim.kill()
            victim.wait(10)
            killed.append((st["jobID"], st["step"], time.monotonic()))
            time.sleep(0.5)  # the horse dies with its worker; nothing of it is half-written
            before.update({p: p.stat().st_mtime_ns for p in (data / "sweeps").glob("*/*.json")})

        try:
            with Server(data, POLYDDA_BACKEND="rq", POLYDDA_REDIS_URL=redis.url, **env) as srv, \
                    httpx.Client(base_url=srv.url, timeout=60) as c:
                doc = sweep_jobs(c, scene, 2, tmp_path / "out", on_progress=kill_first,
                                 poll=0.2)
                assert killed
                job = c.get(f"/jobs/{killed[0][0]}").json()
                assert job["status"] == "successful" and job["attempts"] == 2, job
        finally:
            stop_workers(workers)
    assert [j["status"] for j in doc["jobs"]] == ["successful", "successful"]
    assert killed[0][0] in doc["jobs"][0]["url"]  # re-queued, not submitted again
    assert doc["done"] == n and doc["analytic"] == local["analytic"]
    assert doc["realisations"] == local["realisations"]
    assert len(before) >= killed[0][1]
    assert all(p.stat().st_mtime_ns == t for p, t in before.items())


@pytest.mark.slow
def test_sweep_jobs_resubmit_a_share_whose_process_died(tmp_path: Path) -> None:
    """The process of one share is SIGKILLed mid-share (as a dying worker would leave it):
    the job fails for a system reason, `sweep_jobs` submits the share again, and the new job
    redoes none of the realisations written before the kill; the merged numbers are those
    of the local sweep."""
    import os
    import signal

    from service.api.app import create_app
    from service.cli.client import sweep_jobs
    from service.settings import Settings
    from service.sweep import spec_of_scene
    from tests.service_helpers import TestClient, job_row

    scene = sweep_scene(n=1000)
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    settings = Settings(data_dir=tmp_path / "data", max_workers=2)
    before: dict[Path, int] = {}
    killed: list[str] = []

    def kill_first(done: int, n: int, statuses: list[dict]) -> None:
        if killed or done < 100 or statuses[0]["status"] != "running":
            return
        pid = job_row(settings.data_dir, statuses[0]["jobID"])["worker_pid"]
        os.kill(pid, signal.SIGKILL)
        killed.append(statuses[0]["jobID"])
        time.sleep(0.5)
        before.update({p: p.stat().st_mtime_ns
                       for p in (settings.data_dir / "sweeps").glob("*/*.json")})

    with TestClient(create_app(settings, listen="127.0.0.1")) as c:
        doc = sweep_jobs(c, scene, 2, tmp_path / "out", on_progress=kill_first, poll=0.2)
        assert killed and c.get(f"/jobs/{killed[0]}").json()["status"] == "failed"
    assert [j["status"] for j in doc["jobs"]] == ["successful", "successful"]
    assert killed[0] not in doc["jobs"][0]["url"]  # the share ran again as a new job
    assert doc["analytic"] == local["analytic"] and doc["done"] == 1000
    assert before and all(p.stat().st_mtime_ns == t for p, t in before.items())
