"""Limit equilibrium (engine.analyses.limit_equilibrium, `polydda le`, the API process) against
cases worked by hand from Hoek & Bray / Wyllie & Mah, each within 0.1 % (the method is exact:
the only differences are the scenes' 6-decimal coordinates), its modes, and the scenes it
refuses, saying why.

The planar block of examples/planar_*.json (examples/planar_cases.py): 2 × 2 × 1 m,
ρ 2600 kg/m³, so W = 4 × 2600 × 9.81 = 102 024 N on a plane dipping α = 35°:
W cos α = 83 573.6 N, W sin α = 58 518.6 N, base area A = 4 m².
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from engine.analyses.le_model import ContactPlane, NotApplicable
from engine.analyses.limit_equilibrium import limit_equilibrium, solve_modes
from schemas.convert import build_model
from service.cli.main import main

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
W = 4 * 2600 * 9.81
A = math.radians(35.0)
TAN = {phi: math.tan(math.radians(phi)) for phi in (20, 30, 38, 40, 45)}


def planar_cases():
    """The generator of examples/planar_*.json as a module."""
    spec = importlib.util.spec_from_file_location("planar_cases", EXAMPLES / "planar_cases.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_planar_scenes_are_what_their_generator_writes() -> None:
    for name, scene in planar_cases().scenes().items():
        assert json.loads((EXAMPLES / f"{name}.json").read_text()) == scene, name


def le(name: str):
    return limit_equilibrium(build_model(EXAMPLES / f"{name}.json").model)


def test_planar_dry() -> None:
    """examples/incline.json, the 1 m cube on 30°, φ 20°: FS = tan φ / tan α = 0.63041."""
    r = le("incline")
    assert r.factor_of_safety == pytest.approx(TAN[20] / math.tan(math.radians(30)), rel=1e-4)
    assert r.mode_name == "sliding on one plane"
    assert r.strength_reduction_factor == pytest.approx(r.factor_of_safety, rel=1e-12)


def test_planar_with_cohesion() -> None:
    """φ 38°, c = 5 kPa: FS = (c A + W cos α tan φ) / (W sin α)
    = (20 000 + 83 573.6 × 0.781286) / 58 518.6 = 1.45757 (1.11579 without c)."""
    expected = (5000 * 4 + W * math.cos(A) * TAN[38]) / (W * math.sin(A))
    assert expected == pytest.approx(1.45757, abs=1e-5)
    assert le("planar_cohesion").factor_of_safety == pytest.approx(expected, rel=1e-4)


def test_planar_with_a_water_filled_tension_crack_and_cohesion() -> None:
    """Hoek & Bray's slope (H 10 m, face 60°, plane ψ 30°, vertical crack z = 4 m, water
    zw = 3 m, φ 45°), 2 m wide, c = 10 kPa. Cross-section (0, 0), (10.392305, 6),
    (10.392305, 10), (5.773503, 10): 43.87862 m², W = 43.87862 × 2 × 2600 × 9.81
    = 2 238 336 N; base 12 m long, A = 24 m²; U = ½ γw zw × 12 × 2 = 353 160 N; V = ½ γw zw²
    × 2 = 88 290 N. FS = (c A + (W cos ψ − U − V sin ψ) tan φ) / (W sin ψ + V cos ψ)
    = (240 000 + 1 541 152) / 1 195 630 = 1.48972."""
    w = 43.87862 * 2 * 2600 * 9.81
    u, v, psi = 0.5 * 9810 * 3 * 12 * 2, 0.5 * 9810 * 9 * 2, math.radians(30)
    expected = ((10000 * 24 + (w * math.cos(psi) - u - v * math.sin(psi)) * TAN[45])
                / (w * math.sin(psi) + v * math.cos(psi)))
    assert expected == pytest.approx(1.48972, abs=1e-5)
    r = le("planar_crack_cohesion")
    assert r.factor_of_safety == pytest.approx(expected, rel=1e-4)
    base, crack = r.loads.planes
    assert (base.water, crack.water) == (pytest.approx(u, rel=1e-6), pytest.approx(v, rel=1e-6))
    assert r.mode.planes == (0,)  # slides on its base; the crack opens
    assert le("planar_tension_crack").factor_of_safety == pytest.approx(1.28899, rel=1e-4)


def test_planar_with_an_active_tendon_at_an_angle() -> None:
    """φ 30°, a 25 kN constant-force tendon plunging 20° into the slope: at θ = 20 + 35 =
    55° to the plane it presses T sin θ = 20 479 N onto it and pulls T cos θ = 14 339 N
    up it (Wyllie & Mah 6.5): FS = (W cos α + T sin θ) tan φ / (W sin α − T cos θ)
    = 60 074.4 / 44 179.2 = 1.35979."""
    t, th = 25000.0, math.radians(55)
    expected = ((W * math.cos(A) + t * math.sin(th)) * TAN[30]
                / (W * math.sin(A) - t * math.cos(th)))
    assert expected == pytest.approx(1.35979, abs=1e-5)
    r = le("planar_tendon_angle")
    assert r.factor_of_safety == pytest.approx(expected, rel=1e-4)
    assert r.strength_reduction_factor == pytest.approx(expected, rel=1e-4)


def test_planar_with_a_passive_bolt() -> None:
    """φ 30°, an untensioned bolt of capacity C = 30 kN at θ = 55° to the plane, mobilized
    as the block moves. Hoek & Bray's passive convention adds its shear component to the
    resistance: FS = ((W cos α + C sin θ) tan φ + C cos θ) / (W sin α) = (62 439.1
    + 17 207.3) / 58 518.6 = 1.36105. Strength reduction divides only the joint, so the
    bolt lowers the driving force: F = (W cos α + C sin θ) tan φ / (W sin α − C cos θ)
    = 62 439.1 / 41 311.3 = 1.51143 (what `polydda fos` finds)."""
    c, th = 30000.0, math.radians(55)
    resist = (W * math.cos(A) + c * math.sin(th)) * TAN[30]
    passive = (resist + c * math.cos(th)) / (W * math.sin(A))
    srf = resist / (W * math.sin(A) - c * math.cos(th))
    assert (passive, srf) == (pytest.approx(1.36105, abs=1e-5), pytest.approx(1.51143, abs=1e-5))
    r = le("planar_bolt_passive")
    assert r.factor_of_safety == pytest.approx(passive, rel=1e-4)
    assert r.strength_reduction_factor == pytest.approx(srf, rel=1e-4)


def test_planar_under_pseudo_static_kh_and_kv() -> None:
    """φ 45°, kh 0.1 out of the slope, kv 0.1 upward (the weight becomes (1 − kv) W):
    FS = ((1 − kv) cos α − kh sin α) tan φ / ((1 − kv) sin α + kh cos α)
    = 0.679879 / 0.598133 = 1.13667; examples/incline_seismic.json (30°, φ 40°, kh 0.1):
    (cos α − kh sin α) tan φ / (sin α + kh cos α) = 1.16727."""
    kh, kv = 0.1, 0.1
    expected = (((1 - kv) * math.cos(A) - kh * math.sin(A)) * TAN[45]
                / ((1 - kv) * math.sin(A) + kh * math.cos(A)))
    assert expected == pytest.approx(1.13667, abs=1e-5)
    assert le("planar_seismic").factor_of_safety == pytest.approx(expected, rel=1e-4)
    a30 = math.radians(30)
    seismic = ((math.cos(a30) - kh * math.sin(a30)) * TAN[40]
               / (math.sin(a30) + kh * math.cos(a30)))
    assert le("incline_seismic").factor_of_safety == pytest.approx(seismic, rel=1e-4)


def test_the_wedge_dry_and_with_water() -> None:
    """docs/validation.md (Hoek & Bray's vector method): N_A = 0.663468 W, N_B = 0.596576 W,
    ψi = 28.750°: FS = (N_A + N_B) tan 40° / (W sin ψi) = 2.19819, sliding on both planes
    along trend 172.59°. examples/wedge_water.json (the 10 m wedge of 2.2, W = 7 277 374 N,
    N_A = 4 828 308 N, N_B = 4 341 508 N, driving 3 500 324 N) with u = 16 350 Pa on J1
    (97.5733 m²) and J2 (91.2474 m²): U_A = 1 595 323 N, U_B = 1 491 895 N, FS = (N_A + N_B
    − U_A − U_B) tan 40° / 3 500 324 = 1.45812."""
    dry = le("wedge")
    assert dry.factor_of_safety == pytest.approx(2.19819, rel=1e-4)
    assert dry.mode_name == "sliding on two planes"
    u = dry.mode.u
    assert math.degrees(math.atan2(u[0], u[1])) % 360 == pytest.approx(172.59, abs=0.01)
    assert math.degrees(math.asin(-u[2])) == pytest.approx(28.750, abs=0.01)
    expected = ((4828308 + 4341508 - 16350 * 97.5733 - 16350 * 91.2474) * TAN[40]
                / 3500324)
    assert expected == pytest.approx(1.45812, abs=1e-5)
    wet = le("wedge_water")
    assert wet.factor_of_safety == pytest.approx(expected, rel=1e-4)
    n = sorted(wet.mode.normal_forces, reverse=True)  # effective: N − U
    assert n == [pytest.approx(4828308 - 16350 * 97.5733, rel=1e-4),
                 pytest.approx(4341508 - 16350 * 91.2474, rel=1e-4)]


def test_issue_tendon_case() -> None:
    """Issue 30: φ 38°, 10 kPa on the plane (U = 40 kN), 70 kN tendon normal to it:
    FS = (W cos α − U + T) tan φ / (W sin α) = 113 573.6 × 0.781286 / 58 518.6 = 1.51629."""
    expected = (W * math.cos(A) - 40000 + 70000) * TAN[38] / (W * math.sin(A))
    assert expected == pytest.approx(1.5163, abs=1e-4)
    assert le("planar_tendon").factor_of_safety == pytest.approx(expected, rel=1e-4)


def _plane(normal: list[float], phi: float = 30.0, area: float = 1.0) -> ContactPlane:
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    return ContactPlane(n, np.zeros(3), area, np.zeros((3, 3)), 0, -1, 0,
                        math.tan(math.radians(phi)), 0.0, 0.0)


def test_modes_lifting_off_one_plane_two_planes() -> None:
    """A resultant pulling away from both planes lifts off (FS 0); pressing on one plane and
    sliding away from the other it slides on one; into the V it slides on both. A wedge
    whose planes are 50/090 and 50/270 (a symmetric V along y) under R = (0, 1, −1): both
    normal reactions are W / (2 cos 50°) ... by the vector method."""
    a = _plane([math.sin(math.radians(50)), 0, math.cos(math.radians(50))])
    b = _plane([-math.sin(math.radians(50)), 0, math.cos(math.radians(50))])
    best, _ = solve_modes([a, b], np.array([0.0, 0.0, 1.0]), np.zeros(3))
    assert best.planes == () and best.factor_of_safety == 0.0
    # down the V (along −y) and down: both planes press equally
    best, _ = solve_modes([a, b], np.array([0.0, -0.5, -1.0]), np.zeros(3))
    assert best.planes == (0, 1)
    n = 1.0 / (2 * math.cos(math.radians(50)))  # N_A = N_B = R_z / (2 cos 50°)
    assert best.normal_forces == (pytest.approx(n), pytest.approx(n))
    assert best.factor_of_safety == pytest.approx(2 * n * TAN[30] / 0.5)
    # pushed hard toward +x: it rides up plane b's side... off a, sliding on b alone
    best, _ = solve_modes([a, b], np.array([3.0, 0.0, -1.0]), np.zeros(3))
    assert best.planes == (1,)


@pytest.mark.parametrize(("name", "why"), [
    ("toppling", "one free block"), ("block_system", "one free block"),
    ("free_fall", "rests on no face of fixed rock"), ("newmark_pulse", "ground-motion")])
def test_scenes_it_does_not_apply_to_are_refused_saying_why(
        name: str, why: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(NotApplicable, match=why):
        le(name)
    assert main(["le", str(EXAMPLES / f"{name}.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("limit equilibrium: ") and why in err


def test_a_block_that_would_topple_and_a_passive_bolt_without_capacity_are_refused() -> None:
    """A 1 × 1 × 4 m column on the 35° plane: its weight passes the base 2 tan 35° = 1.4 m
    from the centre, outside the 0.5 m half-width: it topples, sliding LE does not apply.
    A bolt with stiffness and no capacity could hold any load."""
    scene = json.loads((EXAMPLES / "planar_cohesion.json").read_text())
    cases = planar_cases()
    scene["blocks"][0] = {"name": "block", "vertices": cases._box((0, 1), (0, 1), (0, 4)),
                          "faces": cases.FACES}
    with pytest.raises(NotApplicable, match="topple"):
        limit_equilibrium(build_model(scene).model)
    scene = json.loads((EXAMPLES / "planar_bolt_passive.json").read_text())
    del scene["bolts"][0]["capacity"]
    with pytest.raises(NotApplicable, match="no capacity"):
        limit_equilibrium(build_model(scene).model)


def test_cli_json_names_planes_forces_and_mode(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["le", str(EXAMPLES / "planar_crack_cohesion.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["factor_of_safety"] == pytest.approx(1.48972, rel=1e-4)
    assert doc["mode"] == "sliding on one plane" and doc["sliding_planes"] == ["on base"]
    planes = {p["name"]: p for p in doc["planes"]}
    assert planes["on base"]["joint_material"] == "joint" and planes["on base"]["sliding"]
    assert planes["on back"]["joint_material"] == "crack" and not planes["on back"]["sliding"]
    assert {f["kind"] for f in doc["forces"]} == {"weight", "water"}
    assert doc["direction"]["plunge"] == pytest.approx(30.0, abs=1e-6)
    assert main(["le", str(EXAMPLES / "planar_bolt_passive.json")]) == 0
    out = capsys.readouterr().out
    assert "factor of safety 1.3610" in out and "strength-reduction factor 1.5114" in out


def test_api_process_and_its_refusal(tmp_path: Path) -> None:
    from service.api.app import create_app
    from service.settings import Settings
    from tests.service_helpers import TestClient, wait_final

    scene = json.loads((EXAMPLES / "planar_tendon.json").read_text())
    with TestClient(create_app(Settings(data_dir=tmp_path, max_workers=1),
                               listen="127.0.0.1")) as c:
        r = c.post("/processes/limit-equilibrium/execution", json=scene)
        assert r.status_code == 201, r.text
        assert wait_final(c, r.headers["Location"], 60)["status"] == "successful"
        doc = c.get(r.headers["Location"] + "/results").json()["limit_equilibrium"]
        assert doc["factor_of_safety"] == pytest.approx(1.5163, rel=1e-4)
        toppling = json.loads((EXAMPLES / "toppling.json").read_text())
        r = c.post("/processes/limit-equilibrium/execution", json=toppling)
        assert r.status_code == 422
        assert "one free block" in r.text


def _sweep(name: str, tmp_path: Path, parameters: dict, capsys: pytest.CaptureFixture[str],
           n: int) -> dict:
    scene = json.loads((EXAMPLES / f"{name}.json").read_text())
    scene["sweep"] = {"n": n, "seed": 1, "mode": "analytic", "parameters": parameters}
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(scene))
    assert main(["sweep", str(path), "--out", str(tmp_path / name), "--json", "--quiet"]) == 0
    capsys.readouterr()
    return json.loads((tmp_path / name / "sweep.json").read_text())


def test_the_analytic_sweep_counts_water_cohesion_bolts_and_seismic_load(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 30: a wedge with water got eq. 51's dry FS (21 % above the wet one). Now each
    realisation is limit equilibrium on its own scene: the wet wedge 1.4581 at φ 40°
    ((N_A + N_B − U_A − U_B) tan φ / (W sin ψi)), the planar block with c 0 and 5 kPa
    1.1158 and 1.4576, the passive bolt of capacity 30 and 60 kN (Hoek & Bray's
    ((W cos α + C sin θ) tan φ + C cos θ) / (W sin α): 1.3610, 1.8975), kh 0 and 0.1
    (kv 0.1, φ 45°: ((1 − kv) cos α − kh sin α) tan φ / ((1 − kv) sin α + kh cos α) =
    1.4281 and 1.1367)."""
    wet = _sweep("wedge_water", tmp_path, {"friction_angle": {
        "distribution": "values", "values": [40.0]}}, capsys, 1)
    assert wet["realisations"][0]["factor_of_safety"] == pytest.approx(1.45812, rel=1e-4)
    c = _sweep("planar_cohesion", tmp_path, {"cohesion": {
        "distribution": "values", "values": [0.0, 5000.0]}}, capsys, 2)
    base = W * math.cos(A) * TAN[38]
    assert [r["factor_of_safety"] for r in c["realisations"]] == [
        pytest.approx(base / (W * math.sin(A)), rel=1e-4),
        pytest.approx((base + 20000) / (W * math.sin(A)), rel=1e-4)]
    bolt = _sweep("planar_bolt_passive", tmp_path, {"bolt_capacity": {
        "distribution": "values", "values": [30000.0, 60000.0]}}, capsys, 2)
    th = math.radians(55)
    expected = [((W * math.cos(A) + cap * math.sin(th)) * TAN[30] + cap * math.cos(th))
                / (W * math.sin(A)) for cap in (30000.0, 60000.0)]
    assert [r["factor_of_safety"] for r in bolt["realisations"]] == [
        pytest.approx(e, rel=1e-4) for e in expected]
    kh = _sweep("planar_seismic", tmp_path, {"kh": {
        "distribution": "values", "values": [0.0, 0.1]}}, capsys, 2)
    expected = [(0.9 * math.cos(A) - k * math.sin(A)) * TAN[45]
                / (0.9 * math.sin(A) + k * math.cos(A)) for k in (0.0, 0.1)]
    assert [r["factor_of_safety"] for r in kh["realisations"]] == [
        pytest.approx(e, rel=1e-4) for e in expected]


def test_an_analytic_sweep_where_limit_equilibrium_does_not_apply_exits_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 30: on a scene that is not a wedge `--mode analytic` exited 0 with no result."""
    args = ["sweep", str(EXAMPLES / "toppling.json"), "--friction-mean", "30",
            "--friction-sd", "3", "--n", "5", "--mode", "analytic", "--out", str(tmp_path)]
    assert main(args) == 2
    assert "one free block" in capsys.readouterr().err
