"""Key blocks know what is fixed and judge a recorded run as a strength-reduction trial is
judged (issue 41): a fixed block is the rock mass beyond the model, never a key block; a
block the run shows accelerating is "still moving at the end", not "stayed" because it has
not yet gone 1 % of its size."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from engine.analyses.keyblocks import recorded_motion
from schemas.convert import build_model
from service.cli.main import main
from tests.excavation_scenes import PSI, sidewall_scene

ROOT = Path(__file__).resolve().parent.parent
TUNNEL = ROOT / "examples" / "tunnel_staged.json"
G = 9.81


def test_fixed_blocks_are_never_key_blocks(capsys: pytest.CaptureFixture[str]) -> None:
    """The tunnel example's fixed blocks on the opening (B16, B18, B31, B50: boundary
    blocks, the floor's) were listed as removable, falling or sliding; none is now, and
    every free block on the surface still is."""
    build = build_model(TUNNEL)
    fixed = {name for name, b in zip(build.block_names, build.model.blocks, strict=True)
             if b.fixed}
    assert {"B16", "B18", "B50"} <= fixed
    assert main(["keyblocks", str(TUNNEL), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["excavations"][0]["blocks"]
    listed = {r["block"] for r in rows}
    assert listed and not listed & fixed, listed & fixed
    assert {"B22", "B54"} <= listed  # free blocks on the tunnel's surface stay
    assert main(["keyblocks", str(TUNNEL)]) == 0
    text = capsys.readouterr().out
    assert "B16" not in text and "B18" not in text and "B50" not in text


def _record(a: float, t_end: float, dt: float = 0.02, stop: float | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A block released at t = 0 that slides at `a` m/s² (stopping at `stop` s, if given):
    recorded times, displacements (K, 3) and speeds."""
    t = np.linspace(0.0, t_end, round(t_end / dt) + 1)
    run = np.minimum(t, stop) if stop is not None else t
    v = np.where(t < (stop if stop is not None else np.inf), a * t, 0.0)
    d = np.zeros((len(t), 3))
    d[:, 0] = 0.5 * a * run**2
    return t, d, v


def test_recorded_motion_judges_speed_not_distance() -> None:
    """1.02 m/s² for 0.25 s is 0.0319 m, under 1 % of a 4 m block: still moving (the speed
    grows); the same block stopped after 0.5 s: moved, then stopped; at rest: stayed."""
    t, d, v = _record(1.02, 0.25)
    m = recorded_motion(t, d, v, 0.0, limit=0.04, rest_speed=1e-3)
    assert m.verdict == "still moving at the end"
    assert m.displacement == pytest.approx(0.5 * 1.02 * 0.25**2, rel=1e-9)
    assert m.speed == pytest.approx(1.02 * 0.25, rel=1e-9)
    t, d, v = _record(1.02, 1.0, stop=0.5)
    assert recorded_motion(t, d, v, 0.0, limit=0.04, rest_speed=1e-3).verdict == \
        "moved, then stopped"
    t, d, v = _record(0.0, 1.0)
    assert recorded_motion(t, d, v, 0.0, limit=0.04, rest_speed=1e-3).verdict == "stayed"
    # decaying speed (a block slowing to rest), not yet below the rest speed: not moving on
    t = np.linspace(0.0, 1.0, 51)
    v = 0.2 * np.exp(-5 * t)
    d = np.zeros((51, 3))
    d[:, 0] = 0.04 * (1 - np.exp(-5 * t))
    assert recorded_motion(t, d, v, 0.0, limit=0.1, rest_speed=1e-3).verdict == "stayed"
    # only what follows the release counts (a staged run: the excavation's stage)
    t, d, v = _record(1.02, 1.0, stop=0.5)
    assert recorded_motion(t, d, v, 0.6, limit=0.04, rest_speed=1e-3).verdict == "stayed"


def test_keyblocks_result_says_a_sliding_block_is_still_moving(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The sidewall block on a 30° joint at φ 25° accelerates at g (sin ψ − cos ψ tan φ)
    = 0.94 m/s²; after 0.2 s it has slid about 2 cm, under 1 % of its size: the DDA's
    verdict is "still moving at the end" (it was "stayed"), and the command's last line
    says the key block is not stable."""
    phi = PSI - 5.0
    a = G * (math.sin(math.radians(PSI)) - math.cos(math.radians(PSI))
             * math.tan(math.radians(phi)))
    scene = tmp_path / "sidewall.json"
    scene.write_text(json.dumps(sidewall_scene(phi, fall=0.2)))
    result = tmp_path / "r.h5"
    assert main(["run", str(scene), "--out", str(result), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["keyblocks", str(scene), "--result", str(result), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["excavations"][0]["blocks"]
    (block,) = [r for r in rows if r["mode"] == "sliding on one plane"]
    assert block["factor_of_safety"] < 1
    assert block["dda"] == "still moving at the end"
    assert block["displacement"] == pytest.approx(0.5 * a * 0.2**2, rel=0.3)
    assert main(["keyblocks", str(scene), "--result", str(result)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert f"{block['block']}: removable, sliding on one plane" in "\n".join(lines)
    assert "DDA: still moving at the end" in "\n".join(lines)
    assert lines[-1].startswith(f"Verdict: not stable — the run shows {block['block']} "
                                "still moving at the end; lowest FS")
