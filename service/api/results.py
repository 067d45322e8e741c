"""A finished job's results: the results document, its files (a killed run's HDF5 served as
a recovered copy any HDF5 reader opens), plots made on demand, contacts of a step; and block
motion as frames for the viewer (also while the job runs)."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
from pathlib import Path
from typing import Any

from service.api.frames import Frames, RangeError
from service.api.frames import frames as make_frames
from service.api.models import FILE_TYPES
from service.api.problems import Problem
from service.api.report import report_html
from service.documents import NotRecorded, result_contacts_document
from service.jobs.backend import Backend
from service.jobs.processes import PROCESSES, RESULT_FILE
from service.jobs.store import ACTIVE, FAILED, SUCCESSFUL, JobRecord, JobStore
from service.settings import Settings

log = logging.getLogger("service.api")

#: the copy of a killed run's result.h5 that is served instead of it
RECOVERED_FILE = "result.recovered.h5"

_locks: dict[str, threading.Lock] = {}
_locks_guard = threading.Lock()


def _lock(name: str) -> threading.Lock:
    with _locks_guard:
        return _locks.setdefault(name, threading.Lock())


def ensure_local(job: JobRecord, settings: Settings) -> None:
    """With an object store: copy a finished job's stored files into the data directory
    (once; later calls find them there). Nothing without a store or while the job runs."""
    from service.jobs.objectstore import ResultStore

    if job.status in ACTIVE:
        return
    store = ResultStore.of(settings)
    if store is None:
        return
    d = settings.job_dir(job.id)
    with _lock(job.id + "/fetch"):
        if (d / ".fetched").is_file():
            return
        try:
            if store.fetch_job(job.id, d):
                (d / ".fetched").touch()
        except Exception as exc:
            log.warning("results of job %s not fetched from the object store: %s", job.id,
                        exc)
            raise Problem(503, "store-unavailable", "Result store unavailable",
                          f"job {job.id}'s results could not be read from the object store "
                          f"({type(exc).__name__}); retry later",
                          headers={"Retry-After": "10"}) from None


def require_final(job: JobRecord) -> None:
    """404 `result-not-ready` (with Retry-After) while the job is accepted or running."""
    if job.status in ACTIVE:
        raise Problem(404, "result-not-ready", "Result not ready",
                      f"job {job.id} is {job.status} ({int(job.progress)} %); its results "
                      "are available when it ends", headers={"Retry-After": "2"})


def artifact(job: JobRecord, settings: Settings, name: str) -> Path:
    """The path of one of the job's result files (404 if it has none of that name)."""
    require_final(job)
    ensure_local(job, settings)
    path = settings.job_dir(job.id) / name
    if name not in PROCESSES[job.process].artifacts or not path.is_file():
        from schemas.errors import echo

        have = [a for a in PROCESSES[job.process].artifacts
                if (settings.job_dir(job.id) / a).is_file()]
        raise Problem(404, "no-such-result", "No such result",
                      f"job {job.id} has no result '{echo(name)}'; the job is {job.status}"
                      + (f" ({job.message})" if job.message else "")
                      + (f"; its results: {', '.join(have)}" if have else
                         "; it has no result files"))
    return path


def _opens_plainly(path: Path) -> bool:
    """True if an ordinary HDF5 reader opens `path` (a killed SWMR writer leaves its file
    marked open-for-writing, which only SWMR readers accept)."""
    import h5py

    try:
        with h5py.File(path, "r"):
            return True
    except OSError:
        return False


def readable_result(job: JobRecord, settings: Settings) -> tuple[Path, bool]:
    """The job's result.h5 as a file any HDF5 reader opens, and whether it is a recovered
    copy (engine.results.reader.recover_result: the steps flushed before the run was killed)."""
    path = artifact(job, settings, RESULT_FILE)
    copy = path.with_name(RECOVERED_FILE)
    with _lock(job.id + "/h5"):
        if copy.is_file() and copy.stat().st_mtime >= path.stat().st_mtime:
            return copy, True
        if _opens_plainly(path):
            return path, False
        from engine.results.reader import recover_result

        tmp = path.with_name(f".{RECOVERED_FILE}.{os.getpid()}.tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        try:
            recover_result(path, tmp)
            os.replace(tmp, copy)
        except Exception as exc:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            log.warning("result of job %s could not be recovered: %s", job.id, exc)
            raise Problem(404, "no-such-result", "Result unreadable",
                          f"job {job.id}'s result.h5 was left unreadable by its killed run "
                          f"and could not be recovered: {exc}") from None
        return copy, True


def stored_file(job: JobRecord, settings: Settings, name: str) -> int | None:
    """With an object store, the size of a finished job's stored file `name` when it is
    to be streamed from the store (a successful job's; a killed run's result.h5 is
    recovered from the local copy instead); else None."""
    from service.jobs.objectstore import ResultStore

    store = ResultStore.of(settings)
    if store is None or job.status != SUCCESSFUL:
        return None
    if name not in PROCESSES[job.process].artifacts:
        return None
    try:
        return store.size(job.id, name)
    except Exception as exc:
        raise Problem(503, "store-unavailable", "Result store unavailable",
                      f"the object store did not answer ({type(exc).__name__}); retry later",
                      headers={"Retry-After": "10"}) from None


def so_far_document(job: JobRecord, store: JobStore, backend: Backend,
                    root: str) -> dict[str, Any]:
    """A running sweep parent's results: the aggregate of the realisations its children
    recorded so far (`partial`; the merged children's documents once it ends)."""
    from service.jobs.fanout import so_far

    return {"jobID": job.id, "processID": job.process, "status": job.status,
            "message": job.message, "partial": True, "sweep": so_far(store, backend, job),
            "links": [{"href": f"{root}/jobs/{job.id}", "rel": "status",
                       "type": "application/json"}]}


def results_document(job: JobRecord, settings: Settings, root: str) -> dict[str, Any]:
    """The results document: status, the main JSON artifact inline, links to the files."""
    require_final(job)
    ensure_local(job, settings)
    p = PROCESSES[job.process]
    d = settings.job_dir(job.id)
    base = f"{root}/jobs/{job.id}/results"
    files = [n for n in p.artifacts if (d / n).is_file()]
    if not files:
        raise Problem(404, "no-such-result", "No results",
                      f"job {job.id} {job.status} without results: {job.message}")
    doc: dict[str, Any] = {"jobID": job.id, "processID": job.process, "status": job.status,
                           "message": job.message, "partial": job.status != SUCCESSFUL}
    main = d / p.main_artifact
    if main.is_file():
        doc[p.result_key] = json.loads(main.read_text(encoding="utf-8"))
    elif (d / RESULT_FILE).is_file():  # a run killed before it could write its summary
        from engine.results.summary import summarize

        summary = summarize(d / RESULT_FILE)
        if summary.get("status") == "running":  # the file's word when its run was killed
            summary["status"] = "killed" if job.status == FAILED else job.status
            summary["message"] = (f"the run was stopped before it ended ({job.message}); "
                                  "the steps recorded until then are kept")
        doc[p.result_key] = summary
    links = []
    for n in files:
        link = {"href": f"{base}/{n}", "rel": "enclosure", "type": FILE_TYPES[Path(n).suffix],
                "title": n}
        if n == RESULT_FILE and not main.is_file():
            link["title"] = (f"{n} (the steps recorded before the run was killed, copied "
                             "into a file any HDF5 reader opens)")
        links.append(link)
    if RESULT_FILE in files:
        links += [{"href": f"{root}/jobs/{job.id}/viewer", "rel": "related",
                   "type": "text/html", "title": "3-D viewer"},
                  {"href": f"{base}/plots", "rel": "related", "type": "application/json",
                   "title": "PNG plots (made on first request)"},
                  {"href": f"{base}/contacts?format=csv", "rel": "related", "type": "text/csv",
                   "title": "contacts of the last recorded step (?step=N for another)"}]
    links.append({"href": f"{root}/jobs/{job.id}/report", "rel": "describedby",
                  "type": "text/html", "title": "printable report"})
    doc["links"] = links
    return doc


def plots(job: JobRecord, settings: Settings) -> list[Path]:
    """The job's PNG plots, made on first request (engine.results.plots.plot_all)."""
    h5 = artifact(job, settings, RESULT_FILE)  # the engine's reader opens a killed run's file
    out = settings.job_dir(job.id) / "plots"
    done = out / ".done"
    with _lock(job.id + "/plots"):
        if not done.exists():
            from engine.results.plots import plot_all

            try:
                plot_all(h5, out)
            except Exception as exc:
                log.exception("plots of job %s failed", job.id)
                raise Problem(500, "plot-failed", "Plots could not be made",
                              f"system error: {type(exc).__name__}: {exc}") from None
            done.touch()
    return sorted(out.glob("*.png"))


def contacts(job: JobRecord, settings: Settings, step: int | None) -> dict[str, Any]:
    """service.documents.result_contacts_document of the job's result (404 / 422 when the
    file has no contacts or not that step)."""
    from engine.results.reader import open_result

    h5 = artifact(job, settings, RESULT_FILE)
    with open_result(h5) as r:
        try:
            return result_contacts_document(r, step)
        except NotRecorded as exc:
            if exc.loc:
                raise Problem(422, "invalid-request", "Step not recorded", exc.message,
                              errors=[{"loc": exc.loc, "msg": exc.message}]) from None
            raise Problem(404, "contacts-not-recorded", "Contacts not recorded",
                          exc.message) from None


def result_meta(r: Any) -> dict[str, Any]:
    """What a report says of an open result file `r` (engine.results.reader.Result): its
    versions, the scene's hash, the blocks' fixity and volumes, the steps recorded and the
    last one."""
    meta: dict[str, Any] = {"engine_version": r.engine_version,
                            "schema_version": r.schema_version or "–",
                            "scene_sha256": r.scene_sha256 or "–",
                            "fixed": r.fixed.tolist(), "volume": r.volume.tolist(),
                            "n_steps": r.n_steps}
    if r.n_steps:
        meta["last"] = {"time": float(r.times[-1]), "step": int(r.steps[-1])}
        # the run's largest energy (J): an energy round-off against it reads as 0
        import numpy as np

        # (synthetic or partial files may hold only NaN: they add nothing)
        finite = [np.abs(v[np.isfinite(v)]) for v in
                  (np.asarray(e, float) for e in r.energies().values())]
        meta["energy_scale"] = max((float(v.max()) for v in finite if v.size), default=0.0)
    return meta


def live_result(job: JobRecord, settings: Settings) -> Path:
    """The job's result.h5 as it is now: also while running (the steps written so far);
    404 while it has none yet (Retry-After when it may come)."""
    ensure_local(job, settings)
    path = settings.job_dir(job.id) / RESULT_FILE
    if RESULT_FILE not in PROCESSES[job.process].artifacts:
        raise Problem(404, "no-such-result", "No result file",
                      f"job {job.id} is a {job.process} job: it records no steps")
    if not path.is_file():
        if job.status in ACTIVE:
            raise Problem(404, "result-not-ready", "Result not ready",
                          f"job {job.id} is {job.status}; its first step is not written yet",
                          headers={"Retry-After": "1"})
        raise Problem(404, "no-such-result", "No result file",
                      f"job {job.id} {job.status} without a result file: {job.message}")
    return path


def frames(job: JobRecord, settings: Settings, start: int, stop: int | None, stride: int,
           with_geometry: bool, contacts: bool) -> Frames:
    """service.api.frames.frames of the job's result (running or not); 422 for a bad range."""
    from engine.results.reader import open_result

    path = live_result(job, settings)
    try:
        r = open_result(path)
    except (OSError, ValueError) as exc:
        log.warning("result of job %s could not be opened: %s", job.id, exc)
        raise Problem(503 if job.status in ACTIVE else 404,
                      "result-unreadable", "Result unreadable now",
                      f"job {job.id}'s result.h5 could not be read: {exc}",
                      headers={"Retry-After": "1"} if job.status in ACTIVE else None) from None
    with r:
        try:
            return make_frames(r, start, stop, stride, with_geometry=with_geometry,
                               contacts=contacts)
        except RangeError as exc:
            raise Problem(422, "invalid-range", "Steps not recorded", str(exc),
                          errors=[{"loc": "query.start", "msg": str(exc)}]) from None


def report(job: JobRecord, settings: Settings, scene_text: str, root: str) -> str:
    """The printable HTML report of a finished job (plots and figures made if not yet):
    its FS or sweep, the kinematic screening of the scene's joints against its slope face,
    the blocks at the last recorded step, the plots."""
    require_final(job)
    ensure_local(job, settings)
    d = settings.job_dir(job.id)
    names: list[str] = []
    meta: dict[str, Any] = {}
    snapshot = None
    if (d / RESULT_FILE).is_file():
        from engine.results.reader import open_result

        names = [p.name for p in plots(job, settings)]
        with open_result(d / RESULT_FILE) as r:
            meta = result_meta(r)
        if "snapshot_final.png" in names:  # the blocks at the last recorded step
            names.remove("snapshot_final.png")
            snapshot = png_uri(d / "plots" / "snapshot_final.png")
    figures = {}
    fos = d / "fos.json"
    if fos.is_file():
        figures["Bisection of the reduction factor"] = fos_figure(fos)
    return report_html(job, root, d, scene_text, names, meta, figures,
                       kinematics=kinematics_part(d, scene_of(scene_text)),
                       snapshot=snapshot, sweep=sweep_part(d))


def scene_of(scene_text: str) -> dict[str, Any]:
    """The scene of a job's stored text (a scene, or an execute request's inputs.scene;
    {} if it is no JSON object)."""
    try:
        scene = json.loads(scene_text) if scene_text else {}
    except ValueError:
        return {}
    if not isinstance(scene, dict):
        return {}
    inner = (scene.get("inputs") or {}).get("scene") if "inputs" in scene else None
    return inner if isinstance(inner, dict) else scene


def png_uri(path: Path) -> str:
    """A PNG file as a data: URI (the report carries its figures when saved or printed)."""
    import base64

    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()


def _figure(path: Path, newer_than: Path | None, make: Any) -> str:
    """`path` made by `make(path)` once (again when `newer_than` changed since), as a URI."""
    with _lock(str(path)):
        if not path.is_file() or (newer_than is not None and path.stat().st_mtime
                                  < newer_than.stat().st_mtime):
            path.parent.mkdir(parents=True, exist_ok=True)
            make(path)
    return png_uri(path)


def kinematics_part(job_dir: Path, scene: dict[str, Any]) -> dict[str, Any]:
    """The kinematic screening of the scene (engine.analyses.kinematics: its joints against its
    slope face) and its stereonet as a data: URI (`doc`, `src`); or `reason` when the
    scene gives no slope face or no joints."""
    from schemas.errors import SceneError
    from service.documents import kinematic_result, kinematics_document

    missing = [k for k in ("slope_face", "joints") if not scene.get(k)]
    if missing:
        return {"reason": f"the scene gives no {' and no '.join(missing)} (the screening "
                          "tests the joints' orientations against the slope face's)"}
    try:
        result = kinematic_result(scene)
    except SceneError as exc:
        return {"reason": "; ".join(exc.lines())}
    except ValueError as exc:  # an orientation the screening refuses (slope dip 0...)
        return {"reason": str(exc)}
    made = job_dir / "stereonet.png"  # a kinematics job drew it already
    if made.is_file():
        src = png_uri(made)
    else:
        from engine.analyses.stereonet import plot_stereonet

        src = _figure(job_dir / "report" / "stereonet.png", None,
                      lambda path: plot_stereonet(result, path))
    return {"doc": kinematics_document(result), "src": src}


def sweep_part(job_dir: Path) -> dict[str, Any] | None:
    """A sweep job's sweep.json (`doc`) and its FS histogram and CDF as a data: URI (`src`,
    None while no realisation has a factor of safety); None for other jobs."""
    path = job_dir / "sweep.json"
    if not path.is_file():
        return None
    doc = json.loads(path.read_text(encoding="utf-8"))
    mode = (doc.get("spec") or {}).get("mode", "dda")
    aggs = {mode: doc.get(mode) or {}}
    if mode != "analytic" and doc.get("analytic"):
        aggs["limit equilibrium"] = doc["analytic"]
    src = None
    if any((a.get("histogram") or {}).get("counts") for a in aggs.values()):
        from engine.results.plots import plot_fs_distribution

        src = _figure(job_dir / "report" / "sweep.png", path,
                      lambda out: plot_fs_distribution(aggs, out))
    return {"doc": doc, "src": src, "aggregates": aggs}


def fos_figure(fos: Path) -> str:
    """The FoS trials plot of a fos.json (made beside it once) as a data: URI."""
    png = fos.with_name("fos_trials.png")
    with _lock(str(fos) + "/plot"):
        if not png.is_file() or png.stat().st_mtime < fos.stat().st_mtime:
            from engine.results.plots import plot_fos_trials

            doc = json.loads(fos.read_text(encoding="utf-8"))
            fs = doc.get("factor_of_safety")
            plot_fos_trials(doc.get("runs") or [], png, fs if isinstance(fs, float) else None)
    return png_uri(png)
