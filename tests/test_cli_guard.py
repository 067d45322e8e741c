"""What a newcomer meets first on the command line: big scenes refused at once, validation
that grows linearly with the blocks, warnings about scenes that are valid but odd, commands
that start without importing the engine, files written with the usual mode."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.bench_startup import cubes
from service.cli.main import main

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def write(tmp_path: Path, scene: dict, name: str = "scene.json") -> str:
    path = tmp_path / name
    path.write_text(json.dumps(scene))
    return str(path)


# --------------------------------------------------------------------------- size guard


@pytest.mark.parametrize("command", ["validate", "blocks", "run"])
def test_25001_explicit_blocks_are_refused_within_5_s(
        capsys: pytest.CaptureFixture[str], tmp_path: Path, command: str) -> None:
    """25,001 cubes (200,008 vertices) exceed the format's 20,000 blocks and 200,000
    vertices: every command that loads a scene refuses them before validating a block
    (it took over 600 s), in one line per limit, exit 2, nothing written. The 5 s are CPU
    time (about 0.5 s here: reading 7.6 MB of JSON); on a machine shared at a load of 10,
    the wall time is several times that."""
    path = write(tmp_path, cubes(25_001))
    extra = ["--out", str(tmp_path / "r.h5")] if command == "run" else []
    t0, cpu0 = time.monotonic(), time.process_time()
    code, out, err = run(capsys, command, path, *extra)
    assert time.process_time() - cpu0 < 5 and time.monotonic() - t0 < 60
    assert code == 2 and out == ""
    assert err.splitlines() == ["the scene has 200,008 vertices in all; the limit is 200,000",
                                "blocks: 25,001 blocks; the limit is 20,000"]
    assert not (tmp_path / "r.h5").exists()


def test_service_limits_on_request(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """`validate --service-limits` applies a server's POLYDDA_MAX_* limits (the API's own
    check, naming the setting); without the flag the format's limits only."""
    path = write(tmp_path, cubes(6))
    monkeypatch.setenv("POLYDDA_MAX_BLOCKS", "5")
    assert run(capsys, "validate", path)[:2] == (0, "ok: 6 blocks, 1 fixed\n")
    code, out, err = run(capsys, "validate", "--service-limits", path)
    assert code == 2 and out == ""
    assert err == "blocks: 6 blocks; this service accepts at most 5 (POLYDDA_MAX_BLOCKS)\n"
    code, out, _ = run(capsys, "validate", "--service-limits", "--json", path)
    assert code == 2 and json.loads(out)["problems"] == [
        {"loc": "blocks", "msg": "6 blocks; this service accepts at most 5 (POLYDDA_MAX_BLOCKS)"}]
    monkeypatch.setenv("POLYDDA_MAX_BLOCKS", "6")
    assert run(capsys, "validate", "--service-limits", path)[0] == 0


def test_validation_reads_each_explicit_block_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The reference checks name each block by its place (`blocks[k] ('name')`): the list of
    names is made once per scene, not once per block (that was O(n²): 12,001 blocks took
    85 s). Counted, not timed: the names listed in all stay 2 n for n blocks."""
    import schemas.scene as scene_module
    from schemas.convert import build_model

    listed = [0]
    raw_names = scene_module._raw_names

    def counting(items: list) -> list:
        listed[0] += len(items)
        return raw_names(items)

    monkeypatch.setattr(scene_module, "_raw_names", counting)
    for n in (10, 400):
        listed[0] = 0
        assert len(build_model(cubes(n)).model.blocks) == n
        assert listed[0] <= 2 * n


# --------------------------------------------------------------------------- warnings


def incline(friction_angle: float = 20.0, slab_fixed: bool = True) -> dict:
    scene = json.loads((EXAMPLES / "incline.json").read_text())
    scene["joint_materials"]["joint"]["friction_angle"] = friction_angle
    scene["blocks"][1]["fixed"] = slab_fixed
    return scene


def test_a_friction_angle_that_reads_as_tan_phi_is_a_warning(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """φ = 0.66 is valid (0 to 90°) but is tan 33.4°: validate says ok, with a warning naming
    the field and the angle it may have meant (atan 0.66 = 33.42°); φ = 0 (frictionless, on
    purpose) and φ = 1.5° do not warn."""
    code, out, err = run(capsys, "validate", write(tmp_path, incline(0.66)))
    assert code == 0 and out == "ok: 2 blocks, 1 fixed (1 warning)\n"
    assert err == ("warning: joint_materials.joint.friction_angle: 0.66° is a very low "
                   "friction angle; if 0.66 is tan φ, the angle is 33.4° (friction angles are "
                   "in degrees)\n")
    code, out, _ = run(capsys, "validate", "--json", write(tmp_path, incline(0.66)))
    assert json.loads(out)["warnings"] == [err.removeprefix("warning: ").strip()]
    for phi in (0.0, 1.5, 35.0):
        code, out, err = run(capsys, "validate", write(tmp_path, incline(phi)))
        assert (code, out, err) == (0, "ok: 2 blocks, 1 fixed\n", ""), phi


def test_a_scene_with_nothing_fixed_is_a_warning(capsys: pytest.CaptureFixture[str],
                                                 tmp_path: Path) -> None:
    """No fixed block and no fixed point: everything falls; a fixed point is enough."""
    scene = incline(slab_fixed=False)
    code, out, err = run(capsys, "validate", write(tmp_path, scene))
    assert code == 0 and out == "ok: 2 blocks, 0 fixed (1 warning)\n"
    assert err.startswith("warning: nothing is fixed (no fixed block, no fixed point)")
    scene["boundary"] = {"fixed_points": [{"block": "slab", "point": [-1.366025, -1.0,
                                                                      -0.366025]}]}
    assert run(capsys, "validate", write(tmp_path, scene)) == (0, "ok: 2 blocks, 0 fixed\n", "")


def test_the_run_summary_carries_the_warnings(capsys: pytest.CaptureFixture[str],
                                              tmp_path: Path) -> None:
    """The build's warnings reach the run's JSON summary (and the --json document)."""
    scene = incline(0.66)
    scene["analysis"].update(duration=0.002)
    code, out, _ = run(capsys, "run", write(tmp_path, scene), "--out", str(tmp_path / "r.h5"),
                       "--json")
    assert code == 0
    assert any("friction_angle: 0.66°" in w for w in json.loads(out)["warnings"])


# --------------------------------------------------------------------------- files


def test_the_summary_file_has_the_mode_of_the_result(capsys: pytest.CaptureFixture[str],
                                                     tmp_path: Path) -> None:
    """The JSON summary is written 0644 under umask 022, as the HDF5 result (it was 0600:
    mkstemp's mode survived the rename)."""
    scene = json.loads((EXAMPLES / "free_fall.json").read_text())
    scene["analysis"].update(duration=0.002)
    old = os.umask(0o022)
    try:
        code, _, err = run(capsys, "run", write(tmp_path, scene), "--out",
                           str(tmp_path / "r.h5"), "--summary", str(tmp_path / "s.json"))
    finally:
        os.umask(old)
    assert code == 0, err
    assert (tmp_path / "s.json").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "r.h5").stat().st_mode & 0o777 == 0o644


# --------------------------------------------------------------------------- start-up


def imported_by(*argv: str) -> set[str]:
    """The heavy packages a fresh interpreter has imported after `polydda ARGV`."""
    heavy = ("numpy", "scipy", "numba", "pydantic", "h5py", "matplotlib", "fastapi")
    code = ("import contextlib, io, sys\n"
            "from service.cli.main import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    main({list(argv)!r})\n"
            f"print(' '.join(m for m in {heavy!r} if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, timeout=120, check=True)
    return set(done.stdout.split())


def test_commands_import_only_what_they_use() -> None:
    """`--version` and `--help` import none of numpy, pydantic, the engine; `schema` and the
    validation of explicit blocks not numba (its kernels, even cached, take a second to
    load and a minute to compile on a fresh machine), scipy, h5py or matplotlib. Times are
    in benchmarks/bench_startup.py; this pins the imports that make them."""
    assert imported_by("--version") == set()
    assert imported_by("--help") == set()
    assert imported_by("schema") == {"numpy", "pydantic"}
    assert imported_by("validate", str(EXAMPLES / "stack.json")) == {"numpy", "pydantic"}


def test_the_help_states_the_documents_search_distance() -> None:
    """The parser writes the contacts' default search distance out (it imports no numpy);
    it must be service.documents' value."""
    from service.cli.main import SEARCH_DISTANCE_HELP
    from service.documents import SEARCH_DISTANCE_RATIO

    assert f"default {SEARCH_DISTANCE_RATIO:g} x model size" in SEARCH_DISTANCE_HELP


def test_the_warnings_reach_a_service_job_and_its_report(tmp_path: Path) -> None:
    """The same build runs for the service: a job of a scene with φ = 0.66° carries the
    warning in its summary, and its report's conclusion names it."""
    from tests.service_helpers import cube_scene, make_client, wait_final

    scene = cube_scene(duration=0.01)
    scene["joint_materials"] = {"joint": {"friction_angle": 0.66}}
    with make_client(tmp_path / "data") as c:
        r = c.post("/jobs", json=scene)
        assert r.status_code == 201, r.text
        url = r.headers["Location"]
        assert wait_final(c, url, timeout=120)["status"] == "successful"
        summary = c.get(url + "/results/summary.json").json()
        report = c.get(url + "/report").text
    warning = ("joint_materials.joint.friction_angle: 0.66° is a very low friction angle; if "
               "0.66 is tan φ, the angle is 33.4° (friction angles are in degrees)")
    assert warning in summary["warnings"]
    conclusion = report.split("id='conclusion'>", 1)[1].split("<h2", 1)[0]
    assert "<b>1 warning</b>: " + warning.replace("'", "&#x27;") in conclusion
