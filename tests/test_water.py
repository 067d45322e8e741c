"""Water in the joints (issue 16): pressure normal to the wetted contact faces, uplift on a
sliding plane, thrust in a tension crack (Hoek & Bray's planar failure), following the
blocks; recorded per block per step."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.loads.water import Water, overlap, quadrature
from engine.results.plots import plot_all
from engine.results.reader import open_result
from engine.results.writer import ResultWriter
from engine.step.simulation import STATUS_COMPLETED, run
from schemas.convert import build_model
from schemas.errors import SceneError
from schemas.scene import load_scene
from service.cli.main import main
from tests.test_simulation import FrameLog, incline_model

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
G, GW = 9.81, 9810.0
W = 2600 * G
ALPHA = np.radians(30.0)
NORMAL = np.array([np.sin(ALPHA), 0.0, np.cos(ALPHA)])  # of the incline, upward
DOWN_DIP = np.array([np.cos(ALPHA), 0.0, -np.sin(ALPHA)])
U_INCLINE = GW * 0.25  # base 1 m², 0 to 0.5 m below the water table at z = 0


def test_overlap_and_quadrature() -> None:
    """Two unit squares facing each other, offset by (0.5, 0.25): overlap 0.375 m²; the
    quadrature integrates a linear pressure and its moment exactly."""
    a = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)  # CCW about +z
    b = (a + [0.5, 0.25, 0.0])[::-1]  # CCW about -z
    poly = overlap(a, np.array([0.0, 0.0, 1.0]), b)
    x, w = quadrature(poly)
    assert w.sum() == pytest.approx(0.5 * 0.75)
    p = 3.0 + 2.0 * x[:, 0] - x[:, 1]  # linear pressure
    # exact: ∫∫ over [0.5, 1] × [0.25, 1]
    assert (p * w).sum() == pytest.approx(3 * 0.375 + 2 * 0.375 * 0.75 - 0.375 * 0.625)
    assert (p * w * x[:, 0]).sum() == pytest.approx(
        0.75 * (3 * 0.375 + 2 * (1 - 0.125) / 3 - 0.625 * 0.375), rel=1e-12)
    far = b + [5.0, 0.0, 0.0]
    assert len(overlap(a, np.array([0.0, 0.0, 1.0]), far)) == 0


def test_uplift_on_the_incline_is_normal_to_the_plane() -> None:
    """examples/incline_uplift.json at rest: U = γw A z̄ = 2452.5 N along the plane's normal."""
    built = build_model(EXAMPLES / "incline_uplift.json")
    built.model.controls = type(built.model.controls)(duration=0.05, time_step=5e-3,
                                                      penalty=1e10, record_interval=1)
    log = FrameLog()
    assert run(built.model, recorder=log).status == STATUS_COMPLETED
    k = built.block_index("cube")
    for f in (log.frames[0], log.frames[-1]):
        assert f.water_force[k] == pytest.approx(U_INCLINE * NORMAL, rel=1e-5)  # settling
        assert np.all(f.water_force[built.block_index("slab")] == 0.0)


def test_factor_of_safety_with_uplift(capsys: pytest.CaptureFixture[str]) -> None:
    """`polydda fos examples/incline_uplift.json`: FS = (W cos α − U) tan φ / (W sin α) =
    1.2920 within 2 % (dry 1.4534)."""
    assert main(["fos", str(EXAMPLES / "incline_uplift.json"), "--json", "--quiet"]) == 0
    doc = json.loads(capsys.readouterr().out)
    expected = (W * np.cos(ALPHA) - U_INCLINE) * np.tan(np.radians(40)) / (W * np.sin(ALPHA))
    assert expected == pytest.approx(1.2920, abs=5e-5)
    assert doc["factor_of_safety"] == pytest.approx(expected, rel=0.02)


def test_joint_pressure_follows_the_sliding_block() -> None:
    """A uniform 5 kPa in the joint under a sliding cube (φ 20°): a = g sin α − (g cos α −
    p A / m) tan φ, constant, within 1 % (the pressure moves with the block)."""
    model = incline_model(20.0, duration=1.0, dt=2e-3)
    model.water = Water(joint_pressure={0: 5000.0})
    log = FrameLog()
    assert run(model, recorder=log).status == STATUS_COMPLETED
    t, c = log.series(1)
    s = (c - c[0]) @ DOWN_DIP
    a = G * np.sin(ALPHA) - (G * np.cos(ALPHA) - 5000.0 / 2600) * np.tan(np.radians(20))
    k = np.argmin(abs(t - 1.0))
    assert s[k] == pytest.approx(0.5 * a * t[k] ** 2, rel=0.01)
    assert log.frames[-1].water_force[1] == pytest.approx(5000.0 * NORMAL, rel=1e-6)


def _planar() -> tuple[dict[str, Any], dict[str, float]]:
    """examples/planar_tension_crack.json and Hoek & Bray's numbers for its geometry (per
    metre of slope, from the scene's own blocks)."""
    scene = json.loads((EXAMPLES / "planar_tension_crack.json").read_text())
    built = build_model(scene)
    slide = built.model.blocks[built.block_index("slide")].polyhedron
    width = np.ptp(slide.vertices[:, 1])
    psi, phi = np.radians(30.0), np.radians(45.0)
    h, z, zw = 10.0, 4.0, 3.0
    area = (h - z) / np.sin(psi)
    w = 2600 * G * slide.volume / width
    assert w == pytest.approx(2600 * G * 0.5 * h**2 * ((1 - (z / h) ** 2) / np.tan(psi)
                                                       - 1 / np.tan(np.radians(60))))
    u, v = 0.5 * GW * zw * area, 0.5 * GW * zw**2
    fs = ((w * np.cos(psi) - u - v * np.sin(psi)) * np.tan(phi)
          / (w * np.sin(psi) + v * np.cos(psi)))
    return scene, {"W": w, "U": u, "V": v, "FS": fs, "width": width}


def test_planar_failure_water_forces() -> None:
    """The slide's water resultant at rest: U (triangular, on the plane) + V (in the crack),
    per metre × width, as Hoek & Bray's model has them."""
    scene, hb = _planar()
    assert hb["FS"] == pytest.approx(1.2890, abs=5e-5)
    scene["analysis"].update(type="simulation", duration=0.01)
    built = build_model(scene)
    log = FrameLog()
    assert run(built.model, recorder=log).status == STATUS_COMPLETED
    plane_normal = np.array([-np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    expected = hb["width"] * (hb["U"] * plane_normal + hb["V"] * np.array([-1.0, 0, 0]))
    got = log.frames[0].water_force[built.block_index("slide")]
    assert got == pytest.approx(expected, rel=1e-6, abs=1e-6 * np.linalg.norm(expected))


@pytest.mark.slow
@pytest.mark.ci
def test_planar_failure_factor_of_safety(capsys: pytest.CaptureFixture[str]) -> None:
    """`polydda fos examples/planar_tension_crack.json`: Hoek & Bray's FS 1.2890 within 2 %."""
    _, hb = _planar()
    assert main(["fos", str(EXAMPLES / "planar_tension_crack.json"), "--json", "--quiet"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["factor_of_safety"] == pytest.approx(hb["FS"], rel=0.02)


def test_water_resultants_in_the_result_file_and_plots(tmp_path: Path) -> None:
    built = build_model(EXAMPLES / "incline_uplift.json")
    built.model.controls = type(built.model.controls)(duration=0.05, time_step=5e-3,
                                                      penalty=1e10)
    with ResultWriter(tmp_path / "r.h5") as w:
        run(built.model, recorder=w)
    with open_result(tmp_path / "r.h5") as r:
        u = r.water_resultants()
        assert u.shape == (r.n_steps, 2, 3)
        assert u[-1, built.block_index("cube")] == pytest.approx(U_INCLINE * NORMAL, rel=1e-5)
        assert r.bolts() is None
        assert tmp_path / "plots" / "water.png" in plot_all(r, tmp_path / "plots")


def test_water_scene_errors_name_the_field() -> None:
    scene = json.loads((EXAMPLES / "incline_uplift.json").read_text())
    scene["water"] = {"unit_weight": 9810}
    with pytest.raises(SceneError) as err:
        load_scene(scene)
    assert [p["loc"] for p in err.value.problems] == ["water"]
    scene["water"] = {"joint_pressures": [{"joint_material": "wet", "pressure": 1e4}],
                      "phreatic_surface": {"point": [0, 0, 0], "dip": 90}}
    with pytest.raises(SceneError) as err:
        load_scene(scene)
    assert [p["loc"] for p in err.value.problems] == ["water.phreatic_surface.dip"]
    del scene["water"]["phreatic_surface"]
    with pytest.raises(SceneError) as err:
        load_scene(scene)
    assert [p["loc"] for p in err.value.problems] == [
        "water.joint_pressures[0].joint_material"]


#: docs/validation.md: the wedge's weight, normal reactions (N) and face areas (m²)
WEDGE_W, WEDGE_NA, WEDGE_NB = 7_277_374.0, 4_828_308.0, 4_341_508.0
WEDGE_AREAS = (97.5733, 91.2474)
N1 = np.array([0.719846, -0.262003, 0.642788])
N2 = np.array([-0.709406, -0.409576, 0.573576])
PSI_I = np.radians(28.750)


def _wedge_fs(u: float) -> float:
    """FS of the wedge with a uniform water pressure `u` (Pa) on both planes: the water
    forces are normal to the planes, so N_A − U_A and N_B − U_B carry the friction."""
    ua, ub = u * WEDGE_AREAS[0], u * WEDGE_AREAS[1]
    return ((WEDGE_NA + WEDGE_NB - ua - ub) * np.tan(np.radians(40.0))
            / (WEDGE_W * np.sin(PSI_I)))


def test_wedge_water_forces_are_normal_to_both_planes() -> None:
    """examples/wedge_water.json at rest: u A1 n1 + u A2 n2 on the wedge (u = γw H / 6)."""
    scene = json.loads((EXAMPLES / "wedge_water.json").read_text())
    u = scene["water"]["joint_pressures"][0]["pressure"]
    assert u == pytest.approx(GW * 10 / 6)
    assert _wedge_fs(0.0) == pytest.approx(2.19819, abs=2e-4)
    assert _wedge_fs(u) == pytest.approx(1.4581, abs=2e-4)
    scene["analysis"].update(type="simulation", duration=0.005)
    built = build_model(scene)
    log = FrameLog()
    assert run(built.model, recorder=log).status == STATUS_COMPLETED
    expected = u * (WEDGE_AREAS[0] * N1 + WEDGE_AREAS[1] * N2)
    got = log.frames[0].water_force[built.block_index("wedge")]
    assert got == pytest.approx(expected, rel=1e-5, abs=1e-5 * np.linalg.norm(expected))


@pytest.mark.slow
@pytest.mark.ci
def test_wedge_with_water_factor_of_safety(capsys: pytest.CaptureFixture[str]) -> None:
    """`polydda fos examples/wedge_water.json`: FS 1.4581 (dry 2.1982) within 2 %."""
    assert main(["fos", str(EXAMPLES / "wedge_water.json"), "--json", "--quiet"]) == 0
    doc = json.loads(capsys.readouterr().out)
    scene = json.loads((EXAMPLES / "wedge_water.json").read_text())
    expected = _wedge_fs(scene["water"]["joint_pressures"][0]["pressure"])
    assert doc["factor_of_safety"] == pytest.approx(expected, rel=0.02)
