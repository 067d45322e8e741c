"""Simulation commands: `polydda run` (HDF5 result, summary), `fos` (strength reduction)
and `seismic` (critical seismic coefficient), with their progress lines on stderr."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

from engine.analyses.strength_reduction import (
    TrialRun,
    critical_seismic_coefficient,
    factor_of_safety,
)
from engine.results.writer import ResultWriter
from engine.step.simulation import STATUS_COMPLETED, Progress, run
from schemas.scene import SCHEMA_VERSION
from service.cli.common import (
    EXIT_IO,
    EXIT_OK,
    EXIT_RUN,
    load_scene,
    note_compilation,
    print_json,
)
from service.documents import (
    fos_controls,
    fos_document,
    run_summary,
    seismic_controls,
    seismic_document,
    write_json_atomic,
)


class _ProgressPrinter:
    """Prints run progress to stderr: in place on a terminal, else every 10 %."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.tty = sys.stderr.isatty()
        self.last_wall = 0.0
        self.last_decile = -1

    def __call__(self, p: Progress) -> None:
        now = time.monotonic()
        decile = int(10 * p.fraction)
        if self.tty and now - self.last_wall < 0.2 and p.fraction < 1:
            return
        if not self.tty and decile == self.last_decile:
            return
        self.last_wall, self.last_decile = now, decile
        line = (f"{self.label}: step {p.step}  t = {p.time:.4g} / {p.duration:g} s  "
                f"({100 * p.fraction:.0f} %)  dt = {p.dt:.3g} s")
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n",
              file=sys.stderr, flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    """Run the scene's simulation; write the HDF5 result and optionally a JSON summary."""
    built = load_scene(args.scene, quiet=args.json)
    scene_text = Path(args.scene).read_text(encoding="utf-8")
    out = Path(args.out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        writer = ResultWriter(out, overwrite=True, schema_version=SCHEMA_VERSION,
                              record_contacts=built.model.controls.record_contacts)
    except OSError as exc:
        print(f"cannot write {out}: {exc}", file=sys.stderr)
        return EXIT_IO
    printer = None if args.quiet or args.json else _ProgressPrinter(Path(args.scene).stem)
    if printer is not None:
        note_compilation()
    res = run(built.model, recorder=writer, progress=printer, scene_json=scene_text)
    if printer is not None and printer.tty:
        print(file=sys.stderr)
    summary = run_summary(res.summary, built)
    if args.summary:
        try:
            write_json_atomic(Path(args.summary), summary)
        except OSError as exc:
            print(f"cannot write {args.summary}: {exc}", file=sys.stderr)
            return EXIT_IO
    if args.json:
        print_json(summary | {"result": str(out)})
        return EXIT_OK if res.status == STATUS_COMPLETED else EXIT_RUN
    print(f"{res.status}: {res.steps} steps, {res.state.time:.6g} s simulated in "
          f"{res.wall_time:.3g} s; max penetration {res.max_penetration:.3g} m; "
          f"result {out}", file=sys.stderr)
    if res.message:
        print(res.message, file=sys.stderr)
    for w in res.summary.get("warnings", []):
        print(f"warning: {w}", file=sys.stderr)
    return EXIT_OK if res.status == STATUS_COMPLETED else EXIT_RUN



def _trial_printer(args: argparse.Namespace, factor: str) -> Callable[[TrialRun], None]:
    """The progress line of a bisection trial (`factor` formats the value tried), printed
    to stderr unless --quiet; says first when the kernels still have to compile."""
    if not args.quiet:
        note_compilation()

    def note(r: TrialRun) -> None:
        if not args.quiet:
            verdict = "fails" if r.failed else "holds"
            print(f"{factor.format(r.factor)}: {verdict} (mean acceleration "
                  f"{r.mean_acceleration:.3g} m/s²)", file=sys.stderr, flush=True)

    return note


def cmd_fos(args: argparse.Namespace) -> int:
    """Factor of safety by strength reduction (bisection on tan φ / F)."""
    built = load_scene(args.scene)
    note = _trial_printer(args, "F = {:.4f}")
    result = factor_of_safety(built.model, fos_controls(built), progress=note)
    doc = fos_document(result, built)
    if args.json:
        print_json(doc)
    else:
        print(f"factor of safety {result.factor_of_safety:.4f} "
              f"(critical friction angle {doc['critical_friction_angle']}) "
              f"from {len(result.runs)} runs")
        if result.message:
            print(result.message)
    return EXIT_OK if result.status == STATUS_COMPLETED else EXIT_RUN


def cmd_seismic(args: argparse.Namespace) -> int:
    """Critical (yield) seismic coefficient by bisection on kh."""
    built = load_scene(args.scene)
    note = _trial_printer(args, "kh = {:.5f}")
    result = critical_seismic_coefficient(built.model, seismic_controls(built), progress=note)
    doc = seismic_document(result, built)
    if args.json:
        print_json(doc)
    else:
        print(f"critical seismic coefficient kh = {result.critical_coefficient:.5f} "
              f"(azimuth {result.azimuth_deg:g}°, kv {result.kv:g}) "
              f"from {len(result.runs)} runs")
        if result.message:
            print(result.message)
    return EXIT_OK if result.status == STATUS_COMPLETED else EXIT_RUN
