"""Measured orientations, as in Dips (engine.analyses.orientations, `polydda stereonet`):
poles drawn from known Fisher sets are picked apart and fitted back; the contoured stereonet
is written; the sets become a scene's joints and the sweep's Fisher parameters."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from engine.analyses.jointstats import fisher_orientations
from engine.analyses.kinematics import normal
from engine.analyses.orientations import fit_sets, pick_sets
from service.cli.main import main

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
#: the two sets sampled: (dip, dip direction, κ, poles); the second is steep, its poles
#: fall on both sides of the net (dips past 90° turn the dip direction by 180°)
SETS = [(60.0, 135.0, 40.0, 300), (85.0, 240.0, 25.0, 200)]


def sample(seed: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Poles drawn from SETS by the exact inverse CDF of Fisher's distribution
    (engine.analyses.jointstats.fisher_orientations), the sets one after the other."""
    parts = [fisher_orientations(d, a, k, n, seed + j) for j, (d, a, k, n) in enumerate(SETS)]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def axis_angle(d1: float, a1: float, d2: float, a2: float) -> float:
    """Angle (degrees) between two planes' poles (axes: either side)."""
    c = abs(float(normal(d1, a1) @ normal(d2, a2)))
    return math.degrees(math.acos(min(1.0, c)))


def test_two_fisher_sets_are_fitted_back() -> None:
    """Means within 2° and κ within 20 % of the sets drawn. By hand: the mean of N poles of
    concentration κ strays about 1/√(κN) rad (0.52° and 0.81° here), the estimate of κ
    about κ/√N (5.8 % and 7.1 %), so 2° and 20 % are three standard errors or more; and the
    k-means puts nearly every pole in its own set (the means are 70° apart, the sets'
    spreads ~1/√κ = 9° and 11°)."""
    dips, dds = sample()
    sets, labels = fit_sets(dips, dds, 2, seed=0)
    for s, (d, a, kappa, n) in zip(sets, SETS, strict=True):
        assert axis_angle(s.dip, s.dip_direction, d, a) < 2.0, s
        assert s.kappa == pytest.approx(kappa, rel=0.2), s
        assert abs(s.count - n) <= 3, s
        assert 0.0 < s.cone_95 < 2.5  # α95 ≈ 140° / √(κN): 1.0° and 1.3°
    truth = np.repeat([0, 1], [n for *_, n in SETS])
    assert np.mean(labels == truth) > 0.99
    # the steep set straddles the net: its poles are on both sides, yet one set
    steep = dds[truth == 1]
    assert np.sum(np.abs(((steep - 240.0 + 180.0) % 360.0) - 180.0) > 90.0) > 10


def test_the_sets_are_reproducible_and_numbered_by_size() -> None:
    dips, dds = sample(5)
    first = pick_sets(dips, dds, 2, seed=3)
    assert np.array_equal(first, pick_sets(dips, dds, 2, seed=3))
    assert np.bincount(first).tolist() == sorted(np.bincount(first).tolist(), reverse=True)
    with pytest.raises(ValueError, match="cannot pick 3 sets from 2 measurements"):
        pick_sets([10, 20], [0, 0], 3)


def write_csv(path: Path, dips: np.ndarray, dds: np.ndarray, header: str = "Dip,Dip Direction"
              ) -> Path:
    lines = ["# field mapping, bench 3", header] + [f"{d:.1f},{a:.1f}"
                                                    for d, a in zip(dips, dds, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_polydda_stereonet_writes_the_contoured_net_and_a_scene(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """The CSV (header 'Dip,Dip Direction', a comment): the sets printed, the contoured
    stereonet PNG written, and jointed_slope.json with the sets as joints (the 'bedding'
    joint takes the largest set's orientation, J2 is added through the domain's centre
    with the given spacing) and their κ as the sweep's Fisher parameters: a valid scene."""
    from schemas.scene import load_scene

    dips, dds = sample()
    csv_path = write_csv(tmp_path / "bench3.csv", dips, dds)
    code = main(["stereonet", str(csv_path), "--names", "bedding,J2", "--scene",
                 str(EXAMPLES / "jointed_slope.json"), "--out", str(tmp_path / "new.json"),
                 "--spacing", "5", "--sweep"])
    out = capsys.readouterr().out
    assert code == 0
    png = tmp_path / "bench3_stereonet.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 30_000
    lines = out.splitlines()
    assert lines[0] == "500 measurements, 2 sets (k-means on the poles, seed 0):"
    assert lines[2].split()[0] == "bedding" and lines[3].split()[0] == "J2"
    assert f"written: {png}" in lines
    scene = json.loads((tmp_path / "new.json").read_text())
    joints = {j["name"]: j for j in scene["joints"]}
    bedding, j2 = joints["bedding"], joints["J2"]
    assert axis_angle(bedding["dip"], bedding["dip_direction"], 60, 135) < 2.0
    assert bedding["spacing"] == 10  # the scene's own spacing and point are kept
    assert axis_angle(j2["dip"], j2["dip_direction"], 85, 240) < 2.0 and j2["spacing"] == 5
    params = scene["sweep"]["parameters"]
    assert params["J2_orientation"]["quantity"] == "joint_orientation"
    assert params["J2_orientation"]["kappa"] == pytest.approx(25.0, rel=0.2)
    load_scene(scene)  # valid
    code = main(["stereonet", str(csv_path), "--json", "--plot", str(tmp_path / "n.png")])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and doc["measurements"] == 500 and len(doc["sets"]) == 2
    assert doc["sweep_parameters"]["J1_orientation"]["distribution"] == "fisher"
    assert (tmp_path / "n.png").is_file()


def test_bad_measurements_exit_2_naming_the_line(capsys: pytest.CaptureFixture[str],
                                                 tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("dip,dip_direction\n45,120\n95,130\n40,x\n")
    assert main(["stereonet", str(bad), "--sets", "1"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"{bad} line 3: dip 95 is not in 0 to 90 degrees",
                   f"{bad} line 4: expected numbers in columns 1 and 2, got 40,x"]
    bad.write_text("strike,dip\n10,20\n")
    assert main(["stereonet", str(bad)]) == 2
    assert "needs the columns 'dip' and 'dip_direction'" in capsys.readouterr().err
    bad.write_text("45,120\n50,125\n")  # no header: dip, dip direction
    assert main(["stereonet", str(bad), "--sets", "3"]) == 2
    assert "--sets: cannot pick 3 sets from 2 measurements" in capsys.readouterr().err
