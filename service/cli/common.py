"""What the `polydda` commands share: exit codes, JSON output, loading a scene with its
warnings on stderr, the note about compiling the kernels."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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


def note_compilation() -> None:
    """Say why the first step of the first run on a machine takes a while."""
    from engine import kernels_cached

    if not kernels_cached():
        print("compiling the engine's numerical kernels: the first run on this machine "
              "takes about a minute longer (they are cached afterwards)", file=sys.stderr)


def listed(values: list[str] | None) -> list[str] | None:
    """Values of a repeatable option that also takes comma-separated lists."""
    if values is None:
        return None
    return [v.strip() for value in values for v in value.split(",") if v.strip()]

