"""The LMGC90 export of benchmarks/lmgc90.py (a benchmark-only peer, issue 38): our blocks as
LMGC90 sees them. The LMGC90 checks skip when compas_lmgc90 is not installed
(benchmarks/setup_peers.sh installs it); no timing is asserted."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmarks.lmgc90 import export_errors, export_model, triangle_mass
from benchmarks.pile import rock_mass_model
from engine.geometry.shapes import box
from engine.model import Block, JointMaterial, Model


def test_export_keeps_every_block_whole() -> None:
    """The 36-block rock mass exported: the triangles have our volumes, centroids and
    second moments (to round-off), the base is held, φ 30° becomes tan 30°, Δt is kept."""
    model = rock_mass_model(5.0)
    scene = export_model(model)
    assert len(scene.blocks) == len(model.blocks) == 37
    assert [b.fixed for b in scene.blocks] == [b.fixed for b in model.blocks]
    assert scene.friction == pytest.approx(np.tan(np.radians(30.0)), rel=1e-15)
    assert scene.dt == model.controls.time_step and scene.blocks[1].density == 2600.0
    errors = export_errors(model, scene)
    assert max(errors.values()) < 1e-12, errors
    vol, _, _ = triangle_mass(scene.blocks[1].vertices, scene.blocks[1].triangles)
    assert vol > 0  # outward triangles


def test_export_refuses_what_lmgc90_cannot_carry() -> None:
    """Cohesion, a second friction angle or another gravity would be silently lost: refused."""
    model = rock_mass_model(5.0)
    with pytest.raises(ValueError, match="cohesion"):
        export_model(dataclasses.replace(
            model, joint_materials=[JointMaterial(np.radians(30.0), cohesion=1e4)]))
    with pytest.raises(ValueError, match="gravity"):
        export_model(dataclasses.replace(model, gravity=np.array([0.0, 0.0, -9.8])))
    two = Model(blocks=[Block(box([0, 0, 0], [1, 1, 1])), Block(box([0, 0, 1], [1, 1, 2]))],
                joint_materials=[JointMaterial(0.5), JointMaterial(0.6)],
                pair_joint_material={(0, 1): 1})
    with pytest.raises(ValueError, match="one joint material"):
        export_model(two)


def test_lmgc90_sees_our_blocks_and_runs_them() -> None:
    """In LMGC90 itself (fresh processes: one simulation each): the exported bodies' centroids
    and masses are ours to 1e-9, their principal moments to 1e-6 (a one-step turn measures
    them to ~1e-7); two steps of the rock mass complete, no block faster than free fall, and
    with the contacts re-detected every step too."""
    pytest.importorskip("compas_lmgc90")
    from benchmarks.lmgc90 import in_subprocess

    v = in_subprocess("verify", "rock_mass_model(5.0)", timeout=300)
    assert v["blocks"] == 37 and v["contacts"] == 0
    assert v["centroid"] < 1e-9 and v["mass"] < 1e-9, v
    assert v["principal_moments"] < 1e-6, v
    r = in_subprocess("run", "rock_mass_model(5.0)", "0.002", timeout=300)
    assert (r["status"], r["steps"], r["blocks"]) == ("completed", 2, 36)
    assert r["centroid_error"] < 1e-9
    assert 0.0 < r["disp_max_m"] <= 0.5 * 9.81 * 0.002**2 * (1 + 1e-6)
    again = in_subprocess("run", "rock_mass_model(5.0)", "0.002", "redetect", timeout=300)
    assert again["status"] == "completed" and "every step" in again["detection"]


def test_lmgc90_section_renders() -> None:
    """REPORT.md's section from a stored run (made up here): a row per engine, the export
    check, the load averages; and the note when LMGC90 was missing."""
    from benchmarks.bench_lmgc90 import report_part

    def row(solver: str, shift: float) -> dict:
        return {"solver": solver, "case_s": 0.01, "steps": 10, "mean_dt": 1e-3,
                "per_step_s": 0.1, "per_sim_second_s": 100.0, "cpu_s": 1.0,
                "iterations_mean": None if solver == "LMGC90" else 12.0, "contacts_mean": 9.0,
                "disp_mean_m": 1e-4, "disp_max_m": 2e-4, "settlement_mean_m": 1e-4,
                "rotation_max_rad": 1e-5, "kinetic_step_mean_J": 5.0,
                "max_penetration_m": 1e-7, "overlap_end_m": 1e-7, "status": "completed",
                "load_before": [3.0] * 3,
                "load_after": [3.5] * 3, "displacements": [[0.0, 0.0, -1e-4 - shift]]}

    data = {"spacing": 2.5, "repeat": 1, "note": None,
            "machine": {"nproc": 2, "cpu": "cpu"},
            "verify": {"blocks": 135, "centroid": 1e-14, "mass": 3e-11,
                       "principal_moments": 1.5e-7, "export_volume": 4e-16,
                       "export_centroid": 1e-15, "export_second_moments": 6e-16},
            "rows": [row("LMGC90", 0.0), row("newton", 1e-5)]}
    text = report_part(data)
    assert "## 7b. LMGC90 on the same cut rock mass" in text
    assert "| 0.01 s | LMGC90 | 10 |" in text and "| 0.01 s | newton | 10 |" in text
    assert "| 10% | completed |" in text and "3.0→3.5" in text and "mass" in text
    data["note"] = "compas_lmgc90 not installed"
    assert "LMGC90 not run: compas_lmgc90 not installed." in report_part(data)
    assert "(section not run)" in report_part(None)
