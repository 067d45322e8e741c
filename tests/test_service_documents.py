"""One document layer for CLI and API (service.documents, service.jobs.processes): the same scene
gives the same factor of safety, summary and blocks through `polydda` and through a job."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from schemas.convert import build_model
from service.api.app import create_app
from service.cli.main import main
from service.documents import fos_controls, run_summary
from service.jobs.processes import PROCESS_IDS, PROCESSES, default_process
from service.settings import Settings
from tests.service_helpers import TestClient, wait_final

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DOWN_DIP = 2.0 * np.array([0.866025, 0.0, -0.5])  # 2 m down the 30° slab


def two_cubes_fos_scene() -> dict[str, Any]:
    """The incline example with a second cube 2 m down-dip: `rough` (35°) under the watched
    cube, `smooth` (25°: it slides at F = 1 already) under the other; only `rough` is
    weakened. FS = tan 35° / tan 30° = 1.21 for the watched cube; a search that weakened
    every joint and watched every block would answer tan 25° / tan 30° = 0.81."""
    scene = json.loads((EXAMPLES / "incline.json").read_text())
    cube = scene["blocks"][0]
    other = copy.deepcopy(cube)
    other["name"] = "lower"
    other["vertices"] = (np.array(cube["vertices"]) + DOWN_DIP).round(6).tolist()
    scene["blocks"].append(other)
    scene["joint_materials"] = {"rough": {"friction_angle": 35},
                                "smooth": {"friction_angle": 25}}
    scene["default_joint_material"] = "rough"
    scene["block_pairs"] = [{"blocks": ["lower", "slab"], "joint_material": "smooth"}]
    scene["analysis"] = {
        "type": "factor_of_safety", "time_step": 0.005, "penalty": 1e10,
        "factor_of_safety": {"observation_time": 0.6, "tolerance": 0.02, "min_factor": 0.5,
                             "max_factor": 3.0, "joint_materials": ["rough"],
                             "watch": ["cube"]}}
    return scene


def test_process_registry_is_the_one_list() -> None:
    assert PROCESS_IDS == ("simulation", "factor-of-safety", "critical-seismic-coefficient",
                           "limit-equilibrium", "block-cutting", "kinematics", "sweep")
    assert default_process("limit_equilibrium") == "limit-equilibrium"
    assert default_process("factor_of_safety") == "factor-of-safety"
    assert default_process("critical_seismic_coefficient") == "critical-seismic-coefficient"
    assert default_process("simulation") == "simulation"
    for p in PROCESSES.values():
        assert p.main_artifact in p.artifacts and callable(p.run)


def test_fos_controls_carry_watched_blocks_and_joint_materials() -> None:
    build = build_model(two_cubes_fos_scene())
    c = fos_controls(build)
    assert c.watch_blocks == (build.block_index("cube"),)
    assert c.joint_materials == (build.joint_material_names.index("rough"),)
    assert (c.observation_time, c.tolerance) == (0.6, 0.02)


def test_fos_job_equals_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A factor-of-safety job through the API gives the CLI's answer, trial for trial."""
    scene = two_cubes_fos_scene()
    path = tmp_path / "two_cubes.json"
    path.write_text(json.dumps(scene))
    assert main(["fos", str(path), "--json", "--quiet"]) == 0
    cli = json.loads(capsys.readouterr().out)
    expected = np.tan(np.radians(35)) / np.tan(np.radians(30))
    assert cli["factor_of_safety"] == pytest.approx(expected, rel=0.03)
    assert cli["watch_blocks"] == ["cube"] and cli["joint_materials"] == ["rough"]
    settings = Settings(data_dir=tmp_path / "data", max_workers=1)
    with TestClient(create_app(settings, listen="127.0.0.1")) as c:
        r = c.post("/jobs", json=scene)  # analysis.type picks the process
        assert r.status_code == 201, r.text
        assert r.json()["processID"] == "factor-of-safety"
        assert wait_final(c, r.headers["Location"], 120)["status"] == "successful"
        api = c.get(r.headers["Location"] + "/results").json()["factor_of_safety"]
    assert api == cli


def test_summary_keeps_engine_and_build_warnings() -> None:
    build = build_model(two_cubes_fos_scene())
    build.warnings.append("a build warning")
    engine_summary = {"status": "completed", "warnings": ["contacts penetrated up to ..."],
                      "blocks": [{"name": "block0"}, {"name": "block1"}, {"name": "block2"}],
                      "max_penetration": float("nan")}
    doc = run_summary(engine_summary, build)
    assert doc["warnings"] == ["a build warning", "contacts penetrated up to ..."]
    assert [b["name"] for b in doc["blocks"]] == build.block_names == doc["block_names"]
    assert doc["max_penetration"] is None  # strict JSON
    assert engine_summary["blocks"][0]["name"] == "block0"  # the engine's dict is not changed


def test_cutting_warnings_name_the_joints(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A joint outside the domain cuts nothing: the warning names it as errors do."""
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [4, 4, 4]}},
             "joints": [{"name": "bedding", "dip": 0, "dip_direction": 0,
                         "point": [0, 0, 2]},
                        {"name": "far-away", "dip": 0, "dip_direction": 0,
                         "point": [0, 0, 50]}],
             "analysis": {"duration": 0.01}}
    build = build_model(scene)
    assert any("joints[1] ('far-away')" in w for w in build.warnings), build.warnings
    assert not any("joint 1" in w or "joint plane" in w for w in build.warnings)
    path = tmp_path / "s.json"
    path.write_text(json.dumps(scene))
    assert main(["blocks", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    assert "joints[1] ('far-away')" in err
    assert json.loads(out)["warnings"] == build.warnings
