"""`import polydda`: the stable Python API (docs/python.md) gives what the command line gives
(blocks, limit equilibrium, a run's result as DataFrames, the inline viewer), and the old
import paths users called still work, warning once."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import polydda
from service.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
WEDGE = ROOT / "examples" / "wedge.json"


def test_version_and_a_light_import() -> None:
    """`python -c "import polydda; print(polydda.__version__)"` prints the package's
    version and loads neither the engine's numerics nor the web service."""
    code = ("import sys, polydda; print(polydda.__version__); "
            "print(sorted(m for m in ('numpy', 'fastapi', 'engine', 'pandas') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout.split("\n")
    from importlib.metadata import version

    assert out[0] == version("polydda") == polydda.__version__
    assert out[1] == "[]"
    assert set(polydda.__all__) >= {"Scene", "run", "le", "fos", "keyblocks", "open_result",
                                    "sweep", "__version__"}


def test_scene_load_validate_build_save(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    scene = polydda.Scene.load(WEDGE)
    blocks = scene.build()
    assert main(["blocks", str(WEDGE), "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert list(blocks.frame.index) == [b["name"] for b in cli["blocks"]]
    assert blocks.frame["volume"].tolist() == pytest.approx([b["volume"] for b in cli["blocks"]])
    saved = scene.save(tmp_path / "copy.json")
    assert polydda.Scene.load(saved) == scene
    assert json.loads(saved.read_text()) == json.loads(WEDGE.read_text())
    bad = scene.copy()
    bad["joint_materials"] = {"joint": {"friction_angle": 95}}
    problems = bad.validate()
    assert [p["loc"] for p in problems] == ["joint_materials.joint.friction_angle"]
    with pytest.raises(polydda.SceneError, match="friction_angle"):
        polydda.Scene.load(bad.data)
    assert scene.validate() == []


def test_le_is_the_commands(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["le", str(WEDGE), "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    doc = polydda.le(WEDGE)
    assert doc["factor_of_safety"] == pytest.approx(cli["factor_of_safety"], rel=1e-12)
    assert doc["mode"] == cli["mode"]


def test_run_gives_dataframes_and_an_inline_viewer(tmp_path: Path) -> None:
    scene = polydda.Scene.load(WEDGE)
    scene["analysis"]["duration"] = 0.05
    result = polydda.run(scene, out=tmp_path / "wedge.h5", progress=False)
    with result:
        assert result.status == "completed"
        blocks = result.blocks()
        assert list(blocks.index) == ["B1", "B2"] and blocks.loc["B1", "fixed"]
        one = result.history("B2")
        assert len(one) == len(result.times) == 6  # steps 0, 10, ..., 50
        assert {"time", "ux", "uy", "uz", "u", "vx"} <= set(one.columns)
        assert one["u"].iloc[-1] == pytest.approx(blocks.loc["B2", "u"])
        every = result.history()
        assert len(every) == 2 * len(one) and set(every["block"]) == {"B1", "B2"}
        contacts = result.contacts()
        assert len(contacts) > 0 and set(contacts["mode"]) <= {"open", "locked", "sliding"}
        assert "kinetic" in " ".join(result.energies().columns) or len(result.energies())
        html = result._repr_html_()
    assert html.startswith("<iframe srcdoc=") and "&quot;/static/" not in html  # no URL
    assert "three/core" in html and "viewer-config" in html


def test_old_import_paths_warn_once_and_work(tmp_path: Path) -> None:
    """A user's script that imports the engine's reader and the schema's builder directly:
    both work, and each warns once (DeprecationWarning naming the polydda name), however
    often it is called."""
    scene = polydda.Scene.load(WEDGE)
    scene["analysis"]["duration"] = 0.01
    out = tmp_path / "r.h5"
    polydda.run(scene, out=out, progress=False).close()
    code = f"""
from engine.results.reader import open_result
from schemas.convert import build_model
from schemas import load_scene
for _ in range(3):
    with open_result({str(out)!r}) as r:
        n = r.n_blocks
    built = build_model({str(WEDGE)!r})
    load_scene({str(WEDGE)!r})
print(n, len(built.model.blocks))
"""
    proc = subprocess.run([sys.executable, "-W", "default::DeprecationWarning", "-c", code],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["2", "2"]
    warned = [ln for ln in proc.stderr.splitlines() if "DeprecationWarning" in ln]
    assert len(warned) == 3, proc.stderr
    for old, new in (("engine.results.reader.open_result", "polydda.open_result"),
                     ("schemas.convert.build_model", "polydda.Scene.load(...).build()"),
                     ("schemas.scene.load_scene", "polydda.Scene.load")):
        assert sum(old in ln and new in ln for ln in warned) == 1, (old, warned)


def test_keyblocks_is_the_commands_table(capsys: pytest.CaptureFixture[str]) -> None:
    tunnel = ROOT / "examples" / "tunnel_staged.json"
    assert main(["keyblocks", str(tunnel), "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    table = polydda.keyblocks(tunnel)
    rows = [(e["name"], r["block"], r["mode"], r["removable"]) for e in cli["excavations"]
            for r in e["blocks"]]
    assert list(zip(table["excavation"], table["block"], table["mode"], table["removable"],
                    strict=True)) == rows
    assert len(rows) > 0


@pytest.mark.slow
def test_fos_is_the_analytic_planar_block() -> None:
    """Strength reduction from Python on the planar block with cohesion: FS 1.4576 by
    hand (examples/planar_cohesion.json), within the bisection's tolerance."""
    doc = polydda.fos(ROOT / "examples" / "planar_cohesion.json", progress=False)
    assert doc["factor_of_safety"] == pytest.approx(1.4576, rel=0.01)
