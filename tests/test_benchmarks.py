"""The benchmark harness on a tiny configuration, so the benchmark code cannot rot."""

from __future__ import annotations

import csv
from pathlib import Path

from benchmarks.__main__ import main
from benchmarks.harness import energy_check, growth_exponent, pareto_front


def test_incline_benchmark_writes_csv_png_report(tmp_path: Path) -> None:
    """`--only incline` on two grid points: CSV, PNG and REPORT exist; error < 1 %."""
    assert main(["--only", "incline", "--dts", "0.02", "0.01", "--penalties", "1e10",
                 "--out", str(tmp_path)]) == 0
    with (tmp_path / "accuracy.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2
    assert all(r["status"] == "completed" for r in rows)
    assert all(float(r["rel_error"]) < 0.01 for r in rows)
    assert (tmp_path / "accuracy_incline.png").stat().st_size > 1000
    report = (tmp_path / "REPORT.md").read_text()
    assert "accuracy_incline.png" in report
    assert "## 1. Speed against accuracy" in report
    assert "python -m benchmarks --only incline" in report


def test_pareto_front_and_exponent() -> None:
    """Dominated points are dropped; the exponent of y = x² is 2."""
    front = pareto_front([1.0, 2.0, 3.0, 0.5], [1e-2, 1e-3, 1e-2, 1e-1])
    assert front.tolist() == [3, 0, 1]
    assert abs(growth_exponent([10, 100, 1000], [1, 100, 10000]) - 2.0) < 1e-12


def test_energy_check_flags_growth() -> None:
    """A run whose kinetic energy rises with no work done shows positive growth."""

    class F:
        def __init__(self, ke: float) -> None:
            self.energies = {"kinetic": ke}

    class Log:
        frames = [F(0.0), F(5.0)]

        def energy(self, key: str):
            import numpy as np

            return np.array([f.energies.get(key, 0.0) for f in self.frames])

    assert energy_check(Log(), 10.0)["growth"] == 0.5


def test_components_section_cuts_and_reports() -> None:
    """The cutting part of `--only components` on a coarse spacing conserves volume, and
    the section renders its tables and exponents."""
    from benchmarks.components import components_part, cut_cube

    blocks, wall, planes = cut_cube(40.0)
    assert planes > 3 and len(blocks) > 20 and wall > 0
    assert abs(sum(b.volume for b in blocks) - 1e6) < 1e-6
    row = {"blocks": len(blocks), "search_m": 0.1, "contacts": 10, "wall_s": 0.01}
    text = components_part({
        "cutting": [{"spacing_m": 40.0, "planes": planes, "blocks": len(blocks),
                     "wall_s": wall, "volume_error": 0.0}],
        "rock_mass": [row], "boxes": [row, row, row], "exponent_rock_mass": 1.0,
        "exponent_boxes": 1.1, "call_2_blocks_s": 5e-5, "call_2_blocks_contacts": 4})
    assert "## 6. Cutting and contact detection" in text
    assert f"| 40 | {planes} | {len(blocks)} |" in text
    assert "p = 1.00" in text and "numpy implementation: 54.6" in text


def test_stability_map_v2_verdicts() -> None:
    """benchmarks/trust.py: the cube on the φ 35° incline set exactly on the slab and the
    stack of ten dropped 1 mm stay put with no energy created; the verdicts name a
    completed run outside tolerance a silent failure, a `failed` run with a reason a clean
    stop, a cancelled one stopped."""
    from types import SimpleNamespace

    import numpy as np

    from benchmarks.trust import (
        FAILED,
        MAP_SCENES,
        PASS,
        STOPPED,
        WRONG,
        run_map_one,
        verdict_of,
    )

    exact = run_map_one(MAP_SCENES["incline35"], 1e-2, 1e11, "exact")
    assert exact["verdict"] == PASS and abs(exact["metric"]) < 1e-4
    assert exact["created_ratio"] <= 5e-3
    stack = run_map_one(MAP_SCENES["stack10_starts"], 1e-2, 1e11, "drop 1 mm")
    assert stack["verdict"] == PASS

    def outcome(status: str, message: str = "") -> SimpleNamespace:
        state = SimpleNamespace(centroid=np.zeros((2, 3)))
        return SimpleNamespace(status=status, message=message,
                               result=SimpleNamespace(state=state))

    assert verdict_of(outcome("completed"), within=False, created_ok=True) == WRONG
    assert verdict_of(outcome("completed"), within=True, created_ok=False) == WRONG
    assert verdict_of(outcome("failed", "penetration"), within=False, created_ok=True) == FAILED
    assert verdict_of(outcome("cancelled"), within=False, created_ok=True) == STOPPED


def test_the_shared_piles_live_in_the_repository() -> None:
    """The piles the step digests, the stages and the benchmarks run are the scenes the peers'
    numbers refer to: byte for byte the shared JSON (SHA-256 listed in their README), read
    from benchmarks/scenes/, the copies the repository keeps."""
    import gzip
    import hashlib
    import re

    from benchmarks.pile import SCENES, pile_path, pile_scene

    readme = (SCENES / "README.md").read_text()
    for n in (100, 400, 1000):
        path = pile_path(n)
        assert path.parent == SCENES and path.is_file()
        digest = hashlib.sha256(gzip.decompress(path.read_bytes())).hexdigest()
        assert re.search(rf"- pile_{n}: `{digest}`", readme), n
        scene = pile_scene(n)
        assert (scene["N"], len(scene["bodies"]), len(scene["walls"])) == (n, n, 5)
