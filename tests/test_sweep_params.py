"""Sweeps of several scene parameters (issue 17): each parameter's own random stream, the
friction-only numbers unchanged, every parameter reaching the built model, validation
errors naming the field (422 through the API), the skip-done re-run and the aggregate's
sensitivity to each parameter."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import stats

from engine.analyses.kinematics import normal
from engine.analyses.reliability import wedge_factor_of_safety, wedge_geometry
from engine.analyses.sweep import Parameter, SweepSpec
from schemas.convert import build_model
from schemas.errors import SceneError
from schemas.scene import load_scene
from service.cli.main import main
from service.sweep import (
    analytic_fs,
    evaluate,
    parameter_of,
    realisation_scene,
    run_sweep,
    spec_of_scene,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SEED = 2026


def example(name: str, **sweep: Any) -> dict[str, Any]:
    """An example scene, with `sweep` as its sweep section when given."""
    scene = json.loads((EXAMPLES / f"{name}.json").read_text())
    if sweep:
        scene["sweep"] = sweep
    return scene


def params(**specs: dict[str, Any]) -> tuple[Parameter, ...]:
    return tuple(parameter_of(name, spec) for name, spec in specs.items())


FRICTION = {"distribution": "normal", "mean": 40, "sd": 5}
COHESION = {"distribution": "uniform", "low": 0, "high": 2e4}
J1 = {"quantity": "joint_orientation", "distribution": "fisher", "kappa": 50, "joint": "J1"}


# --------------------------------------------------------------------------- draws


def test_each_parameter_draws_from_its_own_stream() -> None:
    """Realisation k is the same for N = 10 and N = 300; adding a parameter leaves the
    others' draws as they were; two parameters of one distribution but different names
    draw differently; the samples follow their distributions."""
    three = SweepSpec(300, SEED, parameters=params(friction_angle=FRICTION,
                                                   cohesion=COHESION, J1=J1)).draws()
    short = SweepSpec(10, SEED, parameters=params(cohesion=COHESION, J1=J1)).draws()
    for name in ("cohesion", "J1"):
        assert np.array_equal(three[name][:10], short[name])
    other = SweepSpec(300, SEED, parameters=params(cohesion=COHESION, c2={
        "quantity": "cohesion", **COHESION})).draws()
    assert np.array_equal(other["cohesion"], three["cohesion"])
    assert not np.allclose(other["c2"], other["cohesion"])
    assert not np.array_equal(three["cohesion"], SweepSpec(
        300, SEED + 1, parameters=params(cohesion=COHESION)).draws()["cohesion"])
    c = three["cohesion"]
    assert c.min() >= 0 and c.max() < 2e4
    assert stats.kstest(c, stats.uniform(0, 2e4).cdf).pvalue > 0.001
    theta = np.degrees(three["J1"][:, 0])  # Fisher: P(θ > θ_p) = p for cos θ_p below
    theta_95 = math.degrees(math.acos(1 + math.log(0.05) / 50))
    assert 0.01 < (theta > theta_95).mean() < 0.10
    assert np.all((0 <= three["J1"][:, 1]) & (three["J1"][:, 1] < 2 * math.pi))


def test_friction_only_draws_are_the_seeds_as_before() -> None:
    """The short form `friction_angle: {mean, sd}` and the parameter `friction_angle`
    normal(mean, sd) both draw φ_k = truncnorm⁻¹(u_k) of the seed's k-th uniform, as the
    friction-only sweeps always did; the short form's population (the realisation files'
    key) has no new field, so files written before are found again."""
    u = np.random.default_rng(SEED).random(50)
    expected = stats.truncnorm.ppf(u, -40 / 5, 50 / 5, loc=40, scale=5)
    old = SweepSpec(50, SEED, 40, 5)
    new = SweepSpec(50, SEED, parameters=params(friction_angle=FRICTION))
    assert np.array_equal(old.friction_angles(), expected)
    assert np.array_equal(new.friction_angles(), expected)
    assert old.population() == {"n": 50, "seed": SEED, "friction_mean": 40.0,
                                "friction_sd": 5.0, "mode": "dda"}
    assert new.population()["parameters"][0]["mean"] == 40.0


def test_values_form_a_grid() -> None:
    """Two value lists (3 and 2 values): the first varies fastest, the 6 combinations each
    once in 6 realisations, then again (cycling); a random parameter beside them draws."""
    spec = SweepSpec(8, SEED, mode="analytic", parameters=params(
        friction_angle={"distribution": "values", "values": [20, 30, 40]},
        J1={**J1, "kappa": 100}))
    d = spec.draws()
    assert d["friction_angle"].tolist() == [20, 30, 40, 20, 30, 40, 20, 30]
    spec2 = SweepSpec(8, SEED, parameters=params(
        friction_angle={"distribution": "values", "values": [20, 30, 40]},
        kh={"distribution": "values", "values": [0, 0.1]}))
    d2 = spec2.draws()
    assert list(zip(d2["friction_angle"][:6], d2["kh"][:6], strict=True)) == [
        (20, 0), (30, 0), (40, 0), (20, 0.1), (30, 0.1), (40, 0.1)]
    assert d2["kh"][6] == 0.0


def test_lognormal_and_truncated_normal() -> None:
    """A lognormal penalty has the asked mean; a normal cohesion stays at or above 0 Pa
    and within an explicit truncation."""
    d = SweepSpec(2000, SEED, parameters=params(
        penalty={"distribution": "lognormal", "mean": 1e10, "sd": 3e9},
        cohesion={"distribution": "normal", "mean": 1000, "sd": 2000, "high": 3000})).draws()
    assert abs(d["penalty"].mean() / 1e10 - 1) < 3 * 0.3 / math.sqrt(2000)
    assert d["cohesion"].min() >= 0 and d["cohesion"].max() <= 3000


# --------------------------------------------------------------------------- the model


def face_normals(build: Any, tag: int) -> np.ndarray:
    """Unit normals of every block face on joint `tag` (Newell's method)."""
    out = []
    for b in build.model.blocks:
        poly = b.polyhedron
        for f, t in zip(poly.faces, poly.face_tags, strict=True):
            if t == tag:
                v = poly.vertices[f]
                n = np.cross(v, np.roll(v, -1, axis=0)).sum(axis=0)
                out.append(n / np.linalg.norm(n))
    return np.array(out)


def test_joint_parameters_reach_the_model() -> None:
    """Friction and cohesion of one named joint material (the other keeps its own); the
    orientation of J1 re-cuts the wedge: its faces on J1 lie on the drawn plane (their
    extent turned with it), at the drawn angle θ from the scene's J1."""
    scene = example("wedge")
    scene["joint_materials"]["weak"] = {"friction_angle": 25}
    scene["default_joint_material"] = "joint"
    scene["joints"][1]["joint_material"] = "weak"
    ps = params(phi_weak={"quantity": "friction_angle", "distribution": "values",
                          "values": [0], "joint_material": "weak"},
                cohesion={**COHESION, "joint_material": "weak"}, J1=J1)
    theta, psi = 0.15, 1.0
    s = realisation_scene(scene, {"phi_weak": 31.5, "cohesion": 5000.0, "J1": [theta, psi]},
                          ps)
    build = build_model(s)
    names = build.joint_material_names
    weak, joint = build.model.joint_materials[names.index("weak")], \
        build.model.joint_materials[names.index("joint")]
    assert math.degrees(weak.friction_angle_rad) == pytest.approx(31.5)
    assert weak.cohesion == 5000.0 and joint.cohesion == 0.0
    assert math.degrees(joint.friction_angle_rad) == pytest.approx(40)
    new = normal(s["joints"][0]["dip"], s["joints"][0]["dip_direction"])
    old = normal(50, 110)
    assert math.degrees(math.acos(new @ old)) == pytest.approx(math.degrees(theta), abs=1e-9)
    faces = face_normals(build, 0)
    assert len(faces) >= 2 and np.allclose(np.abs(faces @ new), 1.0, atol=1e-6)
    assert analytic_fs(s) != pytest.approx(analytic_fs(scene), rel=1e-3)


@pytest.mark.parametrize(("name", "quantity", "value", "read"), [
    ("incline_seismic", "kh", 0.23, lambda m: m.seismic.kh),
    ("incline_uplift", "water_level", -0.2, lambda m: m.water.surface_point[2]),
    ("incline_bolt", "bolt_pretension", 15000.0, lambda m: m.bolts[0].pretension),
    ("incline_bolt", "bolt_capacity", 42000.0, lambda m: m.bolts[0].capacity),
    ("incline", "penalty", 3e9, lambda m: m.controls.penalty),
    ("incline", "time_step", 0.002, lambda m: m.controls.time_step),
])
def test_scene_parameters_reach_the_model(name: str, quantity: str, value: float,
                                          read: Any) -> None:
    """Each parameter's value is in the built model, where the scene's own was before."""
    scene = example(name)
    before = read(build_model(scene).model)
    ps = params(**{quantity: {"distribution": "values", "values": [value]}})
    after = read(build_model(realisation_scene(scene, {quantity: value}, ps)).model)
    assert after == pytest.approx(value) and before != pytest.approx(value)


def test_an_invalid_realisation_is_recorded_not_raised() -> None:
    """A capacity below the bolt's pretension makes that realisation's scene invalid: its
    record says why and has no factor of safety (the sweep goes on)."""
    scene = example("incline_bolt")
    spec = SweepSpec(1, SEED, parameters=params(
        bolt_capacity={"distribution": "values", "values": [1000]}))
    rec = evaluate(scene, spec, 0, {"bolt_capacity": 1000.0})
    assert rec["factor_of_safety"] is None and rec["status"] == "invalid scene"
    assert "pretension" in rec["message"] and rec["analytic_fs"] is None


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(("sweep", "loc", "text"), [
    ({"parameters": {"friction": {"distribution": "normal", "mean": 30, "sd": 2}}},
     "sweep.parameters.friction.quantity", "friction_angle"),
    ({"parameters": {"cohesion": {"distribution": "normal", "mean": 1e4, "sd": 0}}},
     "sweep.parameters.cohesion.sd", "must be positive"),
    ({"parameters": {"c": {"quantity": "cohesion", "distribution": "uniform", "low": 0,
                           "high": 1, "joint_material": "nope"}}},
     "sweep.parameters.c.joint_material", "unknown joint material 'nope'"),
    ({"parameters": {"J9": {**J1, "joint": "J9"}}}, "sweep.parameters.J9.joint",
     "unknown joint 'J9'"),
    ({"parameters": {"kh": {"distribution": "values", "values": [0.1]}}},
     "sweep.parameters.kh", "needs 'seismic'"),
    ({"parameters": {"bolt_pretension": {"distribution": "values", "values": [1e4]}}},
     "sweep.parameters.bolt_pretension", "has none"),
    ({"mode": "analytic", "parameters": {"penalty": {"distribution": "values",
                                                     "values": [1e9]}}},
     "sweep.parameters.penalty", "limit equilibrium (mode 'analytic') has no penalty"),
    ({"parameters": {"friction_angle": {"distribution": "uniform", "low": 10, "high": 95}}},
     "sweep.parameters.friction_angle", "outside the range"),
    ({"parameters": {"J1": {**J1, "distribution": "normal", "mean": 1, "sd": 1}}},
     "sweep.parameters.J1", "fisher"),
    ({"parameters": {"cohesion": {"distribution": "uniform", "low": 0, "high": 1, "sd": 3}}},
     "sweep.parameters.cohesion", "not 'sd'"),
    ({"friction_angle": {"mean": 40, "sd": 5}, "parameters": {"friction_angle": FRICTION}},
     "sweep", "given twice"),
    ({"n": 10}, "sweep", "give 'parameters'"),
])
def test_invalid_sweeps_name_the_field(sweep: dict[str, Any], loc: str, text: str) -> None:
    with pytest.raises(SceneError) as err:
        load_scene(example("wedge", **sweep))
    assert any(p["loc"] == loc and text in p["msg"] for p in err.value.problems), \
        err.value.problems


def test_api_refuses_an_invalid_sweep_with_422_naming_the_field(tmp_path: Path) -> None:
    """POST /jobs?process=sweep with an unknown joint material, sd 0 or a parameter eq. 51
    does not take: 422 naming the field; a valid two-parameter sweep is accepted."""
    from tests.service_helpers import make_client, wait_final

    bad = [({"c": {"quantity": "cohesion", **COHESION, "joint_material": "nope"}},
            "sweep.parameters.c.joint_material"),
           ({"friction_angle": {**FRICTION, "sd": 0}}, "sweep.parameters.friction_angle.sd"),
           ({"kh": {"distribution": "values", "values": [0.1]}}, "sweep.parameters.kh")]
    with make_client(tmp_path / "data") as c:
        for parameters, loc in bad:
            scene = example("wedge", n=5, seed=SEED, mode="analytic", parameters=parameters)
            r = c.post("/jobs", params={"process": "sweep"}, json=scene)
            assert r.status_code == 422 and loc in r.text, r.text
        scene = example("wedge", n=20, seed=SEED, mode="analytic",
                        parameters={"friction_angle": FRICTION, "J1": J1})
        r = c.post("/jobs", params={"process": "sweep"}, json=scene)
        assert r.status_code == 201, r.text
        assert wait_final(c, r.headers["Location"])["status"] == "successful"
        doc = c.get(r.headers["Location"] + "/results").json()["sweep"]
    assert doc["done"] == 20 and set(doc["parameters"]) == {"friction_angle", "J1"}
    assert doc == run_sweep(scene, spec_of_scene(scene), tmp_path / "local") | {
        "realisations": doc["realisations"]}


# --------------------------------------------------------------------------- sweeps


def test_rerun_with_several_parameters_skips_the_done(tmp_path: Path) -> None:
    """Limit equilibrium over φ and J1's orientation: a re-run evaluates only the missing
    realisations and gives the same document; the realisation files are keyed by every
    parameter's values (another κ is another population, refused in the same folder,
    even when the spec does not come from the scene); FS of each realisation (the vector
    method on the blocks cut with the turned joint) matches eq. 51 of its recorded φ and J1
    (dry, friction only: the two are the same formula); FS grows with φ (ρ > 0.5)."""
    scene = example("wedge", n=40, seed=SEED, mode="analytic",
                    parameters={"friction_angle": FRICTION, "J1": J1})
    spec = spec_of_scene(scene)
    first = run_sweep(scene, spec, tmp_path / "a")
    for k in (2, 5, 39):
        (tmp_path / "a" / "realisations" / f"{k:05d}.json").unlink()
    evaluated: list[int] = []
    again = run_sweep(scene, spec, tmp_path / "a",
                      progress=lambda done, n, now: evaluated.append(now))
    assert evaluated == [1, 2, 3] and again == first
    bare = example("wedge")
    run_sweep(bare, spec, tmp_path / "b")
    wider = SweepSpec(40, SEED, mode="analytic", parameters=params(
        friction_angle=FRICTION, J1={**J1, "kappa": 20}))
    with pytest.raises(ValueError, match="another scene or spec"):
        run_sweep(bare, wider, tmp_path / "b")
    j2 = bare["joints"][1]
    # a turned J1 whose extent (the wedge's face, turned with it) no longer meets J2 cuts no
    # free block: limit equilibrium refuses that realisation, saying so (17 of the 40),
    # where eq. 51 of the two orientations gave a number for a wedge the scene does not have
    refused = [r for r in first["realisations"] if r["factor_of_safety"] is None]
    assert refused and all("no free block" in r["analytic_note"] for r in refused)
    assert "no free block" in first["analytic_note"]
    assert first["analytic"]["n"] == 40 - len(refused) >= 20
    for rec in [r for r in first["realisations"] if r["factor_of_safety"] is not None][:5]:
        j1 = rec["parameters"]["J1"]
        g = wedge_geometry(j1["dip"], j1["dip_direction"], j2["dip"], j2["dip_direction"])
        eq51 = float(wedge_factor_of_safety(g, rec["parameters"]["friction_angle"]))
        assert rec["factor_of_safety"] == pytest.approx(eq51, rel=1e-4)
        assert rec["friction_angle"] == rec["parameters"]["friction_angle"]
    sens = first["analytic"]["sensitivity"]
    assert set(sens) == {"friction_angle", "J1.dip", "J1.dip_direction"}
    assert sens["friction_angle"] > 0.5
    assert first["parameters"]["J1"]["kappa"] == 50.0


def test_dda_sweep_of_kh_follows_the_pseudo_static_formula(tmp_path: Path) -> None:
    """The cube on the 30° slab (φ 40°) for kh = 0, 0.05 and 0.1 by the engine's strength
    reduction: FS within 1 % of (cos α − kh sin α) tan φ / (sin α + kh cos α) (1.4534 to
    1.1673), and limit equilibrium's (the analytic aggregate, kh counted) to 1e-4; FS falls
    with kh (ρ = −1)."""
    scene = example("incline_seismic")
    scene["analysis"]["factor_of_safety"]["tolerance"] = 0.02
    scene["sweep"] = {"n": 3, "seed": SEED, "parameters": {
        "kh": {"distribution": "values", "values": [0, 0.05, 0.1]}}}
    doc = run_sweep(scene, spec_of_scene(scene), tmp_path)
    a, phi = math.radians(30), math.radians(40)
    for rec in doc["realisations"]:
        kh = rec["parameters"]["kh"]
        exact = (math.cos(a) - kh * math.sin(a)) * math.tan(phi) / (
            math.sin(a) + kh * math.cos(a))
        assert rec["status"] == "completed"
        assert rec["factor_of_safety"] == pytest.approx(exact, rel=0.01)
        assert rec["analytic_fs"] == pytest.approx(exact, rel=1e-4)
    assert doc["dda"]["sensitivity"] == {"kh": pytest.approx(-1.0)}
    assert doc["analytic"]["sensitivity"] == {"kh": pytest.approx(-1.0)}


def test_cli_parameter_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`--parameter NAME=JSON` adds a parameter to the short-form friction; the numbers are
    those of the same sweep from the scene; a malformed one or an unknown joint: exit 2."""
    args = ["sweep", str(EXAMPLES / "wedge.json"), "--n", "30", "--seed", str(SEED),
            "--friction-mean", "40", "--friction-sd", "5", "--mode", "analytic",
            "--parameter", "J1=" + json.dumps(J1), "--out", str(tmp_path / "cli"),
            "--quiet", "--json"]
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out)
    scene = example("wedge", n=30, seed=SEED, mode="analytic",
                    friction_angle={"mean": 40, "sd": 5}, parameters={"J1": J1})
    local = run_sweep(scene, spec_of_scene(scene), tmp_path / "local")
    assert doc["analytic"] == local["analytic"]
    assert main(args[:-6] + ["--parameter", "J1", "--out", str(tmp_path / "x")]) == 2
    assert main(args[:-6] + ["--parameter", "J1=" + json.dumps({**J1, "joint": "J7"}),
                             "--out", str(tmp_path / "y")]) == 2
    assert "unknown joint 'J7'" in capsys.readouterr().err
