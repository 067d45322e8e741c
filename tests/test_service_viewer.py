"""The viewer's data endpoint, the HTML pages (home, viewer, report) in-process.

Real-browser tests of the same pages: tests/test_service_viewer_browser.py.
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from engine.results.plots import plot_snapshot
from engine.results.reader import open_result
from service.api.frames import decode_binary
from service.readable import trend_plunge
from service.settings import Settings
from tests.service_helpers import (
    TestClient,
    cube_scene,
    make_client,
    synthetic_job,
    wait_final,
    wait_until,
)

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def cube_job(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str, Path]]:
    """A client, the URL of a finished cube simulation and its result.h5."""
    data = tmp_path_factory.mktemp("viewer") / "data"
    with make_client(data) as c:
        r = c.post("/processes/simulation/execution", json=cube_scene())
        assert r.status_code == 201, r.text
        url = r.headers["Location"]
        assert wait_final(c, url)["status"] == "successful"
        yield c, url, data / "jobs" / url.rsplit("/", 1)[1] / "result.h5"


def moved_vertices(payload: Any, k: int) -> np.ndarray:
    """Surface vertices at frame k from a frames payload: c0 + d + R (X0 - c0) + origin."""
    a = payload.arrays
    vb = np.repeat(np.arange(len(a["centroid0"])), np.diff(a["vertex_offsets"].astype(int)))
    c0 = a["centroid0"].astype(float)[vb]
    rot = Rotation.from_quat(a["rotation"][k].astype(float)[vb])
    return (c0 + a["displacement"][k].astype(float)[vb]
            + rot.apply(a["vertices"].astype(float) - c0) + payload.header["origin"])


def test_frames_hold_the_geometry_once_and_the_motion_per_step(cube_job: Any) -> None:
    c, url, h5 = cube_job
    r = c.get(url + "/results/frames")
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    p = decode_binary(r.content)
    h, a = p.header, p.arrays
    assert h["format"] == "polydda-frames" and h["status"] == "completed"
    assert h["block_names"] == ["cube", "base"] and h["fixed"] == [False, True]
    with open_result(h5) as res:
        n = res.n_steps
        assert h["count"] == h["n_steps"] == n == 11 and h["next_start"] is None
        assert h["steps"] == res.steps.tolist()
        assert a["vertices"].shape == (16, 3) and a["vertex_offsets"].tolist() == [0, 8, 16]
        assert a["triangles"].shape == (24, 3) and a["edges"].shape == (24, 2)
        assert a["triangle_block"].tolist() == [0] * 12 + [1] * 12
        assert a["displacement"].shape == (n, 2, 3) and a["rotation"].shape == (n, 2, 4)
        assert a["velocity"].shape == (n, 2, 3)
        assert all(v.dtype in (np.float32, np.uint32) for v in a.values())
        for k in (0, n - 1):  # the payload moves the vertices where the result has them
            np.testing.assert_allclose(moved_vertices(p, k), res.all_vertices(k), atol=1e-5)
        assert np.abs(a["displacement"][-1, 0]).max() > 0  # the cube settles a little
    # a range of steps, without the geometry; JSON says the same
    part = decode_binary(c.get(url + "/results/frames",
                               params={"start": 2, "stop": 9, "stride": 3,
                                       "geometry": "false"}).content)
    assert part.header["steps"] == [h["steps"][k] for k in (2, 5, 8)]
    assert "vertices" not in part.arrays and "block_names" not in part.header
    np.testing.assert_array_equal(part.arrays["displacement"], a["displacement"][2:9:3])
    js = c.get(url + "/results/frames", params={"start": 2, "stop": 9, "stride": 3,
                                                "format": "json"}).json()
    assert js["steps"] == part.header["steps"] and len(js["vertices"]) == 16
    np.testing.assert_allclose(js["rotation"], part.arrays["rotation"], rtol=1e-6)
    # stop beyond the recorded steps is clipped; start == n gives no frame (what a
    # viewer following a run asks for when nothing is new)
    assert decode_binary(c.get(url + "/results/frames?stop=999").content).header["count"] == n
    empty = decode_binary(c.get(url + f"/results/frames?start={n}&geometry=false").content)
    assert empty.header["count"] == 0 and empty.arrays["displacement"].shape == (0, 2, 3)


def test_frames_carry_each_steps_contacts_with_normals_and_forces(cube_job: Any) -> None:
    """contacts=true: per step the contacts' mid-points, modes, unit normals and normal
    forces as the result file has them; the cube at rest is carried by its weight."""
    c, url, h5 = cube_job
    p = decode_binary(c.get(url + "/results/frames",
                            params={"start": 9, "stop": 11, "contacts": "true"}).content)
    a = p.arrays
    assert p.header["contact_forces"] is True
    offs = a["contact_offsets"].astype(int)
    assert len(offs) == 3 and a["contact_normal"].shape == (offs[-1], 3)
    with open_result(h5) as r:
        for f, k in enumerate((9, 10)):
            rows = slice(offs[f], offs[f + 1])
            rec = r.contacts(k)
            np.testing.assert_allclose(a["contact_force"][rows], rec["normal_force"],
                                       rtol=1e-6)
            np.testing.assert_allclose(a["contact_normal"][rows], rec["normal"], atol=1e-6)
            np.testing.assert_array_equal(a["contact_mode"][rows], rec["mode"])
            mid = (rec["point_i"] + rec["point_j"]) / 2 - p.header["origin"]
            np.testing.assert_allclose(a["contact_point"][rows], mid, atol=1e-5)
            # the normal forces carry the cube: their vertical sum is its weight (2600 kg)
            up = (a["contact_force"][rows, None] * a["contact_normal"][rows]).sum(axis=0)
            assert abs(up[2]) == pytest.approx(2600 * 9.81, rel=1e-3)
    js = c.get(url + "/results/frames", params={"start": 10, "stop": 11, "contacts": "true",
                                                "format": "json"}).json()
    assert len(js["contact_force"]) == len(js["contact_mode"]) == offs[2] - offs[1]


@pytest.mark.parametrize("query, loc", [
    ("start=12", "query.start"), ("start=5&stop=2", "query.start"),
    ("stride=0", "query.stride"), ("start=-1", "query.start"), ("stop=x", "query.stop"),
    ("format=xml", "query.format")])
def test_frames_bad_ranges_are_422_problems(cube_job: Any, query: str, loc: str) -> None:
    c, url, _ = cube_job
    r = c.get(url + "/results/frames?" + query)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
    assert r.json()["errors"][0]["loc"] == loc


def test_frames_follow_a_running_job(tmp_path: Path) -> None:
    with make_client(tmp_path / "data") as c:
        url = c.post("/jobs", json=cube_scene(duration=30.0, record_interval=1)).headers[
            "Location"]

        def frames_while_running() -> Any:
            r = c.get(url + "/results/frames", params={"geometry": "false"})
            status = c.get(url).json()["status"]
            if r.status_code == 404:
                assert r.headers["content-type"] == PROBLEM and status in ("accepted",
                                                                            "running")
                return None
            assert r.status_code == 200, r.text
            head = decode_binary(r.content).header
            return head if status == "running" and head["count"] >= 2 else None

        head = wait_until(frames_while_running, 60, "frames of the running job")
        assert head["status"] == "running" and head["count"] == head["n_steps"]
        later = wait_until(lambda: (h := decode_binary(c.get(
            url + f"/results/frames?start={head['count']}&geometry=false").content).header)[
            "count"] and h, 30, "more frames")
        assert later["start"] == head["count"] and later["steps"][0] > head["steps"][-1]
        assert c.delete(url).status_code in (200, 202)
        wait_final(c, url)


def test_frames_and_pages_of_another_keys_job_are_404(tmp_path: Path) -> None:
    with make_client(tmp_path / "data", api_keys="k1, k2") as c:
        k1, k2 = {"X-API-Key": "k1"}, {"X-API-Key": "k2"}
        url = c.post("/jobs", json=cube_scene(), headers=k1).headers["Location"]
        wait_until(lambda: c.get(url, headers=k1).json()["status"] == "successful", 60,
                   "the job to end")
        for page in ("/results/frames", "/viewer", "/report"):
            assert c.get(url + page, headers=k1).status_code == 200, page
            r = c.get(url + page, headers=k2)
            assert r.status_code == 404 and r.headers["content-type"] == PROBLEM, page
            assert c.get(url + page).status_code == 401
        # a browser sends its key as a cookie (GET only; never enough to submit)
        c.cookies.set("polydda_key", "k1")
        try:
            assert c.get(url + "/viewer").status_code == 200
            assert c.get(url + "/results/frames").status_code == 200
            assert c.post("/jobs", json=cube_scene()).status_code == 401
            home = c.get("/", headers={"Accept": "text/html"}).text
            assert f'href="{url}/viewer"' in home
        finally:
            c.cookies.clear()
        home = c.get("/", headers={"Accept": "text/html"})
        assert home.status_code == 200 and 'id="key-form"' in home.text
        assert url not in home.text


def test_frames_of_1000_blocks_are_under_a_tenth_of_the_hdf5(tmp_path: Path) -> None:
    job_id, h5 = synthetic_job(tmp_path / "data", n_blocks=1000, n_steps=100)
    with make_client(tmp_path / "data") as c:
        t0 = time.perf_counter()
        r = c.get(f"/jobs/{job_id}/results/frames")
        seconds = time.perf_counter() - t0
    p = decode_binary(r.content)
    assert p.header["n_blocks"] == 1000 and p.header["count"] == 100
    ratio = len(r.content) / h5.stat().st_size
    print(f"frames: {len(r.content) / 1e6:.2f} MB in {seconds:.2f} s for a "
          f"{h5.stat().st_size / 1e6:.1f} MB result.h5 (ratio {ratio:.3f})")
    assert ratio < 0.1


def test_home_page_names_jobs_by_their_scene_with_dates_and_an_upload_form(
        cube_job: Any) -> None:
    """The home page names each job by its scene (`name`; the description when the name is
    the default), gives its status and dates, and carries the form that starts a process;
    the names come from the job table in one query."""
    from datetime import UTC, datetime

    c, url, _ = cube_job
    job = url.rsplit("/", 1)[1]
    unnamed = {k: v for k, v in cube_scene().items() if k != "name"}
    unnamed["description"] = "a cube left <unnamed>"
    url2 = c.post("/jobs", json=unnamed).headers["Location"]
    wait_final(c, url2)
    page = c.get("/?f=html").text
    row = page[page.index(f"data-job='{job}'"):]
    row = row[:row.index("</tr>")]
    assert "<span class='job-name' title=''>cube</span>" in row
    assert "status-successful" in row and "100 %" in row
    created = c.get(url).json()["created"]  # ISO 8601
    day = datetime.fromisoformat(created.replace("Z", "+00:00")).astimezone(UTC)
    assert f"{day:%Y-%m-%d %H:%M} UTC" in row
    # no name: the description, escaped
    assert "a cube left &lt;unnamed&gt;" in page
    assert "id='upload-form'" in page and "/static/home.js" in page
    for process in ("simulation", "factor-of-safety", "sweep"):
        assert f'<option value="{process}">' in page
    assert c.get("/static/home.js").status_code == 200


def test_home_page_for_browsers_and_the_json_landing_for_clients(cube_job: Any) -> None:
    c, url, _ = cube_job
    landing = c.get("/")
    assert landing.headers["content-type"] == "application/json"
    assert {"service-desc", "alternate"} <= {lk["rel"] for lk in landing.json()["links"]}
    for r in (c.get("/", headers={"Accept": "text/html,application/xhtml+xml,*/*;q=0.8"}),
              c.get("/?f=html")):
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert f'href="{url}/viewer"' in r.text and f'href="{url}/report"' in r.text
    assert c.get("/?f=json", headers={"Accept": "text/html"}).json()["title"] == "PolyDDA"
    status_links = {lk["href"] for lk in c.get(url).json()["links"]}
    result_links = {lk["href"] for lk in c.get(url + "/results").json()["links"]}
    assert {url + "/viewer", url + "/report"} <= status_links & result_links


def test_viewer_and_report_pages_use_only_local_assets(cube_job: Any) -> None:
    c, url, h5 = cube_job
    viewer = c.get(url + "/viewer")
    assert viewer.status_code == 200 and viewer.headers["content-type"].startswith("text/html")
    cfg = json.loads(re.search(r'id="viewer-config">([^<]*)</script>', viewer.text)[1])
    assert cfg["max_frames"] == 2000 and cfg["frames"] == url + "/results/frames"
    seven = c.get(url + "/viewer?max_frames=7").text
    cfg = json.loads(re.search(r'id="viewer-config">([^<]*)</script>', seven)[1])
    first = c.get(cfg["first"])  # what the page fetches before its scripts load
    assert first.status_code == 200 and decode_binary(first.content).header["count"] == 7
    bad = c.get(url + "/viewer?max_frames=1")
    assert bad.status_code == 422 and bad.headers["content-type"] == PROBLEM
    refs = re.findall(r'(?:src|href)="([^"]+)"', viewer.text) + re.findall(
        r'"(/static/[^"]+)"', viewer.text)
    assert "https://" not in viewer.text and "http://" not in viewer.text
    for ref in {r for r in refs if r.startswith("/static/") and not r.endswith("/")} | {
            "/static/three/three.core.min.js", "/static/three/OrbitControls.js",
            "/static/three/LICENSE"}:
        assert c.get(ref).status_code == 200, ref
    report = c.get(url + "/report")
    assert report.status_code == 200
    text = report.text
    scene_text = open_result(h5).scene_json
    assert scene_text is not None
    assert hashlib.sha256(scene_text.encode()).hexdigest() in text
    sections = [text.index(f">{s}") for s in ("Conclusion", "Blocks that moved", "Result",
                                                "Plots", "Warnings", "Appendix: the scene",
                                                "Versions")]
    assert sections == sorted(sections)  # the conclusion first, the scene in an appendix
    imgs = re.findall(r'<img src="([^"]+)"', text)
    linked = [i for i in imgs if not i.startswith("data:")]
    assert len(linked) >= 3 and all(c.get(i).status_code == 200 for i in linked)
    assert "cube" in text and "fixed" in text
    # the blocks at the last step: inline, drawn from the result file's last step (the
    # same PNG engine.results.plots draws from it; not the first step's) and not repeated in Plots
    snap = re.search(r"<figure id='snapshot-figure'><img src=\"data:image/png;base64,([^\"]+)\"",
                     text)
    assert snap is not None and "snapshot_final.png" not in text
    with open_result(h5) as r:
        last = plot_snapshot(r, -1, h5.with_name("test-last.png")).read_bytes()
        first = plot_snapshot(r, 0, h5.with_name("test-first.png")).read_bytes()
        assert f"step {int(r.steps[-1])}, t = {r.times[-1]:.4g} s" in text
    assert base64.b64decode(snap[1]) == last != first
    assert "Kinematic screening" in text and "the scene gives no slope_face and no joints" in text
    r = c.post("/jobs", json={**cube_scene(), "process": "block-cutting"})
    cut = wait_final(c, r.headers["Location"])
    assert c.get(r.headers["Location"] + "/viewer").status_code == 404
    assert c.get(r.headers["Location"] + "/report").status_code == 200, cut


def test_report_of_1000_blocks_without_a_summary(tmp_path: Path) -> None:
    """A 1,000-block, 100-step result with no summary (as a killed run leaves): the report
    still draws the blocks at the last step; its time to make (plots included) is
    printed."""
    job_id, h5 = synthetic_job(tmp_path / "data", n_blocks=1000, n_steps=100,
                               contacts=False)
    with make_client(tmp_path / "data") as c:
        t0 = time.perf_counter()
        r = c.get(f"/jobs/{job_id}/report")
        seconds = time.perf_counter() - t0
    print(f"report of 1,000 blocks x 100 steps (plots made): {seconds:.2f} s")
    assert r.status_code == 200
    assert "100 recorded steps; the run wrote no summary" in r.text
    assert "<figure id='snapshot-figure'><img src=\"data:image/png;base64," in r.text
    assert "step 990, t = 0.99 s" in r.text
    assert seconds < 20


def test_trend_and_plunge() -> None:
    assert trend_plunge([0, 0, 0]) is None
    assert trend_plunge([1, 0, 0]) == pytest.approx((90.0, 0.0))  # East, horizontal
    assert trend_plunge([0, -1, -1]) == pytest.approx((180.0, 45.0))  # South, down 45°
    assert trend_plunge([-1, 1, 0]) == pytest.approx((315.0, 0.0))


def test_report_of_a_factor_of_safety_job(tmp_path: Path) -> None:
    from service.jobs.store import JobStore

    settings = Settings(data_dir=tmp_path / "data")
    settings.data_dir.mkdir(parents=True)
    store = JobStore(settings.db_path)
    scene = {**cube_scene(), "name": "cube FoS"}
    job, _ = store.submit(process="factor-of-safety", scene=json.dumps(scene),
                          client="ip:testclient", quota=10)
    runs = [{"factor": 1.0, "failed": False, "mean_acceleration": 0.0, "status": "completed"},
            {"factor": 2.0, "failed": True, "mean_acceleration": 0.4, "status": "completed"},
            {"factor": 1.5, "failed": False, "mean_acceleration": 0.0, "status": "completed"}]
    settings.job_dir(job.id).mkdir(parents=True)
    (settings.job_dir(job.id) / "fos.json").write_text(json.dumps({
        "factor_of_safety": 1.625, "critical_friction_angle": 27.3, "runs": runs,
        "status": "completed", "message": "", "warnings": ["a warning of the build"]}))
    store.update(job.id, status="successful", progress=100.0, finished=time.time())
    with make_client(settings.data_dir) as c:
        r = c.get(f"/jobs/{job.id}/report")
        assert c.get(f"/jobs/{job.id}/viewer").status_code == 404  # no steps to view
    assert r.status_code == 200
    text = r.text
    assert "<b id='fs'>1.625</b>" in text and "cube FoS" in text
    assert "a warning of the build" in text and "Bisection history" in text
    assert text.count("<tr>") >= 4 and 'src="data:image/png;base64,' in text
    assert hashlib.sha256(json.dumps(scene).encode()).hexdigest() in text


def test_report_of_a_sweep_has_its_distribution_and_the_kinematics(tmp_path: Path) -> None:
    """A sweep job's report: PoF with its interval per method, the FS histogram and CDF as
    an inline figure; the wedge scene's kinematic screening (its slope face and J1/J2)
    with the stereonet inline."""
    from engine.analyses.sweep import SweepSpec
    from service.jobs.store import JobStore
    from service.sweep import run_sweep
    from tests.service_helpers import wedge_scene

    settings = Settings(data_dir=tmp_path / "data")
    settings.data_dir.mkdir(parents=True)
    store = JobStore(settings.db_path)
    scene = wedge_scene(2.0)
    job, _ = store.submit(process="sweep", scene=json.dumps(scene), client="ip:testclient",
                          quota=10)
    job_dir = settings.job_dir(job.id)
    doc = run_sweep(scene, SweepSpec(n=60, seed=7, friction_mean=25.0, friction_sd=5.0,
                                     mode="analytic"), job_dir)
    store.update(job.id, status="successful", progress=100.0, finished=time.time())
    with make_client(settings.data_dir) as c:
        t0 = time.perf_counter()
        r = c.get(f"/jobs/{job.id}/report")
        seconds = time.perf_counter() - t0
    print(f"sweep report (stereonet and FS figure made): {seconds:.2f} s")
    assert r.status_code == 200
    text = r.text
    a = doc["analytic"]
    assert 0 < a["failures"] < 60  # φ ~ N(25°, 5°) against the critical 20.89°
    lo, hi = a["pof_interval_95"]
    assert f"<td>{a['probability_of_failure']:.4g}</td>" in text
    assert f"{lo:.3g} – {hi:.3g}" in text and "Monte Carlo sweep" in text
    assert "<figure id='sweep-figure'><img src=\"data:image/png;base64," in text
    assert (job_dir / "report" / "sweep.png").is_file()
    # the kinematics of the wedge in its vertical face 90/180 (docs/validation.md)
    assert "Slope face 90/180" in text and "trend 172.59°, plunge 28.75°" in text
    assert "<tr><td>wedge sliding</td><td>none</td></tr>" in text
    assert "plunge 28.75° &lt; φ 40°" in text  # why the wedge cannot slide
    stereo = re.search(r"<figure id='stereonet'><img src=\"data:image/png;base64,([^\"]+)\"",
                       text)
    assert stereo is not None and base64.b64decode(stereo[1]).startswith(b"\x89PNG")


@pytest.mark.parametrize("turn", [0, 1, 2])
@pytest.mark.parametrize("reverse", [False, True])
def test_ear_clip_of_a_non_convex_face(turn: int, reverse: bool) -> None:
    """An L-shaped face (a fan from a corner would cover its notch) in each axis plane and
    both windings: triangles that tile it, wound like it."""
    from service.api.frames import ear_clip

    L = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]], float)
    P = np.roll(L[::-1] if reverse else L, 2, axis=0)[:, [(turn + i) % 3 for i in range(3)]]
    tris = np.array(ear_clip(P))
    assert len(tris) == 4
    normal = np.cross(P, np.roll(P, -1, axis=0)).sum(axis=0)
    t = np.cross(P[tris[:, 1]] - P[tris[:, 0]], P[tris[:, 2]] - P[tris[:, 0]])
    assert np.all(t @ normal > 0)  # same winding as the face
    assert np.linalg.norm(t, axis=1).sum() / 2 == pytest.approx(3.0)  # the L's area, once
    assert ear_clip(P[:4][[0, 1, 2]]) == [(0, 1, 2)]
