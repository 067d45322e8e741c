"""Bad input on the command line: every subcommand that reads a file, given a missing file,
a file that is not JSON (not CSV, not HDF5), a file of the wrong schema or a missing result
or checkpoint, exits 2 with one message that names the file (the field, for a scene of the
wrong schema) and no traceback (issue 41)."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import pytest

from service.cli.main import main
from tests.excavation_scenes import roof_wedge_scene

ROOT = Path(__file__).resolve().parent.parent
WEDGE = str(ROOT / "examples" / "wedge.json")

#: the subcommands that read a scene, with the options each needs besides it
SCENE_COMMANDS: dict[str, list[str]] = {
    "blocks": [], "contacts": [], "validate": [], "run": ["--out", "{tmp}/r.h5"],
    "fos": [], "le": [], "seismic": [], "kinematics": [], "keyblocks": [],
    "sweep": ["--out", "{tmp}/sweep", "--friction-mean", "40", "--friction-sd", "5"],
    "submit": ["--url", "http://127.0.0.1:9"],
}
#: a scene of the wrong schema and the field its message names
WRONG_SCENE = {"blocks": [{"name": "a", "faces": []}]}
WRONG_FIELD = "blocks[0] ('a').vertices"


def run(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def bad_file(tmp_path: Path, case: str) -> Path:
    """The file of a bad-input case: missing, not JSON (nor HDF5, nor CSV), wrong schema."""
    path = tmp_path / f"{case.replace(' ', '_')}.json"
    if case == "not JSON":
        path.write_text("{not json")
    elif case == "wrong schema":
        path.write_text(json.dumps(WRONG_SCENE))
    return path


def assert_exit_2(code: int, out: str, err: str, names: str) -> None:
    assert code == 2, (code, err)
    assert "Traceback" not in err and "Error:" not in err.split(":", 1)[0], err
    assert names in err, (names, err)
    assert len(err.strip().splitlines()) <= 2, err


@pytest.mark.parametrize("case", ["missing file", "not JSON", "wrong schema"])
@pytest.mark.parametrize("command", list(SCENE_COMMANDS))
def test_a_bad_scene_exits_2_naming_it(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                       command: str, case: str) -> None:
    path = bad_file(tmp_path, case)
    extra = [a.format(tmp=tmp_path) for a in SCENE_COMMANDS[command]]
    code, out, err = run(capsys, [command, str(path), *extra])
    assert_exit_2(code, out, err, WRONG_FIELD if case == "wrong schema" else str(path))
    if case == "not JSON":
        assert f"{path}: not valid JSON" in err
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "sweep").exists()


@pytest.fixture(scope="module")
def result_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Files that are not results: missing, text (not HDF5), an HDF5 file of another kind."""
    d = tmp_path_factory.mktemp("results")
    (d / "text.h5").write_text("PolyDDA? no")
    with h5py.File(d / "other.h5", "w") as f:
        f["x"] = [1.0]
    return {"missing file": d / "missing.h5", "not JSON": d / "text.h5",
            "wrong schema": d / "other.h5"}


#: the subcommands that read a result, as argv with RESULT in its place
RESULT_COMMANDS: dict[str, list[str]] = {
    "plot": ["plot", "RESULT"],
    "view": ["view", "RESULT", "--no-browser", "--port", "0"],
    "report": ["report", "RESULT", "--no-pdf"],
    "keyblocks --result": ["keyblocks", WEDGE, "--result", "RESULT"],
}


@pytest.mark.parametrize("case", ["missing file", "not JSON", "wrong schema"])
@pytest.mark.parametrize("command", list(RESULT_COMMANDS))
def test_a_missing_or_foreign_result_exits_2_naming_it(
        capsys: pytest.CaptureFixture[str], result_files: dict[str, Path], command: str,
        case: str) -> None:
    path = result_files[case]
    argv = [str(path) if a == "RESULT" else a for a in RESULT_COMMANDS[command]]
    code, out, err = run(capsys, argv)
    assert_exit_2(code, out, err, str(path))
    assert "synchronously" not in err  # not h5py's own message
    assert out == ""


def test_stereonet_bad_measurements_and_scene_exit_2(capsys: pytest.CaptureFixture[str],
                                                     tmp_path: Path) -> None:
    """stereonet reads a CSV (missing, not CSV, wrong columns) and a scene (missing)."""
    csv = tmp_path / "m.csv"
    code, out, err = run(capsys, ["stereonet", str(csv)])
    assert_exit_2(code, out, err, str(csv))
    csv.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    code, out, err = run(capsys, ["stereonet", str(csv)])
    assert_exit_2(code, out, err, str(csv))
    csv.write_text("strike,azimuth\n10,20\n")
    code, out, err = run(capsys, ["stereonet", str(csv)])
    assert_exit_2(code, out, err, str(csv))
    csv.write_text("dip,dip_direction\n" + "".join(f"{40 + k % 5},{100 + k}\n"
                                                   for k in range(30)))
    scene = tmp_path / "none.json"
    code, out, err = run(capsys, ["stereonet", str(csv), "--sets", "1", "--plot",
                                  str(tmp_path / "n.png"), "--scene", str(scene),
                                  "--out", str(tmp_path / "new.json")])
    assert_exit_2(code, out, err, str(scene))


# --------------------------------------------------------------------------- checkpoints


@pytest.fixture(scope="module")
def staged(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A short staged run (the roof wedge: settle, excavate): its scene and checkpoints."""
    d = tmp_path_factory.mktemp("staged")
    scene = d / "roof.json"
    scene.write_text(json.dumps(roof_wedge_scene(settle=0.01, fall=0.01)))
    assert main(["run", str(scene), "--out", str(d / "r.h5"), "--quiet"]) == 0
    return scene, d / "r.h5.stages"


def test_resume_from_a_bad_checkpoint_names_the_file_given(
        capsys: pytest.CaptureFixture[str], tmp_path: Path, staged: tuple[Path, Path]) -> None:
    """A missing checkpoint, one that is not a checkpoint (JSON), one whose ledger is gone,
    and the end of the last stage: exit 2, each naming the file the user gave (not the
    ledger `….stage.json` beside it), nothing run."""
    scene, stages = staged
    out = str(tmp_path / "again.h5")
    junk = tmp_path / "stage-1.npz"
    junk.write_text("{}")
    alone = tmp_path / "alone.npz"
    alone.write_bytes((stages / "stage-1.npz").read_bytes())
    for given, says in [(tmp_path / "nope.npz", "no such checkpoint"),
                        (junk, "is not a stage checkpoint"),
                        (alone, "has lost its ledger"),
                        (stages / "stage-2.npz", "no stage is left to run")]:
        code, o, err = run(capsys, ["run", str(scene), "--out", out, "--quiet",
                                    "--resume-from", str(given)])
        assert_exit_2(code, o, err, str(given))
        assert says in err and f"{given}.stage.json" not in err, err
        assert not Path(out).exists()
    code, _, err = run(capsys, ["run", str(scene), "--out", out, "--quiet",
                                "--resume-from", str(stages / "stage-1.npz")])
    assert code == 0, err
