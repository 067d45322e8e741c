"""The scene builder's API (service.api.builder): the page, live validation with the
messages of POST /jobs, the bounded preview (its block count is `polydda blocks`', its
verdicts block theory's; the size guard and the time limit refuse with 422 naming why),
measured orientations fitted into sets, a GeoTIFF as a terrain grid."""

from __future__ import annotations

import base64
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from schemas.convert import build_model
from tests.service_helpers import make_client

ROOT = Path(__file__).resolve().parents[1]


def slope_scene(height: float = 20.0, angle: float = 70.0, spacing: float = 4.0) -> dict:
    """What the builder makes of a bench table (one bench), Fix ground and three sets."""
    run = height / math.tan(math.radians(angle))
    return {"name": "slope", "domain": {"slope": {
        "profile": [[0, 0], [5, 0], [5 + run, height], [20 + run, height]],
        "dip_direction": 180, "width": 20, "base": -5}},
        "joints": [{"name": "ground", "dip": 0, "dip_direction": 0, "point": [0, 0, 0]},
                   {"dip": 35, "dip_direction": 180, "point": [0, 0, 0], "spacing": spacing},
                   {"dip": 80, "dip_direction": 0, "point": [0, 0, 0], "spacing": spacing},
                   {"dip": 85, "dip_direction": 90, "point": [0, 0, 0], "spacing": spacing}],
        "boundary": {"fixed_blocks": [{"centroid_in": {"min": [-1e6, -1e6, -1e6],
                                                       "max": [1e6, 1e6, 0]}}]},
        "analysis": {"duration": 0.02, "time_step": 0.002}}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Any:
    with make_client(tmp_path_factory.mktemp("builder") / "data") as c:
        yield c


def test_page_and_schema(client: Any) -> None:
    r = client.get("/builder")
    assert r.status_code == 200 and "builder.js" in r.text
    assert "script-src 'self'" in r.headers["content-security-policy"]
    assert client.get("/builder/schema").json()["title"] == "PolyDDA scene"


def test_validate_names_the_fields_as_post_jobs_does(client: Any) -> None:
    ok = client.post("/builder/validate", json=slope_scene())
    assert ok.status_code == 200 and ok.json()["estimated_blocks"] > 100
    bad = slope_scene()
    bad["joints"][1]["dip"] = 95
    bad["analysis"]["time_step"] = -1
    r = client.post("/builder/validate", json=bad)
    jobs = client.post("/jobs", json=bad)
    assert r.status_code == jobs.status_code == 422
    assert r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["errors"] == jobs.json()["errors"]
    assert {e["loc"] for e in r.json()["errors"]} == {"joints[1].dip", "analysis.time_step"}


def test_preview_cuts_what_polydda_blocks_cuts(client: Any) -> None:
    scene = slope_scene()
    r = client.post("/builder/preview", json=scene)
    assert r.status_code == 200, r.text
    doc = r.json()
    built = build_model(scene)
    assert doc["count"] == len(built.model.blocks) == len(doc["blocks"])
    assert [b["name"] for b in doc["blocks"]] == built.block_names
    assert [b["fixed"] for b in doc["blocks"]] == [b.fixed for b in built.model.blocks]
    # the mesh: every block has triangles, every vertex index is in range
    mesh = {k: np.frombuffer(base64.b64decode(v["data"]), dtype=np.dtype(v["dtype"]))
            for k, v in doc["mesh"].items()}
    assert set(mesh["triangle_block"].tolist()) == set(range(doc["count"]))
    assert mesh["triangles"].max() < len(mesh["vertices"]) // 3
    assert len(mesh["vertex_offsets"]) == doc["count"] + 1
    verdicts = {b["verdict"] for b in doc["blocks"]}
    assert {"fixed", "interior", "key block"} <= verdicts <= set(doc["verdicts"])
    # a key block slides with FS < 1: its mode is a sliding mode, fixed blocks are fixed
    for b in doc["blocks"]:
        if b["verdict"] == "key block":
            assert b["mode"].startswith(("sliding", "falling"))
            assert b["factor_of_safety"] is not None and b["factor_of_safety"] < 1
        if b["fixed"]:
            assert b["verdict"] == b["mode"] == "fixed"


def test_preview_of_an_excavation_marks_its_rock(client: Any) -> None:
    scene = json.loads((ROOT / "examples" / "tunnel_staged.json").read_text())
    doc = client.post("/builder/preview", json=scene).json()
    built = build_model(scene)
    dug = [b["excavation"] is not None for b in doc["blocks"]]
    assert dug == [o is not None for o in built.excavated]
    assert {b["verdict"] for b, d in zip(doc["blocks"], dug, strict=True) if d} == {"excavated"}
    assert any(b["verdict"] in ("key block", "potential key block", "not removable")
               for b in doc["blocks"])


def test_preview_is_bounded(tmp_path: Path) -> None:
    """The service's size guard before anything is cut; the preview's time limit while it
    cuts (the checking process is killed and a new one takes its place)."""
    with make_client(tmp_path / "a", max_blocks=50) as c:
        r = c.post("/builder/preview", json=slope_scene())
        assert r.status_code == 422 and "POLYDDA_MAX_BLOCKS" in r.text
    with make_client(tmp_path / "b", preview_timeout=0.05) as c:
        r = c.post("/builder/preview", json=slope_scene(spacing=3.0))
        assert r.status_code == 422, r.text
        assert "POLYDDA_PREVIEW_TIMEOUT" in r.json()["errors"][0]["msg"]
    with make_client(tmp_path / "c") as c:
        r = c.post("/builder/preview", content=b"{not json", headers={
            "content-type": "application/json"})
        assert r.status_code == 422


def test_measurements_are_fitted_into_sets(client: Any) -> None:
    from engine.analyses.jointstats import fisher_orientations

    rows = ["dip,dip_direction"]
    for dip, ddir, seed in ((60, 135, 1), (85, 240, 2)):
        d, a = fisher_orientations(dip, ddir, 40, 200, seed)
        rows += [f"{x:.2f},{y:.2f}" for x, y in zip(d, a, strict=True)]
    r = client.post("/builder/stereonet", json={"csv": "\n".join(rows), "sets": 2})
    assert r.status_code == 200, r.text
    doc = r.json()
    got = sorted((round(s["dip"]), round(s["dip_direction"])) for s in doc["sets"])
    assert abs(got[0][0] - 60) <= 3 and abs(got[0][1] - 135) <= 4
    assert abs(got[1][0] - 85) <= 3 and abs((got[1][1] - 240 + 180) % 360 - 180) <= 4
    assert doc["stereonet"].startswith("data:image/png;base64,")
    bad = client.post("/builder/stereonet", json={"csv": "dip,dip_direction\n95,10\n",
                                                   "sets": 1})
    assert bad.status_code == 422 and "line 2" in bad.json()["errors"][0]["msg"]


def test_geotiff_becomes_a_terrain_grid(client: Any) -> None:
    """A GeoTIFF (5 m pixels, top-left corner at (1000, 2040)) as the inline grid: nodes
    at the pixels' centres, rows south to north, no-data cells gaps; the terrain scene it
    makes is valid."""
    tifffile = pytest.importorskip("tifffile")
    z = np.add.outer(np.arange(8, 0, -1) * 2.0, np.arange(10) * 0.5)  # rises to the north
    z[0, 0] = -9999.0
    buf = io.BytesIO()
    tifffile.imwrite(buf, z.astype(np.float32), extratags=[
        (33550, "d", 3, (5.0, 5.0, 0.0)),
        (33922, "d", 6, (0.0, 0.0, 0.0, 1000.0, 2040.0, 0.0)),
        (42113, "s", 0, "-9999", False)])
    r = client.post("/builder/terrain", content=buf.getvalue(),
                    headers={"content-type": "application/octet-stream"})
    assert r.status_code == 200, r.text
    grid = r.json()["grid"]
    assert (grid["x0"], grid["dx"], grid["dy"]) == (1002.5, 5.0, 5.0)
    assert grid["y0"] == 2040.0 - 2.5 - 7 * 5.0
    assert grid["elevations"][0][0] == 2.0 and grid["elevations"][-1][1] == 16.5
    assert grid["elevations"][-1][0] is None  # the no-data cell (north-west corner)
    scene = {"domain": {"terrain": {"grid": grid, "base": -5}},
             "boundary": {"fixed_points": []}}
    assert client.post("/builder/validate", json=scene).status_code == 200
    junk = client.post("/builder/terrain", content=b"not a tiff",
                       headers={"content-type": "application/octet-stream"})
    assert junk.status_code == 422 and "GeoTIFF" in junk.json()["detail"]


def test_polydda_view_serves_the_builder(tmp_path: Path) -> None:
    """`polydda view RESULT.h5`'s app has the builder too (it previews and downloads; no
    jobs to run); `polydda view` without a result is the service itself on a temporary
    folder, opened at the builder."""
    import polydda
    from service.api.local import local_app
    from service.cli.main import build_parser
    from service.cli.results import _builder_service
    from tests.service_helpers import TestClient

    scene = polydda.Scene.load(ROOT / "examples" / "wedge.json")
    scene["analysis"]["duration"] = 0.01
    polydda.run(scene, out=tmp_path / "w.h5", progress=False).close()
    with TestClient(local_app(tmp_path / "w.h5")) as c:
        page = c.get("/builder")
        assert page.status_code == 200 and "polydda run" in page.text  # no job service
        assert c.post("/builder/validate", json=scene.data).status_code == 200
        doc = c.post("/builder/preview", json=scene.data).json()
        assert doc["count"] == 2
    assert build_parser().parse_args(["view"]).result is None
    app, path, work = _builder_service("127.0.0.1")
    try:
        with TestClient(app) as c:
            assert path == "/builder" and "id='run'" in c.get(path).text
    finally:
        import shutil

        shutil.rmtree(work, ignore_errors=True)
