"""The viewer and the report of a local result, without a server: `polydda report RESULT.h5`
(a report that opens with its conclusion, as HTML and PDF) and `polydda view RESULT.h5` (the
service's viewer served for the file)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.cli.main import main

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def sliding(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The cube of docs/validation.md (30° incline, φ 20°) run for 0.3 s: it slides
    d = ½ g (sin 30° − cos 30° tan 20°) t² = ½ × 9.81 × 0.18479 × 0.09 = 81.6 mm and is
    still moving at g × 0.18479 × 0.3 = 0.544 m/s; the slab is fixed."""
    d = tmp_path_factory.mktemp("local")
    scene = json.loads((EXAMPLES / "incline.json").read_text())
    scene["analysis"]["duration"] = 0.3
    (d / "incline.json").write_text(json.dumps(scene))
    assert main(["run", str(d / "incline.json"), "--out", str(d / "incline.h5"),
                 "--quiet"]) == 0
    return d / "incline.h5"


def section(html: str, title: str) -> str:
    """The HTML from the <h2> that starts with `title` to the next <h2>."""
    start = html.index(f">{title}")
    end = html.find("<h2", start)
    return html[start:end if end >= 0 else None]


def test_the_report_opens_with_its_conclusion(capsys: pytest.CaptureFixture[str],
                                              sliding: Path, tmp_path: Path) -> None:
    """Conclusion first (the cube moved 81.6 mm and is still moving: not stable), the moving
    blocks next (the fixed slab left out), the raw scene last, in an appendix; figures
    inline (the file stands alone); no raw floats or Python values outside the scene."""
    out = tmp_path / "report.html"
    code, stdout, err = run(capsys, "report", str(sliding), "--out", str(out), "--no-pdf")
    assert code == 0, err
    assert stdout == f"written: {out}\n"
    html = out.read_text()
    order = [html.index(t) for t in (">Conclusion<", ">Blocks that moved more than 10.0 mm<",
                                     ">Plots<", ">Warnings<", ">Appendix: the scene<",
                                     ">Versions and provenance<")]
    assert order == sorted(order)
    conclusion = section(html, "Conclusion")
    assert "The run completed after 300 steps (0.300 s simulated)." in conclusion
    moved = re.search(r"<b>1 free block moved more than 10.0 mm</b>: cube ([\d.]+) mm\.",
                      conclusion)
    assert moved is not None and float(moved[1]) == pytest.approx(81.6, abs=0.3)
    assert "<b>1 block still moving at the end</b>" in conclusion and "not stable" in conclusion
    moving = section(html, "Blocks that moved")
    assert "<td>cube</td>" in moving and "slab" not in moving
    assert "1 fixed block not listed" in moving
    row = re.search(r"<td>cube</td><td>1.000 m³</td><td>([\d.]+)</td>", moving)
    assert row is not None and float(row[1]) == pytest.approx(81.6, abs=0.3)
    assert "<td>090/30</td>" in moving  # down the dip of the 30° slab, towards East
    appendix = section(html, "Appendix: the scene")
    assert "<pre class='mono scene'>" in appendix and "&quot;slab&quot;" in appendix
    assert 'src="http' not in html and "/static/" not in html  # nothing from a server
    assert html.count('src="data:image/png;base64,') >= 4  # plots and the last step
    text = re.sub(r"<pre.*?</pre>|data:image/png;base64,[^\"]+", "", html, flags=re.S)
    assert not re.search(r"\d\.\d{7,}", text) and ">True<" not in text and "['" not in text
    code, _, _ = run(capsys, "report", str(sliding), "--out", str(out), "--no-pdf",
                     "--threshold", "0.1")
    assert "<b>No free block moved more than 100.0 mm</b>" in out.read_text()


def test_the_report_prints_to_pdf_or_says_why_not(capsys: pytest.CaptureFixture[str],
                                                  sliding: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """With a Chromium on the PATH the PDF is written beside the HTML; without one the HTML
    is still written and one line says why there is no PDF (exit 0)."""
    out = tmp_path / "r.html"
    if shutil.which("chromium") or shutil.which("google-chrome"):
        code, stdout, err = run(capsys, "report", str(sliding), "--out", str(out))
        assert code == 0, err
        pdf = tmp_path / "r.pdf"
        assert stdout.splitlines() == [f"written: {out}", f"written: {pdf}"]
        assert pdf.read_bytes()[:4] == b"%PDF" and pdf.stat().st_size > 50_000
    monkeypatch.setattr(shutil, "which", lambda name: None)
    code, stdout, err = run(capsys, "report", str(sliding), "--out", str(tmp_path / "n.html"))
    assert code == 0 and (tmp_path / "n.html").is_file() and not (tmp_path / "n.pdf").exists()
    assert err.startswith("no PDF: no Chromium found (chromium, chromium-browser, ")


def test_report_and_view_of_a_scene_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for command in ("report", "view"):
        code, out, err = run(capsys, command, str(EXAMPLES / "wedge.json"), "--no-browser"
                             if command == "view" else "--no-pdf")
        assert code == 2 and out == "" and "is a scene, not a result: run it first" in err


def test_the_local_app_serves_the_services_viewer(sliding: Path) -> None:
    """The app answers the viewer's URLs for one job named after the file: the page (the
    service's, its config pointing at the local frames), the frames (geometry and every
    recorded step), the job's status, the report; the static assets."""
    from fastapi.testclient import TestClient

    from service.api.frames import decode_binary
    from service.api.local import local_app

    with TestClient(local_app(sliding)) as c:
        home = c.get("/", follow_redirects=False)
        assert home.status_code == 307 and home.headers["location"] == "/jobs/incline/viewer"
        page = c.get("/jobs/incline/viewer").text
        cfg = json.loads(re.search(r'id="viewer-config">([^<]*)</script>', page)[1])
        assert cfg["frames"] == "/jobs/incline/results/frames" and cfg["job"] == "/jobs/incline"
        frames = decode_binary(c.get(cfg["first"]).content)
        assert frames.header["n_blocks"] == 2 and frames.header["count"] == 31  # 0.3 s / 10 ms
        assert c.get("/jobs/incline").json()["status"] == "successful"
        assert c.get("/static/viewer.js").status_code == 200
        assert ">Conclusion<" in c.get("/jobs/incline/report").text
        bad = c.get("/jobs/incline/results/frames?start=500")
        assert bad.status_code == 422


@pytest.fixture
def served(sliding: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from service.cli.main import "
                             "main; sys.exit(main(sys.argv[1:]))", "view", str(sliding),
                             "--no-browser"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        yield proc, line.strip().removeprefix("viewer: ")
    finally:
        proc.terminate()
        proc.communicate(timeout=30)  # and close its pipes


def test_polydda_view_serves_on_a_free_local_port(served: tuple[subprocess.Popen[str], str]
                                                 ) -> None:
    """`polydda view RESULT.h5 --no-browser` prints the viewer's address on a free port of
    127.0.0.1 and serves it until stopped."""
    proc, url = served
    assert re.fullmatch(r"http://127\.0\.0\.1:\d+/jobs/incline/viewer", url), url
    r = httpx.get(url, timeout=30)
    assert r.status_code == 200 and 'id="viewer-config"' in r.text
    assert proc.poll() is None  # still serving
