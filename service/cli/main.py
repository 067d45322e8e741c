"""`polydda` command line: inspect scenes (blocks, contacts), print the JSON Schema.

Each subcommand is one `cmd_*` function taking the parsed arguments and returning an exit
code; add a command by writing one and registering it in :func:`build_parser`.
Exit codes: 0 success, 3 a run that did not complete (its status and reason on stderr),
2 bad scene or bad arguments (problems on stderr, one per line),
1 an output file could not be written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from engine.analyses.strength_reduction import (
    QuasiStatic,
    TrialRun,
    critical_seismic_coefficient,
    factor_of_safety,
)
from engine.results.writer import ResultWriter
from engine.step.simulation import STATUS_COMPLETED, Progress, run
from schemas.convert import BuildResult, build_model
from schemas.errors import SceneError
from schemas.scene import SCHEMA_VERSION, scene_json_schema
from service.documents import (
    SEARCH_DISTANCE_RATIO,
    blocks_document,
    fos_controls,
    fos_document,
    kinematic_result,
    kinematics_document,
    kinematics_text,
    run_summary,
    scene_contacts_document,
    seismic_controls,
    seismic_document,
    surface,
    write_json_atomic,
)
from service.jobs.processes import PROCESS_IDS
from service.jobs.worker import add_arguments as worker_options

__all__ = ["SEARCH_DISTANCE_RATIO", "build_parser", "fos_controls", "main"]

EXIT_OK, EXIT_IO, EXIT_SCENE, EXIT_RUN = 0, 1, 2, 3


# --------------------------------------------------------------------------- helpers


def _print_json(doc: Any) -> None:
    json.dump(doc, sys.stdout, indent=2, allow_nan=False)
    sys.stdout.write("\n")


def _scene_failed(exc: SceneError) -> int:
    for line in exc.lines():
        print(line, file=sys.stderr)
    return EXIT_SCENE


def _load(path: str, quiet: bool = False) -> BuildResult:
    """Build the scene at `path` (SceneError on any problem); warnings go to stderr (unless
    `quiet`: a --json document carries them)."""
    result = build_model(Path(path))
    if not quiet:
        for w in result.warnings:
            print(f"warning: {w}", file=sys.stderr)
    return result


# --------------------------------------------------------------------------- export


def write_obj(path: Path, result: BuildResult) -> None:
    """Wavefront OBJ: one object per block (named), polygon faces."""
    lines = [f"# PolyDDA blocks, scene format {SCHEMA_VERSION}"]
    base = 1
    for name, block in zip(result.block_names, result.model.blocks, strict=True):
        verts, faces = surface(block.polyhedron)
        lines.append(f"o {name}")
        lines.extend(f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in verts)
        lines.extend("f " + " ".join(str(base + i) for i in f) for f in faces)
        base += len(verts)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_vtk(path: Path, result: BuildResult) -> None:
    """Legacy VTK polydata (ASCII): polygon faces with cell data `block` and `fixed`."""
    points, polys, block_of, fixed = [], [], [], []
    base = 0
    for k, block in enumerate(result.model.blocks):
        verts, faces = surface(block.polyhedron)
        points.append(verts)
        for f in faces:
            polys.append(f"{len(f)} " + " ".join(str(base + i) for i in f))
            block_of.append(k)
            fixed.append(int(block.fixed))
        base += len(verts)
    pts = np.vstack(points) if points else np.zeros((0, 3))
    size = sum(len(p.split()) for p in polys)
    lines = [
        "# vtk DataFile Version 3.0",
        f"PolyDDA blocks: {', '.join(result.block_names)[:200]}",
        "ASCII",
        "DATASET POLYDATA",
        f"POINTS {len(pts)} double",
        *(f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in pts),
        f"POLYGONS {len(polys)} {size}",
        *polys,
        f"CELL_DATA {len(polys)}",
        "SCALARS block int 1",
        "LOOKUP_TABLE default",
        *map(str, block_of),
        "SCALARS fixed int 1",
        "LOOKUP_TABLE default",
        *map(str, fixed),
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


EXPORTERS = {".obj": write_obj, ".vtk": write_vtk}


# --------------------------------------------------------------------------- commands


def cmd_blocks(args: argparse.Namespace) -> int:
    """List the blocks of a scene (name, volume, concave, fixed) and the total volume."""
    if args.export is not None and Path(args.export).suffix.lower() not in EXPORTERS:
        print(f"--export: unknown file type '{Path(args.export).suffix}' "
              f"(use {' or '.join(EXPORTERS)})", file=sys.stderr)
        return EXIT_SCENE
    result = _load(args.scene)
    blocks = result.model.blocks
    if args.export is not None:
        out = Path(args.export)
        try:
            EXPORTERS[out.suffix.lower()](out, result)
        except OSError as exc:
            print(f"--export: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_IO
    if args.json:
        _print_json(blocks_document(result))
        return EXIT_OK
    width = max([len(n) for n in result.block_names] + [5])
    print(f"{len(blocks)} block{'s' if len(blocks) != 1 else ''}")
    print(f"{'name':<{width}}  {'volume (m3)':>14}  {'shape':<7}  fixed")
    for name, b in zip(result.block_names, blocks, strict=True):
        shape = "convex" if b.polyhedron.is_convex else "concave"
        print(f"{name:<{width}}  {b.polyhedron.volume:>14.6g}  {shape:<7}  "
              f"{'yes' if b.fixed else 'no'}")
    total = sum(b.polyhedron.volume for b in blocks)
    print(f"total volume: {total:.6g} m3")
    if args.export is not None:
        print(f"written: {args.export}")
    return EXIT_OK


def cmd_contacts(args: argparse.Namespace) -> int:
    """The contact constraints of the scene as given (before any step)."""
    result = _load(args.scene)
    if args.search_distance is not None and not args.search_distance > 0:
        print("--search-distance: must be positive", file=sys.stderr)
        return EXIT_SCENE
    doc = scene_contacts_document(result, args.search_distance)
    rows, search = doc["contacts"], doc["search_distance"]
    if args.json:
        _print_json(doc)
        return EXIT_OK
    print(f"{len(rows)} contact constraint{'s' if len(rows) != 1 else ''} "
          f"(search distance {search:.3g} m)")
    for k, c in enumerate(rows, 1):
        pt = ", ".join(f"{x:.3f}" for x in c["point_i"])
        nm = ", ".join(f"{x:.3f}" for x in c["normal"])
        print(f"{k:>4}  {c['block_i']} / {c['block_j']}  {c['type']:<13} ({pt})  "
              f"n=({nm})  {c['mode']:<7} gap={c['gap']:.3g} m")
    return EXIT_OK


def cmd_schema(args: argparse.Namespace) -> int:
    """Print the JSON Schema of the scene format."""
    _print_json(scene_json_schema())
    return EXIT_OK


def cmd_validate(args: argparse.Namespace) -> int:
    """Check a scene completely (including cutting and overlaps); print `ok` or the problems
    (with --json: one document `{"valid", "blocks", "fixed", "warnings", "problems"}`)."""
    if not args.json:
        result = _load(args.scene)
        n = len(result.model.blocks)
        print(f"ok: {n} block{'s' if n != 1 else ''}, "
              f"{sum(b.fixed for b in result.model.blocks)} fixed")
        return EXIT_OK
    try:
        result = build_model(Path(args.scene))
    except SceneError as exc:
        _print_json({"valid": False, "problems": exc.problems})
        return EXIT_SCENE
    _print_json({"valid": True, "blocks": len(result.model.blocks),
                 "fixed": sum(b.fixed for b in result.model.blocks),
                 "warnings": result.warnings, "problems": []})
    return EXIT_OK


# --------------------------------------------------------------------------- run, fos, plot


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
    built = _load(args.scene, quiet=args.json)
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
        _note_compilation()
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
        _print_json(summary | {"result": str(out)})
        return EXIT_OK if res.status == STATUS_COMPLETED else EXIT_RUN
    print(f"{res.status}: {res.steps} steps, {res.state.time:.6g} s simulated in "
          f"{res.wall_time:.3g} s; max penetration {res.max_penetration:.3g} m; "
          f"result {out}", file=sys.stderr)
    if res.message:
        print(res.message, file=sys.stderr)
    for w in res.summary.get("warnings", []):
        print(f"warning: {w}", file=sys.stderr)
    return EXIT_OK if res.status == STATUS_COMPLETED else EXIT_RUN


def _note_compilation() -> None:
    """Say why the first step of the first run on a machine takes a while."""
    from engine import kernels_cached

    if not kernels_cached():
        print("compiling the engine's numerical kernels: the first run on this machine "
              "takes about a minute longer (they are cached afterwards)", file=sys.stderr)


def _trial_printer(args: argparse.Namespace, factor: str) -> Callable[[TrialRun], None]:
    """The progress line of a bisection trial (`factor` formats the value tried), printed
    to stderr unless --quiet; says first when the kernels still have to compile."""
    if not args.quiet:
        _note_compilation()

    def note(r: TrialRun) -> None:
        if not args.quiet:
            verdict = "fails" if r.failed else "holds"
            print(f"{factor.format(r.factor)}: {verdict}: {r.reason} (displacement "
                  f"{r.displacement:.3g} m, velocity {r.velocity:.3g} m/s)", file=sys.stderr,
                  flush=True)

    return note


def cmd_fos(args: argparse.Namespace) -> int:
    """Factor of safety by strength reduction (bisection on tan φ / F); exit 2 for a
    quasi-static scene (no trial could fail)."""
    built = _load(args.scene)
    note = _trial_printer(args, "F = {:.4f}")
    try:
        result = factor_of_safety(built.model, fos_controls(built), progress=note)
    except QuasiStatic as exc:
        raise SceneError([{"loc": "analysis.mode", "msg": str(exc)}]) from None
    doc = fos_document(result, built)
    if args.json:
        _print_json(doc)
    else:
        sign = {"lower": "≥ ", "upper": "< "}.get(result.bound or "", "")
        print(f"factor of safety {sign}{result.factor_of_safety:.4f} "
              f"(critical friction angle {doc['critical_friction_angle']}) "
              f"from {len(result.runs)} trials")
        if result.message:
            print(result.message)
    return EXIT_OK if result.status == STATUS_COMPLETED else EXIT_RUN


def cmd_seismic(args: argparse.Namespace) -> int:
    """Critical (yield) seismic coefficient by bisection on kh."""
    built = _load(args.scene)
    note = _trial_printer(args, "kh = {:.5f}")
    try:
        result = critical_seismic_coefficient(built.model, seismic_controls(built),
                                              progress=note)
    except QuasiStatic as exc:
        raise SceneError([{"loc": "analysis.mode", "msg": str(exc)}]) from None
    doc = seismic_document(result, built)
    if args.json:
        _print_json(doc)
    else:
        print(f"critical seismic coefficient kh = {result.critical_coefficient:.5f} "
              f"(azimuth {result.azimuth_deg:g}°, kv {result.kv:g}) "
              f"from {len(result.runs)} runs")
        if result.message:
            print(result.message)
    return EXIT_OK if result.status == STATUS_COMPLETED else EXIT_RUN


def cmd_le(args: argparse.Namespace) -> int:
    """Limit equilibrium of the scene's one free block (planar or two-plane wedge, the
    vector method); exit 2 naming why when it does not apply."""
    from service.documents import le_document, le_result, le_text

    built = _load(args.scene, quiet=args.json)
    doc = le_document(le_result(built), built)
    if args.json:
        _print_json(doc)
    else:
        print(le_text(doc))
    return EXIT_OK


def cmd_kinematics(args: argparse.Namespace) -> int:
    """Kinematic screening (Markland tests) of the scene's joints against its slope face;
    with --plot, the equal-area stereonet as a PNG."""
    result = kinematic_result(Path(args.scene))
    if args.plot is not None:
        from engine.analyses.stereonet import plot_stereonet

        try:
            plot_stereonet(result, Path(args.plot), title=Path(args.scene).stem)
        except OSError as exc:
            print(f"--plot: cannot write {args.plot}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_IO
    if args.json:
        _print_json(kinematics_document(result))
    else:
        print(kinematics_text(result))
        if args.plot is not None:
            print(f"written: {args.plot}")
    return EXIT_OK


def _sweep_options(args: argparse.Namespace,
                   scene: dict[str, Any]) -> dict[str, Any] | None:
    """The scene's `sweep` with the command line's options over it (None: no parameter)."""
    given = scene.get("sweep")
    section = {k: v for k, v in (given if isinstance(given, dict) else {}).items()
               if k != "realisations"}
    for key in ("n", "seed", "mode"):
        if getattr(args, key) is not None:
            section[key] = getattr(args, key)
    if args.friction_mean is not None or args.friction_sd is not None:
        short = dict(section.get("friction_angle") or {})
        short |= {k: v for k, v in (("mean", args.friction_mean), ("sd", args.friction_sd))
                  if v is not None}
        section["friction_angle"] = short
    for text in args.parameter or ():
        name, sep, spec = text.partition("=")
        try:
            value = json.loads(spec) if sep else None
        except json.JSONDecodeError:
            value = None
        if not name or not isinstance(value, dict):
            raise SceneError([{"loc": "--parameter", "msg": f"expected NAME={{JSON object}}, "
                               f"got {text!r}"}])
        section.setdefault("parameters", {})[name] = value
    short = section.get("friction_angle")
    if isinstance(short, dict) and not {"mean", "sd"} <= set(short):
        return None
    if not short and not section.get("parameters"):
        return None
    return section


def cmd_sweep(args: argparse.Namespace) -> int:
    """Sweep or Monte Carlo analysis: N realisations of the scene's parameters from a seed,
    a factor of safety each (engine strength reduction or limit equilibrium), probability of
    failure."""
    from service.sweep import run_sweep, spec_of_scene

    scene = json.loads(Path(args.scene).read_text(encoding="utf-8"))
    built = build_model(scene)  # the scene must be valid before any realisation
    section = _sweep_options(args, scene)
    if section is None:
        print("polydda sweep: give --friction-mean and --friction-sd, or --parameter, or the "
              "scene's sweep.parameters (or sweep.friction_angle)", file=sys.stderr)
        return EXIT_SCENE
    spec = spec_of_scene(dict(scene, sweep=section))  # SceneError: exit 2
    if spec.mode == "analytic":  # limit equilibrium must apply (SceneError: exit 2)
        from service.documents import le_result

        le_result(built)

    def note(done: int, n: int, now: int) -> None:
        if not args.quiet:
            print(f"realisation {done}/{n} done ({now} evaluated now)", file=sys.stderr,
                  flush=True)

    if args.server is not None:
        return _sweep_on_server(args, scene, spec)
    if spec.mode == "dda" and not args.quiet:
        _note_compilation()
    try:
        doc = run_sweep(scene, spec, Path(args.out), workers=args.workers, progress=note,
                        limit=args.limit)
    except ValueError as exc:
        print(f"polydda sweep: {exc}", file=sys.stderr)
        return EXIT_SCENE
    return _print_sweep(args, spec, doc)


def _sweep_on_server(args: argparse.Namespace, scene: dict[str, Any], spec: Any) -> int:
    """`polydda sweep --server URL --jobs K`: the sweep as one job of the service fanned
    out in K child jobs (the server merges them)."""
    import httpx

    from service.cli.client import ServiceError, Unreachable, sweep_parent

    scene = dict(scene, sweep=spec.scene_sweep())
    headers = {"X-API-Key": args.api_key} if args.api_key else {}
    last = [-1]

    def note(done: int, n: int, statuses: list[dict[str, Any]]) -> None:
        if not args.quiet and done != last[0]:
            last[0] = done
            states = ", ".join(s["status"] for s in statuses)
            print(f"{done}/{n} realisations done ({states})", file=sys.stderr, flush=True)

    try:
        with httpx.Client(base_url=args.server.rstrip("/"), headers=headers,
                          timeout=60) as client:
            doc = sweep_parent(client, scene, args.jobs, Path(args.out), on_progress=note)
    except httpx.TransportError as exc:
        print(f"polydda sweep: {Unreachable(str(exc))}", file=sys.stderr)
        return EXIT_IO
    except (Unreachable, ServiceError) as exc:
        print(f"polydda sweep: {exc}", file=sys.stderr)
        return EXIT_IO if isinstance(exc, Unreachable) else EXIT_SCENE
    return _print_sweep(args, spec, doc)


def _print_sweep(args: argparse.Namespace, spec: Any, doc: dict[str, Any]) -> int:
    """The sweep's aggregate: JSON (--json) or a few lines."""
    if args.json:
        _print_json({k: v for k, v in doc.items() if k != "realisations"})
        return EXIT_OK
    for key in dict.fromkeys((spec.mode, "analytic")):
        a = doc.get(key)
        if a and a["n"]:
            lo, hi = a["pof_interval_95"]
            print(f"{key}: {a['n']} realisations, probability of failure "
                  f"{100 * a['probability_of_failure']:.2f} % (95 % interval {100 * lo:.1f} to "
                  f"{100 * hi:.1f} %), FS mean {a['mean']:.4f}, min {a['min']:.4f}")
    if doc.get("pof_difference") is not None:
        print(f"PoF difference ({spec.mode} - analytic): "
              f"{100 * doc['pof_difference']:.2f} percentage points; FS relative difference "
              f"max {100 * doc['fs_relative_difference']['max_abs']:.2f} %")
    print(f"written: {Path(args.out) / 'sweep.json'}")
    return EXIT_OK


def _listed(values: list[str] | None) -> list[str] | None:
    """Values of a repeatable option that also takes comma-separated lists."""
    if values is None:
        return None
    return [v.strip() for value in values for v in value.split(",") if v.strip()]


def cmd_plot(args: argparse.Namespace) -> int:
    """PNG plots of a result file: histories, energy, displacement components, snapshots."""
    from engine.results.plots import plot_all, snapshot_steps  # matplotlib only when plotting
    from engine.results.reader import open_result

    blocks = _listed(args.blocks)
    try:
        times = None if args.time is None else [float(t) for t in _listed(args.time) or []]
        steps = None if args.step is None else [int(n) for n in _listed(args.step) or []]
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


# --------------------------------------------------------------------------- service


def cmd_serve(args: argparse.Namespace) -> int:
    """Start the REST API with its embedded workers (or the RQ backend, by settings); exit
    code 1 when another server owns the data directory."""
    from service.api.app import serve

    return serve(args.host, args.port)


def cmd_worker(args: argparse.Namespace) -> int:
    """Start one scale-out worker on the Redis queue (options: service.jobs.worker)."""
    from service.jobs.worker import run as run_worker

    return run_worker(args)


def cmd_submit(args: argparse.Namespace) -> int:
    """Submit a scene to a running server; with --wait, follow it to the end."""
    from service.cli.client import ServiceError, Unreachable, print_status, submit

    if not Path(args.scene).is_file():
        print(f"polydda submit: no such scene file: {args.scene}", file=sys.stderr)
        return EXIT_IO
    try:
        doc = submit(args.url, args.scene, wait=args.wait, process=args.process,
                     api_key=args.api_key, on_status=print_status, retries=args.retries)
    except Unreachable as exc:
        print(f"polydda submit: {exc}", file=sys.stderr)
        return EXIT_IO
    except ServiceError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_SCENE
    _print_json(doc)
    return EXIT_OK if doc.get("status") in ("successful", "accepted", "running") else EXIT_IO


# --------------------------------------------------------------------------- parser


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors print one line and exit with code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        print(f"{self.prog}: {message}", file=sys.stderr)
        raise SystemExit(EXIT_SCENE)


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser with one subparser per command (`func` set to its cmd_*)."""
    parser = _Parser(prog="polydda",
                     description="3-D Discontinuous Deformation Analysis of rock blocks")
    parser.add_argument("--version", action="version", version=f"polydda {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)

    p = sub.add_parser("blocks", help="list the blocks of a scene (after cutting)")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--export", metavar="FILE", help="write the blocks to FILE (.obj or .vtk)")
    p.set_defaults(func=cmd_blocks)

    p = sub.add_parser("contacts", help="list the contact constraints of a scene as given")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--search-distance", type=float, metavar="M",
                   help=f"contact search distance in m (default {SEARCH_DISTANCE_RATIO:g} x "
                        "model size)")
    p.set_defaults(func=cmd_contacts)

    p = sub.add_parser("validate", help="check a scene and report every problem")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true",
                   help="print one JSON document (valid, blocks, warnings, problems)")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("run", help="run the simulation of a scene")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--out", required=True, metavar="RESULT.h5", help="HDF5 result file")
    p.add_argument("--summary", metavar="SUMMARY.json", help="also write a JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--json", action="store_true",
                   help="print the summary as one JSON document (no progress output)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("fos", help="factor of safety by strength reduction")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_fos)

    p = sub.add_parser("le", help="limit equilibrium of a planar block or a two-plane wedge",
                       description="the vector method (Hoek & Bray; Low 1997) on the scene's "
                                   "one free block: cohesion, water, bolts and tendons, "
                                   "seismic kh / kv, point loads; exit 2 saying why when it "
                                   "does not apply")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_le)

    p = sub.add_parser("seismic", help="critical (yield) seismic coefficient kh by bisection")
    p.add_argument("scene", help="scene JSON file (its 'seismic' gives azimuth and kv)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_seismic)
    p = sub.add_parser("kinematics", help="kinematic screening (Markland tests, stereonet)",
                       description="planar and wedge sliding, flexural and direct toppling "
                                   "of the scene's joints against its slope_face")
    p.add_argument("scene", help="scene JSON file (with a slope_face)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--plot", metavar="OUT.png", help="write the stereonet to this PNG file")
    p.set_defaults(func=cmd_kinematics)

    p = sub.add_parser(
        "sweep", help="sweep or Monte Carlo analysis: probability of failure",
        description="N realisations of the scene's parameters (the scene's sweep.parameters, "
                    "or --parameter, or the joints' friction angle by --friction-mean / "
                    "--friction-sd): each a distribution (normal, uniform, lognormal; Fisher "
                    "for a joint orientation) drawn from the seed, or a list of values (a "
                    "study); a factor of safety each, the probability of failure, FS "
                    "histogram and CDF and the sensitivity of FS to each parameter; "
                    "re-running with the same --out skips the realisations already done")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--n", type=int, help="realisations (default: the scene's sweep.n, or 200)")
    p.add_argument("--seed", type=int, help="random seed (default: sweep.seed, or 0)")
    p.add_argument("--friction-mean", type=float, metavar="DEG",
                   help="mean friction angle (default: sweep.friction_angle.mean)")
    p.add_argument("--friction-sd", type=float, metavar="DEG",
                   help="its standard deviation (default: sweep.friction_angle.sd)")
    p.add_argument("--parameter", action="append", metavar="NAME=JSON",
                   help="a parameter of the sweep, as in the scene's sweep.parameters, e.g. "
                        "'cohesion={\"distribution\": \"uniform\", \"low\": 0, \"high\": "
                        "20000}' (Pa; angles in degrees); repeat for several")
    p.add_argument("--mode", choices=("dda", "analytic"),
                   help="dda: the engine's strength reduction per realisation; analytic: "
                        "limit equilibrium (a planar block or a two-plane wedge, with "
                        "everything the scene has; refused, exit 2, where it does not apply)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the sweep")
    p.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    p.add_argument("--server", metavar="URL",
                   help="run the sweep as one job of this PolyDDA service fanned out in "
                        "--jobs child jobs (embedded workers or `polydda worker`s); the "
                        "server merges them")
    p.add_argument("--jobs", type=int, default=2, metavar="K",
                   help="child jobs (shares) of the sweep on --server (default 2)")
    p.add_argument("--api-key", help="API key for --server, if it requires one")
    p.add_argument("--limit", type=int, metavar="K",
                   help="evaluate at most K new realisations, then aggregate those done")
    p.add_argument("--json", action="store_true", help="print the aggregate as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("plot", help="PNG plots of a result file")
    p.add_argument("result", help="HDF5 result file")
    p.add_argument("--out", metavar="DIR", help="output folder (default: beside the result)")
    p.add_argument("--blocks", metavar="NAMES", action="append",
                   help="blocks in the histories, by name (comma-separated or repeated; "
                        "default: the free blocks that moved most, at most 8)")
    p.add_argument("--time", metavar="SECONDS", action="append",
                   help="3-D snapshot at the recorded step nearest this time (comma-separated "
                        "or repeated; default: initial and final)")
    p.add_argument("--step", metavar="N", action="append",
                   help="3-D snapshot at this recorded solver step (comma-separated or "
                        "repeated)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("serve", help="start the REST API and its embedded workers")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("worker", help="start a scale-out worker (Redis queue)",
                       description="work PolyDDA jobs from the Redis queue; each option "
                                   "overrides its POLYDDA_* variable")
    worker_options(p)
    p.set_defaults(func=cmd_worker)

    p = sub.add_parser("submit", help="submit a scene to a running server")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="server URL")
    p.add_argument("--process", choices=PROCESS_IDS,
                   help="default: from the scene's analysis.type")
    p.add_argument("--api-key", help="API key, if the server requires one")
    p.add_argument("--wait", action="store_true", help="follow the job to its end")
    p.add_argument("--retries", type=int, default=5, metavar="N",
                   help="retries of a submission answered 429 / 503 or cut off, after the "
                        "server's Retry-After (same Idempotency-Key: never two jobs; "
                        "default 5)")
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("schema", help="print the JSON Schema of the scene format")
    p.set_defaults(func=cmd_schema)
    return parser


def _version() -> str:
    """The installed package's version (the source tree's when not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("polydda")
    except PackageNotFoundError:
        from service.api.app import VERSION

        return VERSION


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `polydda`; returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help or a usage error
        return int(exc.code or 0)
    try:
        return int(args.func(args))
    except SceneError as exc:  # any command that builds a scene: problems, exit 2
        return _scene_failed(exc)
    except BrokenPipeError:  # output piped into a reader that closed early (`| head`)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
