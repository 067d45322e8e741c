"""What the long commands print for people: progress with the time left (a bar on a terminal,
plain lines in a log), the end of a run with its moving blocks in units, the factor of safety
with how it was found, the sweep's figure. No raw 7.151881302842081, no Python True."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import pytest

from service.cli.main import main
from service.cli.progress import Progress, bisection_total, clock

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
RAW_FLOAT = re.compile(r"\d\.\d{7,}")


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------- progress


def test_progress_in_a_log_is_a_line_per_tenth_with_the_time_left() -> None:
    stream = io.StringIO()
    bar = Progress("run x", 2.0, unit="s", stream=stream, tty=False)
    for k in range(1, 101):
        bar.update(0.02 * k, f"step {k}")
    bar.event("a trial")
    bar.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 11  # 10 %, 20 %, ... 100 %, and the event
    assert lines[0] == "run x:  10 % · elapsed 0:00 · left 0:00 · step 10"
    assert lines[9].startswith("run x: 100 % · elapsed")
    assert lines[10].endswith("· a trial")
    quiet = io.StringIO()
    off = Progress("run x", 1.0, stream=quiet, tty=False, enabled=False)
    off.update(1.0)
    off.event("x")
    assert quiet.getvalue() == ""


def test_progress_on_a_terminal_is_a_tqdm_bar() -> None:
    stream = io.StringIO()
    bar = Progress("run x", 2.0, unit="s", stream=stream, tty=True)
    bar.update(1.0, "step 10")
    bar.event("trial 1 of about 3")
    bar.update(2.0, "step 20")
    bar.close()
    text = stream.getvalue()
    assert "\r" in text and "run x: 100%|" in text and "<00:00]" in text
    assert "trial 1 of about 3\n" in text and ", step 20" in text


def test_the_time_left_counts_only_the_work_of_this_command() -> None:
    """A resumed sweep (400 of 500 done before) paces the 100 left on the ones done now."""
    bar = Progress("sweep", 500, stream=io.StringIO(), tty=False)
    bar.start -= 10.0  # 10 s ago
    bar.update(450, base=400)
    assert bar.remaining() == pytest.approx(10.0, rel=0.05)  # 50 in 10 s, 50 to go
    assert clock(3725) == "1:02:05" and clock(42) == "0:42" and clock(None) == "?"


def test_bisection_total_estimates_the_trials() -> None:
    """F = 1 fails, 0.5 holds: halvings until (hi - lo) / lo ≤ 0.5 %: 0.5 / 0.0025 = 200,
    log2 200 = 7.6, so 8 more: 10 in all (the incline's search takes 10). Before the
    bracket: one more than done; never more than max_runs."""
    assert bisection_total([], 0.005, 30) == 2
    assert bisection_total([(1.0, True)], 0.005, 30) == 2
    assert bisection_total([(1.0, True), (0.5, False)], 0.005, 30) == 10
    assert bisection_total([(1.0, True), (0.5, False)], 0.005, 6) == 6
    # kh: relative to the upper end (0 held, 0.1 failed: 0.1 / 0.0005 = 200: 8 more)
    assert bisection_total([(0.0, False), (0.1, True)], 0.005, 30, "hi") == 10


# --------------------------------------------------------------------------- run


def test_run_ends_with_the_moving_blocks_in_units(capsys: pytest.CaptureFixture[str],
                                                  tmp_path: Path) -> None:
    """The 1 m cube on the 30° incline with φ 20° slides d = ½ g (sin 30° − cos 30° tan 20°) t²
    = ½ × 9.81 × 0.18479 × 0.5² = 0.2266 m in 0.5 s (docs/validation.md), down the dip: trend
    090, plunge 30. The end of `run` lists it in mm to 0.1 mm, in a log it printed a line per
    tenth with the time left; nothing is raw."""
    scene = json.loads((EXAMPLES / "incline.json").read_text())
    scene["analysis"]["duration"] = 0.5
    path = tmp_path / "incline.json"
    path.write_text(json.dumps(scene))
    code, out, err = run(capsys, "run", str(path), "--out", str(tmp_path / "r.h5"))
    assert code == 0
    lines = out.splitlines()
    assert lines[0].startswith("completed: 500 steps, 0.500 s simulated in ")
    assert "; largest penetration " in lines[0] and lines[0].endswith(f"result {tmp_path}/r.h5")
    assert lines[1] == "1 free block moved more than 10.0 mm:"
    assert lines[2].split() == ["block", "|u|", "(mm)", "u_x", "u_y", "u_z", "trend/plunge",
                                "(°)"]
    row = lines[3].split()
    assert row[0] == "cube" and float(row[1]) == pytest.approx(226.6, abs=0.5)
    assert float(row[2]) == pytest.approx(226.6 * 0.8660, abs=0.5)  # east, cos 30°
    assert float(row[4]) == pytest.approx(-226.6 * 0.5, abs=0.5)  # down, sin 30°
    assert row[5] == "090/30"
    # the last line is the verdict, on the speed at the end (g sin 30° (1 - tan 20° / tan
    # 30°) 0.5 s = 0.906 m/s: still sliding)
    assert lines[-1].startswith("Verdict: not stable — 1 block still moving at the end "
                                "(cube at 0.906 m/s")
    assert not RAW_FLOAT.search(out) and "True" not in out
    progress = [ln for ln in err.splitlines() if ln.startswith("run incline: ")]
    assert len(progress) == 10 and " · left " in progress[0]
    assert progress[0].endswith(" · t = 0.050 s, step 50, Δt 1.00 ms")


# --------------------------------------------------------------------------- fos


def test_fos_text_says_how_it_was_found() -> None:
    """Two decimals, the number of trials and the last bracket; the critical friction angle
    of each weakened joint material by name, in degrees (it printed a Python list)."""
    from service.cli.runs import fos_text

    doc = {"factor_of_safety": 0.630859375, "critical_friction_angle": 29.93107481935,
           "runs": [{"factor": 1.0, "failed": True}, {"factor": 0.5, "failed": False},
                    {"factor": 0.6328125, "failed": True},
                    {"factor": 0.62890625, "failed": False}],
           "status": "completed", "message": "", "joint_materials": ["joint"],
           "warnings": ["a warning"]}
    assert fos_text(doc) == [
        "factor of safety 0.63 (strength reduction, bisection on tan φ / F over 4 trial runs: "
        "holds at F = 0.6289, fails at 0.6328)",
        "critical friction angle of 'joint': 29.9°", "warning: a warning",
        "Verdict: not stable — FS 0.63 < 1"]
    assert fos_text(doc, shown=["a warning"])[-2:] == [  # said when the scene was loaded
        "critical friction angle of 'joint': 29.9°", "Verdict: not stable — FS 0.63 < 1"]
    doc |= {"critical_friction_angle": [29.9310748, 31.25], "joint_materials": ["a", "b"]}
    assert fos_text(doc)[1:3] == ["critical friction angle of 'a': 29.9°",
                                  "critical friction angle of 'b': 31.2°"]


# --------------------------------------------------------------------------- sweep


def test_sweep_writes_its_histogram_and_cdf(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path) -> None:
    """`polydda sweep` (eq. 51 on the paper's wedge) writes sweep.png beside sweep.json, as
    the service's report draws it; the progress counts realisations."""
    code, out, err = run(capsys, "sweep", str(EXAMPLES / "wedge.json"), "--mode", "analytic",
                         "--n", "200", "--friction-mean", "35", "--friction-sd", "5",
                         "--out", str(tmp_path / "sw"))
    assert code == 0, err
    png = tmp_path / "sw" / "sweep.png"
    assert out.splitlines()[-1] == f"written: {png}"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert "sweep wedge: 100 % · elapsed" in err and "200 of 200 realisations" in err
