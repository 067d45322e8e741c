"""The tree is the map: the engine's rooms import downwards only, with no cycles anywhere
(import-linter's contracts in pyproject.toml), and no room grows past what a newcomer can
read (modules ≤ 600 lines and functions ≤ 80 lines, compiled kernels excepted)."""

from __future__ import annotations

import ast
import importlib
import os
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


@pytest.mark.parametrize("room", ROOMS)
def test_each_room_says_what_it_holds_and_may_import(room: str) -> None:
    doc = importlib.import_module(f"engine.{room}").__doc__ or ""
    assert len(doc.split()) > 15, f"engine.{room} needs a package docstring"
    assert "import" in doc, f"engine.{room}'s docstring must say what it may import"


def test_engine_modules_and_functions_stay_readable() -> None:
    long_modules, long_functions = [], []
    for path in _engine_modules():
        if _is_kernels(path):
            continue
        text = path.read_text()
        if text.count("\n") > 600:
            long_modules.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > 80:
                    long_functions.append(f"{path.relative_to(ROOT)}:{node.name} {n} lines")
    assert not long_modules, long_modules
    assert not long_functions, long_functions


def test_no_module_is_left_in_the_engine_root_but_the_foundation() -> None:
    """Every engine module sits in a room, except the foundation every room may use."""
    top = sorted(p.name for p in ENGINE.glob("*.py"))
    assert top == ["__init__.py", "jsonable.py", "model.py", "status.py", "tolerances.py"], top
