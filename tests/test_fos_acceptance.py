"""`polydda fos` against the hand-worked cases of tests/test_limit_equilibrium.py (Hoek & Bray,
Wyllie & Mah; the derivations are in its docstrings), each within 2 %: strength reduction
divides tan φ and c of the joints by F and finds the F at which the block fails, which is
limit equilibrium's factor of safety (for a passive bolt its strength-reduction factor: the
bolt is not divided). Each trial's displacement, velocity and the reason of its verdict are
in the document. A quasi-static scene is refused; a search that never fails or always fails
reports a bound, never a number beyond its own range."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from engine.analyses.strength_reduction import (
    QuasiStatic,
    StrengthReductionControls,
    factor_of_safety,
)
from schemas.convert import build_model
from service.cli.main import main
from tests.test_simulation import incline_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
W, A = 4 * 2600 * 9.81, math.radians(35.0)
TAN = {phi: math.tan(math.radians(phi)) for phi in (20, 30, 38, 40, 45)}

#: name -> the hand-worked factor of safety (see tests/test_limit_equilibrium.py)
CASES = {
    # (W cos α − U + T) tan φ / (W sin α), U = 40 kN, T = 70 kN normal to the plane
    "planar_tendon": (W * math.cos(A) - 40000 + 70000) * TAN[38] / (W * math.sin(A)),
    # (c A + W cos α tan φ) / (W sin α), c = 5 kPa, A = 4 m²
    "planar_cohesion": (5000 * 4 + W * math.cos(A) * TAN[38]) / (W * math.sin(A)),
    # tan φ / tan α: the 1 m cube on 30°, φ 20°
    "incline": TAN[20] / math.tan(math.radians(30)),
    # (W cos α + T sin 55°) tan φ / (W sin α − T cos 55°), T = 25 kN
    "planar_tendon_angle": ((W * math.cos(A) + 25000 * math.sin(math.radians(55))) * TAN[30]
                            / (W * math.sin(A) - 25000 * math.cos(math.radians(55)))),
    # the joint alone divided: (W cos α + C sin 55°) tan φ / (W sin α − C cos 55°), C = 30 kN
    "planar_bolt_passive": ((W * math.cos(A) + 30000 * math.sin(math.radians(55))) * TAN[30]
                            / (W * math.sin(A) - 30000 * math.cos(math.radians(55)))),
    # ((1 − kv) cos α − kh sin α) tan φ / ((1 − kv) sin α + kh cos α), kh = kv = 0.1
    "planar_seismic": ((0.9 * math.cos(A) - 0.1 * math.sin(A)) * TAN[45]
                       / (0.9 * math.sin(A) + 0.1 * math.cos(A))),
    # (c A + (W cos ψ − U − V sin ψ) tan φ) / (W sin ψ + V cos ψ), Hoek & Bray's slope
    "planar_crack_cohesion": 1.48972,
}
# the wedge, dry and with water, by `polydda fos`: tests/test_analyses.py
# (test_paper_wedge_factor_of_safety, 2.19819) and tests/test_water.py
# (test_wedge_with_water_factor_of_safety, 1.45812), both slow and CI's
#: the cases that run in the quick suite (about 3 s each); the others are slow (and CI's)
QUICK = ("planar_tendon", "planar_cohesion")


def _fos(name: str, capsys: pytest.CaptureFixture[str]) -> dict:
    assert main(["fos", str(EXAMPLES / f"{name}.json"), "--json", "--quiet"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=() if n in QUICK else (pytest.mark.slow, pytest.mark.ci))
    for n in CASES])
def test_fos_matches_the_hand_worked_factor_of_safety(
        name: str, capsys: pytest.CaptureFixture[str]) -> None:
    doc = _fos(name, capsys)
    assert doc["factor_of_safety"] == pytest.approx(CASES[name], rel=0.02)
    assert doc["bound"] is None and doc["status"] == "completed"
    for r in doc["runs"]:
        assert {"displacement", "velocity", "peak_velocity", "reason", "failed", "time",
                "steps", "block", "continued_from", "bonds_broken",
                "bonds_broken_progressively"} <= set(r)
        assert r["reason"] and r["displacement"] >= 0 and r["velocity"] >= 0
        if r["failed"]:
            assert r["displacement"] > doc["displacement_limit"] or "moving" in r["reason"] \
                or "failed" in r["reason"]
    if name == "planar_cohesion":  # c A is one bond: it breaks whole when the block goes
        assert all((r["bonds_broken"], r["bonds_broken_progressively"]) ==
                   ((1, 0) if r["failed"] else (0, 0)) for r in doc["runs"])
    # the bracket: the largest factor that held and the smallest that failed are 1 % apart
    held = max(r["factor"] for r in doc["runs"] if not r["failed"])
    failed = min(r["factor"] for r in doc["runs"] if r["failed"] and r["factor"] > held)
    assert failed / held - 1 <= 0.0101


def test_the_issue_tendon_trial_that_slid_fails(capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 30: at F = 2.0 the block slid 2.66 m before the tendon swung round and stopped
    it, and the old criterion (mean acceleration over a window) called it holding. Now it
    fails as soon as it has moved the limit (2 % of its size V^⅓ = 1.587 m: 3.2 cm)."""
    doc = _fos("planar_tendon", capsys)
    assert doc["displacement_limit"] == pytest.approx(0.02 * 4 ** (1 / 3), rel=1e-6)
    at2 = [r for r in doc["runs"] if r["factor"] == 2.0]
    assert at2 and at2[0]["failed"] and "more than the limit" in at2[0]["reason"]
    assert at2[0]["time"] < 0.5 and at2[0]["block"] == "block"


def test_a_quasi_static_scene_is_refused(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 30: in quasi-static mode every trial showed an acceleration of 0 and `polydda
    fos` printed a factor of safety of 32 (above its own maximum) for a block with FS 1.37.
    Now the CLI exits 2 naming analysis.mode, and the API answers 422."""
    scene = json.loads((EXAMPLES / "planar_tendon.json").read_text())
    scene["analysis"]["mode"] = "quasi_static"
    path = tmp_path / "qs.json"
    path.write_text(json.dumps(scene))
    assert main(["fos", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("analysis.mode: the factor of safety needs analysis.mode 'dynamic'")
    assert main(["seismic", str(path)]) == 2
    with pytest.raises(QuasiStatic):
        factor_of_safety(build_model(path).model)

    from service.api.app import create_app
    from service.settings import Settings
    from tests.service_helpers import TestClient

    with TestClient(create_app(Settings(data_dir=tmp_path / "data", max_workers=1),
                               listen="127.0.0.1")) as c:
        r = c.post("/processes/factor-of-safety/execution", json=scene)
        assert r.status_code == 422 and "analysis.mode" in r.text
        scene["analysis"].pop("mode")
        scene["analysis"]["dynamic_ratio"] = 0.9
        r = c.post("/processes/critical-seismic-coefficient/execution", json=scene)
        assert r.status_code == 422 and "analysis.dynamic_ratio" in r.text


def test_a_search_beyond_its_range_reports_a_bound() -> None:
    """φ 80° on 30° (FS 9.8) searched up to F = 3 holds every trial: FS ≥ 3, bound 'lower'
    (never a factor above the maximum); φ 5° (FS 0.15) searched down to 0.5 fails every
    trial: FS < 0.5, bound 'upper'."""
    strong = factor_of_safety(incline_model(80.0, dt=0.01), StrengthReductionControls(
        observation_time=0.3, max_factor=3.0))
    assert (strong.factor_of_safety, strong.bound) == (3.0, "lower")
    assert max(r.factor for r in strong.runs) == 3.0 and not any(r.failed for r in strong.runs)
    weak = factor_of_safety(incline_model(5.0, dt=0.01), StrengthReductionControls(
        observation_time=0.3, min_factor=0.5))
    assert (weak.factor_of_safety, weak.bound) == (0.5, "upper")
    assert all(r.failed for r in weak.runs)
