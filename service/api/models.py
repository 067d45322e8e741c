"""The API's own documents: job status (OGC statusInfo), job lists, process descriptions."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field

from service.jobs.processes import PROCESSES, RESULT_FILE
from service.jobs.store import JobRecord

Status = Literal["accepted", "running", "successful", "failed", "dismissed"]
FILE_TYPES = {".h5": "application/x-hdf5", ".json": "application/json", ".png": "image/png"}


class Link(BaseModel):
    href: str
    rel: str
    type: str | None = None
    title: str | None = None


class StatusInfo(BaseModel):
    """A job's status (OGC statusInfo plus the simulation's progress and its attempts)."""

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
    attempts: int = Field(0, ge=0, description="runs started so far: more than 1 when the "
                                               "job was re-queued after its worker was lost")
    links: list[Link] = []


class JobList(BaseModel):
    jobs: list[StatusInfo]
    numberMatched: int  # noqa: N815
    numberReturned: int  # noqa: N815
    links: list[Link]


def iso_time(t: float | None) -> str | None:
    """Epoch seconds as ISO 8601 UTC with milliseconds (`...Z`)."""
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
    if RESULT_FILE in PROCESSES[job.process].artifacts:
        links.append({"href": f"{href}/viewer", "rel": "related", "type": "text/html",
                      "title": "3-D viewer (follows the run)"})
    if job.parent is not None:
        links.append({"href": f"{root}/jobs/{job.parent}", "rel": "up",
                      "type": "application/json",
                      "title": f"the sweep job this is share {job.share} of"})
    for k, child in enumerate(job.child_ids):
        links.append({"href": f"{root}/jobs/{child}", "rel": "item",
                      "type": "application/json",
                      "title": f"share {k} of {job.shares}: child job"})
    if job.is_final:
        links += [{"href": f"{href}/results",
                   "rel": "http://www.opengis.net/def/rel/ogc/1.0/results",
                   "type": "application/json"},
                  {"href": f"{href}/report", "rel": "describedby", "type": "text/html",
                   "title": "printable report"}]
    return {
        "jobID": job.id, "processID": job.process, "type": "process", "status": job.status,
        "message": job.message, "error_kind": job.error_kind,
        "created": iso_time(job.created), "started": iso_time(job.started),
        "finished": iso_time(job.finished), "updated": iso_time(job.updated),
        "progress": int(job.progress), "step": job.step,
        "simulated_time": job.simulated_time, "duration": job.duration,
        "cancel_requested": job.cancel_requested is not None, "attempts": job.attempts,
        "links": links,
    }


def process_doc(process_id: str, root: str, full: bool) -> dict[str, Any]:
    """OGC process summary (or description with inputs and outputs when `full`)."""
    p = PROCESSES[process_id]
    doc: dict[str, Any] = {
        "id": p.id, "title": p.title, "description": p.description,
        "version": "1.0.0", "jobControlOptions": ["async-execute", "dismiss"],
        "outputTransmission": ["reference"],
        "links": [{"href": f"{root}/processes/{p.id}", "rel": "self",
                   "type": "application/json"},
                  {"href": f"{root}/processes/{p.id}/execution",
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
            "type": "string", "contentMediaType": FILE_TYPES[Path(name).suffix]}}
            for name in p.artifacts}
    return doc
