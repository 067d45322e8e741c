"""The documentation cannot rot: the site builds with `mkdocs build --strict` (every link and
anchor resolves; the references are generated from the code), the generated references
cover every command, scene object and API operation, and every tutorial's commands run.

A fenced ```bash block preceded by `<!-- run -->` (or `<!-- run: slow -->`) in
docs/getting-started.md or docs/tutorials/*.md is executed with bash -euo pipefail in a
temporary folder holding a copy of examples/, the page's blocks in order; a ```text block
preceded by `<!-- output -->` must appear, line by line, in what the block before it printed.
The quick blocks run by default; every block (the long runs too) with `-m slow`.
"""

from __future__ import annotations

import html
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
#: pages whose commands are executed
RUNNABLE = [DOCS / "getting-started.md", *sorted((DOCS / "tutorials").glob("*.md"))]
BLOCK = re.compile(r"<!--\s*(run|run:\s*slow|output)\s*-->[ \t]*\n```(\w+)[^\n]*\n(.*?)\n```",
                   re.S)
#: seconds one block may take (the slow blocks run strength reductions)
TIMEOUT = {"quick": 600, "slow": 3600}


@dataclass
class Block:
    kind: str  # "run", "slow" or "output"
    lang: str
    text: str


def blocks(page: Path) -> list[Block]:
    """The marked blocks of a page, in order."""
    out = []
    for m in BLOCK.finditer(page.read_text()):
        kind = "slow" if "slow" in m.group(1) else m.group(1)
        out.append(Block(kind, m.group(2), m.group(3)))
    return out


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
                if want and want != "..." and not any(want in p for p in printed):
                    raise AssertionError(f"{where}: {want!r} not in the output:\n{last}")
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
    assert len(RUNNABLE) >= 6  # getting started and the five tutorials
    for page in RUNNABLE:
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
        'pip install -e ".[dev]" && polydda run examples/wedge.json --out out/wedge.h5 '
        "--summary out/wedge-summary.json", "python -m pytest"]
    assert "python -m pytest\n" in (ROOT / ".ci" / "run").read_text()
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if "://" not in target:
            assert (ROOT / target).exists(), target
