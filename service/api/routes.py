"""The API's routes, thin: each reads its dependencies and calls one function of
service.api (submission, results) or the job table; errors are Problems."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import shutil
import time
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Header, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers
from starlette.responses import MalformedRangeHeader, RangeNotSatisfiable, StreamingResponse
from starlette.types import Receive, Scope, Send

from service.api import pages, results, submission
from service.api.dependencies import (
    BackendDep,
    ClientDep,
    IdempotencyKey,
    JobDep,
    RootDep,
    SceneBody,
    SettingsDep,
    StoreDep,
    _client,
)
from service.api.frames import encode_binary, to_json
from service.api.models import FILE_TYPES, JobList, Status, StatusInfo, process_doc, status_doc
from service.api.problems import Problem, problem_responses
from service.documents import contacts_csv
from service.jobs.fanout import MAX_SHARES
from service.jobs.fanout import cancel as cancel_job
from service.jobs.fanout import current as current_job
from service.jobs.processes import PROCESS_IDS, PROCESSES, RESULT_FILE, ProcessId
from service.jobs.store import ACTIVE, JobStore

log = logging.getLogger("service.api")

#: the largest offset SQLite takes (a signed 64-bit integer)
MAX_OFFSET = 2**63 - 1
#: bound of step indices in queries (a result never holds more steps)
MAX_STEP = 2**31 - 1

router = APIRouter(dependencies=[Depends(_client)])

#: `?shares=K`: a sweep fanned out over the queue as a parent job of K child jobs
Shares = Annotated[int, Query(ge=1, le=MAX_SHARES, description=(
    "process `sweep` only: fan the sweep out over the job queue in this many shares. The "
    "job is then a parent that runs nothing itself: it submits one child `sweep` job per "
    "share (its realisations in `sweep.realisations`; at most as many shares as "
    "realisations, else 422), links them (`item`; each child links its parent, `up`), "
    "reports the realisations done over all of them, cancels them all when it is "
    "cancelled, submits again once a share whose worker died, and its results are the "
    "children's sweep documents merged (while it runs: the realisations recorded so far)."
    " 1: a plain job"))]


class ProblemFileResponse(FileResponse):
    """FileResponse whose Range errors (400, 416) are problem documents, not plain text."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        http_range = Headers(scope=scope).get("range")
        if http_range is not None and scope["type"] == "http":
            try:
                self._parse_range_header(http_range, os.stat(self.path).st_size)
            except MalformedRangeHeader as exc:
                problem = Problem(400, "malformed-range", "Malformed Range header", exc.content)
                return await problem.response(scope["path"])(scope, receive, send)
            except RangeNotSatisfiable as exc:
                problem = Problem(416, "range-not-satisfiable", "Range not satisfiable",
                                  f"the file has {exc.max_size:,} bytes",
                                  headers={"Content-Range": f"bytes */{exc.max_size}"})
                return await problem.response(scope["path"])(scope, receive, send)
        await super().__call__(scope, receive, send)


def _no_such_process(process_id: str) -> Problem:
    return Problem(404, "no-such-process", "No such process",
                   f"there is no process '{process_id}' (known: {', '.join(PROCESS_IDS)})")


# --------------------------------------------------------------------------- processes


@router.get("/processes", tags=["processes"], summary="List the processes",
            operation_id="listProcesses")
def list_processes(root: RootDep) -> dict[str, Any]:
    return {"processes": [process_doc(p, root, full=False) for p in PROCESSES],
            "links": [{"href": f"{root}/processes", "rel": "self", "type": "application/json"}]}


@router.get("/processes/{process_id}", tags=["processes"], summary="Describe a process",
            operation_id="getProcess", responses=problem_responses(404))
def get_process(process_id: str, root: RootDep) -> dict[str, Any]:
    if process_id not in PROCESSES:
        raise _no_such_process(process_id)
    return process_doc(process_id, root, full=True)


_SCENE_BODY = {"requestBody": {"required": True, "description": "the scene", "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/Scene"}}}}}
_SUBMIT_RESPONSES: dict[int | str, dict[str, Any]] = {
    201: {"description": "Job created (or the job of an earlier request with the same "
                         "Idempotency-Key)", "model": StatusInfo,
          "headers": {"Location": {"schema": {"type": "string"},
                                   "description": "the job's URL"}}},
    **problem_responses(400, 401, 404, 413, 415, 422, 429, 503, 507),
}


@router.post("/processes/{process_id}/execution", tags=["processes"], status_code=201,
             summary="Run a process on a scene (creates a job)", openapi_extra=_SCENE_BODY,
             responses=_SUBMIT_RESPONSES, response_model=None, operation_id="executeProcess")
async def execute_process(process_id: str, data: SceneBody, request: Request,
                          settings: SettingsDep, store: StoreDep, backend: BackendDep,
                          client: ClientDep, root: RootDep, key: IdempotencyKey = None,
                          shares: Shares = 1) -> JSONResponse:
    if process_id not in PROCESSES:
        raise _no_such_process(process_id)
    return await submission.submit(process_id, data, settings=settings, store=store,
                                   backend=backend, client=client, key=key, root=root,
                                   app_state=request.app.state, shares=shares)


# --------------------------------------------------------------------------- jobs


@router.post("/jobs", tags=["jobs"], status_code=201, openapi_extra=_SCENE_BODY,
             summary="Submit a scene (creates a job; process from ?process=, the body's "
                     "'process' or the scene's analysis.type)",
             responses=_SUBMIT_RESPONSES, response_model=None, operation_id="createJob")
async def create_job(data: SceneBody, request: Request, settings: SettingsDep,
                     store: StoreDep, backend: BackendDep, client: ClientDep, root: RootDep,
                     process: ProcessId | None = None, key: IdempotencyKey = None,
                     shares: Shares = 1) -> JSONResponse:
    return await submission.submit(process, data, settings=settings, store=store,
                                   backend=backend, client=client, key=key, root=root,
                                   app_state=request.app.state, shares=shares)


@router.get("/jobs", tags=["jobs"], summary="List your jobs (newest first; admins: all)",
            response_model=JobList, responses=problem_responses(401, 422),
            operation_id="listJobs")
def list_jobs(store: StoreDep, client: ClientDep, root: RootDep,
              status: Annotated[list[Status] | None, Query()] = None,
              process: ProcessId | None = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 50,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> dict[str, Any]:
    jobs, total = store.list(status or (), process, limit, offset,
                             client=None if client.admin else client.id)
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
            response_model=StatusInfo, responses=problem_responses(401, 404),
            operation_id="getJob")
def get_job(job: JobDep, root: RootDep) -> dict[str, Any]:
    return status_doc(job, root)


@router.delete("/jobs/{job_id}", tags=["jobs"], response_model=StatusInfo,
               summary="Cancel a job (partial results stay) or remove a finished one (a sweep's "
                       "parent job: with its children)",
               responses={202: {"description": "cancel requested; the job is still stopping",
                                "model": StatusInfo}, **problem_responses(401, 404)},
               operation_id="dismissJob")
def dismiss_job(job: JobDep, store: StoreDep, backend: BackendDep, settings: SettingsDep,
                root: RootDep) -> Any:
    if job.status in ACTIVE:
        cancel_job(store, backend, job)  # a parent: every unfinished child
        deadline = time.monotonic() + settings.cancel_grace + 5.0
        current = current_job(store, backend, job.id) or job
        while current.status in ACTIVE and time.monotonic() < deadline:
            time.sleep(0.05)
            current = current_job(store, backend, job.id) or current
        return JSONResponse(status_doc(current, root),
                            status_code=200 if current.is_final else 202)
    for gone in (job.id, *(c.id for c in store.children(job.id) if c.is_final)):
        shutil.rmtree(settings.job_dir(gone), ignore_errors=True)
        forget_stored(settings, gone)
        store.delete(gone)
    doc = status_doc(job, root)
    doc.update(status="dismissed", message="removed with its results",
               links=[lk for lk in doc["links"] if lk["rel"] == "self"])
    return doc


def forget_stored(settings: SettingsDep, job_id: str) -> None:
    """Remove a dismissed job's objects from the object store, if there is one."""
    from service.jobs.objectstore import ResultStore

    store = ResultStore.of(settings)
    if store is not None:
        try:
            store.delete_job(job_id)
        except Exception as exc:  # the job's row goes; its objects are orphans then
            log.warning("objects of job %s not deleted: %s", job_id, exc)


#: one server-sent event of /jobs/{id}/events (Open API before 3.2: the schema of a
#: text/event-stream describes each event)
SSE_EVENT: dict[str, Any] = {
    "type": "object", "required": ["data"],
    "description": "`status`: `data` is the job's statusInfo document as JSON, `id` counts "
                   "the events; `gone`: the job was removed",
    "properties": {"event": {"type": "string", "enum": ["status", "gone"]},
                   "id": {"type": "string"},
                   "data": {"type": "string", "contentMediaType": "application/json"},
                   "retry": {"type": "integer", "minimum": 0}}}


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
                             "content": {"text/event-stream": {"schema": SSE_EVENT}}},
                       **problem_responses(401, 404)},
            operation_id="jobEvents")
def job_events(job: JobDep, store: StoreDep, root: RootDep) -> StreamingResponse:
    return StreamingResponse(_events(store, job.id, root), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


# --------------------------------------------------------------------------- results


@router.get("/jobs/{job_id}/results", tags=["results"],
            summary="The job's result document (summary and links to the files; for a "
                    "sweep's parent job while it runs, the realisations done so far)",
            responses=problem_responses(401, 404), operation_id="getResults")
def job_results(job: JobDep, settings: SettingsDep, store: StoreDep, backend: BackendDep,
                root: RootDep) -> dict[str, Any]:
    if job.is_parent and job.status in ACTIVE:  # a fanned-out sweep: the aggregate so far
        return results.so_far_document(job, store, backend, root)
    return results.results_document(job, settings, root)


@router.get("/jobs/{job_id}/results/plots", tags=["results"], summary="List the PNG plots",
            responses=problem_responses(401, 404), operation_id="listPlots")
def job_plots(job: JobDep, settings: SettingsDep, root: RootDep) -> dict[str, Any]:
    base = f"{root}/jobs/{job.id}/results/plots"
    return {"plots": [{"name": p.name, "href": f"{base}/{p.name}", "type": "image/png"}
                      for p in results.plots(job, settings)]}


@router.get("/jobs/{job_id}/results/plots/{name}", tags=["results"], summary="One PNG plot",
            response_class=FileResponse, operation_id="getPlot",
            responses={200: {"content": {"image/png": {}}}, **problem_responses(401, 404)})
def job_plot(job: JobDep, name: str, settings: SettingsDep) -> FileResponse:
    for p in results.plots(job, settings):
        if p.name == name:
            return FileResponse(p, media_type="image/png")
    raise Problem(404, "no-such-result", "No such plot", f"job {job.id} has no plot '{name}'")


@router.get("/jobs/{job_id}/results/contacts", tags=["results"],
            summary="Contacts of one recorded step as CSV or JSON", operation_id="getContacts",
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}},
                                         "application/json": {}}},
                       **problem_responses(401, 404, 422)})
def job_contacts(job: JobDep, settings: SettingsDep,
                 step: Annotated[int | None, Query(
                     ge=0, le=MAX_STEP, description="a recorded solver step (default: the "
                     "last recorded; a step not recorded: 422 naming the recorded range)")
                 ] = None,
                 format: Literal["csv", "json"] = "json") -> Response:
    doc = results.contacts(job, settings, step)
    if format == "csv":
        return Response(contacts_csv(doc), media_type="text/csv; charset=utf-8")
    return JSONResponse(doc)


@router.get("/jobs/{job_id}/results/frames", tags=["results"], operation_id="getFrames",
            summary="Block geometry and per-step block motion for the viewer (also while the "
                    "job runs: the steps written so far)",
            description="Recorded steps `start:stop:stride` (indices into the recorded "
                        "steps; `stop` is clipped to the steps written so far). Binary: a "
                        "uint32 header length, a JSON header, then 8-byte aligned arrays "
                        "(see service/frames.py); `format=json` gives the same as JSON.",
            responses={200: {"content": {"application/octet-stream": {},
                                         "application/json": {}}},
                       **problem_responses(401, 404, 422)})
def job_frames(job: JobDep, settings: SettingsDep,
               start: Annotated[int, Query(ge=0, le=MAX_STEP)] = 0,
               stop: Annotated[int | None, Query(ge=0, le=MAX_STEP)] = None,
               stride: Annotated[int, Query(ge=1, le=MAX_STEP)] = 1,
               geometry: bool = True, contacts: bool = False,
               format: Literal["binary", "json"] = "binary") -> Response:
    payload = results.frames(job, settings, start, stop, stride, geometry, contacts)
    headers = {"Cache-Control": "no-cache"}
    if format == "json":
        return JSONResponse(to_json(payload), headers=headers)
    return Response(encode_binary(payload), media_type="application/octet-stream",
                    headers=headers)


@router.get("/jobs/{job_id}/results/{name}", tags=["results"], response_class=FileResponse,
            summary="Download a result file (Range requests work; the result.h5 of a killed "
                    "run is served as a recovered copy any HDF5 reader opens, marked "
                    "X-PolyDDA-Recovered: true)", operation_id="getResultFile",
            responses={200: {"content": {"application/x-hdf5": {}, "application/json": {}}},
                       206: {"description": "part of the file (Range)",
                             "content": {"application/x-hdf5": {}}},
                       **problem_responses(401, 404, 416)})
def job_file(job: JobDep, name: str, settings: SettingsDep,
             range_header: Annotated[str | None, Header(alias="Range", include_in_schema=False)]
             = None) -> Response:
    size = results.stored_file(job, settings, name)
    if size is not None:  # in the object store: streamed from there
        return stored_response(job.id, name, size, settings, range_header)
    headers = {}
    if name == RESULT_FILE:
        path, recovered = results.readable_result(job, settings)
        if recovered:
            headers["X-PolyDDA-Recovered"] = "true"
    else:
        path = results.artifact(job, settings, name)
    return ProblemFileResponse(path, media_type=FILE_TYPES[path.suffix], headers=headers,
                               filename=f"{job.id}-{name}" if path.suffix == ".h5" else None)


def stored_response(job_id: str, name: str, size: int, settings: SettingsDep,
                    range_header: str | None) -> StreamingResponse:
    """A stored result file streamed from the object store: whole (200) or one byte range
    (206; 416 outside the file, 400 malformed; several ranges: the whole file)."""
    from service.jobs.objectstore import ResultStore

    store = ResultStore.of(settings)
    assert store is not None
    suffix = "." + name.rsplit(".", 1)[-1]
    headers = {"Accept-Ranges": "bytes"}
    if suffix == ".h5":
        headers["Content-Disposition"] = f'attachment; filename="{job_id}-{name}"'
    span = _byte_range(range_header, size) if range_header and "," not in range_header \
        else None
    if span is None:
        headers["Content-Length"] = str(size)
        return StreamingResponse(store.stream(job_id, name), media_type=FILE_TYPES[suffix],
                                 headers=headers)
    start, end = span
    headers |= {"Content-Range": f"bytes {start}-{end}/{size}",
                "Content-Length": str(end - start + 1)}
    return StreamingResponse(store.stream(job_id, name, start, end), status_code=206,
                             media_type=FILE_TYPES[suffix], headers=headers)


def _byte_range(header: str, size: int) -> tuple[int, int]:
    """(start, end) inclusive of one `bytes=a-b`, `bytes=a-` or `bytes=-n` range."""
    m = re.fullmatch(r"\s*bytes\s*=\s*(\d*)\s*-\s*(\d*)\s*", header)
    if m is None or (not m[1] and not m[2]):
        raise Problem(400, "malformed-range", "Malformed Range header",
                      f"expected bytes=START-END, got {header!r}")
    if not m[1]:
        start, end = max(0, size - int(m[2])), size - 1
    else:
        start = int(m[1])
        end = min(int(m[2]), size - 1) if m[2] else size - 1
    if start > end or start >= size or (not m[1] and int(m[2]) == 0):
        raise Problem(416, "range-not-satisfiable", "Range not satisfiable",
                      f"the file has {size:,} bytes", headers={"Content-Range": f"bytes */{size}"})
    return start, end


# --------------------------------------------------------------------------- pages

_HTML = {200: {"content": {"text/html": {"schema": {"type": "string"}}}}}


@router.get("/jobs/{job_id}/viewer", tags=["pages"], response_class=HTMLResponse,
            summary="3-D viewer of the job's blocks over the recorded steps (follows a "
                    "running job)", operation_id="jobViewer",
            responses={**_HTML, **problem_responses(401, 404)})
def job_viewer(job: JobDep, root: RootDep,
               max_frames: Annotated[int, Query(ge=2, le=100_000, description=(
                   "steps loaded at most: every k-th recorded step beyond"))] = 2000,
               play: Annotated[bool, Query(description=(
                   "start playing from the first frame once loaded (false: stay on it)"))]
               = True) -> HTMLResponse:
    if RESULT_FILE not in PROCESSES[job.process].artifacts:
        raise Problem(404, "no-such-result", "No viewer",
                      f"job {job.id} is a {job.process} job: it records no steps to view")
    return HTMLResponse(pages.viewer_html(job, root, max_frames=max_frames, play=play))


@router.get("/jobs/{job_id}/report", tags=["pages"], response_class=HTMLResponse,
            summary="Printable report of a finished job: scene, result, FS, plots, warnings, "
                    "versions", operation_id="jobReport",
            responses={**_HTML, **problem_responses(401, 404)})
def job_report(job: JobDep, settings: SettingsDep, store: StoreDep,
               root: RootDep) -> HTMLResponse:
    return HTMLResponse(results.report(job, settings, store.scene(job.id), root))
