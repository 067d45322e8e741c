"""Analysis commands: `polydda kinematics` (Markland tests, stereonet) and `sweep`
(sweep or Monte Carlo: probability of failure; locally or fanned out on a server)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from schemas.convert import build_model
from schemas.errors import SceneError
from schemas.scene import read_json
from service.cli.common import (
    EXIT_IO,
    EXIT_OK,
    EXIT_SCENE,
    one_model,
    print_json,
)
from service.cli.progress import Progress
from service.cli.warmup import note_compilation
from service.documents import kinematic_result, kinematics_document, kinematics_text


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
        print_json(kinematics_document(result))
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
    a factor of safety each (engine strength reduction or eq. 51), probability of failure."""
    from service.sweep import run_sweep, spec_of_scene

    # the scene must be valid before any realisation: a missing file, bad JSON or a bad
    # scene exits 2 naming it (SceneError)
    built = build_model(Path(args.scene))
    scene = read_json(args.scene)
    one_model(built, "a sweep")
    section = _sweep_options(args, scene)
    if section is None:
        print("polydda sweep: give --friction-mean and --friction-sd, or --parameter, or the "
              "scene's sweep.parameters (or sweep.friction_angle)", file=sys.stderr)
        return EXIT_SCENE
    spec = spec_of_scene(dict(scene, sweep=section))  # SceneError: exit 2
    if spec.mode == "analytic":  # limit equilibrium must apply (SceneError: exit 2)
        from service.documents import le_result

        le_result(built)

    if args.server is not None:
        return _sweep_on_server(args, scene, spec)
    quiet = args.quiet or args.json
    compiling = spec.mode == "dda" and note_compilation(not quiet)
    bar = Progress(f"sweep {Path(args.scene).stem}", spec.n, unit="realisation",
                   enabled=not quiet, compiling=compiling)

    def note(done: int, n: int, now: int) -> None:
        bar.update(done, f"{done:,} of {n:,} realisations", total=n, base=done - now)

    try:
        doc = run_sweep(scene, spec, Path(args.out), workers=args.workers, progress=note,
                        limit=args.limit)
    except ValueError as exc:
        print(f"polydda sweep: {exc}", file=sys.stderr)
        return EXIT_SCENE
    finally:
        bar.close()
    return _print_sweep(args, spec, doc)


def _sweep_on_server(args: argparse.Namespace, scene: dict[str, Any], spec: Any) -> int:
    """`polydda sweep --server URL --jobs K`: the sweep as one job of the service fanned
    out in K child jobs (the server merges them)."""
    import httpx

    from service.cli.client import ServiceError, Unreachable, sweep_parent

    scene = dict(scene, sweep=spec.scene_sweep())
    headers = {"X-API-Key": args.api_key} if args.api_key else {}
    bar = Progress(f"sweep {Path(args.scene).stem} on {args.server}", spec.n,
                   unit="realisation", enabled=not (args.quiet or args.json))

    def note(done: int, n: int, statuses: list[dict[str, Any]]) -> None:
        states = ", ".join(s["status"] for s in statuses)
        bar.update(done, f"{done:,} of {n:,} realisations (jobs: {states})", total=n)

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
    finally:
        bar.close()
    return _print_sweep(args, spec, doc)


def _print_sweep(args: argparse.Namespace, spec: Any, doc: dict[str, Any]) -> int:
    """The sweep's aggregate: JSON (--json) or a few lines; and its FS histogram and CDF
    (DIR/sweep.png, the figure of the service's report) once a realisation has an FS."""
    png = _sweep_figure(Path(args.out), spec, doc)
    if args.json:
        print_json({k: v for k, v in doc.items() if k != "realisations"})
        return EXIT_OK
    for key in dict.fromkeys((spec.mode, "analytic")):
        a = doc.get(key)
        if a and a["n"]:
            lo, hi = a["pof_interval_95"]
            print(f"{key}: {a['n']:,} realisations, probability of failure "
                  f"{100 * a['probability_of_failure']:.2f} % (95 % interval {100 * lo:.1f} to "
                  f"{100 * hi:.1f} %), FS mean {a['mean']:.3f}, min {a['min']:.3f}")
    if doc.get("pof_difference") is not None:
        print(f"PoF difference ({spec.mode} - analytic): "
              f"{100 * doc['pof_difference']:.2f} percentage points; FS relative difference "
              f"max {100 * doc['fs_relative_difference']['max_abs']:.2f} %")
    print(f"written: {Path(args.out) / 'sweep.json'}")
    if png is not None:
        print(f"written: {png}")
    return EXIT_OK


def _sweep_figure(out: Path, spec: Any, doc: dict[str, Any]) -> Path | None:
    """DIR/sweep.png: histogram and empirical CDF of FS per method (None: no FS yet)."""
    aggs = {spec.mode: doc.get(spec.mode) or {}}
    if spec.mode != "analytic" and doc.get("analytic"):
        aggs["analytic (eq. 51)"] = doc["analytic"]
    if not any((a.get("histogram") or {}).get("counts") for a in aggs.values()):
        return None
    from engine.results.plots import plot_fs_distribution

    return plot_fs_distribution(aggs, out / "sweep.png")

