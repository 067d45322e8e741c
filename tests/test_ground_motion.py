"""Acceleration time histories (issue 16): the ground's acceleration as the inertial body
force −m a(t) on the moving blocks; Newmark's rigid sliding block under a rectangular pulse."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from engine.loads.seismic import GroundMotion
from engine.step.simulation import STATUS_COMPLETED, run
from schemas.convert import build_model
from schemas.errors import SceneError
from schemas.scene import load_scene
from tests.test_simulation import FrameLog

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
G = 9.81
A, TP = 0.5 * G, 0.5
AY = G * np.tan(np.radians(20.0))
#: Newmark: permanent displacement of a block (yield acceleration a_y) under a pulse A, t_p
NEWMARK = A * TP**2 * (A - AY) / (2 * AY)


def test_mean_acceleration_is_exact_for_the_piecewise_linear_history() -> None:
    gm = GroundMotion(np.array([0.0, 1.0, 1.0, 3.0]),
                      np.array([[2.0, 0, 0], [2.0, 0, 0], [0, 0, 0], [0, 0, -4.0]]))
    assert gm.mean(0.5, 1.5) == pytest.approx([1.0, 0.0, -0.25])  # across the jump
    assert gm.mean(1.0, 3.0) == pytest.approx([0.0, 0.0, -2.0])  # a ramp
    assert gm.mean(2.0, 3.0) == pytest.approx([0.0, 0.0, -3.0])
    assert gm.mean(3.0, 4.0) == pytest.approx([0.0, 0.0, 0.0])  # after the record
    assert gm.mean(-1.0, 0.0) == pytest.approx([0.0, 0.0, 0.0])  # before it


def test_newmark_sliding_block_under_a_rectangular_pulse() -> None:
    """examples/newmark_pulse.json: the cube slides west (against the ground's acceleration)
    by A t_p² (A − a_y) / (2 a_y) = 0.229149 m and stops, within 2 % (measured 1e-5)."""
    assert NEWMARK == pytest.approx(0.229149, abs=1e-6)
    built = build_model(EXAMPLES / "newmark_pulse.json")
    log = FrameLog()
    res = run(built.model, recorder=log)
    assert res.status == STATUS_COMPLETED, res.message
    k = built.block_index("cube")
    d = log.frames[-1].centroids[k] - log.frames[0].centroids[k]
    assert -d[0] == pytest.approx(NEWMARK, rel=0.02)
    assert abs(d[1]) < 1e-3
    assert np.linalg.norm(log.frames[-1].velocity[k, :3]) < 1e-3  # at rest again
    # during the pulse the block lags the ground at A − a_y
    t, c = log.series(k)
    j = np.argmin(abs(t - 0.4))
    assert -(c[j, 0] - c[0, 0]) == pytest.approx(0.5 * (A - AY) * t[j] ** 2, rel=0.02)
    assert res.summary["energy"]["created_ratio"] < 1e-6


def test_ground_motion_scene_fields() -> None:
    scene = json.loads((EXAMPLES / "newmark_pulse.json").read_text())
    scene["ground_motion"] = {"csv": "t, ax, ay, az\n0, 1, 0, 0\n0.5, 1, 0, 0\n0.5, 0, 0, 0",
                              "scale": 2.0}
    gm = build_model(scene).model.ground_motion
    assert gm.times.tolist() == [0.0, 0.5, 0.5]
    assert gm.acceleration[0].tolist() == [2.0, 0.0, 0.0]
    for bad in ({"time": [0, 1], "acceleration": [[0, 0, 0]]},
                {"time": [1, 0], "acceleration": [[0, 0, 0], [0, 0, 0]]},
                {"csv": "0, 1, 0\n"}):
        scene["ground_motion"] = bad
        with pytest.raises(SceneError) as err:
            load_scene(scene)
        assert [p["loc"] for p in err.value.problems] == ["ground_motion"], bad
