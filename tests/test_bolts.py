"""Rock bolts and cables (issue 16): a bolt normal to the slope holds the incline's cube
above the analytic pretension, its factor of safety follows (W cos α + T) tan φ / (W sin α),
a bolt below the needed capacity yields and breaks, and forces are recorded."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.loads.bolts import BROKEN, ELASTIC, YIELDED
from engine.results.plots import plot_all
from engine.results.reader import open_result
from engine.results.writer import ResultWriter
from engine.step.simulation import STATUS_COMPLETED, run
from schemas.convert import build_model, pattern_bolts
from schemas.errors import Problems, SceneError
from schemas.scene import BoltPatternSpec, load_scene
from service.cli.main import main
from tests.test_simulation import FrameLog

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
W = 2600 * 9.81
ALPHA, PHI = np.radians(30.0), np.radians(20.0)
DOWN_DIP = np.array([np.cos(ALPHA), 0.0, -np.sin(ALPHA)])
NORMAL = np.array([np.sin(ALPHA), 0.0, np.cos(ALPHA)])
#: pretension that holds the cube: W (sin α / tan φ − cos α)
T_HOLD = W * (np.sin(ALPHA) / np.tan(PHI) - np.cos(ALPHA))
#: force a tie-back along the dip must carry: W (sin α − cos α tan φ)
NEEDED = W * (np.sin(ALPHA) - np.cos(ALPHA) * np.tan(PHI))


def _scene() -> dict[str, Any]:
    return json.loads((EXAMPLES / "incline_bolt.json").read_text())


def _slide(scene: dict[str, Any]) -> tuple[float, FrameLog, Any]:
    """Down-dip slide (m) of the cube at the end of the scene's run."""
    built = build_model(scene)
    log = FrameLog()
    res = run(built.model, recorder=log)
    assert res.status == STATUS_COMPLETED, res.message
    k = built.block_index("cube")
    return float((log.frames[-1].centroids[k] - log.frames[0].centroids[k]) @ DOWN_DIP), log, res


def test_analytic_numbers() -> None:
    assert np.tan(PHI) / np.tan(ALPHA) == pytest.approx(0.6304, abs=5e-5)
    assert T_HOLD == pytest.approx(12950, abs=1.0)
    fs = (W * np.cos(ALPHA) + 20000) * np.tan(PHI) / (W * np.sin(ALPHA))
    assert fs == pytest.approx(1.2012, abs=5e-5)


def test_example_builds_a_ground_anchored_bolt() -> None:
    built = build_model(EXAMPLES / "incline_bolt.json")
    (b,) = built.model.bolts
    assert b.block == built.block_index("cube") and b.anchor_block == -1
    assert (b.pretension, b.axial_stiffness) == (20000.0, 0.0)
    axis = (b.anchor - b.head) / np.linalg.norm(b.anchor - b.head)
    assert axis == pytest.approx(-NORMAL, abs=1e-6)


@pytest.mark.parametrize("ratio", [0.98, 1.02])
def test_pretension_threshold(ratio: float) -> None:
    """A stiff bolt (5 MN/m, 20 m) pretensioned to 2 % below T_hold lets the cube slide;
    2 % above holds it (within the penalty spring's creep check, < 1e-5 m)."""
    scene = _scene()
    scene["bolts"][0].update(pretension=ratio * T_HOLD, axial_stiffness=5e6)
    scene["analysis"].update(type="simulation", duration=1.5)
    s, log, res = _slide(scene)
    if ratio < 1:
        assert s > 0.02  # a ≈ 0.036 m/s² → 0.04 m by 1.5 s, less the bolt's tilt
    else:
        assert abs(s) < 1e-5
        assert log.frames[-1].bolt_axial_force[0] == pytest.approx(ratio * T_HOLD, rel=1e-3)
    assert res.summary["energy"]["created_ratio"] < 1e-6


def test_factor_of_safety_with_bolt(capsys: pytest.CaptureFixture[str]) -> None:
    """`polydda fos examples/incline_bolt.json`: FS = (W cos α + T) tan φ / (W sin α) =
    1.2012 within 2 %."""
    assert main(["fos", str(EXAMPLES / "incline_bolt.json"), "--json", "--quiet"]) == 0
    doc = json.loads(capsys.readouterr().out)
    expected = (W * np.cos(ALPHA) + 20000) * np.tan(PHI) / (W * np.sin(ALPHA))
    assert doc["factor_of_safety"] == pytest.approx(expected, rel=0.02)


def _tie_back(pretension: float, capacity: float) -> dict[str, Any]:
    """The cube held by a tie-back along the dip from the centre of its up-dip face to a
    ground anchor 5 m up-slope (its line passes through the centroid)."""
    scene = _scene()
    head = np.array([0.25, 0.5, 0.4330127])
    scene["bolts"] = [{"name": "tie", "head": head.tolist(),
                       "anchor": (head - 5.0 * DOWN_DIP).tolist(), "axial_stiffness": 5e6,
                       "pretension": pretension, "capacity": capacity,
                       "rupture_displacement": 0.05}]
    scene["analysis"].update(type="simulation", duration=1.5)
    return scene


def test_bolt_below_the_needed_capacity_breaks_and_the_block_slides() -> None:
    """Needed 4 713 N; capacity 4 000 N: the tie-back yields at its capacity, stretches
    5 cm, breaks, and the cube slides freely (a = g (sin α − cos α tan φ) after)."""
    s, log, res = _slide(_tie_back(4000.0, 4000.0))
    status = np.array([f.bolt_status[0] for f in log.frames])
    axial = np.array([f.bolt_axial_force[0] for f in log.frames])
    assert status[-1] == BROKEN and YIELDED in status
    before = status < BROKEN
    assert axial[before] == pytest.approx(4000.0, rel=1e-6)
    assert np.all(axial[~before] == 0.0)
    assert s > 0.5
    assert res.summary["bolts"][0]["state"] == "broken"
    assert res.summary["energy"]["created_ratio"] < 1e-6


def test_bolt_above_the_needed_capacity_holds() -> None:
    s, log, _ = _slide(_tie_back(1.2 * NEEDED, 8000.0))
    assert abs(s) < 1e-5
    assert log.frames[-1].bolt_status[0] == ELASTIC
    assert log.frames[-1].bolt_axial_force[0] == pytest.approx(1.2 * NEEDED, rel=1e-3)


def test_bolt_forces_are_in_the_result_file_and_plots(tmp_path: Path) -> None:
    built = build_model(_tie_back(4000.0, 4000.0))
    with ResultWriter(tmp_path / "r.h5") as w:
        run(built.model, recorder=w)
    with open_result(tmp_path / "r.h5") as r:
        b = r.bolts()
        assert b["names"] == ["tie"] and b["anchor_block"].tolist() == [-1]
        assert b["axial_force"].shape == (r.n_steps, 1)
        assert b["status"][-1, 0] == BROKEN and b["axial_force"][1, 0] == pytest.approx(4000)
        paths = plot_all(r, tmp_path / "plots")
    assert (tmp_path / "plots" / "bolts.png") in paths


def test_bolt_scene_errors_name_the_field() -> None:
    scene = _scene()
    scene["bolts"][0].update(pretension=5000.0, capacity=4000.0)
    with pytest.raises(SceneError) as err:
        load_scene(scene)
    assert [p["loc"] for p in err.value.problems] == ["bolts[0] ('B1')"]
    assert "pretension" in err.value.problems[0]["msg"]
    scene = _scene()
    scene["bolts"][0]["head"] = [50.0, 50.0, 50.0]
    with pytest.raises(SceneError) as err:
        build_model(scene)
    assert [p["loc"] for p in err.value.problems] == ["bolts[0].head"]
    scene = _scene()
    scene["bolts"][0]["anchor_block"] = "nothing"
    with pytest.raises(SceneError) as err:
        build_model(scene)
    assert [p["loc"] for p in err.value.problems] == ["bolts[0].anchor_block.name"]


def test_anchor_in_a_block_couples_the_two_blocks() -> None:
    """An anchor inside the fixed slab anchors to it (found at the point)."""
    scene = _scene()
    scene["bolts"][0]["anchor"] = (np.array(scene["bolts"][0]["head"]) - 1.5 * NORMAL).tolist()
    built = build_model(scene)
    assert built.model.bolts[0].anchor_block == built.block_index("slab")


def test_bolt_pattern_grid() -> None:
    """A 2 × 3 pattern on the incline's face: heads `spacing` apart in the face, anchors
    `length` along trend / plunge."""
    spec = BoltPatternSpec(origin=[0, 0, 0], face_normal=NORMAL.tolist(),
                           row_direction=[0, 1, 0], spacing=1.5, row_spacing=2.0, rows=2,
                           columns=3, length=4.0, trend=270.0, plunge=60.0)
    p = Problems()
    bolts = pattern_bolts(spec, "bolt_patterns[0]", p)
    assert not p.items and [b[0] for b in bolts][-1] == "bolt6"
    heads = np.array([b[1] for b in bolts])
    assert np.abs(heads @ NORMAL).max() < 1e-12
    assert heads[1] - heads[0] == pytest.approx([0, 1.5, 0])
    assert np.linalg.norm(heads[3] - heads[0]) == pytest.approx(2.0)
    d = (bolts[0][2] - bolts[0][1]) / 4.0
    assert d == pytest.approx(-NORMAL, abs=1e-12)  # 270° / 60°: normal into the slope
    bad = copy.deepcopy(spec)
    bad.plunge = -60.0
    p = Problems()
    assert pattern_bolts(bad, "bolt_patterns[0]", p) == []
    assert p.items[0]["loc"] == "bolt_patterns[0].trend"


def test_bolt_count_is_limited_before_any_work() -> None:
    scene = _scene()
    scene["bolt_patterns"] = [{"origin": [0.933013, 0.5, 0.616025],
                               "face_normal": NORMAL.tolist(), "row_direction": [0, 1, 0],
                               "spacing": 0.001, "rows": 200, "columns": 100, "length": 3,
                               "trend": 270, "plunge": 60}]
    with pytest.raises(SceneError) as err:
        load_scene(scene)
    assert [p["loc"] for p in err.value.problems] == ["bolt_patterns"]


def test_bolt_pattern_in_a_scene() -> None:
    """Two pattern bolts on the cube's top face, normal to the slope, anchored in the
    ground 5 m deep."""
    scene = _scene()
    scene["bolts"] = []
    scene["bolt_patterns"] = [{"origin": [0.933013, 0.25, 0.616025],
                               "face_normal": NORMAL.tolist(), "row_direction": [0, 1, 0],
                               "spacing": 0.5, "columns": 2, "length": 5.0, "trend": 270,
                               "plunge": 60, "pretension": 7000.0, "name_prefix": "P"}]
    built = build_model(scene)
    bolts = built.model.bolts
    assert [b.name for b in bolts] == ["P1", "P2"]
    assert all(b.block == built.block_index("cube") and b.anchor_block == -1 for b in bolts)
    assert bolts[1].head - bolts[0].head == pytest.approx([0.0, 0.5, 0.0], abs=1e-9)
    assert (bolts[0].anchor - bolts[0].head) == pytest.approx(-5.0 * NORMAL, abs=1e-9)
    assert bolts[0].pretension == 7000.0


def test_resumed_run_with_a_yielding_bolt_is_bit_for_bit(tmp_path: Path) -> None:
    """A checkpoint carries the bolts' plastic elongation, shear force and state."""
    from engine.step.simulation import Simulation

    model = build_model(_tie_back(4000.0, 4000.0)).model
    full, half = Simulation(model), Simulation(model)
    for _ in range(60):
        full.step()
        half.step()
    assert half.state.bolt_status[0] == YIELDED and half.state.bolt_plastic[0] > 0
    half.checkpoint(tmp_path / "state.npz")
    resumed = Simulation.resume(model, tmp_path / "state.npz")
    for _ in range(100):
        assert np.array_equal(full.step().d, resumed.step().d)
    for name in ("centroid", "bolt_plastic", "bolt_shear", "bolt_status"):
        assert np.array_equal(getattr(full.state, name), getattr(resumed.state, name)), name
    assert full.state.bolt_status[0] == BROKEN


def test_bolt_between_two_free_blocks_couples_them() -> None:
    """Two free cubes without gravity joined by a pretensioned bolt (T = 1 kN, k = 1 MN/m)
    between their facing faces: internal forces (momentum stays zero) and a two-body
    oscillator about elongation −T/k at ω = √(2k/m): the bolt shortens to −2T/k at t = π/ω
    (a bolt seen by each block alone, without the coupling terms, would give √(k/m))."""
    from engine.geometry.shapes import box
    from engine.model import AnalysisControls, Block, Bolt, Model

    k, t0, m = 1e6, 1000.0, 2600.0
    model = Model(blocks=[Block(box([0, 0, 0], [1, 1, 1]), "a"),
                          Block(box([3, 0, 0], [4, 1, 1]), "b")],
                  gravity=np.zeros(3),
                  bolts=[Bolt(block=0, head=np.array([1.0, 0.5, 0.5]),
                              anchor=np.array([3.0, 0.5, 0.5]), anchor_block=1,
                              axial_stiffness=k, pretension=t0)],
                  controls=AnalysisControls(duration=0.2, time_step=2e-4, record_interval=1))
    log = FrameLog()
    assert run(model, recorder=log).status == STATUS_COMPLETED
    t = np.array([f.time for f in log.frames])
    c = np.array([f.centroids for f in log.frames])
    v = np.array([f.velocity[:, :3] for f in log.frames])
    assert np.abs(v.sum(axis=1)).max() < 1e-9 * np.abs(v).max()
    elong = (c[:, 1, 0] - c[:, 0, 0]) - 3.0
    omega = np.sqrt(2 * k / m)
    j = int(np.argmin(elong))
    assert t[j] == pytest.approx(np.pi / omega, rel=0.02)
    assert elong[j] == pytest.approx(-2 * t0 / k, rel=0.05)
