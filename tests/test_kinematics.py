"""Kinematic screening (issue 17): Markland tests against hand results, the stereonet's data,
`polydda kinematics` and the `kinematics` API process."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from engine.analyses.kinematics import (
    JointSet,
    LateralLimits,
    SlopeFace,
    apparent_dip,
    kinematic_analysis,
    normal,
)
from engine.analyses.stereonet import stereonet_data
from schemas.convert import kinematic_inputs
from schemas.errors import SceneError
from service.cli.main import main
from tests.service_helpers import TestClient, wait_final

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
WEDGE = EXAMPLES / "wedge.json"


def failed(conditions: list) -> list[str]:
    return [c.test for c in conditions if not c.passed]


def wedge_scene(**face: float) -> dict:
    scene = json.loads(WEDGE.read_text())
    scene["slope_face"] |= face
    return scene


# --------------------------------------------------------------------------- hand cases


def test_paper_wedge_intersection_and_verdicts() -> None:
    """J1 50/110, J2 55/240 in the vertical face 90/180 of examples/wedge.json: the
    intersection is 172.59/28.75 (docs/validation.md); it daylights (vertical face) but
    plunges less than φ = 40°, so no wedge; the sets' dip directions are 70° and 60° off the
    face (no planar sliding), their poles 110° and 120° off (no toppling)."""
    sets, face = kinematic_inputs(WEDGE)
    assert [(s.name, s.dip, s.dip_direction, s.friction_angle) for s in sets] == [
        ("J1", 50, 110, 40), ("J2", 55, 240, 40)]
    assert (face.dip, face.dip_direction, face.friction_angle) == (90, 180, 40)
    r = kinematic_analysis(sets, face)
    (w,) = r.wedge
    assert w.trend == pytest.approx(172.59, abs=0.005)
    assert w.plunge == pytest.approx(28.750, abs=0.0005)
    assert failed(w.conditions) == ["steeper than friction"]
    assert [failed(p.conditions) for p in r.planar] == [["lateral limit"], ["lateral limit"]]
    assert all(not t.admissible for t in r.flexural_toppling + r.direct_toppling)
    assert r.admissible() == {"planar": [], "wedge": [], "flexural_toppling": [],
                              "direct_toppling": []}


def test_paper_wedge_slides_below_its_plunge() -> None:
    """With φ = 20° < 28.75° the wedge is admissible and rides on both planes (neither dip
    direction lies between the trend 172.6° and the face's 180°/175°); in the face 65/175 of
    docs/validation.md it daylights: apparent dip atan(tan 65° cos 2.41°) = 64.98° > 28.75°."""
    for face in ({"friction_angle": 20}, {"dip": 65, "dip_direction": 175, "friction_angle": 20}):
        r = kinematic_analysis(*kinematic_inputs(wedge_scene(**face)))
        (w,) = r.wedge
        assert w.admissible and w.sliding_on == "both"
    assert apparent_dip(65, 175, w.trend) == pytest.approx(64.98, abs=0.01)
    assert "64.98°" in w.conditions[1].detail


def test_planar_cases_by_hand() -> None:
    """Face 60/180, φ 30°: 45/190 slides (10° off, 45° < atan(tan 60° cos 10°) = 59.62°,
    45° > 30°); 45/215 is 35° off (lateral limit); 25/180 is flatter than φ; 70/180 is
    steeper than the face (does not daylight)."""
    face = SlopeFace(60, 180, 30)
    sets = [JointSet("P1", 45, 190), JointSet("P2", 45, 215), JointSet("P3", 25, 180),
            JointSet("P4", 70, 180)]
    r = kinematic_analysis(sets, face)
    assert r.admissible()["planar"] == ["P1"]
    assert [failed(p.conditions) for p in r.planar] == [
        [], ["lateral limit"], ["steeper than friction"], ["daylights"]]
    assert apparent_dip(60, 180, 190) == pytest.approx(59.62, abs=0.01)
    assert "59.62°" in r.planar[0].conditions[1].detail
    # a set's own friction angle wins over the slope's
    assert not kinematic_analysis([JointSet("P1", 45, 190, friction_angle=46)], face).planar[
        0].admissible


def test_flexural_toppling_by_hand() -> None:
    """Face 70/090, φ 30°: slabs need dip ≥ 90 − 70 + 30 = 50° into the slope. 75/270
    topples; 45/270 is too flat; 75/295 has its pole 25° off: inside Goodman's ±30°, outside
    Wyllie & Mah's ±10°."""
    face = SlopeFace(70, 90, 30)
    sets = [JointSet("D", 75, 270), JointSet("F", 45, 270), JointSet("G", 75, 295)]
    r = kinematic_analysis(sets, face)
    assert r.admissible()["flexural_toppling"] == ["D", "G"]
    assert failed(r.flexural_toppling[1].conditions) == ["interlayer slip"]
    narrow = kinematic_analysis(sets, face, LateralLimits(flexural_toppling=10))
    assert narrow.admissible()["flexural_toppling"] == ["D"]
    assert "50°" in r.flexural_toppling[1].conditions[1].detail


def test_direct_toppling_by_hand() -> None:
    """Face 70/090, φ 30°: columns between 80/235 and 80/305 (intersection trend 270°,
    plunge atan(tan 80° cos 35°) = 77.85° ≥ 90 − 70 = 20°, into the slope) on the base 10/090
    (dips out of the face, flatter than the face and than φ: non-sliding release)."""
    sets = [JointSet("A", 80, 235), JointSet("B", 80, 305), JointSet("C", 10, 90)]
    r = kinematic_analysis(sets, SlopeFace(70, 90, 30))
    assert r.admissible() == {"planar": [], "wedge": [], "flexural_toppling": [],
                              "direct_toppling": [["A", "B"]]}
    d = r.direct_toppling[0]
    assert d.trend == pytest.approx(270.0, abs=1e-9)
    expected = math.degrees(math.atan(math.tan(math.radians(80)) * math.cos(math.radians(35))))
    assert d.plunge == pytest.approx(expected, abs=1e-9) and expected == pytest.approx(77.85,
                                                                                        abs=0.01)
    assert (d.base_planes, d.base_release) == (["C"], ["non-sliding"])
    # without the base plane the columns cannot topple
    alone = kinematic_analysis(sets[:2], SlopeFace(70, 90, 30)).direct_toppling[0]
    assert failed(alone.conditions) == ["base plane"]


def test_stable_slope_by_hand() -> None:
    """Face 50/180, φ 35°: 30/170 is flatter than φ, 70/090 strikes across the face, 35/020
    dips into it but far flatter than the 75° toppling needs; every intersection lies in one
    of the planes so plunges at most min(dips) ≤ 35° (no wedge, no direct toppling)."""
    sets = [JointSet("S1", 30, 170), JointSet("S2", 70, 90), JointSet("S3", 35, 20)]
    r = kinematic_analysis(sets, SlopeFace(50, 180, 35))
    assert r.admissible() == {"planar": [], "wedge": [], "flexural_toppling": [],
                              "direct_toppling": []}
    for w in r.wedge:
        a, b = (next(s for s in sets if s.name == n) for n in w.sets)
        assert w.plunge <= min(a.dip, b.dip) + 1e-9
    s12 = r.wedge[0]
    assert failed(s12.conditions) == ["steeper than friction"]
    assert failed(r.flexural_toppling[2].conditions) == ["interlayer slip"]


def test_intersection_is_in_both_planes() -> None:
    """The reported trend/plunge is a line lying in both planes (normal · line = 0)."""
    r = kinematic_analysis([JointSet("a", 37, 12), JointSet("b", 81, 287)], SlopeFace(60, 0, 30))
    t, p = math.radians(r.wedge[0].trend), math.radians(r.wedge[0].plunge)
    line = np.array([math.sin(t) * math.cos(p), math.cos(t) * math.cos(p), -math.sin(p)])
    for dip, dd in ((37, 12), (81, 287)):
        assert abs(normal(dip, dd) @ line) < 1e-12


def test_jointed_slope_example_by_hand() -> None:
    """examples/jointed_slope.json, face 65/180, φ 40°: the bedding 35/180 daylights but is
    flatter than φ; the 80/000 set topples (80° ≥ 90 − 65 + 40 = 65°); the discs 60/130 and
    60/230 meet along 180/atan(tan 60° cos 50°) = 48.07° (> 40°, < 65°): a wedge on both; the
    release joints 85/090 with 60/130 meet along 173.7/51.4 (daylights: 64.87° along it)."""
    r = kinematic_analysis(*kinematic_inputs(EXAMPLES / "jointed_slope.json"))
    assert failed(r.planar[0].conditions) == ["steeper than friction"]
    assert r.admissible()["flexural_toppling"] == ["toppling"]
    w = {tuple(x.sets): x for x in r.wedge}
    ew = w[("wedge_east", "wedge_west")]
    assert ew.admissible and ew.sliding_on == "both"
    assert (ew.trend, ew.plunge) == (pytest.approx(180.0, abs=1e-9), pytest.approx(
        math.degrees(math.atan(math.tan(math.radians(60)) * math.cos(math.radians(50)))),
        abs=1e-9))
    assert ew.plunge == pytest.approx(48.07, abs=0.01)
    re = w[("release", "wedge_east")]
    assert re.admissible and (re.trend, re.plunge) == (pytest.approx(173.7, abs=0.05),
                                                       pytest.approx(51.4, abs=0.05))
    assert r.admissible()["planar"] == [] and r.admissible()["direct_toppling"] == []


def test_scene_without_slope_face_is_an_error() -> None:
    scene = json.loads(WEDGE.read_text())
    del scene["slope_face"]
    with pytest.raises(SceneError) as exc:
        kinematic_inputs(scene)
    assert exc.value.problems[0]["loc"] == "slope_face"
    scene["slope_face"] = {"dip": 0, "dip_direction": 180}
    with pytest.raises(SceneError) as exc:
        kinematic_inputs(scene)
    assert exc.value.problems[0]["loc"] == "slope_face.dip"


# --------------------------------------------------------------------------- stereonet data


def plunge_trend(lonlat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from mplstereonet import stereonet_math as sm

    plunge, trend = sm.geographic2plunge_bearing(lonlat[0], lonlat[1])
    return np.ravel(plunge), np.ravel(trend)


def test_stereonet_data_is_what_it_says() -> None:
    """Every plotted array, converted back by mplstereonet, is the orientation it stands for:
    poles (40/290, 35/060), the intersection (28.75/172.59), great circles perpendicular to
    the normals, the friction cone at plunge 90 − φ, the daylight envelope at the face's
    apparent dip, the toppling zone's edge at plunge slope dip − φ within ±30°."""
    r = kinematic_analysis(*kinematic_inputs(wedge_scene(dip=65, dip_direction=175,
                                                         friction_angle=20)))
    d = stereonet_data(r)
    for name, (pl, tr) in {"J1": (40, 290), "J2": (35, 60)}.items():
        p, t = plunge_trend(d["poles"][name])
        assert (p[0], t[0]) == (pytest.approx(pl, abs=1e-9), pytest.approx(tr, abs=1e-9))
    p, t = plunge_trend(d["intersections"]["J1/J2"])
    assert (p[0], t[0]) == (pytest.approx(28.750, abs=1e-3), pytest.approx(172.591, abs=1e-3))
    for name, (dip, dd) in {"J1": (50, 110), "J2": (55, 240)}.items():
        p, t = np.radians(plunge_trend(d["great_circles"][name]))
        lines = np.column_stack([np.sin(t) * np.cos(p), np.cos(t) * np.cos(p), -np.sin(p)])
        assert np.abs(lines @ normal(dip, dd)).max() < 1e-9
    assert plunge_trend(d["friction_cone"])[0] == pytest.approx(70.0, abs=1e-9)
    assert plunge_trend(d["line_friction_circle"])[0] == pytest.approx(20.0, abs=1e-9)
    p, t = plunge_trend(d["daylight_envelope"])
    dips, ddirs = 90 - p, t - 180
    inner = (p > 1e-6) & (p < 90 - 1e-6)
    assert inner.sum() > 100
    hand = np.degrees(np.arctan(np.tan(np.radians(65)) * np.cos(np.radians(ddirs - 175))))
    assert np.abs(dips[inner] - hand[inner]).max() < 1e-9
    p, t = plunge_trend(d["toppling_zone"])
    edge = np.abs(p - 45.0) < 1e-9  # slope dip 65 − φ 20
    off = (t[edge] - 175 + 180) % 360 - 180
    assert edge.sum() > 100 and np.abs(off).max() == pytest.approx(30.0, abs=1e-9)
    for side, line in zip((-20.0, 20.0), d["planar_lateral_limits"], strict=True):
        p, t = plunge_trend(line)
        off = (t[p < 90 - 1e-6] - 355 + 180) % 360 - 180  # the trend of the centre is moot
        assert off == pytest.approx(side, abs=1e-9)


# --------------------------------------------------------------------------- CLI and API


def test_cli_kinematics_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "net.png"
    assert main(["kinematics", str(WEDGE), "--json", "--plot", str(png)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["admissible"]["wedge"] == []
    w = doc["wedge"][0]
    assert w["sets"] == ["J1", "J2"] and w["trend"] == pytest.approx(172.59, abs=0.005)
    assert doc["lateral_limits"] == {"planar": 20, "flexural_toppling": 30,
                                     "direct_toppling": 20}
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert main(["kinematics", str(WEDGE)]) == 0
    out = capsys.readouterr().out
    assert "J1/J2: trend 172.59°, plunge 28.75°" in out and "wedge sliding: none" in out


def test_the_text_says_what_held_and_what_did_not(capsys: pytest.CaptureFixture[str]) -> None:
    """Every condition of every test is printed as met or not met with a statement that is
    true either way (the wedge's 28.75° plunge is *below* φ 40°); planes and lines that
    point into the slope say so instead of showing a negative apparent dip."""
    assert main(["kinematics", str(EXAMPLES / "jointed_slope.json")]) == 0
    out = capsys.readouterr().out
    assert "  bedding: not admissible\n" in out
    assert ("    not met  steeper than friction: dip 35° < φ 40°\n"
            "  toppling: not admissible") in out.split("planar sliding:")[1]
    assert "    met      daylights: dip 35° < the face's apparent dip 65.00° along 180°" in out
    assert ("    not met  daylights: the plane dips into the slope, away from the face"
            in out)  # toppling, 80/000 in a face dipping to 180
    assert "the plane dips along the face's strike, not out of the face" in out  # 85/090
    assert "  wedge_east/wedge_west: admissible (slides on both planes)" in out
    assert "    met      steeper than friction: plunge 48.07° > φ 40°" in out
    assert "    met      interlayer slip: dip 80° > 90° − slope dip 65° + φ 40° = 65°" in out
    assert "apparent dip -" not in out and "vs" not in out
    assert main(["kinematics", str(WEDGE)]) == 0
    out = capsys.readouterr().out
    assert ("  J1/J2: not admissible\n"
            "    met      plunges out of the face: intersection trend 172.59° is 7.41° from "
            "the face's dip direction 180° (out of the face)\n"
            "    met      daylights: plunge 28.75° < the face's apparent dip 90.00° along "
            "172.59°\n"
            "    not met  steeper than friction: plunge 28.75° < φ 40°\n") in out


def test_cli_kinematics_without_slope_face(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["kinematics", str(EXAMPLES / "incline.json")]) == 2
    assert "slope_face: kinematic screening needs the slope face" in capsys.readouterr().err


def test_api_kinematics_process(tmp_path: Path) -> None:
    """POST /jobs?process=kinematics: done well under a second, the document inline and the
    stereonet served as a PNG."""
    from service.api.app import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", max_workers=1)
    with TestClient(create_app(settings, listen="127.0.0.1")) as c:
        scene = wedge_scene(friction_angle=20)
        t0 = time.monotonic()
        r = c.post("/jobs", params={"process": "kinematics"}, json=scene)
        assert r.status_code == 201, r.text
        job = wait_final(c, r.headers["Location"])
        wall = time.monotonic() - t0
        assert job["status"] == "successful", job
        message = job["message"]
        assert message.startswith("admissible: 1 wedge (screened in ")
        screening = float(message.split("screened in ")[1].split(" s")[0])
        assert screening < 1.0  # the screening and the figure, in the job process
        doc = c.get(r.headers["Location"] + "/results").json()
        assert doc["kinematics"]["admissible"]["wedge"] == [["J1", "J2"]]
        png = c.get(r.headers["Location"] + "/results/stereonet.png")
        assert png.status_code == 200 and png.headers["content-type"] == "image/png"
        bad = dict(scene)
        del bad["slope_face"]
        r = c.post("/jobs", params={"process": "kinematics"}, json=bad)
        assert r.status_code == 422 and "slope_face" in r.text
    assert wall < 15.0  # a fresh job process (imports) on a loaded machine: ~2-3 s
