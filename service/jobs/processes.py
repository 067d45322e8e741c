"""The process registry: every process the service runs (and the CLI names), in one place.

A :class:`Process` says what it is (id, title, description), what it writes (artifacts, the
main JSON one and its key in the results document), which scene `analysis.type` makes it
the default of `POST /jobs`, and how it runs (`run`: scene build -> files in the job
directory -> Outcome). The API's routes, its OpenAPI enums, the results document, the job
function and `polydda submit --process` all read this table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from service.documents import (
    blocks_document,
    dynamic_trials,
    finite,
    fos_controls,
    fos_document,
    run_summary,
    seismic_controls,
    seismic_document,
    write_json_atomic,
)
from service.jobs.tasks import MODEL, Cancelled, Outcome, TaskContext

if TYPE_CHECKING:
    from schemas.convert import BuildResult

#: the HDF5 result of a simulation
RESULT_FILE = "result.h5"
#: folder of the data directory where sweep jobs keep realisation records, by population
SWEEPS_DIR = "sweeps"

Runner = Callable[["BuildResult | None", str, Path, TaskContext], Outcome]


@dataclass(frozen=True)
class Process:
    """One process: its OGC description, its files and its runner."""

    id: str
    title: str
    description: str
    #: files a job of this process may leave in its directory
    artifacts: tuple[str, ...]
    #: the main JSON artifact and its key in the results document
    main_artifact: str
    result_key: str
    #: the scene `analysis.type` for which this is the default process of POST /jobs
    analysis_type: str | None
    run: Runner
    #: whether the runner needs the built model (cut blocks); else it gets None
    needs_model: bool = True
    #: extra check of a validated Scene at submission (raises SceneError), if any
    check: Callable[[Any], Any] | None = None


def _simulation(build: BuildResult, scene_text: str, job_dir: Path,
                ctx: TaskContext) -> Outcome:
    from engine.results.writer import ResultWriter
    from engine.step.simulation import STATUS_CANCELLED, STATUS_COMPLETED, Progress
    from engine.step.staged_run import run_scene
    from schemas.scene import SCHEMA_VERSION

    def progress(p: Progress) -> None:
        ctx.report(100.0 * p.fraction, step=p.step, simulated_time=p.time,
                   duration=p.duration)

    ctx.report(0.0, force=True, step=0, simulated_time=0.0,
               duration=build.model.controls.duration)
    writer = ResultWriter(job_dir / RESULT_FILE, overwrite=True, schema_version=SCHEMA_VERSION,
                          record_contacts=build.model.controls.record_contacts)
    res = run_scene(build.model, build.stages, recorder=writer, progress=progress,
                    should_stop=ctx.should_stop, scene_json=scene_text,
                    checkpoints=job_dir / "stages" if build.stages else None)
    write_json_atomic(job_dir / "summary.json", run_summary(res.summary, build))
    s = res.summary
    ctx.report(100.0 * min(1.0, s["simulated_time"] / build.model.controls.duration),
               force=True, step=s["steps"], simulated_time=s["simulated_time"])
    if res.status == STATUS_COMPLETED:
        return Outcome("successful", f"completed {res.steps} steps")
    if res.status == STATUS_CANCELLED:
        return Outcome("dismissed", f"cancelled at t = {s['simulated_time']:.6g} s after "
                                    f"{res.steps} steps; partial results kept")
    return Outcome("failed", f"model problem: {res.message}", MODEL)


def _bisection_job(build: BuildResult, job_dir: Path, ctx: TaskContext, artifact: str,
                   analysis: Callable[..., Any], controls: Any,
                   document: Callable[[Any, BuildResult], dict[str, Any]], trial_label: str,
                   answer: Callable[[Any], str]) -> Outcome:
    """A bisection analysis as a job (factor of safety, critical seismic coefficient):
    progress per trial, cancel between trials with the trials so far kept in `artifact`,
    the analysis's document written atomically; `answer(result)` names its number."""
    from engine.analyses.strength_reduction import QuasiStatic, TrialRun

    runs: list[TrialRun] = []

    def progress(r: TrialRun) -> None:
        runs.append(r)
        verdict = "fails" if r.failed else "holds"
        ctx.report(100.0 * len(runs) / controls.max_runs, force=True, step=len(runs),
                   message=f"trial {len(runs)}: {trial_label} {r.factor:.4g} {verdict}: "
                           f"{r.reason}")
        if ctx.should_stop():
            raise Cancelled

    ctx.report(0.0, force=True, message="first trial running")
    try:
        result = analysis(build.model, controls, progress=progress)
    except QuasiStatic as exc:  # refused at submission; a job from before says why here
        return Outcome("failed", f"model problem: {exc}", MODEL)
    except Cancelled:
        write_json_atomic(job_dir / artifact, finite({
            "status": "cancelled", "runs": [r.__dict__ for r in runs],
            "message": f"cancelled after {len(runs)} trials"}))
        return Outcome("dismissed", f"cancelled after {len(runs)} trials; partial results kept")
    write_json_atomic(job_dir / artifact, document(result, build))
    ctx.report(100.0, force=True, step=len(result.runs))
    if result.status == "completed":
        return Outcome("successful", answer(result)
                       + (f" ({result.message})" if result.message else ""))
    return Outcome("failed", f"model problem: {result.message}", MODEL)


def _factor_of_safety(build: BuildResult, scene_text: str, job_dir: Path,
                      ctx: TaskContext) -> Outcome:
    from engine.analyses.strength_reduction import factor_of_safety

    return _bisection_job(build, job_dir, ctx, "fos.json", factor_of_safety,
                          fos_controls(build), fos_document, "reduction factor",
                          lambda r: f"factor of safety {r.factor_of_safety:.4g}")


def _critical_seismic(build: BuildResult, scene_text: str, job_dir: Path,
                      ctx: TaskContext) -> Outcome:
    from engine.analyses.strength_reduction import critical_seismic_coefficient

    return _bisection_job(build, job_dir, ctx, "seismic.json", critical_seismic_coefficient,
                          seismic_controls(build), seismic_document, "kh",
                          lambda r: f"critical seismic coefficient {r.critical_coefficient:.4g}")


def _kinematics(build: BuildResult | None, scene_text: str, job_dir: Path,
                ctx: TaskContext) -> Outcome:
    import time

    from engine.analyses.stereonet import plot_stereonet
    from service.documents import kinematic_result, kinematics_document

    start = time.perf_counter()
    result = kinematic_result(scene_text)
    write_json_atomic(job_dir / "kinematics.json", kinematics_document(result))
    plot_stereonet(result, job_dir / "stereonet.png")
    ctx.report(100.0, force=True)
    found = [f"{len(v)} {k.replace('_', ' ')}" for k, v in result.admissible().items() if v]
    return Outcome("successful", "admissible: " + (", ".join(found) if found else "none")
                   + f" (screened in {time.perf_counter() - start:.2f} s)")


def _kinematics_check(scene: Any) -> None:
    from schemas.convert import kinematic_inputs

    kinematic_inputs(scene)


def _sweep(build: BuildResult | None, scene_text: str, job_dir: Path,
           ctx: TaskContext) -> Outcome:
    import json

    from service.sweep import run_sweep, spec_of_scene

    scene = json.loads(scene_text)
    spec = spec_of_scene(scene)

    def progress(done: int, n: int, now: int) -> None:
        ctx.report(100.0 * done / n, force=True, step=done,
                   message=f"{done} of {n} realisations done")

    ctx.report(0.0, force=True, step=0,
               message=f"0 of {len(spec.indices())} realisations done")
    # realisation files in DATA_DIR/sweeps/<population>/ (job_dir is DATA_DIR/jobs/<id>):
    # a job resubmitted after its worker died, or another share, skips those already done
    doc = run_sweep(scene, spec, job_dir, progress=progress, should_stop=ctx.should_stop,
                    shared=job_dir.parent.parent / SWEEPS_DIR)
    a = doc[spec.mode]
    pof = "none evaluated" if not a["n"] else (
        f"probability of failure {100 * a['probability_of_failure']:.2f} % over {a['n']}")
    share = len(spec.indices())
    if doc["done"] < share:
        return Outcome("dismissed", f"cancelled after {doc['done']} of {share} "
                                    f"realisations; {pof} (partial aggregate kept)")
    return Outcome("successful", f"{spec.mode}: {pof} realisations")


def _trial_check(analysis: str) -> Callable[[Any], None]:
    """The check of a process of strength-reduction trials: one model (no stages,
    schemas.stage_checks) analysed dynamically (a quasi-static scene is refused)."""
    def check(scene: Any) -> None:
        from schemas.stage_checks import refuse_stages

        refuse_stages(scene, analysis)
        dynamic_trials(scene.analysis)
    return check


def _sweep_check(scene: Any) -> None:
    from schemas.stage_checks import refuse_stages
    from service.sweep import spec_of_scene

    refuse_stages(scene, "a sweep")
    spec = spec_of_scene(scene.model_dump(mode="json", exclude_none=True))
    if spec.mode == "analytic":  # limit equilibrium must apply to the scene
        from schemas.convert import build_model
        from service.documents import le_result

        le_result(build_model(scene))


def _limit_equilibrium(build: BuildResult, scene_text: str, job_dir: Path,
                       ctx: TaskContext) -> Outcome:
    from schemas.errors import SceneError
    from service.documents import le_document, le_result

    try:
        doc = le_document(le_result(build), build)
    except SceneError as exc:  # checked at submission; a job from before says why here
        return Outcome("failed", "; ".join(exc.lines()), MODEL)
    write_json_atomic(job_dir / "le.json", doc)
    ctx.report(100.0, force=True)
    fs = doc["factor_of_safety"]
    return Outcome("successful", f"factor of safety {'unbounded' if fs is None else f'{fs:.4g}'}"
                                 f" ({doc['mode']})")


def _limit_equilibrium_check(scene: Any) -> None:
    from schemas.convert import build_model
    from schemas.stage_checks import refuse_stages
    from service.documents import le_result

    refuse_stages(scene, "limit equilibrium")
    le_result(build_model(scene))


def _block_cutting(build: BuildResult, scene_text: str, job_dir: Path,
                   ctx: TaskContext) -> Outcome:
    write_json_atomic(job_dir / "blocks.json", blocks_document(build))
    ctx.report(100.0, force=True)
    n = len(build.model.blocks)
    return Outcome("successful", f"{n} block{'s' if n != 1 else ''}")


PROCESSES: dict[str, Process] = {p.id: p for p in (
    Process("simulation", "DDA simulation",
            "Run the scene's blocks through time (3-D DDA) and record every recorded step "
            "in an HDF5 result file (VTKHDF for ParaView).",
            ("summary.json", RESULT_FILE), "summary.json", "summary", "simulation",
            _simulation),
    Process("factor-of-safety", "Factor of safety (strength reduction)",
            "Divide the joints' strength by trial factors and find by bisection the factor "
            "at which the watched blocks fail: each trial starts from the model settled "
            "under its loads and fails when a watched block moves beyond the displacement "
            "limit or keeps moving, holds once every watched block is at rest on stuck "
            "contacts; every trial's displacement, velocity and verdict with its reason are "
            "in the result (the scene's analysis.factor_of_safety: watched blocks, joint "
            "materials, limit, times). A quasi-static scene is refused.",
            ("fos.json",), "fos.json", "factor_of_safety", "factor_of_safety",
            _factor_of_safety, check=_trial_check("the factor-of-safety search")),
    Process("critical-seismic-coefficient", "Critical seismic coefficient",
            "Find by bisection on the horizontal pseudo-static coefficient kh (the scene's "
            "seismic azimuth and kv, full joint strengths) the kh at which the watched blocks "
            "fail (the trials of the factor of safety, from the equilibrium at kh = 0; the "
            "scene's analysis.critical_seismic_coefficient).",
            ("seismic.json",), "seismic.json", "critical_seismic_coefficient",
            "critical_seismic_coefficient", _critical_seismic,
            check=_trial_check("the critical seismic coefficient search")),
    Process("limit-equilibrium", "Limit equilibrium (planar block, two-plane wedge)",
            "The factor of safety of the scene's one free block on the planes it rests on by "
            "the vector method (Hoek & Bray; Low 1997), with cohesion, water on the planes "
            "and in a tension crack, bolts and tendons (active and passive), seismic kh / kv "
            "and point loads; the failure mode (sliding on both planes, on one, lifting "
            "off). A scene it does not apply to is refused at submission, saying why.",
            ("le.json",), "le.json", "limit_equilibrium", "limit_equilibrium",
            _limit_equilibrium, check=_limit_equilibrium_check),
    Process("block-cutting", "Block cutting",
            "Cut the domain by the joints and list the blocks (volume, centroid, vertices, "
            "faces); nothing is run.",
            ("blocks.json",), "blocks.json", "blocks", None, _block_cutting),
    Process("kinematics", "Kinematic screening (Markland tests)",
            "Test the scene's joints against its slope_face for planar sliding, wedge "
            "sliding (every pair), flexural and direct toppling; list the admissible sets "
            "and pairs and draw the equal-area stereonet (stereonet.png); nothing is run.",
            ("kinematics.json", "stereonet.png"), "kinematics.json", "kinematics", None,
            _kinematics, needs_model=False, check=_kinematics_check),
    Process("sweep", "Monte Carlo sweep (probability of failure)",
            "Draw the scene's sweep.n realisations of the joints' friction angle from "
            "sweep.seed; find each one's factor of safety (the engine's strength reduction, "
            "or limit equilibrium with mode 'analytic', refused at submission when it does "
            "not apply); aggregate the probability of failure, FS histogram and CDF and the "
            "sensitivity to φ, beside limit equilibrium over the same realisations. "
            "Progress counts realisations; a cancelled job keeps the aggregate of those "
            "done. sweep.realisations makes a job one share of a sweep; ?shares=K makes the "
            "job a parent of K such jobs spread over the queue (progress, cancel and merged "
            "results of the whole); realisation records are kept by sweep in the data "
            "directory, so a job resubmitted after its worker died redoes none that were "
            "done.",
            ("sweep.json",), "sweep.json", "sweep", None, _sweep, check=_sweep_check),
)}
PROCESS_IDS: tuple[str, ...] = tuple(PROCESSES)
#: the process ids as a type (query parameters, OpenAPI enums)
ProcessId = Literal[PROCESS_IDS]  # type: ignore[valid-type]


#: process id -> its main JSON artifact
MAIN_ARTIFACTS: dict[str, str] = {p.id: p.main_artifact for p in PROCESSES.values()}


def default_process(analysis_type: str) -> str:
    """The process POST /jobs runs for a scene of this `analysis.type` (else simulation)."""
    for p in PROCESSES.values():
        if p.analysis_type == analysis_type:
            return p.id
    return "simulation"
