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
        keys_on = app.state.settings.keys_required
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
                if op.get("operationId") in ("createJob", "executeProcess"):
                    responses["201"]["links"] = _job_links()
                if op.get("operationId") == "getJob":
                    responses["200"]["links"] = {k: v for k, v in _job_links().items()
                                                 if k != "GetJob"}
        app.openapi_schema = spec
        return spec

    return build
