"""Result commands: `polydda plot` (PNG plots of an HDF5 result)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli.common import EXIT_IO, EXIT_OK, EXIT_SCENE, listed

if TYPE_CHECKING:
    from engine.results.reader import Result

#: the first bytes of every HDF5 file (at offset 0 for the files the engine writes)
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def open_result_file(command: str, path: str) -> Result | int:
    """The result file at `path`, open; or, said in one line on stderr, the exit code: 1 when
    it cannot be read, 2 when it is not a result (a scene, another HDF5 file)."""
    from engine.results.reader import open_result

    file = Path(path)
    if not file.is_file():
        print(f"polydda {command}: no such result file: {path}", file=sys.stderr)
        return EXIT_IO
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


def cmd_plot(args: argparse.Namespace) -> int:
    """PNG plots of a result file: histories, energy, displacement components, snapshots."""
    from engine.results.plots import plot_all, snapshot_steps  # matplotlib only when plotting

    blocks = listed(args.blocks)
    try:
        times = None if args.time is None else [float(t) for t in listed(args.time) or []]
        steps = None if args.step is None else [int(n) for n in listed(args.step) or []]
    except ValueError as exc:
        print(f"--time / --step: not a number: {exc}", file=sys.stderr)
        return EXIT_SCENE
    result = open_result_file("plot", args.result)
    if isinstance(result, int):
        return result
    with result:
        try:  # the choices, against the file: bad arguments exit 2
            for b in blocks or []:
                result.block_index(b)
            snapshot_steps(result, times, steps)
        except (KeyError, ValueError) as exc:
            names = ", ".join(result.block_names)
            hint = f" (blocks: {names})" if isinstance(exc, KeyError) else ""
            print(f"{exc.args[0] if exc.args else exc}{hint}", file=sys.stderr)
            return EXIT_SCENE
        try:
            paths = plot_all(result, args.out, blocks=blocks, times=times, steps=steps)
        except (OSError, KeyError, ValueError) as exc:
            print(f"cannot plot {args.result}: {exc}", file=sys.stderr)
            return EXIT_IO
    for p in paths:
        print(p)
    return EXIT_OK

