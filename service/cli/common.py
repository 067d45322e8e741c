"""What the `polydda` commands share: exit codes, JSON output, loading a scene with its
warnings on stderr, opening a result file."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from engine.results.reader import Result
    from schemas.convert import BuildResult
    from schemas.errors import SceneError

EXIT_OK, EXIT_IO, EXIT_SCENE, EXIT_RUN = 0, 1, 2, 3
#: problems of a scene printed at most (then how many more there are)
MAX_PROBLEM_LINES = 50


def print_json(doc: Any) -> None:
    """One JSON document on stdout (no NaN: the documents are finite)."""
    json.dump(doc, sys.stdout, indent=2, allow_nan=False)
    sys.stdout.write("\n")


def scene_failed(exc: SceneError) -> int:
    """The scene's problems on stderr, one per line (each bounded by SceneError, at most
    MAX_PROBLEM_LINES of them, then how many more); exit code 2."""
    lines = exc.lines()
    for line in lines[:MAX_PROBLEM_LINES]:
        print(line, file=sys.stderr)
    if len(lines) > MAX_PROBLEM_LINES:
        print(f"… and {len(lines) - MAX_PROBLEM_LINES:,} more problems", file=sys.stderr)
    return EXIT_SCENE


def load_scene(path: str, quiet: bool = False, service_limits: bool = False) -> BuildResult:
    """Build the scene at `path` (SceneError on any problem); warnings go to stderr (unless
    `quiet`: a --json document carries them). With `service_limits`, the scene must also
    keep a server's limits (POLYDDA_MAX_* settings), checked before anything is cut."""
    from schemas.convert import build_model

    if service_limits:
        from schemas.errors import SceneError
        from schemas.scene import load_scene as parse
        from service.settings import Settings, limit_problems

        scene = parse(Path(path))
        problems = limit_problems(scene, Settings())
        if problems:
            raise SceneError(problems)
        result = build_model(scene, base_dir=Path(path).resolve().parent)
    else:
        result = build_model(Path(path))
    if not quiet:
        for w in result.warnings:
            print(f"warning: {w}", file=sys.stderr)
    return result


def one_model(built: BuildResult, analysis: str) -> None:
    """SceneError (exit 2) when an analysis of one model is asked of a staged scene."""
    from schemas.stage_checks import refuse_stages

    refuse_stages(built, analysis)


def listed(values: list[str] | None) -> list[str] | None:
    """Values of a repeatable option that also takes comma-separated lists."""
    if values is None:
        return None
    return [v.strip() for value in values for v in value.split(",") if v.strip()]


#: the first bytes of every HDF5 file (at offset 0 for the files the engine writes)
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def open_result_file(command: str, path: str) -> Result | int:
    """The result file at `path`, open; or, said in one line on stderr naming the file, the
    exit code: 2 when it is not there or not a result (a scene, another HDF5 file), like any
    other bad input; 1 when it is there but cannot be read."""
    from engine.results.reader import open_result

    file = Path(path)
    if not file.is_file():
        print(f"polydda {command}: no such result file: {path}", file=sys.stderr)
        return EXIT_SCENE
    try:
        with file.open("rb") as f:
            head = f.read(8)
    except OSError as exc:
        print(f"polydda {command}: cannot read {path}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_IO
    if head != _HDF5_SIGNATURE:
        if head.lstrip()[:1] in (b"{", b"["):
            print(f"polydda {command}: {path} is a scene, not a result: run it first "
                  f"(polydda run {path} --out RESULT.h5), then polydda {command} RESULT.h5",
                  file=sys.stderr)
        else:
            print(f"polydda {command}: {path} is not a PolyDDA result (the HDF5 file that "
                  "polydda run --out writes)", file=sys.stderr)
        return EXIT_SCENE
    try:
        return open_result(path)
    except (KeyError, ValueError):
        print(f"polydda {command}: {path} is an HDF5 file but not a PolyDDA result",
              file=sys.stderr)
        return EXIT_SCENE
    except OSError as exc:
        print(f"polydda {command}: cannot read {path}: {exc}", file=sys.stderr)
        return EXIT_IO
