"""docs/cli-extras.md cannot rot: every bash block of the page runs, in a copy of the
examples, without an error (`polydda view` waits for Ctrl-C: tests/test_cli_report.py runs
it), and the outputs the page shows are those of the commands."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "cli-extras.md"


@pytest.mark.slow
@pytest.mark.ci
def test_every_command_of_the_page_runs(tmp_path: Path) -> None:
    text = PAGE.read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    assert len(blocks) >= 4
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    outputs = []
    for block in blocks:
        script = "\n".join(line for line in block.splitlines()
                           if not line.startswith("polydda view "))
        done = subprocess.run(["bash", "-e", "-c", script], cwd=tmp_path, capture_output=True,
                              text=True, timeout=1800)
        assert done.returncode == 0, (script, done.stderr[-2000:])
        outputs.append(done.stdout)
    shown = "\n".join(outputs)
    for line in ("  cube        906.3      784.9        0.0     -453.1  090/30",
                 "critical friction angle of 'joint': 29.9°",
                 "  bedding           60.3/135.8     39.4    300  1.3°"):
        assert line in text and line in shown, line
    for made in ("out/incline-report.html", "out/sweep/sweep.png",
                 "out/measurements_stereonet.png", "out/jointed_slope_measured.json"):
        assert (tmp_path / made).is_file(), made
