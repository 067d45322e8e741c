"""The complementarity contact solve against the analytic cases (docs/validation.md).

Hard contacts: no penalty spring, so where the open-close iteration's answers carry the
spring's penetration W/k, these are exact (to the solve's tolerance). Each case's model is
test_simulation's, with `contact_solver="complementarity"`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.contact.solvers import complementarity
from engine.geometry.shapes import box
from engine.model import AnalysisControls, Block, JointMaterial, Model
from engine.step.simulation import STATUS_COMPLETED, STATUS_FAILED, Simulation, run
from tests.test_simulation import (
    ALPHA,
    DOWN_DIP,
    RHO,
    FrameLog,
    G,
    W,
    _cut_rock_mass,
    _fall_model,
    _stack_model,
    incline_model,
    interface_force,
    pushed_model,
)


def cc(model: Model, **controls) -> Model:
    """`model` under the complementarity solve (and any other `controls`)."""
    model.controls = dataclasses.replace(model.controls, contact_solver="complementarity",
                                         **controls)
    return model


def slide(phi_deg: float) -> float:
    """Case 1: the acceleration down a 30° incline at friction angle φ (m/s²)."""
    return G * (np.sin(ALPHA) - np.cos(ALPHA) * np.tan(np.radians(phi_deg)))


@pytest.mark.parametrize("dt", [1e-4, 1e-3, 1e-2])
@pytest.mark.parametrize("phi", [20.0, 0.0])
def test_block_slides_down_incline_at_any_time_step(phi: float, dt: float) -> None:
    """Case 1a / 1c at Δt ×0.1–×10: d(t) = ½ a t² within 0.5 %, no drift, no spin."""
    log = FrameLog()
    res = run(cc(incline_model(phi, duration=0.5, dt=dt)), recorder=log)
    assert res.status == STATUS_COMPLETED
    t, c = log.series(1)
    s = (c[-1] - c[0]) @ DOWN_DIP
    assert s == pytest.approx(0.5 * slide(phi) * t[-1] ** 2, rel=0.005)
    assert abs(c[-1, 1] - c[0, 1]) < 1e-6
    assert np.abs(log.frames[-1].rotation[1]).max() < 1e-6


def test_block_on_incline_holds_without_creep() -> None:
    """Case 1b (φ = 35° > 30°): with no spring the block does not move at all (< 1 µm)."""
    res = run(cc(incline_model(35.0, duration=1.0)))
    assert res.status == STATUS_COMPLETED
    assert np.linalg.norm(res.summary["blocks"][1]["displacement"]) < 1e-6


def test_free_fall_then_a_plastic_impact() -> None:
    """Case 4 with the impact law's default e = 0: drop = ½ g t² to 1e-6 before the impact
    (t = √(2·1/g) = 0.4515 s), then the cube stays on the base: no rebound, no penetration
    beyond the contact tolerance, no kinetic energy left."""
    log = FrameLog()
    res = run(cc(_fall_model(1e9, 0.8)), recorder=log)
    assert res.status == STATUS_COMPLETED
    t, c = log.series(1)
    for tq in (0.1, 0.2, 0.3, 0.4):
        k = np.argmin(abs(t - tq))
        assert 1.5 - c[k, 2] == pytest.approx(0.5 * G * t[k] ** 2, rel=1e-6)
    after = t > 0.46
    assert np.abs(c[after, 2] - 0.5).max() < 2e-6
    assert log.frames[-1].energies["kinetic"] < 1e-9 * W


def test_impact_law_restitution() -> None:
    """Restitution e = 0.5: the cube (1 m above the base) leaves it at e·v with v = √(2 g)
    = 4.429 m/s, so it rises to e² · 1 m = 0.25 m (within 2 %: the impact falls inside a
    step)."""
    log = FrameLog()
    run(cc(_fall_model(1e9, 0.8), restitution=0.5), recorder=log)
    t, c = log.series(1)
    after = t > 0.46
    assert c[after, 2].max() - 0.5 == pytest.approx(0.25, rel=0.02)


def test_stack_of_three_cubes_contact_forces_are_exact() -> None:
    """Case 5a: normal forces W, 2W, 3W within 1e-4 (hard contacts, dynamic)."""
    sim = Simulation(cc(_stack_model("rigid"), dynamic_ratio=1.0))
    for _ in range(50):
        res = sim.step()
    for upper, expect in ((3, W), (2, 2 * W), (1, 3 * W)):
        assert interface_force(res, upper, upper - 1) == pytest.approx(expect, rel=1e-4)
    assert np.abs(sim.state.centroid[1:, 2] - [0.5, 1.5, 2.5]).max() < 2e-6


def test_stack_of_elastic_cubes_average_stress() -> None:
    """Case 5a elastic (E = 1 GPa, ν = 0): σ_zz = −(W_above + W/2)/A within 0.5 %."""
    sim = Simulation(cc(_stack_model("elastic")))
    for _ in range(200):
        sim.step()
    szz = sim.state.stress[1:, 2]
    assert szz == pytest.approx([-2.5 * W, -1.5 * W, -0.5 * W], rel=0.005)


@pytest.mark.parametrize(("factor", "moves"), [(0.95, False), (1.5, True)])
def test_pushed_block(factor: float, moves: bool) -> None:
    """Case 6: static at 0.95 W tan φ; at 1.5 W tan φ a = (P − μW)/m within 0.5 %."""
    mu = np.tan(np.radians(30))
    p = factor * W * mu
    res = run(pushed_model(p, contact_solver="complementarity"))
    assert res.status == STATUS_COMPLETED
    dx = res.state.centroid[1, 0] - 0.5
    if moves:
        assert dx == pytest.approx(0.5 * (p - mu * W) / RHO, rel=0.005)
    else:
        assert abs(dx) < 1e-6


def test_goodman_bray_cases() -> None:
    """Case 3: φ 40° b/h 1 stands; φ 15° slides 1.314291 m in 1 s without rotating; b/h 0.4
    topples about its toe with θ̈₀ ≈ 1.948 rad/s² (2 %)."""
    stable = run(cc(incline_model(40.0, duration=0.5))).summary["blocks"][1]
    assert np.linalg.norm(stable["displacement"]) < 1e-6
    sliding = run(cc(incline_model(15.0, duration=1.0))).summary["blocks"][1]
    assert np.array(sliding["displacement"]) @ DOWN_DIP == pytest.approx(1.314291, rel=0.005)
    assert np.linalg.norm(sliding["rotation"]) < 1e-6
    log = FrameLog()
    run(cc(incline_model(40.0, b=0.4, h=1.0, duration=0.1)), recorder=log)
    t = np.array([f.time for f in log.frames])
    theta = np.array([np.linalg.norm(f.rotation[1]) for f in log.frames])
    sel = (t > 0.005) & (t < 0.05)
    assert 2 * np.polyfit(t[sel], theta[sel], 2)[0] == pytest.approx(1.948340, rel=0.02)


@pytest.mark.parametrize(("cohesion", "holds"), [(5200.0, True), (4200.0, False)])
def test_cohesion_over_the_base_holds_until_limit_equilibrium(cohesion: float,
                                                              holds: bool) -> None:
    """φ = 20° on 30° with cohesion c on the 1 m² base: limit equilibrium holds the block
    for c > W (sin 30° − cos 30° tan 20°) = 4 713 Pa. The bond is one patch, so it holds
    or breaks whole (no corner contacts failing one by one): c 5 200 Pa holds, 4 200 Pa
    breaks at once and the block slides on residual friction, ½ a t² with a = 1.812815."""
    model = cc(incline_model(20.0, duration=0.5))
    model.joint_materials = [JointMaterial(np.radians(20.0), cohesion=cohesion)]
    res = run(model)
    assert res.status == STATUS_COMPLETED
    s = np.array(res.summary["blocks"][1]["displacement"]) @ DOWN_DIP
    if holds:
        assert abs(s) < 1e-6
    else:
        assert s == pytest.approx(0.5 * 1.812815 * 0.5**2, rel=0.01)


@pytest.mark.parametrize(("tension", "holds"), [(27000.0, True), (24000.0, False)])
def test_tensile_strength_holds_hanging_block(tension: float, holds: bool) -> None:
    """A 1 m cube glued under a fixed slab hangs while T·A > W = 25 506 N (no spring, so
    no dynamic overshoot); below W it breaks and falls freely."""
    model = Model(
        blocks=[Block(box([-1, -1, 1], [2, 2, 2]), "roof", fixed=True),
                Block(box([0, 0, 0], [1, 1, 1]), "cube")],
        joint_materials=[JointMaterial(np.radians(30), tensile_strength=tension)],
        controls=AnalysisControls(duration=0.2, time_step=1e-3,
                                  contact_solver="complementarity"),
    )
    res = run(model)
    assert res.status == STATUS_COMPLETED
    dz = res.summary["blocks"][1]["displacement"][2]
    if holds:
        assert abs(dz) < 1e-6
    else:
        assert dz == pytest.approx(-0.5 * G * 0.2**2, rel=0.01)


@pytest.mark.parametrize("case", ["free_fall_settled", "incline_sliding"])
def test_energy_is_accounted_for(case: str) -> None:
    """Work of gravity = kinetic + friction + impact dissipation (1e-6 of the work)."""
    model = (_fall_model(1e9, 0.8) if case == "free_fall_settled"
             else incline_model(20.0, duration=0.5))
    log = FrameLog()
    run(cc(model), recorder=log)
    e = log.frames[-1].energies
    work = e["gravity_work"] + e["external_work"]
    assert work > 0
    from engine.step.frame import energy_created
    assert abs(energy_created(e)) < 1e-6 * work


def test_cut_rock_mass_stands_at_the_asked_time_step() -> None:
    """37 cut blocks touching from the start, φ 80°: every step at the asked 1 ms, nothing
    moves more than a micrometre."""
    sim = Simulation(cc(_cut_rock_mass(80.0)))
    for _ in range(20):
        sim.step()
    assert sim.state.time == pytest.approx(0.02, rel=1e-9)
    assert np.linalg.norm(sim.state.centroid - sim.system.c0, axis=1).max() < 1e-6


def test_contact_solve_that_cannot_converge_stops_with_clear_status(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A solve allowed one sweep cannot settle the impact: Δt is cut to its floor, then the
    run stops, says why, and keeps the frames before."""
    monkeypatch.setattr(complementarity, "MAX_SWEEPS", 1)
    log = FrameLog()
    model = cc(_fall_model(1e9, 1.0), record_interval=10)
    res = run(model, recorder=log)
    assert res.status == STATUS_FAILED
    assert "did not converge" in res.message
    assert len(log.frames) >= 30
    assert all(np.all(np.isfinite(f.centroids)) for f in log.frames)


def _landing(sleep_velocity: float, n: int = 5) -> Model:
    """A stack of `n` cubes and one more cube 0.5 m above it, landing at t ≈ 0.32 s."""
    blocks = [Block(box([-1, -1, -1], [3, 2, 0]), "base", fixed=True)]
    blocks += [Block(box([0, 0, k], [1, 1, k + 1]), f"c{k}") for k in range(n)]
    blocks += [Block(box([0, 0, n + 0.5], [1, 1, n + 1.5]), "drop")]
    return Model(blocks=blocks, joint_materials=[JointMaterial(np.radians(30))],
                 controls=AnalysisControls(duration=0.5, time_step=1e-3,
                                           contact_solver="complementarity",
                                           sleep_velocity=sleep_velocity))


def test_resting_stack_sleeps_and_wakes_when_a_block_lands() -> None:
    """The stack falls asleep (every contact stuck, at rest for sleep_time), the landing
    cube wakes all of it, and the run ends where the same run without sleeping ends
    (1e-6 m); asleep again at the end."""
    runs = {}
    for sv in (1e-3, 0.0):
        sim = Simulation(_landing(sv))
        asleep = []
        while sim.state.time < 0.5 - 1e-9:
            sim.step()
            a = sim.state.asleep
            asleep.append(0 if a is None else int(a.sum()))
        runs[sv] = (sim.state.centroid.copy(), asleep, sim.state.diagnostics.wakes)
    c_sleep, asleep, wakes = runs[1e-3]
    assert max(asleep[100:300]) == 5  # the stack slept before the landing
    assert wakes >= 5
    assert asleep[-1] == 6
    assert runs[0.0][1][-1] == 0
    assert np.abs(c_sleep - runs[0.0][0]).max() < 1e-6


def test_sleeping_block_is_pushed_off_when_a_neighbour_slides_into_it() -> None:
    """A cube resting (asleep) on a floor (φ 10°) is hit by a cube sent sliding at 1 m/s
    from 0.2 m away (it stops after v²/(2 g tan φ) = 0.29 m): the resting cube wakes with
    the first contact and moves as it moves without sleeping."""
    floor = Block(box([-6, -1, -1], [6, 2, 0]), "floor", fixed=True)
    rest = Block(box([1.0, 0, 0], [2.0, 1, 1]), "resting")
    pusher = Block(box([-0.2, 0, 0], [0.8, 1, 1]), "pusher", velocity=np.array(
        [1.0, 0, 0, 0, 0, 0]))
    out = {}
    for sv in (1e-3, 0.0):
        model = Model(blocks=[floor, rest, pusher],
                      joint_materials=[JointMaterial(np.radians(10))],
                      controls=AnalysisControls(duration=0.4, time_step=1e-3,
                                                contact_solver="complementarity",
                                                sleep_velocity=sv, sleep_time=0.02))
        sim = Simulation(model)
        slept = False
        while sim.state.time < 0.4 - 1e-9:
            sim.step()
            slept |= sim.state.asleep is not None and bool(sim.state.asleep[1])
        out[sv] = (sim.state.centroid.copy(), slept)
    assert out[1e-3][1]  # the resting cube slept before it was hit
    moved = out[0.0][0][1, 0] - 1.5
    assert moved > 0.01
    assert np.abs(out[1e-3][0] - out[0.0][0]).max() < 1e-6
