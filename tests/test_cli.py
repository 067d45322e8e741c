"""`polydda` CLI, run in-process: blocks, contacts, schema, validate, exit codes."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from engine.geometry.polyhedron import dip_normal
from service.cli.main import main
from tests.test_results import vtk_step

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
WEDGE = str(EXAMPLES / "wedge.json")


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def write_scene(tmp_path: Path, scene: dict | str) -> str:
    path = tmp_path / "scene.json"
    path.write_text(scene if isinstance(scene, str) else json.dumps(scene))
    return str(path)


def test_blocks_text(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "blocks", WEDGE)
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert lines[0] == "2 blocks"
    assert lines[1].split() == ["name", "volume", "(m³)", "shape", "fixed", "centroid", "x,",
                                "y,", "z", "(m)"]
    assert lines[2].split() == ["B1", "2770.23", "concave", "yes", "-0.006,", "3.056,", "4.957"]
    # the wedge's centroid is the mean of its 4 vertices (a tetrahedron)
    assert lines[3].split() == ["B2", "29.7708", "convex", "no", "0.601,", "-2.250,", "9.032"]
    assert lines[-1] == "total volume: 2800 m³"


def test_blocks_json(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "blocks", WEDGE, "--json")
    assert code == 0
    doc = json.loads(out)
    assert list(doc) == ["blocks", "count", "total_volume", "warnings"]  # as the API's
    blocks = doc["blocks"]
    assert [b["name"] for b in blocks] == ["B1", "B2"]
    for b in blocks:
        assert set(b) == {"name", "volume", "centroid", "concave", "fixed", "vertices", "faces"}
        assert all(0 <= i < len(b["vertices"]) for f in b["faces"] for i in f)
    wedge = blocks[1]
    assert wedge["volume"] == pytest.approx(29.7708, abs=1e-4)
    assert (wedge["concave"], wedge["fixed"]) == (False, False)
    assert (blocks[0]["concave"], blocks[0]["fixed"]) == (True, True)
    assert len(wedge["vertices"]) == 4 and len(wedge["faces"]) == 4
    assert sum(b["volume"] for b in blocks) == pytest.approx(2800.0, rel=1e-12)


def test_bad_scene_exits_2_with_one_problem_per_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, box_block: Callable
) -> None:
    block = box_block("wedge", [0, 0, 0], [1, 1, 1])
    del block["faces"][0]
    scene = {"materials": {"rock": {"density": -5}}, "blocks": [block]}
    code, out, err = run(capsys, "blocks", write_scene(tmp_path, scene))
    assert code == 2 and out == ""
    assert err.splitlines() == ["materials.rock.density: must be positive, got -5"]
    scene["materials"]["rock"]["density"] = 2600
    code, out, err = run(capsys, "blocks", write_scene(tmp_path, scene), "--json")
    assert code == 2 and out == ""
    lines = err.splitlines()
    assert lines and all(ln.startswith("blocks[0] ('wedge').faces: faces are not closed")
                         for ln in lines)
    assert "Traceback" not in err


def test_malformed_json_and_missing_file(capsys: pytest.CaptureFixture[str],
                                         tmp_path: Path) -> None:
    path = write_scene(tmp_path, '{"blocks": [1,]}')
    code, _, err = run(capsys, "blocks", path)
    assert code == 2 and err.startswith(f"{path}: not valid JSON: ") and "line 1 column" in err
    code, _, err = run(capsys, "validate", str(tmp_path / "missing.json"))
    assert code == 2 and err.strip().endswith("missing.json: file not found")


def test_export_obj_and_vtk(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    obj = tmp_path / "wedge.obj"
    code, out, _ = run(capsys, "blocks", WEDGE, "--export", str(obj))
    assert code == 0 and f"written: {obj}" in out
    text = obj.read_text().splitlines()
    assert [ln for ln in text if ln.startswith("o ")] == ["o B1", "o B2"]
    nv = sum(ln.startswith("v ") for ln in text)
    faces = [[int(i) for i in ln.split()[1:]] for ln in text if ln.startswith("f ")]
    assert min(min(f) for f in faces) == 1 and max(max(f) for f in faces) == nv
    vtk = tmp_path / "wedge.vtk"
    assert run(capsys, "blocks", WEDGE, "--export", str(vtk))[0] == 0
    lines = vtk.read_text().splitlines()
    assert lines[0] == "# vtk DataFile Version 3.0" and lines[3] == "DATASET POLYDATA"
    npts = int(lines[4].split()[1])
    assert npts == nv
    polys = next(ln for ln in lines if ln.startswith("POLYGONS")).split()
    assert int(polys[1]) == len(faces)
    code, _, err = run(capsys, "blocks", WEDGE, "--export", str(tmp_path / "wedge.stl"))
    assert code == 2 and "unknown file type '.stl'" in err


def test_contacts_of_the_wedge(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "contacts", WEDGE, "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["search_distance"] == pytest.approx(1e-3 * 20.0)
    rows = doc["contacts"]
    assert doc["count"] == len(rows) == 6  # paper Table 4: six constraints, four positions
    keys = {"block_i", "block_j", "type", "point_i", "point_j", "normal", "tangent", "mode",
            "penetration", "gap", "joint"}
    n1, n2 = dip_normal(50, 110), dip_normal(55, 240)
    for c in rows:
        assert set(c) == keys
        assert {c["block_i"], c["block_j"]} == {"B1", "B2"}
        assert c["penetration"] == max(0.0, -c["gap"]) and abs(c["gap"]) < 1e-6
        n = np.array(c["normal"])
        assert min(np.linalg.norm(np.cross(n, n1)), np.linalg.norm(np.cross(n, n2))) < 1e-6
    points = {tuple(np.round(c["point_i"], 2)) for c in rows}
    assert points == {(0.0, 3.0, 10.0), (-2.55, -4.0, 10.0), (0.91, -4.0, 6.13),
                      (4.04, -4.0, 10.0)}


def test_contacts_text_and_search_distance(capsys: pytest.CaptureFixture[str]) -> None:
    stack = str(EXAMPLES / "stack.json")
    code, out, _ = run(capsys, "contacts", stack, "--search-distance", "0.01")
    assert code == 0 and "search distance 10.0 mm" in out.splitlines()[0]
    assert "gap=0 µm" in out.splitlines()[1]
    code, out, _ = run(capsys, "contacts", stack, "--json")
    pairs = {frozenset((c["block_i"], c["block_j"])) for c in json.loads(out)["contacts"]}
    assert pairs == {frozenset(p) for p in [("top", "middle"), ("middle", "bottom"),
                                           ("bottom", "base")]}
    code, _, err = run(capsys, "contacts", stack, "--search-distance", "-1")
    assert code == 2 and "--search-distance: must be positive" in err


def test_schema_and_validate(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "schema")
    assert code == 0
    schema = json.loads(out)
    assert schema["title"] == "PolyDDA scene" and "blocks" in schema["properties"]
    code, out, _ = run(capsys, "validate", str(EXAMPLES / "toppling.json"))
    assert code == 0 and out.strip() == "ok: 7 blocks, 1 fixed"


def test_usage_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert run(capsys, "--help")[0] == 0
    code, _, err = run(capsys)
    assert code == 2 and "usage: polydda" in err
    code, _, err = run(capsys, "blocks")
    assert code == 2 and "scene" in err


def test_worker_options_and_help(capsys: pytest.CaptureFixture[str]) -> None:
    """`polydda worker` takes the options of service.jobs.worker (running one: test_service_rq)."""
    code, out, _ = run(capsys, "worker", "--help")
    assert code == 0 and out.startswith("usage: polydda worker")
    for option in ("--redis-url", "--queue", "--data-dir", "--name", "--burst", "--max-jobs",
                   "--log-level"):
        assert option in out
    code, _, err = run(capsys, "worker", "--redis-url", "redis://x:6379/0", "--bogus")
    assert code == 2 and "unrecognized arguments: --bogus" in err
    code, _, err = run(capsys, "worker", "--max-jobs", "0")
    assert code == 2 and "--max-jobs: must be at least 1, got 0" in err
    code, _, err = run(capsys, "worker", "--log-level", "chatty")
    assert code == 2 and "--log-level" in err
    from service.cli.main import build_parser
    from service.jobs.worker import argv_of
    from service.jobs.worker import build_parser as worker_parser

    argv = ["worker", "--redis-url", "redis://h:6379/1", "--queue", "q", "--data-dir", "/d",
            "--name", "w", "--burst", "--max-jobs", "3", "--log-level", "debug"]
    args = build_parser().parse_args(argv)
    assert (args.redis_url, args.queue, args.data_dir, args.name, args.burst, args.max_jobs,
            args.log_level) == ("redis://h:6379/1", "q", "/d", "w", True, 3, "DEBUG")
    again = worker_parser().parse_args(argv_of(args))  # what the worker re-executes with
    assert {k: v for k, v in vars(args).items() if k in vars(again)} == vars(again)


def test_joint_sets_cutting_millions_of_blocks_are_refused_at_once(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [100, 100, 100]}},
             "joints": [{"dip": dip, "dip_direction": ddir, "point": [0, 0, 0], "spacing": 0.6}
                        for dip, ddir in [(0, 0), (90, 0), (90, 90)]]}
    path = write_scene(tmp_path, scene)
    t0 = time.monotonic()
    code, out, err = run(capsys, "validate", path)
    assert time.monotonic() - t0 < 2
    assert code == 2 and out == ""
    assert err.splitlines() == ["joints: the joints would cut the domain into about 4.71 "
                                "million blocks; the limit is 20,000 (increase the spacings)"]
    scene["joints"][0]["spacing"] = 25.0  # 5 x 167.7 x 167.7 cells: still too many
    code, _, err = run(capsys, "blocks", write_scene(tmp_path, scene))
    assert code == 2 and "about 141,000 blocks" in err


def test_run_writes_result_summary_and_vtkhdf(capsys: pytest.CaptureFixture[str],
                                              tmp_path: Path) -> None:
    """`polydda run` on the wedge (φ = 0 so it moves): summary fields, result file readable by
    our reader and by VTK's vtkHDFReader with the wedge's moved points at the last step."""
    scene = json.loads(Path(WEDGE).read_text())
    scene["joint_materials"]["joint"]["friction_angle"] = 0
    scene["analysis"].update(duration=0.1, record_interval=10)
    out, summ = tmp_path / "wedge.h5", tmp_path / "summary.json"
    code, _, err = run(capsys, "run", write_scene(tmp_path, scene), "--out", str(out),
                       "--summary", str(summ))
    assert code == 0, err
    doc = json.loads(summ.read_text())
    assert doc["status"] == "completed" and doc["steps"] == 100
    assert doc["simulated_time"] == pytest.approx(0.1)
    assert {"wall_time", "max_penetration", "blocks"} <= set(doc)
    wedge = next(b for b in doc["blocks"] if b["name"] == "B2")
    assert set(wedge) >= {"name", "centroid", "rotation", "displacement", "velocity"}
    # ½ a t² along the line of intersection at a = g sin ψ (docs/validation.md)
    assert np.linalg.norm(wedge["displacement"]) == pytest.approx(0.5 * 4.718485 * 0.01,
                                                                  rel=0.02)

    from engine.results.reader import open_result

    with open_result(out) as res:
        assert res.status == "completed"
        assert res.n_steps == 11  # step 0 and every 10th step
        last = res.vertices(res.n_steps - 1)[1]
        first = res.vertices(0)[1]
        # a translation (the wedge's rotation is ~1e-6 rad)
        np.testing.assert_allclose(last - first, np.broadcast_to(wedge["displacement"],
                                                                 last.shape), atol=1e-5)

    reader, data = vtk_step(out, 10)
    from vtk.util.numpy_support import vtk_to_numpy

    assert reader.GetNumberOfSteps() == 11

    pts = vtk_to_numpy(data.GetPoints().GetData())
    ids = vtk_to_numpy(data.GetPointData().GetArray("block_id"))
    np.testing.assert_allclose(np.sort(pts[ids == 1], axis=0), np.sort(last, axis=0),
                               atol=1e-9)


def test_run_of_a_bad_scene_exits_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = run(capsys, "run", write_scene(tmp_path, "{not json"), "--out",
                       str(tmp_path / "x.h5"))
    assert code == 2 and "Traceback" not in err
    assert not (tmp_path / "x.h5").exists()


def test_plot_of_a_missing_or_foreign_file_says_so_in_one_line(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """`polydda plot` of a file that is not there, or is a scene, or is not a result (exit 2,
    like any other bad input): one line that says what it is, not h5py's message."""
    code, out, err = run(capsys, "plot", str(tmp_path / "nope.h5"), "--out", str(tmp_path))
    assert code == 2 and err.strip() == f"polydda plot: no such result file: {tmp_path}/nope.h5"
    foreign = tmp_path / "scene.h5"
    foreign.write_text("{}")
    code, out, err = run(capsys, "plot", str(foreign), "--out", str(tmp_path))
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"{foreign} is a scene, not a result: run it first" in err
    code, out, err = run(capsys, "plot", WEDGE)
    assert code == 2 and f"polydda run {WEDGE} --out RESULT.h5" in err
    foreign.write_bytes(b"PK\x03\x04 a zip")
    code, out, err = run(capsys, "plot", str(foreign))
    assert code == 2 and err == f"polydda plot: {foreign} is not a PolyDDA result (the HDF5 " \
                                "file that polydda run --out writes)\n"
    import h5py

    with h5py.File(foreign, "w") as f:
        f["x"] = [1.0]
    code, out, err = run(capsys, "plot", str(foreign))
    assert code == 2 and err == f"polydda plot: {foreign} is an HDF5 file but not a PolyDDA " \
                                "result\n"
    assert "signature" not in err and "Traceback" not in err


def test_plot_chooses_blocks_and_snapshot_times(capsys: pytest.CaptureFixture[str],
                                                tmp_path: Path) -> None:
    """`polydda plot`: default plots; --blocks (names) for the histories; --time / --step
    for the 3-D snapshots; unknown names, times and steps exit 2."""
    from tests.test_results import write_run

    result = tmp_path / "run.h5"
    write_run(result, n_steps=12)  # blocks base (fixed) and cube; steps 0, 10, ... 110
    code, out, err = run(capsys, "plot", str(result), "--out", str(tmp_path / "default"))
    assert code == 0, err
    assert [Path(p).name for p in out.split()] == [
        "histories.png", "energy.png", "displacements.png", "snapshot_initial.png",
        "snapshot_final.png"]
    code, out, err = run(capsys, "plot", str(result), "--out", str(tmp_path / "chosen"),
                         "--blocks", "base,cube", "--time", "0.31", "--step", "50",
                         "--step", "110,30")
    assert code == 0, err
    paths = [Path(p) for p in out.split()]
    assert [p.name for p in paths] == ["histories.png", "energy.png", "displacements.png",
                                       "snapshot_step30.png", "snapshot_step50.png",
                                       "snapshot_step110.png"]
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in paths)
    # the default histories show the free block only; base and cube is another plot
    assert paths[0].read_bytes() != (tmp_path / "default" / "histories.png").read_bytes()
    # step 110 is the last one: the same picture as the default final snapshot
    assert paths[5].read_bytes() == (tmp_path / "default" / "snapshot_final.png").read_bytes()

    for args, message in [(["--blocks", "cube,rock"], "no block named 'rock' (blocks: base, cube)"),
                          (["--time", "5"], "time 5 s is outside the recorded times (0 to 1.1 s)"),
                          (["--step", "15"], "step 15 was not recorded"),
                          (["--time", "soon"], "not a number")]:
        code, out, err = run(capsys, "plot", str(result), "--out", str(tmp_path / "bad"), *args)
        assert code == 2 and out == "" and message in err, (args, err)
    assert not (tmp_path / "bad").exists()
    code, _, err = run(capsys, "plot", str(tmp_path / "missing.h5"))
    # one line that says what is wrong, not the HDF5 library's message
    assert code == 2 and err == f"polydda plot: no such result file: {tmp_path / 'missing.h5'}\n"


def test_run_says_when_it_compiles_the_kernels(capsys: pytest.CaptureFixture[str],
                                               tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """On a machine whose numba cache is empty, `polydda run` says why its first step
    takes a minute; with the kernels cached it says nothing of it."""
    import engine

    monkeypatch.setenv("POLYDDA_WARM_UP", "0")  # no parallel compilation (tests/test_warmup)
    scene = EXAMPLES / "free_fall.json"
    for cached, expected in ((False, True), (True, False)):
        monkeypatch.setattr(engine, "kernels_cached", lambda c=cached: c)
        code, _, err = run(capsys, "run", str(scene), "--out", str(tmp_path / "r.h5"))
        assert code == 0, err
        assert ("compiling the engine's numerical kernels" in err) is expected


def test_kernels_cached_looks_for_numbas_index_files(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The check finds numba's index file of the narrow phase in the cache folder of the
    current kernel sources (or under NUMBA_CACHE_DIR), and nothing in an empty place or in
    the folder of other sources."""
    import engine

    here = tmp_path / "engine"
    here.mkdir()
    (here / "_motion_kernels.py").write_text("x = 1\n")
    monkeypatch.setattr(engine, "__file__", str(here / "__init__.py"))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert not engine.kernels_cached()
    cache = engine.kernel_cache_dir() / "engine"
    cache.mkdir(parents=True)
    (cache / "_detection_kernels.narrow_phase-493.py311.nbi").write_bytes(b"")
    assert engine.kernels_cached()
    (here / "_motion_kernels.py").write_text("x = 2\n")  # a kernel changed: compile again
    assert not engine.kernels_cached()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    shutil.copytree(cache, tmp_path / "cache" / "engine")
    assert engine.kernels_cached()


def test_version_and_json_documents(capsys: pytest.CaptureFixture[str],
                                    tmp_path: Path) -> None:
    """`--version`; `validate --json` and `run --json` print one document (problems too)."""
    code, out, _ = run(capsys, "--version")
    assert code == 0 and out.strip() == "polydda 0.1.0"
    code, out, err = run(capsys, "validate", WEDGE, "--json")
    assert code == 0 and err == ""
    assert json.loads(out) == {"valid": True, "blocks": 2, "fixed": 1, "warnings": [],
                               "problems": []}
    scene = json.loads(Path(WEDGE).read_text())
    scene["joint_materials"]["joint"]["friction_angle"] = 95
    code, out, err = run(capsys, "validate", write_scene(tmp_path, scene), "--json")
    doc = json.loads(out)
    assert code == 2 and doc["valid"] is False and err == ""
    assert doc["problems"][0]["loc"] == "joint_materials.joint.friction_angle"
    incline = json.loads((Path(WEDGE).parent / "incline.json").read_text())
    incline["analysis"].update(duration=0.05, time_step=0.01)
    out_h5 = tmp_path / "incline.h5"
    code, out, err = run(capsys, "run", write_scene(tmp_path, incline), "--out", str(out_h5),
                         "--json")
    doc = json.loads(out)
    assert code == 0 and doc["status"] == "completed" and doc["result"] == str(out_h5)
    assert doc["block_names"] == ["cube", "slab"] and doc["warnings"] == []
    assert "step" not in err  # no progress lines with --json


def test_submit_to_an_absent_server_says_so_in_one_line(capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code, out, err = run(capsys, "submit", WEDGE, "--url", f"http://127.0.0.1:{port}")
    assert code == 1 and out == ""
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith(f"polydda submit: cannot reach the PolyDDA server at "
                          f"http://127.0.0.1:{port}")
    code, _, err = run(capsys, "submit", "no-such-scene.json")
    assert code == 2 and err == "polydda submit: no such scene file: no-such-scene.json\n"
