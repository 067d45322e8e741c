"""Submitting a scene: unwrap the body; cheap checks first (the disk, an idempotent
replay, the client's quota, the scene's structure and the service's limits), then the
scene's geometry (schemas.convert.build_model) in the validation pool apart from the API
process, within the client's budget; then commit the job row and hand it to the backend."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import shutil
import threading
import time
from collections.abc import Iterator
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


def check_structure(data: Any, settings: Settings) -> Any:
    """The validated Scene of `data` (Problem 422 naming every bad field): field types,
    names and references, the service's size limits. Milliseconds: nothing is cut or
    built (that is :func:`service.api.validation.ValidationPool.check`'s part).

    The service's size limits are checked right after the field types, before the
    format's own checks: a scene over a limit is refused at once.
    """
    from pydantic import ValidationError

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
    except SceneError as exc:
        raise invalid_scene(exc.problems) from None
    except RecursionError:
        raise invalid_scene([{"loc": "", "msg": "the scene is nested too deeply"}]) from None
    return scene


def validate_scene(data: Any, settings: Settings) -> Any:
    """The validated Scene of `data`, its model built too (in this process: the CLI's and
    tests' way; the API checks the geometry in its validation pool)."""
    from schemas.convert import build_model
    from schemas.errors import SceneError

    scene = check_structure(data, settings)
    try:
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


def canonical_json(value: Any) -> str:
    """`value` as canonical JSON (keys sorted, no spaces): the same scene written with its
    keys in another order or other spacing is the same request."""
    return json.dumps(value, ensure_ascii=False, sort_keys=True, separators=(",", ":"))


def _guess_process(process: str | None, scene_data: Any) -> str:
    """The process a request names or its scene's analysis.type implies (before the scene
    is validated: an invalid one is refused later anyway)."""
    if process is not None:
        return process
    analysis = scene_data.get("analysis") if isinstance(scene_data, dict) else None
    kind = analysis.get("type") if isinstance(analysis, dict) else None
    return default_process(kind if isinstance(kind, str) else "simulation")


class InFlight:
    """Submissions of each client being checked now: they count against its quota of
    unfinished jobs before their jobs exist."""

    def __init__(self) -> None:
        self._n: dict[str, int] = {}
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def hold(self, client: str, active: int, quota: int) -> Iterator[None]:
        """Count one submission of `client` (which has `active` unfinished jobs) while
        it is checked; 429 when that would exceed `quota`."""
        with self._lock:
            n = self._n.get(client, 0)
            if active + n + 1 > quota:
                raise quota_exceeded(active, quota, checking=n)
            self._n[client] = n + 1
        try:
            yield
        finally:
            with self._lock:
                self._n[client] -= 1
                if not self._n[client]:
                    del self._n[client]


def quota_exceeded(active: int, quota: int, checking: int = 0) -> Problem:
    """429: the client has `active` unfinished jobs and `checking` other submissions being
    checked (each counted apart: a submission being checked is not a job yet)."""
    jobs = f"{active} unfinished job{'s' if active != 1 else ''} (accepted or running)"
    more = f" and {checking} more submission{'s' if checking != 1 else ''} being checked" \
        if checking else ""
    return Problem(429, "quota-exceeded", "Too many unfinished jobs",
                   f"you have {jobs}{more}; the limit is {quota} at once. Wait for one to "
                   "finish or dismiss one.", headers={"Retry-After": "5"})


def _replay(store: JobStore, client: Client, key: str | None, digest: str) -> Any:
    """The job an earlier request with this Idempotency-Key created (None: none, or one
    that failed for a cause of ours, which does not hold its key); 422 when the key was
    used for a different request."""
    if key is None:
        return None
    job = store.by_key(client.id, key)
    if job is None or (job.status == "failed" and job.error_kind == "system"):
        return None
    if job.request_hash != digest:
        raise Problem(422, "idempotency-key-reused", "Idempotency-Key reused",
                      "this Idempotency-Key was used for a different request")
    return job


async def check_geometry(app_state: Any, settings: Settings, client: Client,
                         scene_data: Any) -> None:
    """Cut and build the scene in the validation pool (service.api.validation), within
    the client's budget (checked when the scene's turn comes) and the time limit; 422
    naming every problem, 429 over budget, 503 when no checking process could answer."""
    import anyio

    budget = app_state.validation_budget
    text = json.dumps(scene_data, ensure_ascii=False)
    async with app_state.validation_limiter:
        wait = budget.wait_for(client.id)
        if wait > 0:
            raise Problem(429, "validation-budget-exhausted", "Scene-checking budget used up",
                          f"this client may use {settings.validation_budget:g} s of scene "
                          "checking per minute (POLYDDA_VALIDATION_BUDGET); retry in "
                          f"{wait:.0f} s",
                          headers={"Retry-After": str(max(1, math.ceil(wait)))})
        start = time.monotonic()
        try:
            verdict = await anyio.to_thread.run_sync(
                _check, app_state.validation_pool, text, settings.validation_timeout,
                limiter=app_state.validation_threads)
        finally:
            budget.charge(client.id, time.monotonic() - start)
    if verdict.problems:
        raise invalid_scene(verdict.problems)


def _check(pool: Any, text: str, timeout: float) -> Any:
    """pool.check(text, timeout), its failures as problems: 422 past the time limit, 503
    when no checking process answered."""
    from service.api.validation import CheckTimeout, CheckUnavailable

    try:
        return pool.check(text, timeout)
    except CheckTimeout:
        raise invalid_scene([{"loc": "", "msg": (
            f"checking the scene's blocks took longer than {timeout:g} s, the most this "
            "service spends on one scene (POLYDDA_VALIDATION_TIMEOUT): make it smaller "
            "(fewer blocks or joints)")}]) from None
    except CheckUnavailable as exc:
        log.error("scene check failed: %s", exc)
        raise Problem(503, "check-unavailable", "Scene check unavailable",
                      f"the service could not check the scene ({exc}); retry later",
                      headers={"Retry-After": "10"}) from None


async def submit(process: str | None, data: Any, *, settings: Settings, store: JobStore,
                 backend: Backend, client: Client, key: str | None, root: str,
                 app_state: Any, shares: int = 1) -> JSONResponse:
    """Validate and create a job: 201 with its status (or the earlier job of the same
    Idempotency-Key, `Idempotent-Replayed: true`). A sweep with `shares` > 1 is a parent
    job of that many child jobs, each a share of the realisations (service.jobs.fanout).

    Cheap checks come first (the disk, an idempotent replay, the quota, the scene's
    structure), the geometry (cutting, overlaps) last, apart from the API process."""
    from starlette.concurrency import run_in_threadpool

    body_process, scene_data = unwrap(data)
    if process is not None and body_process is not None and process != body_process:
        raise invalid_scene([{"loc": "process", "msg": f"'{body_process}' in the body but "
                              f"'{process}' in the URL"}])
    await run_in_threadpool(check_disk, settings)
    guess = _guess_process(process or body_process, scene_data)
    request = canonical_json(scene_data)
    request = f"{guess}\n{request}" if shares == 1 else f"{guess}\n{shares}\n{request}"
    digest = hashlib.sha256(request.encode()).hexdigest()
    earlier = await run_in_threadpool(_replay, store, client, key, digest)
    if earlier is not None:
        return _created(earlier, root, replayed=True)
    active = await run_in_threadpool(store.active_count, client.id)
    with app_state.in_flight.hold(client.id, active, settings.client_quota):
        scene, children = await anyio_run(app_state, _structure, process or body_process,
                                          scene_data, settings, shares)
        await check_geometry(app_state, settings, client, scene_data)
        return await run_in_threadpool(
            _commit, process or body_process or default_process(scene.analysis.type),
            scene_data, children, digest, settings=settings, store=store, backend=backend,
            client=client, key=key, root=root)


async def anyio_run(app_state: Any, fn: Any, *args: Any) -> Any:
    """`fn(*args)` in a thread of the structure checks' own limiter (a flood of big scenes
    waits for it without holding the threads other requests need)."""
    import anyio

    return await anyio.to_thread.run_sync(fn, *args, limiter=app_state.structure_limiter)


def _structure(process: str | None, scene_data: Any, settings: Settings,
               shares: int) -> tuple[Any, list[str]]:
    """The validated Scene and the child scenes of a fanned-out sweep (422s)."""
    scene = check_structure(scene_data, settings)
    process = process or default_process(scene.analysis.type)
    if PROCESSES[process].check is not None:  # e.g. kinematics needs a slope face
        from schemas.errors import SceneError

        try:
            PROCESSES[process].check(scene)
        except SceneError as exc:
            raise invalid_scene(exc.problems) from None
    return scene, fan_out(process, scene_data, shares)


def _commit(process: str, scene_data: Any, children: list[str], digest: str, *,
            settings: Settings, store: JobStore, backend: Backend, client: Client,
            key: str | None, root: str) -> JSONResponse:
    """Commit the job row (and its children) and hand it to the backend; 201."""
    text = json.dumps(scene_data, ensure_ascii=False, separators=(",", ":"))
    check_disk(settings)
    try:
        job, created = store.submit(process=process, scene=text, client=client.id,
                                    quota=settings.client_quota, idempotency_key=key,
                                    request_hash=digest, children=children)
    except QuotaExceeded as exc:
        raise quota_exceeded(exc.active, exc.quota) from None
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
    current = job if created else (store.get(job.id) or job)  # a replay: its state now
    return _created(current, root, replayed=not created)


def _created(job: Any, root: str, replayed: bool) -> JSONResponse:
    headers = {"Location": f"{root}/jobs/{job.id}"}
    if replayed:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(status_doc(job, root), status_code=201, headers=headers)
