"""The REST service: processes, jobs and their results (OGC API - Processes, Part 1 shape).

Routes stay thin: a scene is read and size-checked (`SceneBody`), validated completely by
`schemas.convert.build_model` before any job exists, and committed as one row of the job
table; a backend (service.backends) runs it with the job function (service.jobs). Every
error is an RFC 9457 `application/problem+json` document.
Run with `serve(host, port)` or `uvicorn --factory service.app:create_app`.
"""

from __future__ import annotations

import asyncio
import csv
import hashlib
import hmac
import io
import json
import logging
import shutil
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Header, Query, Request, Security
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.security import APIKeyHeader
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import StreamingResponse
from starlette.routing import Match

from service.backends import Backend, make_backend
from service.backends.store import (
    ACTIVE,
    SUCCESSFUL,
    IdempotencyConflict,
    JobRecord,
    JobStore,
    QuotaExceeded,
)
from service.jobs import MAIN_ARTIFACT, PROCESSES, RESULT_FILE
from service.settings import Settings

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
PROBLEM_TYPE = "/problems/"
ProcessId = Literal["simulation", "factor-of-safety", "block-cutting"]
Status = Literal["accepted", "running", "successful", "failed", "dismissed"]
#: scene analysis.type -> default process of POST /jobs
_PROCESS_OF_ANALYSIS = {"simulation": "simulation", "factor_of_safety": "factor-of-safety"}
_FILE_TYPES = {".h5": "application/x-hdf5", ".json": "application/json"}


# --------------------------------------------------------------------------- problems


class Problem(Exception):
    """An error answered as `application/problem+json` (RFC 9457)."""

    def __init__(self, status: int, slug: str, title: str, detail: str = "",
                 errors: list[dict[str, str]] | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(detail or title)
        self.status, self.slug, self.title, self.detail = status, slug, title, detail
        self.errors, self.headers = errors, headers

    def response(self, instance: str = "") -> JSONResponse:
        body: dict[str, Any] = {"type": PROBLEM_TYPE + self.slug, "title": self.title,
                                "status": self.status, "detail": self.detail}
        if instance:
            body["instance"] = instance
        if self.errors is not None:
            body["errors"] = self.errors
        return JSONResponse(body, status_code=self.status, headers=self.headers,
                            media_type="application/problem+json")


class ProblemError(BaseModel):
    """One problem with the input: the field path and what is wrong."""

    loc: str
    msg: str


class ProblemDoc(BaseModel):
    """RFC 9457 problem details."""

    type: str
    title: str
    status: int
    detail: str = ""
    instance: str | None = None
    errors: list[ProblemError] | None = None


def _invalid_scene(errors: list[dict[str, str]]) -> Problem:
    lines = [f"{e['loc']}: {e['msg']}" if e["loc"] else e["msg"] for e in errors]
    more = f" (and {len(lines) - 3} more)" if len(lines) > 3 else ""
    return Problem(422, "invalid-scene", "Invalid scene", "; ".join(lines[:3]) + more,
                   errors=errors)


def _problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    titles = {400: "Bad request", 401: "API key missing or wrong",
              404: "Not found", 409: "Conflict", 413: "Request body too large",
              422: "Invalid input", 429: "Too many unfinished jobs",
              503: "Job queue unavailable"}
    ref = {"schema": {"$ref": "#/components/schemas/ProblemDoc"}}
    return {c: {"description": titles[c], "content": {"application/problem+json": ref}}
            for c in codes}


# --------------------------------------------------------------------------- documents


class Link(BaseModel):
    href: str
    rel: str
    type: str | None = None
    title: str | None = None


class StatusInfo(BaseModel):
    """A job's status (OGC statusInfo plus the simulation's progress)."""

    jobID: str  # noqa: N815 - OGC field names
    processID: str  # noqa: N815
    type: Literal["process"] = "process"
    status: Status
    message: str = ""
    error_kind: Literal["model", "system"] | None = Field(
        None, description="for failed jobs: a problem of the model, or of the service")
    created: str
    started: str | None = None
    finished: str | None = None
    updated: str
    progress: int = Field(ge=0, le=100, description="percent")
    step: int | None = None
    simulated_time: float | None = Field(None, description="s")
    duration: float | None = Field(None, description="s to simulate")
    cancel_requested: bool = False
    links: list[Link] = []


class JobList(BaseModel):
    jobs: list[StatusInfo]
    numberMatched: int  # noqa: N815
    numberReturned: int  # noqa: N815
    links: list[Link]


def _time(t: float | None) -> str | None:
    if t is None:
        return None
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds").replace(
        "+00:00", "Z")


def status_doc(job: JobRecord, root: str = "") -> dict[str, Any]:
    """The statusInfo document of a job."""
    href = f"{root}/jobs/{job.id}"
    links = [{"href": href, "rel": "self", "type": "application/json"},
             {"href": f"{href}/events", "rel": "monitor", "type": "text/event-stream",
              "title": "progress as server-sent events"}]
    if job.is_final:
        links.append({"href": f"{href}/results",
                      "rel": "http://www.opengis.net/def/rel/ogc/1.0/results",
                      "type": "application/json"})
    return {
        "jobID": job.id, "processID": job.process, "type": "process", "status": job.status,
        "message": job.message, "error_kind": job.error_kind, "created": _time(job.created),
        "started": _time(job.started), "finished": _time(job.finished),
        "updated": _time(job.updated), "progress": int(job.progress),
        "step": job.step, "simulated_time": job.simulated_time, "duration": job.duration,
        "cancel_requested": job.cancel_requested is not None, "links": links,
    }


def process_doc(process_id: str, root: str, full: bool) -> dict[str, Any]:
    """OGC process summary (or description with inputs and outputs when `full`)."""
    p = PROCESSES[process_id]
    doc: dict[str, Any] = {
        "id": process_id, "title": p["title"], "description": p["description"],
        "version": "1.0.0", "jobControlOptions": ["async-execute", "dismiss"],
        "outputTransmission": ["reference"],
        "links": [{"href": f"{root}/processes/{process_id}", "rel": "self",
                   "type": "application/json"},
                  {"href": f"{root}/processes/{process_id}/execution",
                   "rel": "http://www.opengis.net/def/rel/ogc/1.0/execute",
                   "type": "application/json", "title": "POST the scene here"}],
    }
    if full:
        from schemas.scene import scene_json_schema

        doc["inputs"] = {"scene": {
            "title": "scene", "description": "the PolyDDA scene (POST it as the request body, "
            "or as {\"inputs\": {\"scene\": ...}})", "minOccurs": 1, "maxOccurs": 1,
            "schema": scene_json_schema()}}
        doc["outputs"] = {Path(name).stem: {"title": name, "schema": {
            "type": "string", "contentMediaType": _FILE_TYPES[Path(name).suffix]}}
            for name in p["artifacts"]}
    return doc


# --------------------------------------------------------------------------- dependencies


def _settings(request: Request) -> Settings:
    return request.app.state.settings


def _store(request: Request) -> JobStore:
    return request.app.state.store


def _backend(request: Request) -> Backend:
    return request.app.state.backend


def _root(request: Request) -> str:
    return str(request.scope.get("root_path", "")).rstrip("/")


SettingsDep = Annotated[Settings, Depends(_settings)]
StoreDep = Annotated[JobStore, Depends(_store)]
BackendDep = Annotated[Backend, Depends(_backend)]
RootDep = Annotated[str, Depends(_root)]
_api_key = APIKeyHeader(name="X-API-Key", auto_error=False,
                        description="needed when the service has API keys configured")


def _client(request: Request, settings: SettingsDep,
            key: Annotated[str | None, Security(_api_key)] = None) -> str:
    """Who is asking: the API key (when keys are on, a valid one is required) or the address."""
    if settings.api_keys:
        if key is None or not any(hmac.compare_digest(key.encode(), k.encode())
                                  for k in settings.api_keys):
            raise Problem(401, "unauthorized", "API key missing or wrong",
                          "send a valid key in the X-API-Key header",
                          headers={"WWW-Authenticate": 'ApiKey header="X-API-Key"'})
        return "key:" + hashlib.sha256(key.encode()).hexdigest()[:16]
    return "ip:" + (request.client.host if request.client else "unknown")


ClientDep = Annotated[str, Depends(_client)]


def _job(job_id: str, store: StoreDep) -> JobRecord:
    job = store.get(job_id)
    if job is None:
        raise Problem(404, "no-such-job", "No such job", f"there is no job '{job_id}'")
    return job


JobDep = Annotated[JobRecord, Depends(_job)]


async def _scene_body(request: Request, settings: SettingsDep) -> Any:
    """The request body as parsed JSON; 413 above the size limit (checked before parsing)."""
    limit = settings.max_body_bytes
    too_large = Problem(413, "body-too-large", "Request body too large",
                        f"the body may have at most {limit:,} bytes")
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > limit:
        raise too_large
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large
        chunks.append(chunk)
    raw = b"".join(chunks)
    if not raw.strip():
        raise _invalid_scene([{"loc": "", "msg": "the request body is empty: send the scene "
                                                 "as a JSON object"}])
    try:
        return json.loads(raw)
    except UnicodeDecodeError:
        raise _invalid_scene([{"loc": "", "msg": "not valid JSON: the body is not UTF-8"}]) \
            from None
    except json.JSONDecodeError as exc:
        raise _invalid_scene([{"loc": "", "msg": f"not valid JSON: {exc.msg} at line "
                                                 f"{exc.lineno} column {exc.colno}"}]) from None
    except RecursionError:
        raise _invalid_scene([{"loc": "", "msg": "not valid JSON: nested too deeply"}]) \
            from None


SceneBody = Annotated[Any, Depends(_scene_body)]
IdempotencyKey = Annotated[str | None, Header(
    alias="Idempotency-Key", max_length=200,
    description="a retry with the same key returns the job the first request created")]


# --------------------------------------------------------------------------- submission


def _unwrap(data: Any) -> tuple[str | None, Any]:
    """`(process, scene)` from a bare scene, `{"inputs": {"scene": ...}}` (OGC) or
    `{"process": ..., "scene": ...}`."""
    if not isinstance(data, dict):
        return None, data
    process = None
    if "process" in data:
        data = dict(data)
        process = data.pop("process")
        if not isinstance(process, str) or process not in PROCESSES:
            raise _invalid_scene([{"loc": "process", "msg": f"unknown process {process!r} "
                                   f"(known: {', '.join(PROCESSES)})"}])
    inputs = data.get("inputs")
    if set(data) == {"inputs"} and isinstance(inputs, dict) and "scene" in inputs:
        return process, inputs["scene"]
    if set(data) == {"scene"}:
        return process, data["scene"]
    return process, data


def _limit_problems(scene: Any, settings: Settings) -> list[dict[str, str]]:
    """Service limits (stricter than the format's), each naming its setting: vertices,
    blocks (explicit ones plus the estimate of those the joints cut), duration, steps.

    Only counts and arithmetic on the validated scene: nothing is cut or built yet.
    """
    from schemas.errors import fmt_count
    from schemas.scene import estimate_cut_blocks

    problems = []
    nv = sum(len(b.vertices) for b in scene.blocks)
    if scene.domain is not None and scene.domain.polyhedron is not None:
        nv += len(scene.domain.polyhedron.vertices)
    if nv > settings.max_vertices:
        problems.append({"loc": "blocks", "msg": f"the scene has {nv:,} vertices in all; this "
                         f"service accepts at most {settings.max_vertices:,} "
                         "(POLYDDA_MAX_VERTICES)"})
    if len(scene.blocks) > settings.max_blocks:
        problems.append({"loc": "blocks", "msg": f"{len(scene.blocks):,} blocks; this service "
                         f"accepts at most {settings.max_blocks:,} (POLYDDA_MAX_BLOCKS)"})
    elif scene.joints:
        cut = estimate_cut_blocks(scene)
        if cut + len(scene.blocks) > settings.max_blocks:
            extra = f" (and {len(scene.blocks):,} explicit ones)" if scene.blocks else ""
            problems.append({"loc": "joints", "msg": f"the joints would cut the domain into "
                             f"about {fmt_count(cut)} blocks{extra}; this service accepts at "
                             f"most {settings.max_blocks:,} (POLYDDA_MAX_BLOCKS): increase the "
                             "joint spacings or make the domain smaller"})
    a = scene.analysis
    if a.duration > settings.max_duration:
        problems.append({"loc": "analysis.duration", "msg": f"{a.duration:g} s; this service "
                         f"simulates at most {settings.max_duration:g} s "
                         "(POLYDDA_MAX_DURATION)"})
    if a.duration / a.time_step > settings.max_steps:
        problems.append({"loc": "analysis.time_step", "msg": f"duration / time_step = "
                         f"{a.duration / a.time_step:.3g} steps; this service runs at most "
                         f"{settings.max_steps:,} (POLYDDA_MAX_STEPS)"})
    return problems


def validate_scene(data: Any, settings: Settings) -> Any:
    """The validated Scene of `data` (Problem 422 naming every bad field); builds the model.

    The service's size limits are checked right after the field types, before the
    format's own checks and long before cutting: a scene over a limit is refused at once.
    """
    from pydantic import ValidationError

    from schemas.convert import build_model
    from schemas.errors import SceneError, from_validation_error
    from schemas.scene import Scene, scene_problems

    if not isinstance(data, dict):
        raise _invalid_scene([{"loc": "", "msg": "a scene must be a JSON object {...}"}])
    try:
        try:
            scene = Scene.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, data, Scene) from None
        problems = _limit_problems(scene, settings) or scene_problems(scene)
        if problems:
            raise _invalid_scene(problems)
        build_model(scene)
    except SceneError as exc:
        raise _invalid_scene(exc.problems) from None
    return scene


_VALIDATION_SLOTS = threading.BoundedSemaphore(4)


def _submit(process: str | None, data: Any, *, settings: Settings, store: JobStore,
            backend: Backend, client: str, key: str | None, root: str) -> JSONResponse:
    body_process, scene_data = _unwrap(data)
    if process is not None and body_process is not None and process != body_process:
        raise _invalid_scene([{"loc": "process", "msg": f"'{body_process}' in the body but "
                               f"'{process}' in the URL"}])
    with _VALIDATION_SLOTS:
        scene = validate_scene(scene_data, settings)
    process = process or body_process or _PROCESS_OF_ANALYSIS.get(scene.analysis.type,
                                                                  "simulation")
    text = json.dumps(scene_data, ensure_ascii=False, separators=(",", ":"))
    digest = hashlib.sha256(f"{process}\n{text}".encode()).hexdigest()
    try:
        job, created = store.submit(process=process, scene=text, client=client,
                                    quota=settings.client_quota, idempotency_key=key,
                                    request_hash=digest)
    except QuotaExceeded as exc:
        raise Problem(429, "quota-exceeded", "Too many unfinished jobs",
                      f"you have {exc.active} jobs accepted or running; the limit is "
                      f"{exc.quota}. Wait for one to finish or dismiss one.",
                      headers={"Retry-After": "5"}) from None
    except IdempotencyConflict:
        raise Problem(422, "idempotency-key-reused", "Idempotency-Key reused",
                      "this Idempotency-Key was used for a different request") from None
    if created:
        try:
            backend.submitted(job)
        except Exception as exc:
            log.exception("backend could not take job %s", job.id)
            raise Problem(503, "queue-unavailable", "Job queue unavailable",
                          f"the job was recorded as failed: {exc}",
                          headers={"Retry-After": "30"}) from None
    headers = {"Location": f"{root}/jobs/{job.id}"}
    if not created:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(status_doc(job, root), status_code=201, headers=headers)


# --------------------------------------------------------------------------- results helpers


def _require_final(job: JobRecord) -> None:
    if job.status in ACTIVE:
        raise Problem(404, "result-not-ready", "Result not ready",
                      f"job {job.id} is {job.status} ({int(job.progress)} %); its results "
                      "are available when it ends", headers={"Retry-After": "2"})


def _artifact(job: JobRecord, settings: Settings, name: str) -> Path:
    _require_final(job)
    path = settings.job_dir(job.id) / name
    if name not in PROCESSES[job.process]["artifacts"] or not path.is_file():
        raise Problem(404, "no-such-result", "No such result",
                      f"job {job.id} has no result '{name}'"
                      + (f" (it {job.status}: {job.message})" if job.message else ""))
    return path


_plot_locks: dict[str, threading.Lock] = {}
_plot_locks_guard = threading.Lock()


def _plots(job: JobRecord, settings: Settings) -> list[Path]:
    """The job's PNG plots, made on first request (engine.plots.plot_all)."""
    h5 = _artifact(job, settings, RESULT_FILE)
    out = settings.job_dir(job.id) / "plots"
    done = out / ".done"
    with _plot_locks_guard:
        lock = _plot_locks.setdefault(job.id, threading.Lock())
    with lock:
        if not done.exists():
            from engine.plots import plot_all

            try:
                plot_all(h5, out)
            except Exception as exc:
                log.exception("plots of job %s failed", job.id)
                raise Problem(500, "plot-failed", "Plots could not be made",
                              f"system error: {type(exc).__name__}: {exc}") from None
            done.touch()
    return sorted(out.glob("*.png"))


def _contacts(job: JobRecord, settings: Settings, step: int | None) -> dict[str, Any]:
    import numpy as np

    from engine.contacts import KIND_NAMES, MODE_NAMES
    from engine.results import open_result

    h5 = _artifact(job, settings, RESULT_FILE)
    with open_result(h5) as r:
        if not r.contacts_recorded:
            raise Problem(404, "contacts-not-recorded", "Contacts were not recorded",
                          "the scene set analysis.record_contacts to false")
        if r.n_steps == 0:
            raise Problem(404, "no-such-result", "No recorded steps",
                          "the run recorded no step")
        steps = r.steps
        if step is None:
            k = r.n_steps - 1
        else:
            hits = np.flatnonzero(steps == step)
            if not len(hits):
                raise Problem(422, "invalid-request", "Step not recorded",
                              f"step {step} was not recorded",
                              errors=[{"loc": "query.step", "msg": (
                                  f"step {step} was not recorded; recorded steps run from "
                                  f"{int(steps[0])} to {int(steps[-1])} "
                                  f"({r.n_steps} records)")}])
            k = int(hits[0])
        c = r.contacts(k)
        names = r.block_names
        rows = []
        for i in range(len(c["gap"])):
            rows.append({
                "block_i": names[int(c["block_i"][i])], "block_j": names[int(c["block_j"][i])],
                "kind": KIND_NAMES.get(int(c["kind"][i]), str(int(c["kind"][i]))),
                "mode": MODE_NAMES.get(int(c["mode"][i]), str(int(c["mode"][i]))),
                "point_i": c["point_i"][i].tolist(), "point_j": c["point_j"][i].tolist(),
                "normal": c["normal"][i].tolist(), "tangent": c["tangent"][i].tolist(),
                "gap": float(c["gap"][i]), "normal_force": float(c["normal_force"][i]),
                "shear_force": c["shear_force"][i].tolist(),
            })
        return {"step": int(steps[k]), "time": float(r.times[k]), "count": len(rows),
                "contacts": rows}


def contacts_csv(doc: dict[str, Any]) -> str:
    """The contact list as CSV, one row per contact, vectors split into _x, _y, _z."""
    vectors = ("point_i", "point_j", "normal", "tangent", "shear_force")
    cols = ["step", "time", "block_i", "block_j", "kind", "mode"]
    for v in ("point_i", "point_j", "normal", "tangent"):
        cols += [f"{v}_{a}" for a in "xyz"]
    cols += ["gap", "normal_force"] + [f"shear_force_{a}" for a in "xyz"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for c in doc["contacts"]:
        row: dict[str, Any] = {"step": doc["step"], "time": repr(doc["time"])}
        for k, v in c.items():
            if k in vectors:
                row.update({f"{k}_{a}": repr(x) for a, x in zip("xyz", v, strict=True)})
            else:
                row[k] = repr(v) if isinstance(v, float) else v
        w.writerow([row[k] for k in cols])
    return buf.getvalue()


# --------------------------------------------------------------------------- routes

router = APIRouter(dependencies=[Depends(_client)])


@router.get("/processes", tags=["processes"], summary="List the processes")
def list_processes(root: RootDep) -> dict[str, Any]:
    return {"processes": [process_doc(p, root, full=False) for p in PROCESSES],
            "links": [{"href": f"{root}/processes", "rel": "self", "type": "application/json"}]}


@router.get("/processes/{process_id}", tags=["processes"], summary="Describe a process",
            responses=_problem_responses(404))
def get_process(process_id: str, root: RootDep) -> dict[str, Any]:
    if process_id not in PROCESSES:
        raise Problem(404, "no-such-process", "No such process",
                      f"there is no process '{process_id}' (known: {', '.join(PROCESSES)})")
    return process_doc(process_id, root, full=True)


_SCENE_BODY = {"requestBody": {"required": True, "description": "the scene", "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/Scene"}}}}}
_SUBMIT_RESPONSES: dict[int | str, dict[str, Any]] = {
    201: {"description": "Job created (or the job of an earlier request with the same "
                         "Idempotency-Key)", "model": StatusInfo,
          "headers": {"Location": {"schema": {"type": "string"},
                                   "description": "the job's URL"}}},
    **_problem_responses(401, 404, 413, 422, 429, 503),
}


@router.post("/processes/{process_id}/execution", tags=["processes"], status_code=201,
             summary="Run a process on a scene (creates a job)", openapi_extra=_SCENE_BODY,
             responses=_SUBMIT_RESPONSES, response_model=None)
def execute_process(process_id: str, data: SceneBody, settings: SettingsDep, store: StoreDep,
                    backend: BackendDep, client: ClientDep, root: RootDep,
                    key: IdempotencyKey = None) -> JSONResponse:
    if process_id not in PROCESSES:
        raise Problem(404, "no-such-process", "No such process",
                      f"there is no process '{process_id}' (known: {', '.join(PROCESSES)})")
    return _submit(process_id, data, settings=settings, store=store, backend=backend,
                   client=client, key=key, root=root)


@router.post("/jobs", tags=["jobs"], status_code=201, openapi_extra=_SCENE_BODY,
             summary="Submit a scene (creates a job; process from ?process=, the body's "
                     "'process' or the scene's analysis.type)",
             responses=_SUBMIT_RESPONSES, response_model=None)
def create_job(data: SceneBody, settings: SettingsDep, store: StoreDep, backend: BackendDep,
               client: ClientDep, root: RootDep, process: ProcessId | None = None,
               key: IdempotencyKey = None) -> JSONResponse:
    return _submit(process, data, settings=settings, store=store, backend=backend,
                   client=client, key=key, root=root)


@router.get("/jobs", tags=["jobs"], summary="List jobs (newest first)",
            response_model=JobList, responses=_problem_responses(401, 422))
def list_jobs(store: StoreDep, root: RootDep,
              status: Annotated[list[Status] | None, Query()] = None,
              process: ProcessId | None = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 50,
              offset: Annotated[int, Query(ge=0)] = 0) -> dict[str, Any]:
    jobs, total = store.list(status or (), process, limit, offset)
    query = "".join(f"&status={s}" for s in status or ()) + (
        f"&process={process}" if process else "")

    def page(off: int) -> str:
        return f"{root}/jobs?limit={limit}&offset={off}{query}"

    links = [{"href": page(offset), "rel": "self", "type": "application/json"}]
    if offset + len(jobs) < total:
        links.append({"href": page(offset + limit), "rel": "next", "type": "application/json"})
    if offset > 0:
        links.append({"href": page(max(0, offset - limit)), "rel": "prev",
                      "type": "application/json"})
    return {"jobs": [status_doc(j, root) for j in jobs], "numberMatched": total,
            "numberReturned": len(jobs), "links": links}


@router.get("/jobs/{job_id}", tags=["jobs"], summary="Status of a job",
            response_model=StatusInfo, responses=_problem_responses(401, 404))
def get_job(job: JobDep, root: RootDep) -> dict[str, Any]:
    return status_doc(job, root)


@router.delete("/jobs/{job_id}", tags=["jobs"], response_model=StatusInfo,
               summary="Cancel a job (partial results stay) or remove a finished one",
               responses={202: {"description": "cancel requested; the job is still stopping",
                                "model": StatusInfo}, **_problem_responses(401, 404)})
def dismiss_job(job: JobDep, store: StoreDep, backend: BackendDep, settings: SettingsDep,
                root: RootDep) -> Any:
    if job.status in ACTIVE:
        backend.cancel(job.id)
        deadline = time.monotonic() + settings.cancel_grace + 5.0
        current = store.get(job.id) or job
        while current.status in ACTIVE and time.monotonic() < deadline:
            time.sleep(0.05)
            current = store.get(job.id) or current
        return JSONResponse(status_doc(current, root),
                            status_code=200 if current.is_final else 202)
    shutil.rmtree(settings.job_dir(job.id), ignore_errors=True)
    store.delete(job.id)
    doc = status_doc(job, root)
    doc.update(status="dismissed", message="removed with its results",
               links=[lk for lk in doc["links"] if lk["rel"] == "self"])
    return doc


async def _events(store: JobStore, job_id: str, root: str) -> AsyncIterator[str]:
    """Server-sent events: one `status` event per change, closing after the final one."""
    yield "retry: 2000\n\n"
    last: tuple[float, str] | None = None
    n = 0
    beat = time.monotonic()
    while True:
        job = await run_in_threadpool(store.get, job_id)
        if job is None:
            yield "event: gone\ndata: {}\n\n"
            return
        if (job.updated, job.status) != last:
            last = (job.updated, job.status)
            n += 1
            yield f"event: status\nid: {n}\ndata: {json.dumps(status_doc(job, root))}\n\n"
            beat = time.monotonic()
        if job.is_final:
            return
        if time.monotonic() - beat > 15:
            yield ": keep-alive\n\n"
            beat = time.monotonic()
        await asyncio.sleep(0.25)


@router.get("/jobs/{job_id}/events", tags=["jobs"], response_class=StreamingResponse,
            summary="Progress as server-sent events (ends when the job ends)",
            responses={200: {"description": "`status` events with statusInfo documents",
                             "content": {"text/event-stream": {"schema": {"type": "string"}}}},
                       **_problem_responses(401, 404)})
def job_events(job: JobDep, store: StoreDep, root: RootDep) -> StreamingResponse:
    return StreamingResponse(_events(store, job.id, root), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


@router.get("/jobs/{job_id}/results", tags=["results"],
            summary="The job's result document (summary and links to the files)",
            responses=_problem_responses(401, 404))
def job_results(job: JobDep, settings: SettingsDep, root: RootDep) -> dict[str, Any]:
    _require_final(job)
    d = settings.job_dir(job.id)
    base = f"{root}/jobs/{job.id}/results"
    main = d / MAIN_ARTIFACT[job.process]
    files = [n for n in PROCESSES[job.process]["artifacts"] if (d / n).is_file()]
    if not files:
        raise Problem(404, "no-such-result", "No results",
                      f"job {job.id} {job.status} without results: {job.message}")
    doc: dict[str, Any] = {"jobID": job.id, "processID": job.process, "status": job.status,
                           "message": job.message, "partial": job.status != SUCCESSFUL}
    key = {"summary.json": "summary", "fos.json": "factor_of_safety",
           "blocks.json": "blocks"}[main.name]
    if main.is_file():
        doc[key] = json.loads(main.read_text(encoding="utf-8"))
    elif (d / RESULT_FILE).is_file():  # a run killed before it could write its summary
        from engine.summary import summarize

        doc[key] = summarize(d / RESULT_FILE)
    links = [{"href": f"{base}/{n}", "rel": "enclosure", "type": _FILE_TYPES[Path(n).suffix],
              "title": n} for n in files]
    if RESULT_FILE in files:
        links += [{"href": f"{base}/plots", "rel": "related", "type": "application/json",
                   "title": "PNG plots (made on first request)"},
                  {"href": f"{base}/contacts?format=csv", "rel": "related", "type": "text/csv",
                   "title": "contacts of the last recorded step (?step=N for another)"}]
    doc["links"] = links
    return doc


@router.get("/jobs/{job_id}/results/plots", tags=["results"], summary="List the PNG plots",
            responses=_problem_responses(401, 404))
def job_plots(job: JobDep, settings: SettingsDep, root: RootDep) -> dict[str, Any]:
    base = f"{root}/jobs/{job.id}/results/plots"
    return {"plots": [{"name": p.name, "href": f"{base}/{p.name}", "type": "image/png"}
                      for p in _plots(job, settings)]}


@router.get("/jobs/{job_id}/results/plots/{name}", tags=["results"], summary="One PNG plot",
            response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, **_problem_responses(401, 404)})
def job_plot(job: JobDep, name: str, settings: SettingsDep) -> FileResponse:
    for p in _plots(job, settings):
        if p.name == name:
            return FileResponse(p, media_type="image/png")
    raise Problem(404, "no-such-result", "No such plot", f"job {job.id} has no plot '{name}'")


@router.get("/jobs/{job_id}/results/contacts", tags=["results"],
            summary="Contacts of one recorded step as CSV or JSON",
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}},
                                         "application/json": {}}},
                       **_problem_responses(401, 404, 422)})
def job_contacts(job: JobDep, settings: SettingsDep,
                 step: Annotated[int | None, Query(description="solver step (default: last "
                                                               "recorded)")] = None,
                 format: Literal["csv", "json"] = "json") -> Response:
    doc = _contacts(job, settings, step)
    if format == "csv":
        return Response(contacts_csv(doc), media_type="text/csv; charset=utf-8")
    return JSONResponse(doc)


@router.get("/jobs/{job_id}/results/{name}", tags=["results"], response_class=FileResponse,
            summary="Download a result file (result.h5 supports HTTP Range requests)",
            responses={200: {"content": {"application/x-hdf5": {}, "application/json": {}}},
                       206: {"description": "part of the file (Range)",
                             "content": {"application/x-hdf5": {}}},
                       **_problem_responses(401, 404)})
def job_file(job: JobDep, name: str, settings: SettingsDep) -> FileResponse:
    path = _artifact(job, settings, name)
    return FileResponse(path, media_type=_FILE_TYPES[path.suffix],
                        filename=f"{job.id}-{name}" if path.suffix == ".h5" else None)


# --------------------------------------------------------------------------- app

_DOCS_HTML = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>PolyDDA API</title>
<link rel="icon" type="image/png" href="{root}/static/favicon-32x32.png">
<link rel="stylesheet" href="{root}/static/swagger-ui.css"></head>
<body><div id="swagger-ui"></div>
<script src="{root}/static/swagger-ui-bundle.js"></script>
<script src="{root}/static/docs-init.js"></script>
</body></html>
"""


def _openapi(app: FastAPI) -> Callable[[], dict[str, Any]]:
    """OpenAPI with the scene schema as components and every error as problem+json."""

    def build() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        from schemas.scene import scene_json_schema

        spec = get_openapi(title=app.title, version=app.version, description=app.description,
                           routes=app.routes)
        schemas = spec.setdefault("components", {}).setdefault("schemas", {})
        scene = scene_json_schema()
        defs = scene.pop("$defs", {})
        scene.pop("$schema", None)
        text = json.dumps({"Scene": scene, **defs}).replace("#/$defs/", "#/components/schemas/")
        schemas.update(json.loads(text))
        schemas["ProblemDoc"] = ProblemDoc.model_json_schema(
            ref_template="#/components/schemas/{model}")
        schemas["ProblemDoc"].pop("$defs", None)
        schemas["ProblemError"] = ProblemError.model_json_schema()
        for name in ("HTTPValidationError", "ValidationError"):
            schemas.pop(name, None)
        problem = {"application/problem+json": {
            "schema": {"$ref": "#/components/schemas/ProblemDoc"}}}
        keys_on = bool(app.state.settings.api_keys)
        if not keys_on:  # document the key only where it is asked for
            spec["components"].pop("securitySchemes", None)
        for path in spec["paths"].values():
            for op in path.values():
                if not keys_on:
                    op.pop("security", None)
                    op["responses"].pop("401", None)
                responses = op.get("responses", {})
                if "422" in responses:
                    responses["422"] = {"description": "Invalid input", "content": problem}
        app.openapi_schema = spec
        return spec

    return build


def create_app(settings: Settings | None = None) -> FastAPI:
    """The FastAPI application; the job table and backend start with its lifespan."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        store = JobStore(settings.db_path)
        backend = make_backend(settings, store)
        app.state.store, app.state.backend = store, backend
        await run_in_threadpool(backend.start)
        try:
            yield
        finally:
            await run_in_threadpool(backend.stop)

    app = FastAPI(title="PolyDDA", version="0.1.0", lifespan=lifespan, docs_url=None,
                  redoc_url=None,
                  description="3-D Discontinuous Deformation Analysis of rock blocks as jobs: "
                              "submit a scene, follow its progress, download its results.")
    app.state.settings = settings
    app.openapi = _openapi(app)  # type: ignore[method-assign]
    app.mount("/static", StaticFiles(directory=STATIC_DIR, check_dir=False), name="static")
    app.include_router(router)

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> Response:
        return exc.response(request.url.path)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        errors = [{"loc": ".".join(str(p) for p in e.get("loc", ())),
                   "msg": str(e.get("msg", ""))} for e in exc.errors()]
        return Problem(422, "invalid-request", "Invalid request",
                       "; ".join(f"{e['loc']}: {e['msg']}" for e in errors[:3]),
                       errors=errors).response(request.url.path)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        slug = {404: "not-found", 405: "method-not-allowed"}.get(exc.status_code, "http-error")
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:  # every method of the path, not just the first route's
            methods: set[str] = set()
            for route in request.app.router.routes:
                if route.matches(request.scope)[0] != Match.NONE:
                    methods |= set(getattr(route, "methods", None) or ())
            headers = {"Allow": ", ".join(sorted(methods))}
        return Problem(exc.status_code, slug, str(exc.detail), str(exc.detail),
                       headers=headers).response(request.url.path)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> Response:
        log.error("internal error on %s", request.url.path, exc_info=exc)
        return Problem(500, "internal-error", "Internal error",
                       "the service failed to answer; the error was logged").response(
            request.url.path)

    @app.get("/", tags=["service"], summary="Landing page")
    def landing(root: RootDep) -> dict[str, Any]:
        return {"title": "PolyDDA", "description": app.description, "links": [
            {"href": f"{root}/openapi.json", "rel": "service-desc",
             "type": "application/vnd.oai.openapi+json;version=3.1"},
            {"href": f"{root}/docs", "rel": "service-doc", "type": "text/html"},
            {"href": f"{root}/conformance",
             "rel": "http://www.opengis.net/def/rel/ogc/1.0/conformance"},
            {"href": f"{root}/processes",
             "rel": "http://www.opengis.net/def/rel/ogc/1.0/processes"},
            {"href": f"{root}/jobs", "rel": "http://www.opengis.net/def/rel/ogc/1.0/job-list"},
        ]}

    @app.get("/conformance", tags=["service"], summary="OGC conformance classes")
    def conformance() -> dict[str, Any]:
        base = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
        return {"conformsTo": [base + c for c in ("core", "json", "oas30", "job-list",
                                                  "dismiss")]}

    @app.get("/health", tags=["service"], summary="Liveness and queue counts")
    def health(store: StoreDep) -> dict[str, Any]:
        active = store.active()
        return {"status": "ok", "backend": settings.backend,
                "accepted": sum(j.status == "accepted" for j in active),
                "running": sum(j.status == "running" for j in active)}

    @app.get("/docs", include_in_schema=False)
    def docs(root: RootDep) -> HTMLResponse:
        return HTMLResponse(_DOCS_HTML.format(root=root))

    return app


def serve(host: str = "127.0.0.1", port: int = 8000, settings: Settings | None = None) -> None:
    """Run the service with uvicorn until interrupted (`polydda serve`)."""
    import uvicorn

    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.run(create_app(settings), host=host, port=port, timeout_graceful_shutdown=5,
                log_level="info")
