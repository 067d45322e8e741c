"""The OpenAPI document: the scene schema as components, every error as problem+json, the
API key only where keys are on, and OpenAPI links from a created job to its status, events,
results and dismissal (clients and stateful fuzzers follow them with real job ids)."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.api.problems import PROBLEM_JSON, ProblemDoc, ProblemError

_JOB_ID = {"job_id": "$response.body#/jobID"}
#: link name -> operation that takes the job id of a statusInfo response
JOB_LINKS = {
    "GetJob": ("getJob", "the job's status"),
    "JobEvents": ("jobEvents", "the job's progress as server-sent events"),
    "GetResults": ("getResults", "the job's results document (when it has ended)"),
    "ListPlots": ("listPlots", "the plots of a simulation's result"),
    "GetContacts": ("getContacts", "the contacts of a simulation's last recorded step"),
    "GetFrames": ("getFrames", "the block motion of a simulation for the viewer (also while "
                               "it runs)"),
    "JobViewer": ("jobViewer", "the 3-D viewer of a simulation (HTML)"),
    "DismissJob": ("dismissJob", "cancel the job, or remove it when it has ended"),
}


def _job_links() -> dict[str, Any]:
    return {name: {"operationId": op, "parameters": dict(_JOB_ID), "description": text}
            for name, (op, text) in JOB_LINKS.items()}


def _problem(status: int, content: dict[str, Any]) -> dict[str, Any]:
    from service.api.problems import TITLES

    return {"description": TITLES[status], "content": content}


def limits_text(settings: Any) -> str:
    """The service's limits that refuse a scene the Scene schema allows (422 naming the
    setting), as they are configured on this server."""
    return (
        "\n\nBeyond the Scene schema, this server refuses (422, naming the field and the "
        "setting) a scene that is not a valid block system (open or self-intersecting "
        "block surfaces, overlapping blocks, unknown material or block names, joints "
        "without a domain, no blocks at all) and one over its limits: "
        f"{settings.max_vertices:,} vertices in all (POLYDDA_MAX_VERTICES), "
        f"{settings.max_blocks:,} blocks, explicit or cut from the domain "
        f"(POLYDDA_MAX_BLOCKS), {settings.max_duration:g} s simulated "
        f"(POLYDDA_MAX_DURATION), {settings.max_steps:,} steps of duration / time_step "
        f"(POLYDDA_MAX_STEPS), {settings.validation_timeout:g} s to check the blocks' "
        "geometry (POLYDDA_VALIDATION_TIMEOUT); a body over "
        f"{settings.max_body_bytes:,} bytes is 413 (POLYDDA_MAX_BODY_BYTES). 429: over "
        f"the client's {settings.client_quota} unfinished jobs (POLYDDA_CLIENT_QUOTA) or its "
        f"{settings.validation_budget:g} s of scene checking per minute "
        "(POLYDDA_VALIDATION_BUDGET); 507: the data disk has less than "
        f"{settings.min_free_bytes:,} bytes free (POLYDDA_MIN_FREE_BYTES).")


def openapi_builder(app: FastAPI) -> Callable[[], dict[str, Any]]:
    """The `app.openapi` function (built once, then cached on the app)."""

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
        problem = {PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/ProblemDoc"}}}
        settings = app.state.settings
        keys_on = settings.keys_required
        if not keys_on:  # document the key only where it is asked for
            spec["components"].pop("securitySchemes", None)
        limited = keys_on or settings.rate_limit > 0  # wrong keys, or every request
        for path in spec["paths"].values():
            for op in path.values():
                guarded = "security" in op  # the routes behind the API key dependency
                if not keys_on:
                    op.pop("security", None)
                    op["responses"].pop("401", None)
                elif guarded:
                    op["responses"].setdefault("401", _problem(401, problem))
                if guarded and limited:
                    op["responses"].setdefault("429", _problem(429, problem))
                if op.get("operationId") in ("createJob", "executeProcess"):
                    op["description"] = (op.get("description") or "") + limits_text(settings)
                responses = op.get("responses", {})
                if "422" in responses:
                    responses["422"] = {"description": "Invalid input", "content": problem}
                if op.get("operationId") in ("createJob", "executeProcess"):
                    responses["201"]["links"] = _job_links()
                if op.get("operationId") == "getJob":
                    responses["200"]["links"] = {k: v for k, v in _job_links().items()
                                                 if k != "GetJob"}
        app.openapi_schema = spec
        return spec

    return build
