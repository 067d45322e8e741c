"""Result commands: `polydda plot` (PNG plots of an HDF5 result)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.cli.common import EXIT_IO, EXIT_OK, EXIT_SCENE, listed


def cmd_plot(args: argparse.Namespace) -> int:
    """PNG plots of a result file: histories, energy, displacement components, snapshots."""
    from engine.results.plots import plot_all, snapshot_steps  # matplotlib only when plotting
    from engine.results.reader import open_result

    blocks = listed(args.blocks)
    try:
        times = None if args.time is None else [float(t) for t in listed(args.time) or []]
        steps = None if args.step is None else [int(n) for n in listed(args.step) or []]
    except ValueError as exc:
        print(f"--time / --step: not a number: {exc}", file=sys.stderr)
        return EXIT_SCENE
    if not Path(args.result).is_file():
        print(f"polydda plot: no such result file: {args.result}", file=sys.stderr)
        return EXIT_IO
    try:
        result = open_result(args.result)
    except (OSError, KeyError, ValueError) as exc:
        print(f"cannot plot {args.result}: {exc}", file=sys.stderr)
        return EXIT_IO
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

