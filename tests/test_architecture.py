"""The tree is the map: the engine's rooms import downwards only, with no cycles anywhere
(import-linter's contracts in pyproject.toml), and no room grows past what a newcomer can
read (modules ≤ 600 lines and functions ≤ 80 lines, compiled kernels excepted)."""

from __future__ import annotations

import ast
import importlib
import os
import re
from pathlib import Path

import pytest
from importlinter.cli import lint_imports

ROOT = Path(__file__).resolve().parents[1]
ENGINE = ROOT / "engine"
ROOMS = ("geometry", "loads", "dynamics", "contact", "step", "results", "analyses")


def _engine_modules() -> list[Path]:
    return sorted(p for p in ENGINE.rglob("*.py") if "__pycache__" not in p.parts)


def _is_kernels(path: Path) -> bool:
    return path.name.startswith("_") and path.name.endswith("_kernels.py")


def test_import_contracts_are_kept(capsys: pytest.CaptureFixture[str]) -> None:
    """Layers (service → schemas → engine; the engine's rooms top to bottom; the service's
    CLI → HTTP → jobs) and no import cycle between the modules of any package."""
    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        code = lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True,
                            no_logo=True)
    finally:
        os.chdir(cwd)
    assert code == 0, capsys.readouterr().out


def test_no_import_circle_even_through_type_only_imports() -> None:
    """No module reaches back to a module it imports, counting the imports made for type
    hints only (import-linter's contracts leave those out): `service.jobs.backend` and
    `service.jobs.fanout` imported each other so, the last circle in the project."""
    import grimp

    graph = grimp.build_graph("engine", "schemas", "service", cache_dir=None,
                              exclude_type_checking_imports=False)
    circles = sorted({tuple(sorted((a, b))) for a in graph.modules
                      for b in graph.find_modules_directly_imported_by(a)
                      if graph.chain_exists(importer=b, imported=a)})
    assert not circles, circles


@pytest.mark.parametrize("room", ROOMS)
def test_each_room_says_what_it_holds_and_may_import(room: str) -> None:
    doc = importlib.import_module(f"engine.{room}").__doc__ or ""
    assert len(doc.split()) > 15, f"engine.{room} needs a package docstring"
    assert "import" in doc, f"engine.{room}'s docstring must say what it may import"


def test_engine_modules_and_functions_stay_readable() -> None:
    """No engine module over 600 lines and no function over 80, except compiled kernels
    (whose long functions say why in the comment before them); the orchestrator stays under
    250 lines."""
    long_modules, long_functions = [], []
    for path in _engine_modules():
        text = path.read_text()
        lines = text.splitlines()
        if not _is_kernels(path) and len(lines) > 600:
            long_modules.append(f"{path.relative_to(ROOT)}: {len(lines)} lines")
        for fn in ast.walk(ast.parse(text)):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            n = fn.end_lineno - fn.lineno + 1
            if n <= 80:
                continue
            first = min([fn.lineno] + [d.lineno for d in fn.decorator_list])
            compiled = any("njit" in ast.unparse(d) for d in fn.decorator_list)
            explained = lines[first - 2].lstrip().startswith("#")
            if not (compiled and explained):
                long_functions.append(f"{path.relative_to(ROOT)}:{fn.name} {n} lines")
    assert not long_modules, long_modules
    assert not long_functions, long_functions
    assert len((ENGINE / "step" / "simulation.py").read_text().splitlines()) < 250


def test_architecture_page_names_what_the_code_has() -> None:
    """Every `room/module.function` of docs/architecture.md's pipeline exists in the engine,
    every module of its tree exists, and Simulation.step calls the stage functions the
    pipeline lists, in its order."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    pipeline = page.split("## One step", 1)[1].split("```")[1]
    names = re.findall(rf"\b({'|'.join(ROOMS)})/((?:[a-z_]+/)*[a-z_]+)\.([A-Za-z_]+)", pipeline)
    assert len(names) >= 10
    for room, module, attr in names:
        mod = importlib.import_module(f"engine.{room}.{module.replace('/', '.')}")
        assert hasattr(mod, attr), f"{room}/{module}.{attr}"
    tree = page.split("## The tree", 1)[1].split("```")[1]
    listed = set(re.findall(r"^\s+(_?[a-z_]+)(?:\.py)?\s", tree, re.M))
    actual = {p.stem for p in _engine_modules() if p.stem != "__init__"}
    assert actual <= listed, f"modules missing from docs/architecture.md: {actual - listed}"
    step = ast.get_source_segment(
        (ENGINE / "step" / "simulation.py").read_text(),
        next(f for f in ast.walk(ast.parse((ENGINE / "step" / "simulation.py").read_text()))
             if isinstance(f, ast.FunctionDef) and f.name == "step"))
    order = ["first_attempt(", "find_contacts(", "solve_contacts(", "stepping.check(",
             "advance(", "settle_contacts(", "energy.check_step(", "stepping.cut("]
    positions = [step.index(name) for name in order]
    assert positions == sorted(positions)


def test_no_module_is_left_in_the_engine_root_but_the_foundation() -> None:
    """Every engine module sits in a room, except the foundation every room may use."""
    top = sorted(p.name for p in ENGINE.glob("*.py"))
    assert top == ["__init__.py", "jsonable.py", "model.py", "status.py", "tolerances.py"], top
