"""Errors as RFC 9457 `application/problem+json` documents, and the handlers that make every
error one (validation, HTTP errors, a client that went away, anything unexpected)."""

from __future__ import annotations

import logging
import sqlite3
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.routing import Mount

log = logging.getLogger("service.api")

PROBLEM_TYPE = "/problems/"
PROBLEM_JSON = "application/problem+json"
#: errors a problem document lists at most (`more_errors` counts the rest); with the
#: bounds on each field path and message (schemas.errors) a document stays under 50 kB
MAX_ERRORS = 50
#: characters of a problem's detail at most
MAX_DETAIL_CHARS = 2000


class Problem(Exception):
    """An error answered as `application/problem+json` (RFC 9457)."""

    def __init__(self, status: int, slug: str, title: str, detail: str = "",
                 errors: list[dict[str, str]] | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(detail or title)
        self.status, self.slug, self.title, self.detail = status, slug, title, detail
        self.errors, self.headers = errors, headers

    def response(self, instance: str = "") -> JSONResponse:
        """The problem document, bounded whatever the request held: at most MAX_ERRORS
        errors (`more_errors` says how many more), each path and message and the detail
        cut short and printable (schemas.errors.bounded)."""
        from schemas.errors import MAX_LOC_CHARS, MAX_MSG_CHARS, bounded

        body: dict[str, Any] = {"type": PROBLEM_TYPE + self.slug, "title": self.title,
                                "status": self.status,
                                "detail": bounded(self.detail, MAX_DETAIL_CHARS)}
        if instance:
            body["instance"] = bounded(instance, MAX_LOC_CHARS)
        if self.errors is not None:
            body["errors"] = [{"loc": bounded(str(e.get("loc", "")), MAX_LOC_CHARS),
                               "msg": bounded(str(e.get("msg", "")), MAX_MSG_CHARS)}
                              for e in self.errors[:MAX_ERRORS]]
            if len(self.errors) > MAX_ERRORS:
                body["more_errors"] = len(self.errors) - MAX_ERRORS
        return JSONResponse(body, status_code=self.status, headers=self.headers,
                            media_type=PROBLEM_JSON)


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
    more_errors: int | None = Field(
        None, description="errors found beyond those listed (a document lists at most "
                          f"{MAX_ERRORS})")


def invalid_scene(errors: list[dict[str, str]]) -> Problem:
    """422 naming every bad field (the first three in `detail`)."""
    lines = [f"{e['loc']}: {e['msg']}" if e["loc"] else e["msg"] for e in errors]
    more = f" (and {len(lines) - 3} more)" if len(lines) > 3 else ""
    return Problem(422, "invalid-scene", "Invalid scene", "; ".join(lines[:3]) + more,
                   errors=errors)


def no_such_job(job_id: str) -> Problem:
    """404 for a job that does not exist or belongs to someone else (indistinguishable)."""
    return Problem(404, "no-such-job", "No such job", f"there is no job '{job_id}'")


TITLES = {400: "Bad request", 401: "API key missing or wrong", 404: "Not found",
          405: "Method not allowed", 409: "Conflict", 413: "Request body too large",
          415: "Unsupported media type", 416: "Range not satisfiable",
          422: "Invalid input", 429: "Too many requests or unfinished jobs",
          503: "Job queue unavailable", 507: "Insufficient storage"}


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for these error codes (problem+json)."""
    ref = {"schema": {"$ref": "#/components/schemas/ProblemDoc"}}
    return {c: {"description": TITLES[c], "content": {PROBLEM_JSON: ref}} for c in codes}


def _route_methods(routes: list[Any], path: str) -> set[str]:
    """Methods of the routes (walking into included routers and mounts) that serve `path`."""
    methods: set[str] = set()
    for route in routes:
        included = getattr(route, "original_router", None)
        if included is not None:  # FastAPI keeps an included router as one route
            methods |= _route_methods(included.routes, path)
        elif getattr(route, "methods", None):
            if route.path_regex.match(path):
                methods |= set(route.methods)
        elif isinstance(route, Mount) and path.startswith(route.path.rstrip("/") + "/"):
            methods |= {"GET", "HEAD"}  # static files
    return methods


def allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path (for 405's Allow header)."""
    scope = request.scope  # a mount changes root_path; app_root_path is the app's own
    root = str(scope.get("app_root_path", scope.get("root_path", ""))).rstrip("/")
    path = request.url.path.removeprefix(root) or "/"
    methods = _route_methods(request.app.router.routes, path)
    if "GET" in methods:  # service.api.middleware.HeadAsGet
        methods.add("HEAD")
    return sorted(methods)


def install_handlers(app: FastAPI) -> None:
    """Make every error of `app` a problem document (never a stack trace)."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> Response:
        return exc.response(request.url.path)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        from schemas.errors import ECHO_CHARS, echo

        errors = [{"loc": ".".join(echo(str(p), ECHO_CHARS) for p in e.get("loc", ())),
                   "msg": str(e.get("msg", ""))} for e in exc.errors()]
        return Problem(422, "invalid-request", "Invalid request",
                       "; ".join(f"{e['loc']}: {e['msg']}" for e in errors[:3]),
                       errors=errors).response(request.url.path)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        slug = {404: "not-found", 405: "method-not-allowed",
                416: "range-not-satisfiable"}.get(exc.status_code, "http-error")
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # every method of the path, not just the first route's
            headers["Allow"] = ", ".join(allowed_methods(request))
        return Problem(exc.status_code, slug, str(exc.detail), str(exc.detail),
                       headers=headers or None).response(request.url.path)

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect) -> Response:
        # the client closed the connection while sending its body: nobody reads this
        log.info("client disconnected during %s %s", request.method, request.url.path)
        return Problem(400, "client-disconnected", "Client disconnected",
                       "the request body ended early").response(request.url.path)

    async def _storage(request: Request, exc: Exception) -> Response:
        from service.jobs.store import disk_full

        if not disk_full(exc):
            raise exc  # the error boundary (service.api.middleware) answers 500
        log.error("disk full on %s %s: %s", request.method, request.url.path, exc)
        return Problem(507, "insufficient-storage", "Insufficient storage",
                       "the service's disk is full; nothing was changed. Try again later",
                       headers={"Retry-After": "300"}).response(request.url.path)

    app.add_exception_handler(sqlite3.Error, _storage)
    app.add_exception_handler(OSError, _storage)
