"""Submitting a scene: unwrap the body, check the service's limits, validate the scene
completely (schemas.convert.build_model) before any job exists, guard the disk, commit the
job row and hand it to the backend."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import threading
from typing import Any

from fastapi.responses import JSONResponse

from service.api.dependencies import Client
from service.api.models import status_doc
from service.api.problems import Problem, invalid_scene
from service.jobs.backend import Backend
from service.jobs.processes import PROCESS_IDS, PROCESSES, default_process
from service.jobs.store import IdempotencyConflict, JobStore, QuotaExceeded
from service.settings import Settings, limit_problems

log = logging.getLogger("service.api")

#: scenes validated at once (cutting a big domain is CPU work; the rest wait their turn)
_VALIDATION_SLOTS = threading.BoundedSemaphore(4)


def unwrap(data: Any) -> tuple[str | None, Any]:
    """`(process, scene)` from a bare scene, `{"inputs": {"scene": ...}}` (OGC) or
    `{"process": ..., "scene": ...}`."""
    if not isinstance(data, dict):
        return None, data
    process = None
    if "process" in data:
        data = dict(data)
        process = data.pop("process")
        if not isinstance(process, str) or process not in PROCESSES:
            raise invalid_scene([{"loc": "process", "msg": f"unknown process {process!r} "
                                  f"(known: {', '.join(PROCESS_IDS)})"}])
    inputs = data.get("inputs")
    if set(data) == {"inputs"} and isinstance(inputs, dict) and "scene" in inputs:
        return process, inputs["scene"]
    if set(data) == {"scene"}:
        return process, data["scene"]
    return process, data


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
        raise invalid_scene([{"loc": "", "msg": "a scene must be a JSON object {...}"}])
    try:
        try:
            scene = Scene.model_validate(data)
        except ValidationError as exc:
            raise from_validation_error(exc, data, Scene) from None
        problems = limit_problems(scene, settings) or scene_problems(scene)
        if problems:
            raise invalid_scene(problems)
        build_model(scene)
    except SceneError as exc:
        raise invalid_scene(exc.problems) from None
    return scene


def check_disk(settings: Settings) -> None:
    """507 when the data directory's disk has less free space than `min_free_bytes`."""
    free = shutil.disk_usage(settings.data_dir).free
    if free < settings.min_free_bytes:
        raise Problem(507, "insufficient-storage", "Insufficient storage",
                      f"the service's disk has {free / 2**20:,.0f} MiB free, less than the "
                      f"{settings.min_free_bytes / 2**20:,.0f} MiB it keeps free "
                      "(POLYDDA_MIN_FREE_BYTES); try again later",
                      headers={"Retry-After": "300"})


def fan_out(process: str, scene_data: dict[str, Any], shares: int) -> list[str]:
    """The child scene texts of a sweep in `shares` shares (none for 1: a plain job); 422
    naming `shares` when the process is not `sweep` or there are fewer realisations."""
    from service.jobs.fanout import child_scenes

    if shares == 1:
        return []
    if process != "sweep":
        raise invalid_scene([{"loc": "shares", "msg": f"only a sweep is fanned out in shares; "
                              f"this is a {process} job (give shares=1)"}])
    try:
        return child_scenes(scene_data, shares)
    except ValueError as exc:
        raise invalid_scene([{"loc": "shares", "msg": str(exc)}]) from None


def queue_children(job: Any, store: JobStore, backend: Backend) -> None:
    """Hand a new parent's children to the backend; 503 when none could be queued."""
    from service.jobs.fanout import refresh

    errors = []
    for child in store.children(job.id):
        try:
            backend.submitted(child)
        except Exception as exc:
            log.warning("backend could not take job %s: %s", child.id, exc)
            errors.append(exc)
    if errors and len(errors) == job.shares:
        refresh(store, backend, job)  # failed (system): the key is free for a retry
        raise Problem(503, "queue-unavailable", "Job queue unavailable",
                      f"the job was recorded as failed: {errors[0]}; retry (with the same "
                      "Idempotency-Key) later", headers={"Retry-After": "30"})


def submit(process: str | None, data: Any, *, settings: Settings, store: JobStore,
           backend: Backend, client: Client, key: str | None, root: str,
           shares: int = 1) -> JSONResponse:
    """Validate and create a job: 201 with its status (or the earlier job of the same
    Idempotency-Key, `Idempotent-Replayed: true`). A sweep with `shares` > 1 is a parent
    job of that many child jobs, each a share of the realisations (service.jobs.fanout)."""
    body_process, scene_data = unwrap(data)
    if process is not None and body_process is not None and process != body_process:
        raise invalid_scene([{"loc": "process", "msg": f"'{body_process}' in the body but "
                              f"'{process}' in the URL"}])
    with _VALIDATION_SLOTS:
        scene = validate_scene(scene_data, settings)
    process = process or body_process or default_process(scene.analysis.type)
    if PROCESSES[process].check is not None:  # e.g. kinematics needs a slope face
        from schemas.errors import SceneError

        try:
            PROCESSES[process].check(scene)
        except SceneError as exc:
            raise invalid_scene(exc.problems) from None
    children = fan_out(process, scene_data, shares)
    text = json.dumps(scene_data, ensure_ascii=False, separators=(",", ":"))
    request = f"{process}\n{text}" if shares == 1 else f"{process}\n{shares}\n{text}"
    digest = hashlib.sha256(request.encode()).hexdigest()
    check_disk(settings)
    try:
        job, created = store.submit(process=process, scene=text, client=client.id,
                                    quota=settings.client_quota, idempotency_key=key,
                                    request_hash=digest, children=children)
    except QuotaExceeded as exc:
        raise Problem(429, "quota-exceeded", "Too many unfinished jobs",
                      f"you have {exc.active} jobs accepted or running; the limit is "
                      f"{exc.quota}. Wait for one to finish or dismiss one.",
                      headers={"Retry-After": "5"}) from None
    except IdempotencyConflict:
        raise Problem(422, "idempotency-key-reused", "Idempotency-Key reused",
                      "this Idempotency-Key was used for a different request") from None
    if created and job.is_parent:
        queue_children(job, store, backend)
    elif created:
        try:
            backend.submitted(job)
        except Exception as exc:
            log.warning("backend could not take job %s: %s", job.id, exc)
            raise Problem(503, "queue-unavailable", "Job queue unavailable",
                          f"the job was recorded as failed: {exc}; retry (with the same "
                          "Idempotency-Key) later", headers={"Retry-After": "30"}) from None
    headers = {"Location": f"{root}/jobs/{job.id}"}
    if not created:
        headers["Idempotent-Replayed"] = "true"
    current = job if created else (store.get(job.id) or job)  # a replay: its state now
    return JSONResponse(status_doc(current, root), status_code=201, headers=headers)
