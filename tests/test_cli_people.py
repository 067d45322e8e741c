"""What a person reads on the second day (issue 41): numbers from one formatter (units that
fit, round-off as 0, azimuths in [0, 360)), a verdict as the last line of every analysis,
honest times (the whole staged run's wall time, progress that never goes back and reaches
100 %, a time left that leaves the compilation out), warnings once, no progress in --json,
a one-line description of every command."""

from __future__ import annotations

import io
import json
import re
import time
from pathlib import Path

import pytest

from service import readable as rd
from service.cli.main import build_parser, main
from service.cli.progress import Progress

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
#: what a person should never read: round-off, raw exponents, -0, 360°
NOISE = re.compile(r"\d\.\d+e[-+]\d+|-0\.0+\b|\b360\.00°")


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------- the formatter


def test_one_formatter_for_forces_angles_and_energies() -> None:
    """`le` printed [2550.6, 1.56179e-13, 0] N and mixed 365230 N with 3.50035e+06 N;
    kinematics printed plunge -0.00° and trend 360.00°; the report 2.602e-18 J."""
    assert rd.forces([2550.6, 1.56179e-13, 0.0]) == "[2.551, 0, 0] kN"
    assert rd.forces([1.14839e6, -417979.0, 1.02546e6]) == "[1.148, -0.418, 1.025] MN"
    assert rd.force(365230.0) == "365.2 kN" and rd.force(3.50035e6) == "3.500 MN"
    assert rd.force(1e-13, scale=3.5e6) == "0 N" and rd.force(512.0) == "512.0 N"
    assert rd.stress(16350.0) == "16.4 kPa" and rd.stress(0.0) == "0 Pa"
    assert rd.angle(-0.001, 2) == "0.00°" and rd.angle(28.7499, 2) == "28.75°"
    assert rd.azimuth(359.9999) == "0.00°" and rd.azimuth(-7.41) == "352.59°"
    assert rd.azimuth(172.5901) == "172.59°" and rd.degrees(40.0) == "40°"
    assert rd.energy(2.602e-18, scale=2.4e5) == "0 J" and rd.energy(1234.5) == "1.234 kJ"
    assert rd.number(-1e-12, scale=1.0) == "0"


def test_le_and_kinematics_print_no_round_off(capsys: pytest.CaptureFixture[str]) -> None:
    """The wedge with water (le: MN, one unit per vector) and the wedge's kinematics."""
    code, out, _ = run(capsys, "le", str(EXAMPLES / "wedge_water.json"))
    assert code == 0 and not NOISE.search(out), out
    assert "driving 3.500 MN, resisting 5.104 MN" in out
    assert "weight (weight): [0, 0, -7.277] MN" in out
    code, out, _ = run(capsys, "le", str(EXAMPLES / "wedge.json"))
    assert "driving 365.2 kN, resisting 802.8 kN" in out and not NOISE.search(out)
    code, out, _ = run(capsys, "kinematics", str(EXAMPLES / "wedge.json"))
    assert code == 0 and not NOISE.search(out) and "trend 172.59°, plunge 28.75°" in out


def test_kinematics_of_a_horizontal_intersection_reads_0_not_360(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Two joints striking north, dipping 50° east and 70° west, meet in a horizontal line
    of trend 359.999997° (it printed trend 360.00°)."""
    scene = json.loads((EXAMPLES / "wedge.json").read_text())
    scene["joints"] = [
        {"name": "A", "dip": 50, "dip_direction": 89.99999, "point": [0, 3, 10]},
        {"name": "B", "dip": 70, "dip_direction": 270, "point": [0, 3, 10]}]
    path = tmp_path / "flat.json"
    path.write_text(json.dumps(scene))
    code, out, err = run(capsys, "kinematics", str(path))
    assert code == 0, err
    line = next(ln for ln in out.splitlines() if ln.startswith("intersection A/B"))
    assert not NOISE.search(out), line
    assert "trend 0.00°, plunge 0.00°" in line, line


def test_the_report_shows_round_off_energy_as_0() -> None:
    from service.api.report import _result_section

    html = _result_section({"status": "completed", "steps": 10, "simulated_time": 0.1,
                            "wall_time": 1.0, "reseat_dissipation": 2.602e-18},
                           {"energy_scale": 2.4e5})
    assert "2.602e-18" not in html and "<td>0 J</td>" in html


# --------------------------------------------------------------------------- verdicts


def test_le_ends_with_its_verdict(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "le", str(EXAMPLES / "wedge.json"))
    assert out.strip().splitlines()[-1] == "Verdict: stable — FS 2.20"


def test_verdict_lines() -> None:
    from service.cli.runs import seismic_verdict
    from service.documents import run_verdict, verdict_line

    assert verdict_line(0.8312) == "Verdict: not stable — FS 0.83 < 1"
    assert verdict_line(1.3712) == "Verdict: stable — FS 1.37"
    assert verdict_line(0.99961) == "Verdict: not stable — FS 0.9996 < 1"  # not "1.00 < 1"
    assert verdict_line(3.0, bound="lower") == "Verdict: stable — FS ≥ 3.00"
    assert seismic_verdict(0.17633, None).startswith("Verdict: stable below kh 0.176")
    block = {"name": "B2", "displacement": [0.5, 0.0, -0.3], "velocity": [1.2, 0, -0.7]}
    base = {"name": "B1", "displacement": [0, 0, 0], "velocity": [0, 0, 0]}
    summary = {"status": "completed", "blocks": [base, block], "simulated_time": 2.0}
    assert run_verdict(summary, [True, False]).startswith(
        "Verdict: not stable — 1 block still moving at the end (B2 at 1.39 m/s")
    block["velocity"] = [0.0, 0.0, 0.0]
    assert run_verdict(summary, [True, False]).startswith("Verdict: moved, then came to rest")
    block["displacement"] = [7e-6, 0, 0]
    assert run_verdict(summary, [True, False]) == (
        "Verdict: stable — no free block moved more than 10.0 mm (largest 7.0 µm, B2)")
    assert run_verdict({"status": "failed", "simulated_time": 0.5}, []).startswith(
        "Verdict: none — the run failed")


# --------------------------------------------------------------------------- progress


def test_progress_never_goes_back() -> None:
    """A bisection's estimate of its trials grows once the bracket is found (1 of 2, 2 of 3,
    then 3 of 10): the share shown stays, then grows (it went 50 → 67 → 30 %)."""
    stream = io.StringIO()
    bar = Progress("fos x", 2, stream=stream, tty=False)
    shares = []
    for done, total in ((1, 2), (2, 3), (3, 10), (6, 10), (10, 10)):
        bar.update(done, total=total)
        shares.append(bar.share)
    assert shares == sorted(shares) and shares[-1] == 1.0
    tty = io.StringIO()
    bar = Progress("fos x", 2, stream=tty, tty=True)
    for done, total in ((1, 2), (2, 3), (3, 10)):
        bar.update(done, total=total)
    assert bar.bar.n == 667  # of 1000: not back to 300
    bar.close()


def test_a_clock_that_stops_short_of_the_end_prints_100_percent() -> None:
    """The wedge's clock ends at 1.9999999999998905 s of 2 s: its 100 % line is printed."""
    stream = io.StringIO()
    bar = Progress("run wedge", 2.0, stream=stream, tty=False)
    for k in range(1, 2001):
        bar.update(min(k * 0.001 - 1.1e-16 * k, 1.9999999999998905))
    assert stream.getvalue().splitlines()[-1].startswith("run wedge: 100 %")


def test_the_time_left_leaves_the_compilation_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """150 s compiling before the first step, then 1 s per 1 %: at 10 % the time left is
    about 90 s (it said 23 min), and until the pace is known it says "compiling"."""
    clock = [0.0]
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    stream = io.StringIO()
    bar = Progress("run x", 100.0, stream=stream, tty=False, compiling=True)
    assert "compiling" in (bar._line("") or stream.getvalue())
    clock[0] = 150.0
    bar.update(0.5)  # the first step, after the compilation
    for k in range(1, 11):
        clock[0] = 150.0 + k
        bar.update(0.5 + k)
    assert bar.remaining() == pytest.approx(89.5, rel=0.01)
    assert stream.getvalue().splitlines()[-1].split(" · ")[2] == "left 1:30"


# --------------------------------------------------------------------------- noise


def test_every_command_has_a_one_line_description(monkeypatch: pytest.MonkeyPatch) -> None:
    """`polydda --help` lists each command with its description on one line (80 columns),
    and `polydda COMMAND --help` begins with a description."""
    monkeypatch.setenv("COLUMNS", "80")
    parser = build_parser()
    text = parser.format_help()
    sub = next(a for a in parser._actions if getattr(a, "choices", None))
    for name, p in sub.choices.items():
        assert re.search(rf"^    {re.escape(name)} +\S", text, re.M), name
        assert p.description, name
        assert p.format_help().split("\n\n")[1].strip(), name


def test_fos_json_prints_no_progress(capsys: pytest.CaptureFixture[str]) -> None:
    """`fos --json` (as `run --json`) writes nothing on stderr but the scene's warnings."""
    code, out, err = run(capsys, "fos", str(EXAMPLES / "incline_seismic.json"), "--json")
    assert code == 0 and json.loads(out)["factor_of_safety"] > 1
    assert err == ""


def test_warnings_are_said_once(capsys: pytest.CaptureFixture[str]) -> None:
    """The tunnel's merge warning was printed when the scene was loaded and again at the
    end; now once."""
    code, out, err = run(capsys, "keyblocks", str(EXAMPLES / "tunnel_staged.json"))
    said = (out + err).count("small block(s) below 0.5 m³ merged")
    assert code == 0 and said == 1
    from service.cli.runs import fos_text, run_text

    summary = {"status": "completed", "steps": 1, "simulated_time": 0.1, "wall_time": 1.0,
               "blocks": [], "warnings": ["merged", "engine"]}
    lines = run_text(summary, [], "r.h5", shown=["merged"])
    assert "warning: merged" not in lines and "warning: engine" in lines
    doc = {"factor_of_safety": 1.5, "runs": [], "warnings": ["merged"]}
    assert "warning: merged" not in fos_text(doc, shown=["merged"])
