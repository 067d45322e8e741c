"""Domains from a slope profile and a terrain grid, excavations, and staged runs, against
numbers derived by hand (tests/excavation_scenes.py): the roof wedge's tetrahedron and its
free fall, volumes of the excavated rock, a staged run equal to one stopped and resumed at
each stage, the energy books across a stage, and bad input naming its field."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

from engine.dynamics.state import State
from engine.geometry.cutting.cut import cut_blocks
from engine.geometry.domains import slope_polyhedron, terrain
from engine.geometry.excavations import (
    EXCAVATION_TAG_BASE,
    axis_points,
    excavate,
    tunnel,
    tunnel_section,
)
from engine.geometry.joints import joint_set_planes
from engine.geometry.polyhedron import dip_normal
from engine.geometry.shapes import box
from engine.step.frame import energy_created
from engine.step.staged_run import load_checkpoint, run_stages
from schemas.convert import build_model
from schemas.errors import SceneError
from service.cli.main import main
from tests.excavation_scenes import R_IN, WEDGE_VOLUME, H, roof_wedge_scene

G = 9.81


@pytest.fixture(scope="module")
def wedge_build():  # noqa: ANN201
    return build_model(roof_wedge_scene())


def _wedge(build) -> int:  # noqa: ANN001
    """The block whose faces are the three wedge joints (tags 0, 1, 2)."""
    return next(k for k, b in enumerate(build.model.blocks)
                if {0, 1, 2} <= set(b.polyhedron.face_tags.tolist()))


def test_roof_wedge_is_the_analytic_tetrahedron(wedge_build) -> None:  # noqa: ANN001
    """Volume √3 r² H (r = H / tan δ) and apex H above the roof, to 1e-9; the base
    triangle's corners 2 r from the axis."""
    w = wedge_build.model.blocks[_wedge(wedge_build)].polyhedron
    assert w.volume == pytest.approx(WEDGE_VOLUME, rel=1e-9)
    lo, hi = w.bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9) and hi[2] == pytest.approx(H, rel=1e-9)
    base = w.vertices[np.abs(w.vertices[:, 2]) < 1e-9]
    assert np.allclose(np.linalg.norm(base[:, :2], axis=1), 2 * R_IN, rtol=1e-9)
    assert wedge_build.excavated.count("cavern") == 1  # the core, one block
    core = wedge_build.excavated.index("cavern")
    assert wedge_build.model.blocks[core].polyhedron.volume == pytest.approx(6 * 3 * 12)


def test_roof_wedge_falls_free_when_excavated(wedge_build, tmp_path: Path) -> None:  # noqa: ANN001
    """Stage 2 removes the core: the wedge (c = 0) falls ½ g t² in t = 0.5 s within 1 %;
    the arch around it and the base do not move (1e-4 m); the core's energy leaves with it
    (removed_energy > 0) and the run creates none."""
    res = run_stages(wedge_build.model, wedge_build.stages, checkpoints=tmp_path)
    assert res.status == "completed", res.message
    blocks = res.summary["blocks"]
    w = _wedge(wedge_build)
    fall = -blocks[w]["displacement"][2]
    assert fall == pytest.approx(0.5 * G * 0.5**2, rel=0.01)
    core = wedge_build.excavated.index("cavern")
    for k, b in enumerate(blocks):
        if k not in (w, core):
            assert np.abs(b["displacement"]).max() < 1e-4, b["name"]
    assert blocks[core]["removed"] and blocks[core]["removed_in_stage"] == "excavate"
    st = res.summary["stages"]
    assert [s["removed_blocks"] for s in st] == [[], [wedge_build.block_names[core]]]
    assert st[1]["removed_energy"] > 0
    e = res.state.energies
    assert e["removed_energy"] == pytest.approx(st[1]["removed_energy"])
    assert res.summary["energy"]["created_ratio"] < 1e-6


def test_staged_run_equals_resumed_at_each_stage(wedge_build,  # noqa: ANN001
                                                 tmp_path: Path) -> None:
    """Run through the stages, and again from the checkpoint at the first stage's end: the
    final states are equal bit for bit."""
    whole = run_stages(wedge_build.model, wedge_build.stages, checkpoints=tmp_path / "a")
    resumed = run_stages(wedge_build.model, wedge_build.stages,
                         resume=load_checkpoint(tmp_path / "a" / "stage-1.npz"))
    a, b = whole.state, resumed.state
    for name in ("centroid", "affine", "rotation", "velocity", "stress"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert (a.time, a.step, a.dt) == (b.time, b.step, b.dt)
    assert a.energies == b.energies
    assert isinstance(b, State)


def test_energy_books_balance_across_the_excavation(wedge_build) -> None:  # noqa: ANN001
    """Stored + dissipated + removed − work stays ~0 through the stage change (1e-6 of
    the work done)."""
    res = run_stages(wedge_build.model, wedge_build.stages)
    from engine.step.output import energies
    from engine.step.simulation import Simulation
    from engine.step.staged_run import Ledger
    from engine.step.stages import stage_model

    model, _ = stage_model(wedge_build.model, wedge_build.stages[-1], Ledger())
    e = energies(Simulation(model, state=res.state).system, res.state)
    assert abs(float(energy_created(e))) < 1e-6 * e["gravity_work"]
    assert e["removed_energy"] > 0


def test_slope_profile_is_the_polyhedron_and_the_planar_grid() -> None:
    """A benched profile extruded equals the same prism written as a polyhedron, and a
    terrain grid sampling the same planar faces gives the same blocks (volumes 1e-9)."""
    prof = np.array([[0, 10], [10, 10], [20, 20], [30, 20]], float)
    slope = slope_polyhedron(prof, 10.0, 270.0, [0, 0], 0.0)
    x, y = np.arange(0, 31, 5.0), np.arange(0, 11, 5.0)
    grid = terrain(x, y, np.tile(np.interp(x, prof[:, 0], prof[:, 1]), (len(y), 1)), 0.0)
    # section: 10 m at z 10, 10 m ramping 10 -> 20 (mean 15), 10 m at 20 = 450 m², × 10 m
    assert slope.volume == pytest.approx(10 * (10 * 10 + 10 * 15 + 10 * 20), rel=1e-12)
    assert grid.domain.volume == pytest.approx(slope.volume, rel=1e-12)
    joints = (joint_set_planes(dip_normal(60, 90), [3, 1, 2], 4.0, slope, 0)
              + joint_set_planes(dip_normal(80, 0), [3, 1.3, 2], 4.0, slope, 1))
    a = cut_blocks(slope, joints).blocks
    b = cut_blocks(grid.domain, joints, tiles=grid.columns).blocks
    assert len(a) == len(b) > 20
    va, vb = np.sort([q.volume for q in a]), np.sort([q.volume for q in b])
    assert np.allclose(va, vb, rtol=1e-9, atol=1e-9 * slope.volume)


def test_scene_slope_equals_scene_polyhedron() -> None:
    """`domain.slope` gives the blocks of the same shape as `domain.polyhedron`."""
    prof = [[0, 10], [8, 10], [8, 14], [12, 14], [16, 22], [30, 22]]  # a bench 4 m high
    poly = slope_polyhedron(np.array(prof, float), 12.0, 180.0, [0, 0], 0.0)
    base = {"joints": [{"dip": 55, "dip_direction": 180, "point": [1, 1, 1], "spacing": 5},
                       {"dip": 85, "dip_direction": 90, "point": [1, 1, 1], "spacing": 6}]}
    a = build_model({**base, "domain": {"slope": {"profile": prof, "dip_direction": 180,
                                                  "width": 12, "base": 0}}})
    b = build_model({**base, "domain": {"polyhedron": {
        "vertices": poly.vertices.tolist(), "faces": [f.tolist() for f in poly.faces]}}})
    va = [blk.polyhedron.volume for blk in a.model.blocks]
    vb = [blk.polyhedron.volume for blk in b.model.blocks]
    assert np.allclose(va, vb, rtol=1e-9) and len(va) > 10


def test_tunnel_removes_exactly_its_rock() -> None:
    """A horseshoe tunnel through a jointed box, cut without merging slivers: the parts
    inside fill it exactly (section area × length, 1e-9), no part straddles its surface,
    and the rock's volume is kept."""
    dom = box([-15, 0, -15], [15, 20, 15])
    planes = (joint_set_planes(dip_normal(60, 30), [0.3, 0.1, 0.2], 3.0, dom, 0)
              + joint_set_planes(dip_normal(10, 270), [0.3, 0.1, 0.2], 4.0, dom, 1))
    blocks = cut_blocks(dom, planes).blocks
    sec = tunnel_section("horseshoe", 6.0, sides=16)
    area = 0.5 * float(np.sum(sec[:, 0] * np.roll(sec[:, 1], -1)
                              - np.roll(sec[:, 0], -1) * sec[:, 1]))
    exc = tunnel("T", sec, axis_points([0, -1, -3], 0.0, 0.0, 22.0))
    parts, inside, parent = excavate(blocks, exc, EXCAVATION_TAG_BASE)
    vin = sum(q.volume for q, i in zip(parts, inside, strict=True) if i)
    assert vin == pytest.approx(area * 20.0, rel=1e-9)
    assert sum(q.volume for q in parts) == pytest.approx(30 * 20 * 30, rel=1e-12)
    for q, i in zip(parts, inside, strict=True):
        v = q.vertices[q.surface_vertex_ids]
        if i:  # every corner inside or on the surface (within 1e-6 m)
            assert exc.contains(v, tol=-1e-6).all()
        else:  # no corner deeper inside than 1e-6 m
            assert not exc.contains(v, tol=1e-6).any()
    assert set(parent.tolist()) == set(range(len(blocks)))
    # the horseshoe's half-width at the invert: r (√3 − 1)
    assert sec[:, 0].max() == pytest.approx(3.0 * (math.sqrt(3) - 1), rel=1e-12) or \
        np.isclose(sec[sec[:, 1] == 0, 0], 3.0 * (math.sqrt(3) - 1)).any()


# --------------------------------------------------------------------------- bad input

OPEN_STL = """solid open
facet normal 0 0 -1
 outer loop
  vertex 0 0 0
  vertex 1 1 0
  vertex 1 0 0
 endloop
endfacet
facet normal 0 -1 0
 outer loop
  vertex 0 0 0
  vertex 1 0 0
  vertex 0 0 1
 endloop
endfacet
endsolid open
"""

NAN_GRID = """ncols 3
nrows 3
xllcorner 0
yllcorner 0
cellsize 5
NODATA_value -9999
20 21 22
20 -9999 22
20 21 nan
"""


def _problems(scene: dict) -> list[dict[str, str]]:
    with pytest.raises(SceneError) as info:
        build_model(scene)
    return info.value.problems


@pytest.mark.parametrize("case", ["open_stl", "nan_grid", "outside", "unknown_bolt"])
def test_bad_input_names_the_field(case: str) -> None:
    scene = copy.deepcopy(roof_wedge_scene())
    if case == "open_stl":
        scene["domain"] = {"mesh": {"data": OPEN_STL, "format": "stl"}}
        scene["joints"], scene["excavations"], scene["stages"] = [], [], []
        scene["boundary"] = {}
        loc, text = "domain.mesh.data", "open"
    elif case == "nan_grid":
        scene["domain"] = {"terrain": {"data": NAN_GRID, "format": "asc", "base": 0}}
        scene["joints"], scene["excavations"], scene["stages"] = [], [], []
        scene["boundary"] = {}
        loc, text = "domain.terrain.data", "without an elevation"
    elif case == "outside":
        scene["excavations"][0]["cavern"]["center"] = [100, 0, 0]
        loc, text = "excavations[0] ('cavern')", "outside the domain"
    else:
        scene["stages"][1]["add_bolts"] = ["B99"]
        loc, text = "stages[1].add_bolts[0]", "unknown bolt 'B99'"
    problems = _problems(scene)
    assert any(p["loc"] == loc and text in p["msg"] for p in problems), problems


def test_cli_exit_2_and_api_422(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The command line exits 2 naming the field; the REST service answers 422, and refuses
    a file path (a server never reads files a scene names)."""
    scene = roof_wedge_scene()
    scene["stages"][1]["remove_bolts"] = ["nope"]
    path = tmp_path / "s.json"
    path.write_text(json.dumps(scene))
    code = main(["validate", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "stages[1].remove_bolts[0]: unknown bolt 'nope'" in err
    from tests.service_helpers import make_client

    with make_client(tmp_path / "data") as client:
        for bad, loc in ((scene, "stages[1].remove_bolts[0]"),
                         ({"domain": {"terrain": {"file": "/etc/passwd", "base": 0}}},
                          "domain.terrain.file")):
            r = client.post("/processes/simulation/execution", json={"inputs": {"scene": bad}})
            assert r.status_code == 422, r.text
            assert any(e["loc"] == loc for e in r.json()["errors"]), r.json()


# --------------------------------------------------------------------------- key blocks


def _key_table(build):  # noqa: ANN001, ANN202
    from engine.analyses.keyblocks import key_blocks
    from engine.geometry.excavations import EXCAVATION_TAG_BASE as BASE

    m = build.model
    strength = {tag: (math.tan(m.joint_materials[j].friction_angle_rad),
                      m.joint_materials[j].cohesion) for tag, j in m.joint_material_of_tag.items()}
    dj = m.joint_materials[m.default_joint_material]
    dens = np.array([m.materials[b.material].density for b in m.blocks])
    skip = {k for k, o in enumerate(build.excavated) if o is not None}
    return key_blocks([b.polyhedron for b in m.blocks], dens, m.gravity, {BASE}, strength,
                      (math.tan(dj.friction_angle_rad), dj.cohesion), skip, {-1})


def test_roof_wedge_is_a_falling_key_block(wedge_build) -> None:  # noqa: ANN001
    """Block theory: the roof wedge is removable and falls (FS 0); the arch around the
    opening (its outer faces free: the domain's surface) could only be lifted: stable."""
    table = {k.block: k for k in _key_table(wedge_build)}
    w = table[_wedge(wedge_build)]
    assert w.removable and w.mode == "falling" and w.factor_of_safety == 0.0
    others = [k for b, k in table.items() if b != _wedge(wedge_build)]
    assert others and all(k.mode == "stable" for k in others)


@pytest.mark.parametrize("delta", [-2.0, 2.0])
def test_sidewall_block_le_and_dda_agree(delta: float) -> None:
    """The sidewall block slides on its base alone: LE FS = tan φ / tan ψ (c = 0) within
    2 %; the DDA run slides (over 2 cm in 0.5 s: a = g (sin ψ − cos ψ tan φ) = 0.39 m/s²
    gives 4.8 cm at φ = ψ − 2°) when FS < 1 and holds (under 1 mm) when FS > 1."""
    from tests.excavation_scenes import PSI, sidewall_scene

    phi = PSI + delta
    build = build_model(sidewall_scene(phi))
    table = [k for k in _key_table(build) if k.mode != "stable"]
    assert len(table) == 1, table
    k = table[0]
    expected = math.tan(math.radians(phi)) / math.tan(math.radians(PSI))
    assert k.mode == "sliding on one plane" and k.removable
    assert k.factor_of_safety == pytest.approx(expected, rel=0.02)
    res = run_stages(build.model, build.stages)
    assert res.status == "completed", res.message
    moved = float(np.linalg.norm(res.summary["blocks"][k.block]["displacement"]))
    assert (moved > 0.02) if expected < 1 else (moved < 1e-3), moved


def test_cli_runs_stages_resumes_and_tables_key_blocks(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`polydda run` saves each stage's end; `--resume-from` the first stage's end with the
    same scene ends bit for bit where the whole run did, and with the second stage changed
    (the wedge held fixed: other support from the same saved state) ends elsewhere, the
    wedge where it was; `polydda keyblocks --result` says the wedge falls and the DDA moved it."""
    from engine.results.reader import open_result

    scene = roof_wedge_scene(fall=0.2)
    path = tmp_path / "wedge.json"
    path.write_text(json.dumps(scene))
    assert main(["run", str(path), "--out", str(tmp_path / "a.h5"), "--quiet"]) == 0
    stage1 = tmp_path / "a.h5.stages" / "stage-1.npz"
    assert stage1.exists() and (tmp_path / "a.h5.stages" / "stage-2.npz").exists()
    assert main(["run", str(path), "--out", str(tmp_path / "b.h5"), "--quiet",
                 "--resume-from", str(stage1)]) == 0
    glued = copy.deepcopy(scene)
    glued["stages"][1]["fix"] = [{"contains": [0.0, 0.0, 0.5]}]  # the wedge, held
    path2 = tmp_path / "glued.json"
    path2.write_text(json.dumps(glued))
    assert main(["run", str(path2), "--out", str(tmp_path / "c.h5"), "--quiet",
                 "--resume-from", str(stage1)]) == 0
    with open_result(tmp_path / "a.h5") as a, open_result(tmp_path / "b.h5") as b, \
            open_result(tmp_path / "c.h5") as c:
        end = a.centroids(len(a.times) - 1)
        assert np.array_equal(end, b.centroids(len(b.times) - 1))
        held = c.centroids(len(c.times) - 1)
        assert not np.allclose(end, held, atol=1e-3)
        assert np.allclose(held, c.centroids(0), atol=1e-4)  # nothing moves
        assert [s["name"] for s in a.stages()] == ["settle", "excavate"]
        assert a.stages()[1]["removed_blocks"] and "removed_energy" in a.energies()
    capsys.readouterr()
    assert main(["keyblocks", str(path), "--result", str(tmp_path / "a.h5"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = doc["excavations"][0]["blocks"]
    wedge = [r for r in rows if r["mode"] == "falling"]
    assert len(wedge) == 1 and wedge[0]["dda"] == "still moving at the end"  # 0.2 s of fall
    assert wedge[0]["weight"] == pytest.approx(2600 * 9.81 * WEDGE_VOLUME, rel=1e-9)


def test_stage_settings_resolve_in_order() -> None:
    """Each stage's complete setting: a bolt removed and another added, water on then drained,
    a seismic load then quiet, a block fixed then freed, a region excavated, a ground-motion
    record whose time starts with its stage."""
    scene = {
        "domain": {"box": {"min": [0, 0, 0], "max": [10, 10, 10]}},
        "joints": [{"name": "J", "dip": 90, "dip_direction": 90, "point": [5, 5, 5]}],
        "bolts": [{"name": "b1", "head": [2, 5, 5], "anchor": [8, 5, 5]},
                  {"name": "b2", "head": [2, 5, 6], "anchor": [8, 5, 6]}],
        "stages": [
            {"name": "a", "duration": 0.1},
            {"name": "b", "duration": 0.2, "remove_bolts": ["b2"],
             "fix": [{"contains": [2, 5, 5]}],
             "water": {"joint_pressures": [{"joint_material": "joint", "pressure": 1e4}]},
             "seismic": {"kh": 0.1, "azimuth": 90}},
            {"name": "c", "duration": 0.3, "add_bolts": ["b1"], "drain": True, "quiet": True,
             "free": [{"contains": [2, 5, 5]}],
             "excavate_region": {"min": [5, 0, 0], "max": [10, 10, 10]}},
            {"name": "d", "duration": 0.4, "ground_motion": {"time": [0, 1],
                                                             "acceleration": [[0, 0, 0],
                                                                              [1, 0, 0]]}},
        ]}
    build = build_model(scene)
    a, b, c, d = build.stages
    west = build.block_names.index(next(n for k, n in enumerate(build.block_names)
                                        if build.model.blocks[k].polyhedron.centroid[0] < 5))
    assert [s.end_time for s in build.stages] == pytest.approx([0.1, 0.3, 0.6, 1.0])
    assert build.model.controls.duration == pytest.approx(1.0)
    # b2, which no stage adds, acts from the start; b1 from the stage that adds it
    assert (a.bolts, b.bolts, c.bolts) == (("b2",), (), ("b1",))
    assert a.water is None and b.water.joint_pressure == {0: 1e4} and c.water is None
    assert b.seismic.kh == 0.1 and c.seismic is None and c.ground_motion is None
    assert west in b.fixed and west not in c.fixed
    assert not b.removed and c.removed == d.removed == frozenset({1 - west})
    assert d.ground_motion.times.tolist() == pytest.approx([0.6, 1.6])


def test_analyses_of_one_model_refuse_a_staged_scene(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    """A factor-of-safety search of a staged scene would analyse its rock before any stage:
    the command line exits 2 and the service answers 422, both naming `stages`."""
    path = tmp_path / "s.json"
    path.write_text(json.dumps(roof_wedge_scene()))
    assert main(["fos", str(path)]) == 2
    assert "stages: the factor-of-safety search analyses one model" in capsys.readouterr().err
    from tests.service_helpers import make_client

    with make_client(tmp_path / "data") as client:
        r = client.post("/processes/factor-of-safety/execution",
                        json={"inputs": {"scene": roof_wedge_scene()}})
        assert r.status_code == 422 and r.json()["errors"][0]["loc"] == "stages"


def test_an_excavation_cut_before_the_joints() -> None:
    """`cut: before_joints`: the domain never had the cavern's rock (12 × 14 × 18 m box less
    6 × 3 × 12 m), the joints then cut the wedge straight out of the roof; a stage cannot
    dig it again."""
    scene = roof_wedge_scene()
    scene["excavations"][0]["cut"] = "before_joints"
    scene["stages"] = []
    build = build_model(scene)
    assert build.excavated == [None] * len(build.model.blocks)
    total = sum(b.polyhedron.volume for b in build.model.blocks)
    assert total == pytest.approx(12 * 12 * 14 - 6 * 3 * 12, rel=1e-12)
    assert build.model.blocks[_wedge(build)].polyhedron.volume == pytest.approx(
        WEDGE_VOLUME, rel=1e-9)
    scene["stages"] = [{"name": "dig", "duration": 0.1, "excavate": ["cavern"]}]
    problems = _problems(scene)
    assert any(p["loc"] == "stages[0].excavate[0]" and "before the joints" in p["msg"]
               for p in problems), problems
