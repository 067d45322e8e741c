"""Simulation commands: `polydda run` (HDF5 result, summary), `fos` (strength reduction)
and `seismic` (critical seismic coefficient), with their progress lines on stderr."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from engine.analyses.strength_reduction import (
    QuasiStatic,
    TrialRun,
    critical_seismic_coefficient,
    factor_of_safety,
)
from engine.results.writer import ResultWriter
from engine.step.simulation import STATUS_COMPLETED
from engine.step.simulation import Progress as RunProgress
from schemas.convert import BuildResult
from schemas.errors import SceneError
from schemas.scene import SCHEMA_VERSION
from service import readable as rd
from service.cli.common import (
    EXIT_IO,
    EXIT_OK,
    EXIT_RUN,
    EXIT_SCENE,
    load_scene,
    one_model,
    print_json,
)
from service.cli.progress import Progress, bisection_total
from service.cli.warmup import note_compilation
from service.documents import (
    fos_bracket,
    fos_controls,
    fos_document,
    movement,
    run_summary,
    run_verdict,
    seismic_controls,
    seismic_document,
    verdict_line,
    write_json_atomic,
)

#: blocks listed at the end of `polydda run` (the ones that moved most)
SHOWN_BLOCKS = 10


def _run_progress(bar: Progress) -> Callable[[RunProgress], None]:
    """The engine's progress callback feeding `bar` (simulated seconds)."""

    def note(p: RunProgress) -> None:
        bar.update(p.time, f"t = {p.time:.3f} s, step {p.step:,}, "
                           f"Δt {rd.seconds(p.dt)}", total=p.duration)

    return note


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
    show = not (args.quiet or args.json)
    compiling = note_compilation(show)
    duration = built.stages[-1].end_time if built.stages else built.model.controls.duration
    bar = Progress(f"run {Path(args.scene).stem}", duration, unit="s", enabled=show,
                   compiling=compiling)
    try:
        res = _run_built(args, built, writer, _run_progress(bar) if show else None,
                         scene_text, out)
    finally:
        bar.close()
    if res is None:
        return EXIT_SCENE
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
    fixed = [b.fixed for b in built.model.blocks]
    print("\n".join(run_text(summary, fixed, str(out), shown=built.warnings)))
    return EXIT_OK if res.status == STATUS_COMPLETED else EXIT_RUN


def _run_built(args: argparse.Namespace, built: BuildResult, writer: ResultWriter,
               progress: Callable[[RunProgress], None] | None, scene_text: str,
               out: Path) -> Any:
    """Run the scene (through its stages, saving each stage's end in --checkpoints, or from
    --resume-from); None after a problem with the checkpoint (said on stderr)."""
    from engine.step.staged_run import checkpoint_fits, load_checkpoint, run_scene

    resume = None
    if args.resume_from:
        if not built.stages:
            print(f"--resume-from: {args.scene} has no stages to resume", file=sys.stderr)
            return None
        why = checkpoint_problem(args.resume_from)
        if not why:
            try:
                resume = load_checkpoint(args.resume_from)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                why = f"{args.resume_from} is not a stage checkpoint of polydda run ({exc})"
        if not why:
            why = checkpoint_fits(built.model, built.stages, resume[1])
        if not why and resume[1].stage == len(built.stages) - 1:
            why = (f"{args.resume_from} is the end of the last stage "
                   f"('{built.stages[-1].name}', {len(built.stages)} of {len(built.stages)}): "
                   "no stage is left to run, and the run that wrote it is complete; resume "
                   "from an earlier stage's checkpoint, or add a stage after it")
        if why:
            print(f"--resume-from: {why}", file=sys.stderr)
            return None
    checkpoints = args.checkpoints or (f"{out}.stages" if built.stages else None)
    return run_scene(built.model, built.stages, recorder=writer, progress=progress,
                     scene_json=scene_text, checkpoints=checkpoints, resume=resume)


def checkpoint_problem(path: str) -> str:
    """Why the file given to --resume-from is no stage checkpoint ('' when it may be one),
    naming that file: missing, not the .npz of a state, or without the ledger that
    `polydda run` writes beside it (`<path>.stage.json`)."""
    file = Path(path)
    if not file.is_file():
        return f"no such checkpoint: {path}"
    try:
        with file.open("rb") as f:
            head = f.read(4)
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    if head != b"PK\x03\x04":  # an .npz is a zip archive
        return (f"{path} is not a stage checkpoint (the stage-<k>.npz that polydda run "
                "writes at each stage's end)")
    ledger = Path(f"{path}.stage.json")
    if not ledger.is_file():
        return (f"{path} has lost its ledger ({ledger.name}, written beside it at the "
                "stage's end): not a complete stage checkpoint")
    return ""


def run_text(summary: dict[str, Any], fixed: list[bool], result: str,
             shown: Sequence[str] = ()) -> list[str]:
    """What `polydda run` prints at its end: how the run ended, then the free blocks that
    moved more than the threshold (largest first, with units), then the warnings (but those
    `shown` already, when the scene was loaded), then the verdict."""
    lines = [f"{summary['status']}: {summary['steps']:,} steps, "
             f"{rd.seconds(summary['simulated_time'])} simulated in "
             f"{rd.duration(summary['wall_time'])}; largest penetration "
             f"{rd.length(summary.get('max_penetration') or 0.0)}; result {result}"]
    if summary.get("message"):
        lines.append(summary["message"])
    m = movement(summary.get("blocks") or [], fixed)
    moved, limit = m["moved"], rd.length(m["threshold"])
    if moved:
        unit, scale = rd.lengths_unit([b["magnitude"] for b in moved])
        d = 3 if unit == "m" else 1
        width = max(5, *(len(b["name"]) for b in moved[:SHOWN_BLOCKS]))
        lines.append(f"{rd.plural(len(moved), 'free block')} moved more than {limit}:")
        lines.append(f"  {'block':<{width}}  {'|u| (' + unit + ')':>10}  "
                     f"{'u_x':>9}  {'u_y':>9}  {'u_z':>9}  trend/plunge (°)")
        for b in moved[:SHOWN_BLOCKS]:
            u = b["displacement"]
            lines.append(f"  {b['name']:<{width}}  {rd.fixed(b['magnitude'] * scale, d):>10}  "
                         + "  ".join(f"{rd.fixed(x * scale, d):>9}" for x in u)
                         + f"  {rd.direction(u)}")
        if len(moved) > SHOWN_BLOCKS:
            lines.append(f"  ... and {len(moved) - SHOWN_BLOCKS} more (all in the summary: "
                         "--summary FILE)")
    else:
        lines.append(f"no free block moved more than {limit}")
    if m["still"] and moved:
        lines.append(f"{rd.plural(m['still'], 'other free block')} moved less "
                     f"(at most {rd.length(m['still_max'])})")
    elif m["still"]:
        lines.append(f"the largest displacement of a free block is {rd.length(m['still_max'])} "
                     f"({m['still_max_name']})")
    lines += [f"warning: {w}" for w in summary.get("warnings", []) if w not in shown]
    lines.append(run_verdict(summary, fixed))
    return lines


def _trials(args: argparse.Namespace, label: str, what: str, tolerance: float,
            max_runs: int, relative_to: str) -> tuple[Progress, Callable[[TrialRun], None]]:
    """The progress of a bisection (`what` names the value tried, e.g. `F`): a bar over the
    estimated number of trials and one line per trial with its verdict; says first when
    the kernels still have to compile. Nothing with --quiet."""
    quiet = args.quiet or getattr(args, "json", False)
    compiling = note_compilation(not quiet)
    total = bisection_total([], tolerance, max_runs, relative_to)
    bar = Progress(label, total, unit="trial", enabled=not quiet, tenths=False,
                   compiling=compiling)
    seen: list[tuple[float, bool]] = []

    def note(r: TrialRun) -> None:
        seen.append((r.factor, r.failed))
        total = bisection_total(seen, tolerance, max_runs, relative_to)
        verdict = "fails" if r.failed else "holds"
        bar.update(len(seen), f"{what} = {r.factor:.4g} {verdict}", total=total)
        bar.event(f"trial {len(seen)} of about {total}: {what} = {r.factor:.4g} {verdict}: "
                  f"{r.reason}")

    return bar, note


def _searched(search: Callable[[], Any], bar: Progress) -> Any:
    """The result of a strength-reduction `search`; a scene whose trials cannot fail
    (quasi-static) refused at analysis.mode (exit 2); the progress bar closed either way."""
    try:
        return search()
    except QuasiStatic as exc:  # no trial could fail: refused, exit 2
        raise SceneError([{"loc": "analysis.mode", "msg": str(exc)}]) from None
    finally:
        bar.close()


def cmd_fos(args: argparse.Namespace) -> int:
    """Factor of safety by strength reduction (bisection on tan φ / F)."""
    built = load_scene(args.scene)
    one_model(built, "the factor-of-safety search")
    c = fos_controls(built)
    bar, note = _trials(args, f"fos {Path(args.scene).stem}", "F", c.tolerance, c.max_runs,
                        "lo")
    result = _searched(lambda: factor_of_safety(built.model, c, progress=note), bar)
    doc = fos_document(result, built)
    if args.json:
        print_json(doc)
    else:
        print("\n".join(fos_text(doc, shown=built.warnings)))
    return EXIT_OK if result.status == STATUS_COMPLETED else EXIT_RUN


def fos_text(doc: dict[str, Any], shown: Sequence[str] = ()) -> list[str]:
    """The factor of safety for people: the value to two decimals, how it was found (trial
    runs, the last bracket), the critical friction angle of each weakened joint material,
    the warnings not `shown` already, and the verdict."""
    runs = doc.get("runs") or []
    fs = doc.get("factor_of_safety")
    if not isinstance(fs, float):
        return [f"no factor of safety ({doc.get('status')}): {doc.get('message', '')}",
                "Verdict: none — the search found no factor of safety"]
    bracket = fos_bracket(runs)
    how = (f"strength reduction, bisection on tan φ / F over {rd.plural(len(runs), 'trial run')}"
           + (f": holds at F = {bracket[0]:.4g}, fails at {bracket[1]:.4g}" if bracket else ""))
    # a bound: no trial failed up to the largest factor (≥), or every one down to the least
    sign = {"lower": "≥ ", "upper": "< "}.get(doc.get("bound") or "", "")
    lines = [f"factor of safety {sign}{fs:.2f} ({how})"]
    phis = doc.get("critical_friction_angle")
    phis = phis if isinstance(phis, list) else [phis]
    names = doc.get("joint_materials") or []
    for name, phi in zip(names, phis, strict=False):
        if isinstance(phi, float):
            lines.append(f"critical friction angle of '{name}': {rd.angle(phi)}")
    if doc.get("message"):
        lines.append(doc["message"])
    lines += [f"warning: {w}" for w in doc.get("warnings", []) if w not in shown]
    lines.append(verdict_line(fs, "FS", bound=doc.get("bound")))
    return lines


def cmd_seismic(args: argparse.Namespace) -> int:
    """Critical (yield) seismic coefficient by bisection on kh."""
    built = load_scene(args.scene)
    one_model(built, "the critical seismic coefficient search")
    c = seismic_controls(built)
    bar, note = _trials(args, f"seismic {Path(args.scene).stem}", "kh", c.tolerance,
                        c.max_runs, "hi")
    result = _searched(lambda: critical_seismic_coefficient(built.model, c, progress=note),
                       bar)
    doc = seismic_document(result, built)
    if args.json:
        print_json(doc)
    else:
        bracket = fos_bracket(doc.get("runs") or [], key="kh")
        sign = {"lower": "≥ ", "upper": "< "}.get(result.bound or "", "")
        print(f"critical seismic coefficient kh {sign or '= '}{result.critical_coefficient:.3f} "
              f"(horizontal force towards {result.azimuth_deg:03.0f}°, kv "
              f"{result.kv:g}; bisection over {rd.plural(len(result.runs), 'trial run')}"
              + (f": holds at kh = {bracket[0]:.4g}, fails at {bracket[1]:.4g})"
                 if bracket else ")"))
        if result.message:
            print(result.message)
        for w in doc.get("warnings", []):
            if w not in built.warnings:  # the scene's were said when it was loaded
                print(f"warning: {w}")
        print(seismic_verdict(result.critical_coefficient, result.bound))
    return EXIT_OK if result.status == STATUS_COMPLETED else EXIT_RUN


def seismic_verdict(kh: float, bound: str | None) -> str:
    """The last line of `polydda seismic`: the horizontal acceleration (in g) the watched
    blocks withstand."""
    if not math.isfinite(kh):
        return "Verdict: none — the search found no critical seismic coefficient"
    if bound == "lower":
        return f"Verdict: holds up to kh {kh:.3f} at least (no trial failed)"
    if bound == "upper" or kh <= 0:
        return (f"Verdict: not stable — fails even at kh {kh:.3f} (under its static loads "
                "alone)" if kh <= 0 else f"Verdict: fails at every kh tried (kh < {kh:.3f})")
    return (f"Verdict: stable below kh {kh:.3f} — a horizontal acceleration of {kh:.3f} g "
            "makes the watched blocks fail")


def cmd_le(args: argparse.Namespace) -> int:
    """Limit equilibrium of the scene's one free block (planar or two-plane wedge, the
    vector method); exit 2 naming why when it does not apply."""
    from service.documents import le_document, le_result, le_text

    built = load_scene(args.scene, quiet=args.json)
    one_model(built, "limit equilibrium")
    doc = le_document(le_result(built), built)
    if args.json:
        print_json(doc)
    else:
        print(le_text(doc))
    return EXIT_OK
