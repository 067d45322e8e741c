"""Stages that change the loads, checked against limit equilibrium derived by hand: a
block on a 30° plane (φ 40°, tests.test_simulation.incline_model) that holds until a stage
applies a seismic coefficient or water pressure beyond its yield value; a stage that
weakens the joint; elastic blocks through an excavation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.loads.seismic import SeismicLoad
from engine.loads.water import Water
from engine.model import JointMaterial
from engine.step.staged_run import run_stages
from engine.step.stages import Stage
from tests.test_simulation import ALPHA, DOWN_DIP, G, incline_model

PHI = 40.0
#: yield coefficient of a block on a plane dipping α under a horizontal force kh W down
#: the dip: W (sin α + kh cos α) = W (cos α − kh sin α) tan φ  =>  kc = tan(φ − α)
KC = math.tan(math.radians(PHI) - ALPHA)
#: yield uplift pressure on the 1 m² base of the 1 m cube (W = ρ g): tan φ (W cos α − p) =
#: W sin α  =>  p_c = W (cos α − sin α / tan φ)
W = 2600 * G
PC = W * (math.cos(ALPHA) - math.sin(ALPHA) / math.tan(math.radians(PHI)))


def _slid(stages: list[Stage]) -> float:
    """Down-dip displacement (m) of the block at the end of the stages."""
    model = incline_model(PHI, duration=stages[-1].end_time)
    res = run_stages(model, stages)
    assert res.status == "completed", res.message
    assert res.summary["energy"]["created_ratio"] < 1e-3
    return float(np.asarray(res.summary["blocks"][1]["displacement"]) @ DOWN_DIP)


def _stages(**second: object) -> list[Stage]:
    fixed = frozenset({0})
    jm = (JointMaterial(math.radians(PHI)),)
    return [Stage("settle", 0.2, fixed=fixed, joint_materials=jm),
            Stage("load", 0.7, fixed=fixed, **{"joint_materials": jm, **second})]


@pytest.mark.parametrize("factor", [0.8, 1.25])
def test_a_seismic_stage_beyond_the_yield_coefficient_slides(factor: float) -> None:
    """kh = 0.8 kc holds (0.1 mm); kh = 1.25 kc slides ½ a t² over the stage's 0.5 s with
    a = g ((sin α + kh cos α) − (cos α − kh sin α) tan φ) (within 2 %)."""
    kh = factor * KC
    d = _slid(_stages(seismic=SeismicLoad(kh=kh, azimuth_rad=math.radians(90.0))))
    if factor < 1:
        assert abs(d) < 1e-4
    else:
        a = G * ((math.sin(ALPHA) + kh * math.cos(ALPHA))
                 - (math.cos(ALPHA) - kh * math.sin(ALPHA)) * math.tan(math.radians(PHI)))
        assert d == pytest.approx(0.5 * a * 0.5**2, rel=0.02)


@pytest.mark.parametrize("factor", [0.8, 1.2])
def test_a_water_stage_beyond_the_yield_pressure_slides(factor: float) -> None:
    """A uniform pressure p on the joint from the second stage: p = 0.8 p_c holds, 1.2 p_c
    slides (a = g sin α − (g cos α − p / ρ) tan φ, within 3 %: the pressure acts on the
    wetted contact area, which the contact springs keep at 1 m²)."""
    p = factor * PC
    d = _slid(_stages(water=Water(joint_pressure={0: p})))
    if factor < 1:
        assert abs(d) < 1e-4
    else:
        a = G * math.sin(ALPHA) - (G * math.cos(ALPHA) - p / 2600) * math.tan(
            math.radians(PHI))
        assert d == pytest.approx(0.5 * a * 0.5**2, rel=0.03)


def test_a_stage_that_weakens_the_joint() -> None:
    """φ 40° → 20° at the second stage: the block slides ½ g (sin α − cos α tan 20°) t²."""
    d = _slid(_stages(joint_materials=(JointMaterial(math.radians(20.0)),)))
    a = G * (math.sin(ALPHA) - math.cos(ALPHA) * math.tan(math.radians(20.0)))
    assert d == pytest.approx(0.5 * a * 0.5**2, rel=0.01)


def test_elastic_blocks_through_an_excavation() -> None:
    """The roof wedge with elastic blocks: the stress arrays follow the kept blocks, the
    wedge still falls ½ g t² (1 %), and the strain energy of the removed core is booked."""
    from schemas.convert import build_model
    from tests.excavation_scenes import roof_wedge_scene

    scene = roof_wedge_scene(fall=0.3)
    scene["analysis"]["block_model"] = "elastic"
    build = build_model(scene)
    res = run_stages(build.model, build.stages)
    assert res.status == "completed", res.message
    w = next(k for k, b in enumerate(build.model.blocks)
             if {0, 1, 2} <= set(b.polyhedron.face_tags.tolist()))
    assert -res.summary["blocks"][w]["displacement"][2] == pytest.approx(
        0.5 * G * 0.3**2, rel=0.01)
    assert res.state.stress.shape == (len(build.model.blocks) - 1, 6)
    assert res.summary["removed_energy"] > 0
    assert res.summary["energy"]["created_ratio"] < 1e-3


def test_removing_a_falling_block_books_its_kinetic_energy() -> None:
    """A 1 m cube falls freely from rest; a stage at t = 0.2 s removes it in flight. Its
    kinetic energy then, ½ m (g t)² = ½ 2600 (9.81 · 0.2)² = 5,004.5 J, leaves as
    removed_energy (1e-6): the work gravity did on it stays booked, nothing is created."""
    from engine.geometry.shapes import box
    from engine.model import AnalysisControls, Block, Model

    model = Model(
        blocks=[Block(box([-3, -3, -1], [3, 3, 0]), "base", fixed=True),
                Block(box([0, 0, 5], [1, 1, 6]), "falling"),
                Block(box([-2, -2, 0], [-1, -1, 1]), "resting")],
        controls=AnalysisControls(duration=0.3, time_step=1e-3, penalty=1e10))
    stages = [Stage("fall", 0.2, fixed=frozenset({0})),
              Stage("dig", 0.3, removed=frozenset({1}), fixed=frozenset({0}))]
    res = run_stages(model, stages)
    assert res.status == "completed", res.message
    ke = 0.5 * 2600 * (G * 0.2) ** 2
    assert res.summary["stages"][1]["removed_energy"] == pytest.approx(ke, rel=1e-6)
    e = res.state.energies
    assert e["gravity_work"] == pytest.approx(ke, rel=1e-3)  # the resting cube adds ~0
    assert res.summary["energy"]["created_ratio"] < 1e-6
    assert res.summary["blocks"][1]["removed"] and res.summary["blocks"][1][
        "removed_in_stage"] == "dig"
