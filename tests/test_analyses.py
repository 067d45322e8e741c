"""The paper's wedge (docs/validation.md) and the factor of safety by strength reduction."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from engine.analyses.strength_reduction import StrengthReductionControls, factor_of_safety
from engine.model import JointMaterial
from engine.step.simulation import STATUS_COMPLETED, run
from schemas.convert import build_model
from service.cli.main import main
from tests.test_simulation import FrameLog, incline_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
G = 9.81
PSI = np.radians(28.75)  # plunge of the line of intersection
K_WEDGE = 1.437213  # wedge factor sin β / sin(ξ/2)
LINE = np.array([0.113060, -0.869407, -0.480987])  # line of intersection, downward


def _trough(phi_deg: float, duration: float):
    model = build_model(EXAMPLES / "wedge_trough.json").model
    model.joint_materials = [JointMaterial(np.radians(phi_deg))]
    model.controls = dataclasses.replace(model.controls, duration=duration, record_interval=5)
    return model


@pytest.mark.parametrize("phi", [0.0, 10.0])
def test_wedge_slides_along_line_of_intersection(phi: float) -> None:
    """a = g (sin ψ − K cos ψ tan φ) within 0.5 %; trend 172.59°, plunge 28.75° ± 0.5°;
    the wedge does not rotate (< 1e-3 rad)."""
    log = FrameLog()
    res = run(_trough(phi, 1.0), recorder=log)
    assert res.status == STATUS_COMPLETED
    t, v = log.series(0, "velocity")
    sel = t >= 0.5
    a = np.polyfit(t[sel], v[sel, :3] @ LINE, 1)[0]
    expected = G * (np.sin(PSI) - K_WEDGE * np.cos(PSI) * np.tan(np.radians(phi)))
    assert a == pytest.approx(expected, rel=0.005)
    d = log.frames[-1].centroids[0] - log.frames[0].centroids[0]
    trend = np.degrees(np.arctan2(d[0], d[1])) % 360
    plunge = np.degrees(np.arcsin(-d[2] / np.linalg.norm(d)))
    assert trend == pytest.approx(172.59, abs=0.5)
    assert plunge == pytest.approx(28.75, abs=0.5)
    assert np.linalg.norm(log.frames[-1].rotation[0]) < 1e-3


def test_factor_of_safety_of_block_on_incline() -> None:
    """FS = tan φ / tan α = 1.2128 for φ = 35° on 30°, within 2 %."""
    model = incline_model(35.0, duration=1.0, dt=5e-3)
    controls = StrengthReductionControls(observation_time=1.2, tolerance=0.01)
    res = factor_of_safety(model, controls)
    expected = np.tan(np.radians(35)) / np.tan(np.radians(30))
    assert res.factor_of_safety == pytest.approx(expected, rel=0.02)
    assert res.critical_friction_angles_deg[0] == pytest.approx(30.0, abs=0.5)
    assert all(r.failed == (r.factor > expected) for r in res.runs
               if abs(r.factor / expected - 1) > 0.02)


@pytest.mark.slow
@pytest.mark.ci
def test_paper_wedge_factor_of_safety(capsys: pytest.CaptureFixture[str]) -> None:
    """The paper's wedge (examples/wedge.json): FS 2.198 (eq. 51) within 2 %, via the CLI."""
    assert main(["fos", str(EXAMPLES / "wedge.json"), "--json", "--quiet"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["factor_of_safety"] == pytest.approx(2.19819, rel=0.02)
    assert doc["critical_friction_angle"] == pytest.approx(20.893, abs=0.4)
