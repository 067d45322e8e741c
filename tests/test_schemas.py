"""Scene schema: defaults, units, conversion to the engine model, error catalogue, examples."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from engine.geometry.polyhedron import dip_normal, normal_to_dip
from schemas import (
    SCHEMA_VERSION,
    Limits,
    SceneError,
    build_model,
    load_scene,
    scene_json_schema,
)
from schemas.convert import overlap_depth
from tests.test_cutting import WEDGE, check_no_overlap

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def problems_of(source: Any, build: bool = True) -> list[str]:
    """The `loc: msg` lines of the SceneError that loading (and building) raises."""
    with pytest.raises(SceneError) as info:
        build_model(source) if build else load_scene(source)
    return info.value.lines()


def assert_problem(source: Any, expected: str) -> None:
    lines = problems_of(source)
    assert any(expected in line for line in lines), lines


# --------------------------------------------------------------------------- defaults


def test_defaults_serve_a_small_scene(cube_on_base: dict) -> None:
    result = build_model(cube_on_base)
    m = result.model
    assert result.material_names == ["rock"] and result.joint_material_names == ["joint"]
    assert (m.materials[0].density, m.materials[0].young_modulus) == (2600.0, 10e9)
    assert m.materials[0].poisson_ratio == 0.25
    jm = m.joint_materials[0]
    assert jm.friction_angle_rad == pytest.approx(np.radians(30.0), abs=1e-15)
    assert (jm.cohesion, jm.tensile_strength) == (0.0, 0.0)
    assert m.gravity.tolist() == [0.0, 0.0, -9.81]
    c = m.controls
    assert (c.duration, c.time_step, c.penalty, c.dynamic_ratio) == (1.0, 1e-3, None, 1.0)
    from engine.dynamics.system import default_penalty

    assert default_penalty(m) == 5e10  # the 1 m cube: 10 × 2 × 2600 kg / (1 ms)²
    assert c.contact_damping == 0.5
    assert c.block_model == "rigid" and c.record_contacts
    assert result.block_names == ["cube", "base"]
    assert [b.fixed for b in m.blocks] == [False, True]
    assert result.factor_of_safety is None


def test_unnamed_blocks_and_joints_get_position_names(box_block: Callable) -> None:
    scene = load_scene({"blocks": [box_block(None, [0, 0, 0], [1, 1, 1]),
                                   box_block(None, [0, 0, 1], [1, 1, 2])]})
    assert [scene.block_name(0), scene.block_name(1)] == ["block1", "block2"]


def test_degrees_become_radians_and_normals() -> None:
    result = build_model(EXAMPLES / "wedge.json")
    m = result.model
    assert m.joint_materials[0].friction_angle_rad == pytest.approx(np.radians(40.0), rel=1e-15)
    wedge = m.blocks[result.block_index("B2")].polyhedron
    for tag, (dip, ddir) in enumerate([(50, 110), (55, 240)]):
        normals = wedge.face_normals[wedge.face_tags == tag]
        assert len(normals) == 1
        # the wedge lies above its joints: its face normal on a joint points down
        assert normals[0] == pytest.approx(-dip_normal(dip, ddir), abs=1e-9)
        assert normal_to_dip(normals[0]) == pytest.approx((dip, ddir), abs=1e-7)


def test_one_material_is_the_default_several_need_a_choice(box_block: Callable) -> None:
    scene = {"materials": {"granite": {"density": 2700}, "shale": {"density": 2400}},
             "blocks": [box_block("a", [0, 0, 0], [1, 1, 1], material="shale"),
                        box_block("b", [0, 0, 1], [1, 1, 2])]}
    assert_problem(scene, "blocks[1] ('b').material: is required when several materials")
    scene["default_material"] = "granite"
    m = build_model(scene).model
    assert [m.materials[b.material].density for b in m.blocks] == [2400.0, 2700.0]


def test_several_joint_materials_need_a_default(cube_on_base: dict) -> None:
    cube_on_base["joint_materials"] = {"a": {}, "b": {"friction_angle": 10}}
    assert_problem(cube_on_base, "default_joint_material: is required when several joint")
    cube_on_base["default_joint_material"] = "b"
    m = build_model(cube_on_base).model
    assert m.default_joint_material == 1
    assert m.joint_materials[1].friction_angle_rad == pytest.approx(np.radians(10.0))


def test_modes_and_controls(cube_on_base: dict) -> None:
    cube_on_base["analysis"] = {"mode": "quasi_static", "duration": 2, "time_step": 5e-4,
                                "penalty": 3e11, "shear_penalty_ratio": 0.5,
                                "record_interval": 4, "block_model": "elastic",
                                "max_displacement_ratio": 0.005,
                                "max_open_close_iterations": 12, "record_contacts": False,
                                "open_close_tolerance": 1e-3}
    c = build_model(cube_on_base).model.controls
    assert c.dynamic_ratio == 0.0
    assert (c.duration, c.time_step, c.penalty, c.shear_penalty_ratio) == (2, 5e-4, 3e11, 0.5)
    assert (c.record_interval, c.block_model, c.max_displacement_ratio) == (4, "elastic", 0.005)
    assert (c.max_open_close_iterations, c.record_contacts) == (12, False)
    assert c.open_close_tolerance == 1e-3
    cube_on_base["analysis"] = {"dynamic_ratio": 0.9}
    assert build_model(cube_on_base).model.controls.dynamic_ratio == 0.9


def test_factor_of_safety_settings() -> None:
    scene = json.loads((EXAMPLES / "wedge.json").read_text())
    scene["analysis"]["type"] = "factor_of_safety"
    scene["analysis"]["factor_of_safety"] = {"tolerance": 0.005, "joint_materials": ["joint"]}
    fos = build_model(scene).factor_of_safety
    assert fos is not None
    assert (fos.tolerance, fos.joint_materials, fos.watch_blocks) == (0.005, (0,), (1,))
    scene["analysis"]["factor_of_safety"] = {"min_factor": 3, "max_factor": 2}
    assert_problem(scene, "analysis.factor_of_safety: max_factor (2) must exceed min_factor")
    # the old acceleration criterion's settings (and the window's old name) are still read,
    # and said to be unused
    scene["analysis"]["factor_of_safety"] = {"averaging_start": 0.5, "observation_time": 2,
                                             "acceleration_threshold": 0.02,
                                             "displacement_limit": 0.05}
    built = build_model(scene)
    fos = built.factor_of_safety
    assert (fos.observation_time, fos.displacement_limit) == (2.0, 0.05)
    assert [w.split(":")[0] for w in built.warnings] == [
        "analysis.factor_of_safety.window_start",
        "analysis.factor_of_safety.acceleration_threshold"]


def test_scene_defaults_are_the_engines(cube_on_base: dict) -> None:
    """Defaults live in one place, the engine: a scene that says nothing gets the engine's
    analysis controls, materials and strength-reduction settings."""
    from engine.model import (
        AnalysisControls,
        JointMaterial,
        Material,
        StrengthReductionControls,
    )

    cube_on_base["analysis"] = {"type": "factor_of_safety"}
    built = build_model(cube_on_base)
    m = built.model
    assert m.controls == AnalysisControls()
    assert m.materials == [Material()]
    assert m.joint_materials == [JointMaterial()]
    free = tuple(k for k, b in enumerate(m.blocks) if not b.fixed)
    assert built.factor_of_safety == StrengthReductionControls(
        joint_materials=(0,), watch_blocks=free)


# --------------------------------------------------------------------------- conversion


def test_loads_fixed_points_velocity_and_pairs(cube_on_base: dict) -> None:
    cube_on_base["blocks"][0]["velocity"] = {"translation": [1, 2, 3], "spin": [0, 0, 0.5]}
    cube_on_base["joint_materials"] = {"joint": {}, "smooth": {"friction_angle": 5}}
    cube_on_base["default_joint_material"] = "joint"
    cube_on_base["block_pairs"] = [{"blocks": ["base", "cube"], "joint_material": "smooth"}]
    cube_on_base["boundary"] = {
        "point_loads": [{"point": [0, 0.5, 0.5], "force": [100, 0, 0]}],   # on the -x face
        "fixed_points": [{"block": {"contains": [0.5, 0.5, 0.5]}, "point": [1, 1, 1]}],
    }
    m = build_model(cube_on_base).model
    assert m.blocks[0].velocity.tolist() == [1, 2, 3, 0, 0, 0.5]
    assert m.pair_joint_material == {(0, 1): 1}
    assert len(m.point_loads) == 1 and m.point_loads[0].block == 0
    assert m.point_loads[0].force.tolist() == [100, 0, 0]
    assert m.fixed_points[0].block == 0 and m.fixed_points[0].point.tolist() == [1, 1, 1]


def test_joint_tags_map_to_joint_materials() -> None:
    scene = {
        "joint_materials": {"weak": {"friction_angle": 20}, "strong": {"friction_angle": 45}},
        "default_joint_material": "strong",
        "domain": {"box": {"min": [0, 0, 0], "max": [4, 1, 1]}},
        "joints": [{"name": "A", "dip": 90, "dip_direction": 90, "point": [1, 0, 0],
                    "joint_material": "weak"},
                   {"name": "B", "dip": 90, "dip_direction": 90, "point": [3, 0, 0]}],
    }
    result = build_model(scene)
    assert result.model.joint_material_of_tag == {0: 0, 1: 1}
    assert result.joint_names == ["A", "B"]
    assert [round(b.polyhedron.volume, 12) for b in result.model.blocks] == [1.0, 2.0, 1.0]


def test_min_block_volume_merges_small_cut_blocks() -> None:
    """A joint 0.2 mm below the top of a 1 m cube leaves a 2e-4 m³ slab: kept when
    asked (0), merged into the block below by default, never a field error."""
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}},
             "joints": [{"dip": 0, "dip_direction": 0, "point": [0, 0, 0.9998]},
                        {"dip": 0, "dip_direction": 0, "point": [0, 0, 0.5]}]}
    assert [round(b.polyhedron.volume, 9) for b in build_model(scene).model.blocks] == [
        0.5, 0.5]
    scene["domain"]["min_block_volume"] = 0  # still a sliver by its width
    assert [round(b.polyhedron.volume, 9) for b in build_model(scene).model.blocks] == [
        0.5, 0.5]
    scene["domain"]["min_block_width"] = 0
    assert [round(b.polyhedron.volume, 9) for b in build_model(scene).model.blocks] == [
        0.5, 0.4998, 0.0002]
    scene["domain"]["min_block_volume"] = -1
    with pytest.raises(SceneError, match="domain.min_block_volume"):
        build_model(scene)
    scene["domain"]["min_block_volume"] = 0
    scene["domain"]["min_block_width"] = -1
    with pytest.raises(SceneError, match="domain.min_block_width"):
        build_model(scene)


def test_cut_blocks_are_named_by_centroid_z_then_y_then_x() -> None:
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [3, 2, 2]}, "name_prefix": "C"},
             "joints": [{"dip": 90, "dip_direction": 90, "point": [0.5, 0, 0], "spacing": 1},
                        {"dip": 0, "dip_direction": 0, "point": [0, 0, 1]},
                        {"dip": 90, "dip_direction": 0, "point": [0, 1, 0]}]}
    result = build_model(scene)
    assert result.block_names == [f"C{k}" for k in range(1, 17)]
    c = np.array([b.polyhedron.centroid for b in result.model.blocks])
    key = [tuple(np.round(p[::-1], 9)) for p in c]
    assert key == sorted(key)
    assert c[0].tolist() == pytest.approx([0.25, 0.5, 0.5])
    assert c[-1].tolist() == pytest.approx([2.75, 1.5, 1.5])


def test_disc_extent_cuts_only_where_it_reaches() -> None:
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}},
             "joints": [{"dip": 0, "dip_direction": 0, "point": [0.5, 0.5, 0.5],
                         "extent": {"disc": {"radius": 2.0}}}]}
    assert len(build_model(scene).model.blocks) == 2
    scene["joints"][0]["extent"]["disc"]["radius"] = 0.3
    result = build_model(scene)
    assert len(result.model.blocks) == 1
    assert len(result.warnings) == 2 and "cuts nothing" in result.warnings[0]
    assert result.warnings[1].startswith("nothing is fixed")  # and the cube would fall


def test_concave_explicit_block_gets_convex_pieces() -> None:
    # an L-shaped prism: 2 x 2 x 1 with the 1 x 1 corner (x > 1, y > 1) removed
    ring = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]
    verts = [[x, y, 0.0] for x, y in ring] + [[x, y, 1.0] for x, y in ring]
    faces = [[5, 4, 3, 2, 1, 0], [6, 7, 8, 9, 10, 11]]
    faces += [[k, (k + 1) % 6, (k + 1) % 6 + 6, k + 6] for k in range(6)]
    scene = {"blocks": [{"name": "L", "vertices": verts, "faces": faces}]}
    poly = build_model(scene).model.blocks[0].polyhedron
    assert not poly.is_convex
    assert poly.volume == pytest.approx(3.0)
    assert len(poly.convex_pieces()) >= 2


def test_overlap_depth_is_zero_for_touching_and_positive_for_overlapping() -> None:
    from schemas.convert import box_polyhedron
    from schemas.scene import BoxSpec

    a = box_polyhedron(BoxSpec(min=[0, 0, 0], max=[1, 1, 1]))
    b = box_polyhedron(BoxSpec(min=[1, 0, 0], max=[2, 1, 1]))
    c = box_polyhedron(BoxSpec(min=[0.8, 0.2, 0.2], max=[1.8, 1.2, 1.2]))
    assert abs(overlap_depth(a, b)) < 1e-12
    assert overlap_depth(a, c) == pytest.approx(0.1)


# --------------------------------------------------------------------------- errors


def test_open_block_surface_names_the_block_and_edge(box_block: Callable) -> None:
    block = box_block("wedge", [0, 0, 0], [1, 1, 1])
    del block["faces"][1]  # the top
    assert_problem({"blocks": [block]},
                   "blocks[0] ('wedge').faces: faces are not closed: edge (")


def test_inside_out_and_misoriented_blocks(box_block: Callable) -> None:
    block = box_block("a", [0, 0, 0], [1, 1, 1])
    block["faces"] = [f[::-1] for f in block["faces"]]
    assert_problem({"blocks": [block]}, "blocks[0] ('a').faces: volume is not positive")
    block["faces"][0] = block["faces"][0][::-1]
    assert_problem({"blocks": [block]}, "faces are not consistently oriented")


def test_friction_angle_range(box_block: Callable) -> None:
    lines = problems_of({"joint_materials": {"joint": {"friction_angle": 95}},
                         "blocks": [box_block("a", [0, 0, 0], [1, 1, 1])]})
    assert lines == ["joint_materials.joint.friction_angle: must be between 0 and 90 degrees, "
                     "got 95"]


@pytest.mark.parametrize("field,value,message", [
    ("density", -2600, "must be positive, got -2600"),
    ("density", 0, "must be positive, got 0"),
    ("young_modulus", "stiff", "must be a number, got 'stiff'"),
    ("poisson_ratio", 0.5, "must be less than 0.5, got 0.5"),
])
def test_material_values(field: str, value: Any, message: str, box_block: Callable) -> None:
    scene = {"materials": {"rock": {field: value}},
             "blocks": [box_block("a", [0, 0, 0], [1, 1, 1])]}
    assert problems_of(scene) == [f"materials.rock.{field}: {message}"]


def test_unknown_material_lists_the_known_ones(box_block: Callable) -> None:
    scene = {"materials": {"rock": {}},
             "blocks": [box_block(None, [0, 0, 0], [1, 1, 1]),
                        box_block(None, [0, 0, 1], [1, 1, 2], material="granit")]}
    assert problems_of(scene) == ["blocks[1].material: unknown material 'granit' (known: rock)"]


def test_typos_are_caught_with_a_suggestion(cube_on_base: dict) -> None:
    cube_on_base["materials"] = {"rock": {"densty": 2600}}
    cube_on_base["analysis"] = {"time_stp": 0.001}
    lines = problems_of(cube_on_base)
    assert "materials.rock.densty: unknown field (did you mean 'density'?)" in lines
    assert "analysis.time_stp: unknown field (did you mean 'time_step'?)" in lines


def test_shape_and_type_errors() -> None:
    scene = {"blocks": [{"name": "a", "vertices": [[0, 0]], "faces": "none"}],
             "gravity": [0, -9.81], "analysis": {"mode": "dynamik"}}
    lines = problems_of(scene)
    assert "blocks[0] ('a').vertices[0]: must be 3 numbers [x, y, z], got 2" in lines
    assert "blocks[0] ('a').faces: must be a list [...], got 'none'" in lines
    assert "gravity: must be 3 numbers [x, y, z], got 2" in lines
    assert "analysis.mode: must be one of 'dynamic' or 'quasi_static', got 'dynamik'" in lines
    assert problems_of({"blocks": [{"name": "a", "faces": []}]}) == [
        "blocks[0] ('a').vertices: is required"]


def test_malformed_json_and_missing_file(tmp_path: Path) -> None:
    lines = problems_of('{"blocks": [}', build=False)
    assert len(lines) == 1 and lines[0].startswith("not valid JSON:") and "line 1" in lines[0]
    assert problems_of(tmp_path / "nope.json") == [f"{tmp_path / 'nope.json'}: file not found"]
    assert problems_of("[1, 2]") == ["a scene must be a JSON object {...}"]
    assert problems_of({}) == [
        "the scene has no blocks: give a 'domain' (cut by 'joints') or 'blocks'"]


def test_contains_point_inside_no_block(cube_on_base: dict) -> None:
    cube_on_base["boundary"] = {"fixed_blocks": [{"contains": [0, 0, 99]}]}
    assert problems_of(cube_on_base) == [
        "boundary.fixed_blocks[0].contains: point (0, 0, 99) is inside no block"]
    cube_on_base["boundary"] = {"fixed_blocks": [{"contains": [0.5, 0.5, 1.0]}]}
    assert_problem(cube_on_base, "lies on the surface of 'cube'")


def test_unknown_block_name_and_selection_rules(cube_on_base: dict) -> None:
    cube_on_base["boundary"] = {"fixed_blocks": ["cub"]}
    assert problems_of(cube_on_base) == [
        "boundary.fixed_blocks[0].name: unknown block 'cub' (known: cube, base)"]
    cube_on_base["boundary"] = {"fixed_blocks": [{"name": "cube", "contains": [0, 0, 0]}]}
    lines = problems_of(cube_on_base)
    assert ("boundary.fixed_blocks[0] ('cube'): give exactly one of 'name', 'contains' or "
            "'centroid_in' (got 'name' and 'contains')") in lines
    cube_on_base["boundary"] = {"fixed_blocks": [{"centroid_in": {"min": [-5, -5, -5],
                                                                  "max": [5, 5, 0.6]}}]}
    assert all(b.fixed for b in build_model(cube_on_base).model.blocks)


def test_point_load_must_touch_its_block(cube_on_base: dict) -> None:
    cube_on_base["boundary"] = {"point_loads": [{"block": "cube", "point": [5, 5, 5],
                                                 "force": [1, 0, 0]}]}
    assert problems_of(cube_on_base) == [
        "boundary.point_loads[0].point: point (5, 5, 5) is not on or inside block 'cube'"]
    cube_on_base["boundary"] = {"point_loads": [{"point": [0.5, 0.5, 0], "force": [1, 0, 0]}]}
    assert_problem(cube_on_base, "touches several blocks ('cube', 'base')")


def test_overlapping_explicit_blocks(box_block: Callable) -> None:
    scene = {"blocks": [box_block("a", [0, 0, 0], [1, 1, 1]),
                        box_block("b", [0.5, 0.5, 0.5], [1.5, 1.5, 1.5])]}
    lines = problems_of(scene)
    assert len(lines) == 1 and "blocks 'a' and 'b' overlap" in lines[0]
    assert lines[0].startswith("blocks[0] ('a'): ")
    scene["boundary"] = {"fixed_blocks": ["b"]}
    assert len(problems_of(scene)) == 1  # one fixed block still clashes with a free one
    scene["blocks"][0]["fixed"] = True  # two fixed blocks never meet in the analysis
    assert build_model(scene).block_names == ["a", "b"]


def test_explicit_block_overlapping_a_cut_block_and_name_clash(box_block: Callable) -> None:
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [2, 2, 2]}},
             "blocks": [box_block("B1", [1, 1, 1], [3, 3, 3])]}
    lines = problems_of(scene)
    assert any(ln.startswith("blocks[0] ('B1').name: 'B1' is also the name of a block cut")
               for ln in lines), lines
    scene["blocks"][0]["name"] = "intruder"
    assert problems_of(scene) == [
        "blocks[0] ('intruder'): blocks 'intruder' and 'B1' overlap (by up to 1 m)"]


def test_duplicate_names_and_joints_without_domain(box_block: Callable) -> None:
    scene = {"blocks": [box_block("a", [0, 0, 0], [1, 1, 1]), box_block("a", [0, 0, 1],
                                                                        [1, 1, 2])],
             "joints": [{"dip": 10, "dip_direction": 20, "point": [0, 0, 0]}]}
    lines = problems_of(scene)
    assert "blocks[1] ('a').name: block name 'a' is used twice (also blocks[0])" in lines
    assert "joints: joints cut a domain: give 'domain' (a box or a polyhedron)" in lines


def test_bad_joint_polygons() -> None:
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}},
             "joints": [{"name": "J", "dip": 0, "dip_direction": 0, "point": [0, 0, 0.5],
                         "extent": {"polygon": [[0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.9]]}}]}
    assert_problem(scene, "joints[0] ('J').extent.polygon: the polygon is not on the joint plane")
    scene["joints"][0]["extent"]["polygon"] = [[0, 0, 0.5], [1, 1, 0.5], [1, 0, 0.5],
                                               [0, 1, 0.5]]
    assert_problem(scene, "the polygon must be convex")
    scene["joints"][0]["dip"] = 91
    assert_problem(scene, "joints[0] ('J').dip: must be between 0 and 90 degrees, got 91")


def test_limits_are_checked_before_heavy_work(monkeypatch: pytest.MonkeyPatch,
                                              cube_on_base: dict) -> None:
    assert Limits.max_vertices == 200_000 and Limits.max_steps == 10_000_000

    def forbidden(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("geometry was checked before the size limit")

    monkeypatch.setattr("schemas.convert.polyhedron_problems", forbidden)
    monkeypatch.setattr(Limits, "max_vertices", 15)
    assert problems_of(cube_on_base) == ["the scene has 16 vertices in all; the limit is 15"]


def test_absurd_step_count(cube_on_base: dict) -> None:
    cube_on_base["analysis"] = {"duration": 1e5, "time_step": 1e-3}
    assert problems_of(cube_on_base) == [
        "analysis.time_step: duration / time_step = 1e+08 steps; the limit is 10,000,000 "
        "(shorten the duration or enlarge the time step)"]
    cube_on_base["analysis"] = {"duration": 1, "time_step": 2}
    assert_problem(cube_on_base, "analysis: time_step (2 s) must not exceed duration (1 s)")


def test_dense_joint_sets_are_refused() -> None:
    scene = {"domain": {"box": {"min": [0, 0, 0], "max": [100, 100, 100]}},
             "joints": [{"dip": 45, "dip_direction": 0, "point": [0, 0, 0], "spacing": 0.01}]}
    assert_problem(scene, "joints: the joint sets make about 17,322 planes across the domain")


def test_cut_block_estimate_before_cutting(monkeypatch: pytest.MonkeyPatch) -> None:
    """Exact for sets normal to a box's sides, close for oblique ones; a scene over the block
    limit is refused without cutting."""
    from schemas.scene import Scene, estimate_cut_blocks

    def count(scene: dict) -> tuple[float, int]:
        est = estimate_cut_blocks(Scene.model_validate(scene))
        return est, len(build_model(scene).model.blocks)

    grid = {"domain": {"box": {"min": [0, 0, 0], "max": [3, 2, 2]}},
            "joints": [{"dip": 90, "dip_direction": 90, "point": [0.5, 0, 0], "spacing": 1},
                       {"dip": 0, "dip_direction": 0, "point": [0, 0, 1]},
                       {"dip": 90, "dip_direction": 0, "point": [0, 1, 0]}]}
    assert count(grid) == (16, 16)
    grid["joints"].append({"dip": 90, "dip_direction": 270, "point": [0, 0, 0],
                           "spacing": 1})  # parallel to the first set: the planes double
    assert count(grid)[0] == 28
    rock = {"domain": {"box": {"min": [0, 0, 0], "max": [10, 10, 10]}, "min_block_volume": 0},
            "joints": [{"dip": dip, "dip_direction": ddir, "point": [5, 5, 5], "spacing": 2.5}
                       for dip, ddir in [(80, 30), (75, 150), (20, 270)]]}
    est, n = count(rock)
    assert n == pytest.approx(est, rel=0.1), (est, n)

    def no_cutting(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the domain was cut")

    monkeypatch.setattr("engine.geometry.cutting.cut.cut_blocks", no_cutting)
    for j in rock["joints"]:
        j["spacing"] = 0.3
    assert problems_of(rock) == [
        "joints: the joints would cut the domain into about 38,000 blocks; the limit is "
        "20,000 (increase the spacings)"]


def test_scene_error_carries_structured_problems() -> None:
    with pytest.raises(SceneError) as info:
        load_scene({"materials": {"rock": {"density": -1}}, "blocks": []})
    problems = info.value.problems
    assert {"loc": "materials.rock.density", "msg": "must be positive, got -1"} in problems
    assert all(set(p) == {"loc", "msg"} for p in problems)
    assert str(info.value).splitlines() == info.value.lines()


_json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6)
    | st.floats(allow_nan=False, allow_infinity=False, width=32) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                max_size=3),
    max_leaves=8,
)


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for k, v in enumerate(node):
            out += _paths(v, prefix + (k,))
    return out


_BASE = json.loads((EXAMPLES / "pushed_block.json").read_text())
_BASE_PATHS = _paths(_BASE)[1:]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(_BASE_PATHS), _json_values)
def test_any_mutation_gives_a_scene_error_or_a_model(path: tuple, value: Any) -> None:
    scene = copy.deepcopy(_BASE)
    node = scene
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    try:
        result = build_model(scene)
    except SceneError as exc:
        assert exc.problems and all(p["msg"] for p in exc.problems)
    else:
        assert len(result.model.blocks) == 2


# --------------------------------------------------------------------------- JSON Schema


def test_json_schema_export() -> None:
    schema = scene_json_schema()
    assert schema["x-schema-version"] == SCHEMA_VERSION
    assert schema["$schema"].endswith("2020-12/schema")
    assert schema["additionalProperties"] is False
    for key in ("materials", "joint_materials", "domain", "joints", "blocks", "block_pairs",
                "boundary", "gravity", "analysis"):
        assert key in schema["properties"]
    jm = schema["$defs"]["JointMaterialSpec"]["properties"]["friction_angle"]
    assert (jm["minimum"], jm["exclusiveMaximum"], jm["default"]) == (0, 90, 30.0)
    json.dumps(schema)


def test_examples_validate_against_the_json_schema() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    validator = jsonschema.Draft202012Validator(scene_json_schema())
    for path in sorted(EXAMPLES.glob("*.json")):
        errors = list(validator.iter_errors(json.loads(path.read_text())))
        assert not errors, (path.name, errors[:1])
    bad = {"materials": {"rock": {"density": -1}}}
    assert list(validator.iter_errors(bad))


# --------------------------------------------------------------------------- examples


@pytest.fixture(scope="module")
def built() -> dict[str, Any]:
    return {p.stem: build_model(p) for p in sorted(EXAMPLES.glob("*.json"))}


def test_every_example_loads_and_builds(built: dict[str, Any]) -> None:
    assert set(built) >= {"wedge", "block_system", "incline", "free_fall", "pushed_block",
                          "stack", "toppling"}
    for name, result in built.items():
        # cut rock masses merge slivers and say so; the slopes' sets have planes that cross
        # their bounding box above the ground and miss the rock (their warning tells the
        # user); nothing else may warn
        slopes = ("jointed_slope", "benched_slope", "terrain_slope")
        notes = [w for w in result.warnings if "merged into" not in w
                 and not (name in slopes and "cut nothing" in w)]
        assert not notes, (name, result.warnings)
        assert any(b.fixed for b in result.model.blocks), name
        assert not all(b.fixed for b in result.model.blocks), name
    assert "main demo" in json.loads((EXAMPLES / "wedge.json").read_text())["description"]


def test_example_wedge(built: dict[str, Any]) -> None:
    """examples/wedge.json cuts into the paper's tetrahedral wedge (issue's vertices, 1e-5
    m) and one concave, fixed base block; the two do not overlap."""
    r = built["wedge"]
    free = [b for b in r.model.blocks if not b.fixed]
    assert len(r.model.blocks) == 2 and len(free) == 1
    wedge = free[0].polyhedron
    assert wedge.volume == pytest.approx(29.7708, abs=1e-4)
    d = np.linalg.norm(wedge.vertices[:, None] - WEDGE[None], axis=2)
    assert len(wedge.vertices) == 4 and d.min(axis=0).max() < 1e-5
    base = next(b for b in r.model.blocks if b.fixed).polyhedron
    assert not base.is_convex
    check_no_overlap([wedge, base])
    assert r.model.controls.penalty == 3e10


def test_example_block_system(built: dict[str, Any]) -> None:
    r = built["block_system"]
    cut = [b.polyhedron.volume for b, s in zip(r.model.blocks, r.block_sources, strict=True)
           if s == "cut"]
    assert len(cut) == 30
    assert sum(cut) == pytest.approx(1000.0, rel=1e-9)
    check_no_overlap([b.polyhedron for b, s in zip(r.model.blocks, r.block_sources,
                                                   strict=True) if s == "cut"])
    assert all(r.model.joint_materials[r.model.joint_material_of_tag[t]].friction_angle_rad == 0
               for t in range(3))


def test_example_incline(built: dict[str, Any]) -> None:
    r = built["incline"]
    slab = r.model.blocks[r.block_index("slab")].polyhedron
    top = slab.face_normals[np.argmax(slab.face_normals[:, 2])]
    assert normal_to_dip(top) == pytest.approx((30.0, 90.0), abs=1e-4)
    assert r.model.joint_materials[0].friction_angle_rad == pytest.approx(np.radians(20))


def test_example_free_fall(built: dict[str, Any]) -> None:
    r = built["free_fall"]
    cube, base = (r.model.blocks[r.block_index(n)].polyhedron for n in ("cube", "base"))
    assert cube.bounds[0][2] - base.bounds[1][2] == pytest.approx(1.0, abs=1e-12)
    assert r.model.controls.penalty == 1e9


def test_example_pushed_block(built: dict[str, Any]) -> None:
    r = built["pushed_block"]
    (load,) = r.model.point_loads
    weight = r.model.materials[0].density * 9.81 * 1.0
    tan_phi = np.tan(r.model.joint_materials[0].friction_angle_rad)
    assert load.force[0] / (weight * tan_phi) == pytest.approx(1.5, rel=1e-7)
    assert load.point[2] == pytest.approx(r.model.blocks[load.block].polyhedron.centroid[2])


def test_example_stack(built: dict[str, Any]) -> None:
    r = built["stack"]
    free = [b.polyhedron for b in r.model.blocks if not b.fixed]
    assert sorted(p.centroid[2] for p in free) == pytest.approx([0.5, 1.5, 2.5])


def test_example_toppling(built: dict[str, Any]) -> None:
    r = built["toppling"]
    m = r.model
    free = [b.polyhedron for b in m.blocks if not b.fixed]
    assert [p.volume for p in free] == pytest.approx([18.0] * 6, rel=1e-8)
    slab = r.block_index("slab")
    assert sorted(m.pair_joint_material) == [(k, slab) for k in range(6)]
    phi = {round(np.degrees(m.joint_materials[j].friction_angle_rad), 9)
           for j in m.pair_joint_material.values()}
    assert phi == {40.0}
    assert np.degrees(m.joint_materials[m.default_joint_material].friction_angle_rad) == (
        pytest.approx(15.0))
