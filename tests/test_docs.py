"""The documentation cannot rot: the site builds with `mkdocs build --strict` (every link and
anchor resolves; the references are generated from the code), the generated references
cover every command, scene object and API operation, and every tutorial's commands run.

A fenced ```bash block preceded by `<!-- run -->` (or `<!-- run: slow -->`) in any page of
docs/ is executed with bash -euo pipefail in a temporary folder holding a copy of examples/,
the page's blocks in order; a ```text block preceded by `<!-- output -->` must appear, line
by line, in what the block before it printed. With a tolerance, `<!-- output ~2% -->`, each
line must match a printed line whose words are the same and whose every number is within
that percentage of the documented one (the documented numbers come from the run, and say
how close they are held); `…` in a documented line stands for any text (a wall time). The
quick blocks run by default; every block (the long runs too) with `-m slow`.
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: the getting-started page and the tutorials: every bash block runs or says why not
TUTORIALS = [DOCS / "getting-started.md", *sorted((DOCS / "tutorials").glob("*.md"))]
#: pages whose commands are executed: the tutorials and every page with a marked block
RUNNABLE = [*TUTORIALS, *sorted(p for p in DOCS.glob("*.md") if p not in TUTORIALS
                                and "<!-- run" in p.read_text())]
BLOCK = re.compile(r"<!--\s*(run|run:\s*slow|output(?:\s*~\s*[\d.]+\s*%)?)\s*-->[ \t]*\n"
                   r"```(\w+)[^\n]*\n(.*?)\n```", re.S)
#: a number as the commands print it: 2,000 / -0.418 / 1.2e-05 / 29.9
NUMBER = re.compile(r"[-+]?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:e[-+]?\d+)?")
#: seconds one block may take (the slow blocks run strength reductions)
TIMEOUT = {"quick": 600, "slow": 3600}


@dataclass
class Block:
    kind: str  # "run", "slow" or "output"
    lang: str
    text: str
    tolerance: float | None = None  # relative, of an output block's numbers


def blocks(page: Path) -> list[Block]:
    """The marked blocks of a page, in order."""
    out = []
    for m in BLOCK.finditer(page.read_text()):
        mark = m.group(1)
        kind = "slow" if "slow" in mark else mark.split("~")[0].strip()
        tol = re.search(r"~\s*([\d.]+)\s*%", mark)
        out.append(Block(kind, m.group(2), m.group(3),
                         float(tol.group(1)) / 100 if tol else None))
    return out


def _value(text: str) -> float:
    return float(text.replace(",", ""))


def line_matches(want: str, printed: str, tolerance: float | None) -> bool:
    """Whether the documented line `want` is in the printed line: as text (no tolerance),
    or with the same words around numbers that each agree within `tolerance` (relative;
    a documented 0 must print 0); `…` in `want` matches any text."""
    parts = want.split("…")
    if tolerance is None and len(parts) == 1:
        return want in printed
    pattern, wanted = "", []
    for k, part in enumerate(parts):
        pos = 0
        for m in NUMBER.finditer(part) if tolerance is not None else ():
            pattern += re.escape(part[pos:m.start()]) + f"({NUMBER.pattern})"
            wanted.append(_value(m.group()))
            pos = m.end()
        pattern += re.escape(part[pos:]) + (".*?" if k < len(parts) - 1 else "")
    for m in re.finditer(pattern, printed):
        got = [_value(g) for g in m.groups()]
        if all(abs(g - w) <= (tolerance or 0.0) * abs(w) for g, w in zip(got, wanted,
                                                                        strict=True)):
            return True
    return False


def run_page(page: Path, workdir: Path, slow: bool) -> list[str]:
    """Run a page's blocks in `workdir`; the names of the blocks run (AssertionError naming
    the block on a failed command or an output that does not match)."""
    shutil.copytree(ROOT / "examples", workdir / "examples")  # makes workdir too
    env = {**os.environ, "MPLBACKEND": "Agg",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    ran, last = [], None
    for k, b in enumerate(blocks(page)):
        where = f"{page.name} block {k + 1}"
        if b.kind == "output":
            if last is None:  # its command was not run (a slow block in a quick run)
                continue
            printed = [" ".join(line.split()) for line in last.splitlines()]
            for line in b.text.splitlines():
                want = " ".join(line.split())
                if want and want != "..." and not any(line_matches(want, p, b.tolerance)
                                                      for p in printed):
                    within = "" if b.tolerance is None else f" within {100 * b.tolerance:g} %"
                    raise AssertionError(f"{where}: {want!r} not in the output{within}:\n"
                                         f"{last}")
            continue
        assert b.lang == "bash", f"{where}: runnable blocks are bash, not {b.lang}"
        if b.kind == "slow" and not slow:
            last = None
            continue
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", b.text], cwd=workdir,
                              env=env, capture_output=True, text=True,
                              timeout=TIMEOUT["slow" if b.kind == "slow" else "quick"])
        assert proc.returncode == 0, (f"{where} exited {proc.returncode}:\n{b.text}\n"
                                      f"--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr}")
        last = proc.stdout
        ran.append(where)
    return ran


def test_every_tutorial_has_runnable_commands() -> None:
    assert len(TUTORIALS) >= 6  # getting started and the five tutorials
    assert DOCS / "factor-of-safety.md" in RUNNABLE  # a guide with its commands run
    for page in TUTORIALS:
        kinds = [b.kind for b in blocks(page)]
        assert "run" in kinds, f"{page.name}: no block marked <!-- run -->"
        # an unmarked bash block would escape the test: every one is marked, or says why
        text = page.read_text()
        fenced = len(re.findall(r"^```bash", text, re.M))
        marked = sum(k in ("run", "slow") for k in kinds)
        unrun = len(re.findall(r"<!--\s*not run:[^>]*-->\s*\n```bash", text))
        assert fenced == marked + unrun, f"{page.name}: a bash block is neither run nor " \
                                         "marked <!-- not run: why -->"


@pytest.mark.parametrize("page", RUNNABLE, ids=lambda p: p.stem)
def test_tutorial_commands_run(page: Path, tmp_path: Path) -> None:
    """The page's quick blocks run and print what the page shows."""
    run_page(page, tmp_path, slow=False)


#: pages whose long blocks CI runs too (`slow and ci`: two strength reductions, ~1 min)
CI_PAGES = {"bolted-block-water"}


@pytest.mark.slow
@pytest.mark.parametrize("page", [pytest.param(p, marks=[pytest.mark.ci] if p.stem in CI_PAGES
                                               else []) for p in RUNNABLE],
                         ids=lambda p: p.stem)
def test_tutorial_commands_run_in_full(page: Path, tmp_path: Path) -> None:
    """Every block of the page, the strength reductions and long runs too."""
    run_page(page, tmp_path, slow=True)


def test_output_check_can_fail(tmp_path: Path) -> None:
    """The runner rejects a shown output the command does not print, and a failing command."""
    page = tmp_path / "page.md"
    page.write_text("<!-- run -->\n```bash\necho 'FS = 2.195'\n```\n\n<!-- output -->\n"
                    "```text\nFS = 2.198\n```\n")
    with pytest.raises(AssertionError, match="not in the output"):
        run_page(page, tmp_path / "a", slow=False)
    page.write_text("<!-- run -->\n```bash\nfalse\n```\n")
    with pytest.raises(AssertionError, match="exited 1"):
        run_page(page, tmp_path / "b", slow=False)
    # a documented number held within a tolerance: 2.199 is not 2.1904 within 0.1 %
    page.write_text("<!-- run -->\n```bash\necho 'factor of safety 2.1904 (6 trials) in 3.2 s'"
                    "\n```\n\n<!-- output ~0.1% -->\n```text\nfactor of safety 2.199 (6 "
                    "trials) in … s\n```\n")
    with pytest.raises(AssertionError, match="within 0.1 %"):
        run_page(page, tmp_path / "c", slow=False)
    page.write_text(page.read_text().replace("~0.1%", "~0.5%"))
    assert run_page(page, tmp_path / "d", slow=False) == ["page.md block 1"]
    page.write_text(page.read_text().replace("2.199 (6 trials)", "2.199 (7 trials)"))
    with pytest.raises(AssertionError, match="not in the output"):  # 7 is not 6 within 0.5 %
        run_page(page, tmp_path / "e", slow=False)


def test_numbers_within_a_tolerance() -> None:
    assert line_matches("FS 2.19, 6 trials", "FS 2.1904, 6 trials", 0.01)
    assert not line_matches("FS 2.19, 6 trials", "FS 2.30, 6 trials", 0.01)
    assert not line_matches("FS 2.19, 6 trials", "FS 2.19, 6 runs", 0.01)  # the words too
    assert line_matches("2,000 steps in … s", "2,000 steps in 14.2 s", 0.0)
    assert line_matches("moved 0 mm", "moved 0 mm", 0.02)
    assert not line_matches("moved 0 mm", "moved 0.1 mm", 0.02)
    assert line_matches("[-1.058, -0.611] MN", "[-1.06, -0.61] MN", 0.01)


# --------------------------------------------------------------------------- the site


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site built strictly (a broken link, anchor or nav entry fails the build)."""
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                           str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stderr}"
    return out


def _ids(page: Path) -> set[str]:
    return set(re.findall(r'id="([^"]+)"', page.read_text()))


def test_site_builds_strict(site: Path) -> None:
    for page in ("index.html", "getting-started/index.html", "tutorials/wedge/index.html",
                 "theory/index.html", "validation/index.html", "performance/index.html",
                 "architecture/index.html", "reference/scene.schema.json",
                 "reference/openapi.json", "img/benchmarks/trust.png"):
        assert (site / page).is_file(), page


def test_cli_reference_lists_every_command(site: Path) -> None:
    from service.cli.main import build_parser

    ids = _ids(site / "reference" / "cli" / "index.html")
    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and a.choices)
    assert set(sub.choices) <= ids, set(sub.choices) - ids
    text = html.unescape((site / "reference" / "cli" / "index.html").read_text())
    assert "--friction-mean DEG" in text and "--summary" in text


def test_scene_reference_lists_every_object_and_field(site: Path) -> None:
    from schemas import scene_json_schema

    schema = scene_json_schema()
    page = site / "reference" / "scene" / "index.html"
    ids, text = _ids(page), html.unescape(page.read_text())
    assert {name.lower() for name in schema["$defs"]} <= ids
    for model in (schema, *schema["$defs"].values()):
        for field in model.get("properties", {}):
            assert f"<code>{field}</code>" in text, field
    assert "degrees clockwise from North" in text  # a field's description


def test_api_reference_lists_every_operation(site: Path) -> None:
    from service.api.app import create_app

    ids = _ids(site / "reference" / "api" / "index.html")
    ops = {op["operationId"].lower()
           for item in create_app(listen="127.0.0.1").openapi()["paths"].values()
           for op in item.values() if isinstance(op, dict) and "operationId" in op}
    assert ops and ops <= ids, ops - ids


def test_readme_is_a_first_page() -> None:
    """≤ 150 lines, the two commands first, links that exist."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    first = re.search(r"```bash\n(.*?)\n```", text, re.S)
    assert first is not None and first.group(1).splitlines() == [
        'pip install -e ".[dev]" && polydda warm-up && polydda run examples/wedge.json '
        "--out out/wedge.h5 --summary out/wedge-summary.json", "python -m pytest"]
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python -m pytest\n" in ci and first.group(1).splitlines()[0].split(" && ", 1)[1] \
        in ci  # CI runs the README's first command
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if "://" not in target:
            assert (ROOT / target).exists(), target


def _repository_files() -> list[str]:
    """The repository's files: git's list in a clone; in a copy without `.git` (CI's), every
    file outside the virtual environments, caches and outputs."""
    listed = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode == 0 and (ROOT / ".git").exists():
        return listed.stdout.split()
    skip = {".git", "out", "build", ".hypothesis", ".import_linter_cache", "node_modules",
            "__pycache__", ".pytest_cache", ".ruff_cache"}
    return [str(p.relative_to(ROOT)) for p in ROOT.rglob("*")
            if p.is_file() and not any(part in skip or part.startswith(".venv")
                                       or part.endswith(".egg-info")
                                       for part in p.relative_to(ROOT).parts)]


def test_no_file_cites_a_page_that_is_not_there() -> None:
    """Examples, code, tests and pages cited a `VALIDATION.md` the repository does not
    have (the table is docs/validation.md): every `NAME.md` a tracked file names exists."""
    tracked = _repository_files()
    names = {Path(f).name for f in tracked}
    cited = re.compile(r"(?<![\w/.-])((?:[\w-]+/)*[\w-]+\.md)\b")
    missing = []
    for f in tracked:
        if (Path(f).suffix not in (".py", ".json", ".md", ".toml", ".yml", ".html", ".js")
                or f == "tests/test_docs.py"
                # the kernel modules are left to the engine's kernel work (a change there
                # recompiles every kernel): _transform_kernels.py cites THEORY.md
                or re.fullmatch(r"engine/.*/_\w+_kernels\.py", f)):
            continue
        for m in cited.finditer((ROOT / f).read_text(errors="replace")):
            if Path(m.group(1)).name not in names:
                missing.append(f"{f}: {m.group(1)}")
    assert not missing, missing


def test_readme_states_the_measured_first_run() -> None:
    """The README and getting started say how long the first run takes as measured by
    `python -m benchmarks.bench_startup --cold` (benchmarks/results/startup_cold.json),
    in words made from that file."""
    from benchmarks.bench_startup import COLD_RESULT, cold_sentence

    sentence = cold_sentence(json.loads(COLD_RESULT.read_text()))
    for page in (ROOT / "README.md", DOCS / "getting-started.md"):
        assert sentence in " ".join(page.read_text().split()), page.name


def test_contact_solver_tables_come_from_their_results() -> None:
    """docs/contact-solvers.md's measured tables (speed and accuracy of every solver, the
    toppling train at several Δt, sleeping) are those `python -m benchmarks.docs_tables`
    makes from the result files the cited benchmarks write."""
    from benchmarks.docs_tables import PAGE, render

    page = PAGE.read_text()
    assert render(page) == page, "run: python -m benchmarks.docs_tables"
    assert "not measured yet" not in page
