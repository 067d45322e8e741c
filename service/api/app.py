"""The REST service: processes, jobs and their results (OGC API - Processes, Part 1 shape).

`create_app` assembles the API from service.api (problems, dependencies, submission,
results, metrics, OpenAPI, routes) around one Settings object; the job table and the backend
start with its lifespan, after the data directory's lock is taken (one server per data
directory). Run with `serve(host, port)` (`polydda serve`) or
`uvicorn --factory --no-proxy-headers service.api.app:create_app`.

Without API keys the factory refuses to build the app unless it is certain to listen on
loopback only, or `POLYDDA_ALLOW_OPEN_NETWORK` is set (:func:`network_guard`): `serve`
tells it the address; a foreign launcher (uvicorn --factory, gunicorn) calls it with none,
so there keys or the override are needed.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
import sys
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, Literal

from fastapi import FastAPI, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from prometheus_client import CollectorRegistry
from starlette.concurrency import run_in_threadpool

from service.api.addresses import ClientAddress, parse_networks
from service.api.builder import router as builder_router
from service.api.dependencies import RateLimiter, RootDep, StoreDep, _client
from service.api.middleware import ErrorBoundary, HeadAsGet, RequestMetrics, SecurityHeaders
from service.api.openapi import openapi_builder
from service.api.problems import Problem, install_handlers
from service.api.routes import router
from service.jobs.backend import Backend
from service.jobs.datadir import DataDirBusy, DataDirLock
from service.jobs.embedded import EmbeddedBackend
from service.jobs.rq import RqBackend
from service.jobs.store import JobStore
from service.settings import Settings

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parents[1] / "static"
#: /health's own threads (the job table and the queue asked apart from other requests)
_HEALTH_THREADS = ThreadPoolExecutor(2, thread_name_prefix="polydda-health")
VERSION = "0.1.0"
_DOCS_HTML = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>PolyDDA API</title>
<link rel="icon" type="image/png" href="{root}/static/favicon-32x32.png">
<link rel="stylesheet" href="{root}/static/swagger-ui.css"></head>
<body><div id="swagger-ui"></div>
<script src="{root}/static/swagger-ui-bundle.js"></script>
<script src="{root}/static/docs-init.js"></script>
</body></html>
"""


def make_backend(settings: Settings, store: JobStore) -> Backend:
    """The backend `settings.backend` names."""
    if settings.backend == "rq":
        return RqBackend(settings, store)
    return EmbeddedBackend(settings, store)


def _submission_state(app: FastAPI, settings: Settings) -> None:
    """What submissions share: the scene-checking pool and its thread limiter, the
    structure checks' limiter, the clients' checking budgets and in-flight counts."""
    import anyio

    from service.api.submission import InFlight
    from service.api.validation import ValidationBudget, shared_pool

    app.state.validation_pool = shared_pool(settings.validation_workers,
                                            settings.worker_env(), settings.worker_nice)
    app.state.validation_limiter = anyio.CapacityLimiter(settings.validation_workers)
    app.state.validation_threads = anyio.CapacityLimiter(settings.validation_workers)
    app.state.structure_limiter = anyio.CapacityLimiter(2)
    app.state.validation_budget = ValidationBudget(settings.validation_budget)
    app.state.in_flight = InFlight()


class OpenNetworkRefused(RuntimeError):
    """The app would serve the network without API keys: why, and what to do."""


def network_guard(settings: Settings, listen: str | None) -> None:
    """OpenNetworkRefused unless the app may serve without keys where it listens: keys are
    configured, the override is set, or `listen` (the address the server binds) is
    loopback. Without `listen` (a launcher that does not say) loopback is not certain."""
    if settings.keys_required or settings.allow_open_network:
        return
    if listen is not None and is_loopback(listen):
        return
    where = (f"to listen on {listen}" if listen is not None else
             "to serve: the app factory cannot know the address its launcher listens on "
             "(uvicorn --factory calls it without one), so loopback is not certain;")
    raise OpenNetworkRefused(
        f"refusing {where} without API keys: anyone who can reach it could submit jobs. "
        "Set POLYDDA_API_KEYS (see docs/service-security.md), listen on 127.0.0.1 with "
        "`polydda serve`, or set POLYDDA_ALLOW_OPEN_NETWORK=true")


def create_app(settings: Settings | None = None, lock: DataDirLock | None = None, *,
               listen: str | None = None) -> FastAPI:
    """The FastAPI application (OpenNetworkRefused without keys unless `listen`, the
    address its server binds, is loopback or the override is set: :func:`network_guard`;
    an in-process client such as a TestClient reaches it from no network and passes a
    loopback address). Its lifespan takes the data directory's lock (unless `lock` is
    held already), opens the job table and starts the backend."""
    settings = settings or Settings()
    network_guard(settings, listen)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        held = lock or DataDirLock(settings.data_dir).acquire()
        try:
            store = JobStore(settings.db_path)
            backend = make_backend(settings, store)
            app.state.store, app.state.backend = store, backend
            from service.api.metrics import JobCollector

            jobs = JobCollector(store, backend)
            app.state.metrics.register(jobs)
            _submission_state(app, settings)
            await run_in_threadpool(backend.start)
            try:
                yield
            finally:
                app.state.metrics.unregister(jobs)
                await run_in_threadpool(backend.stop)
        finally:
            held.release()

    app = FastAPI(title="PolyDDA", version=VERSION, lifespan=lifespan, docs_url=None,
                  redoc_url=None,
                  description="3-D Discontinuous Deformation Analysis of rock blocks as jobs: "
                              "submit a scene, follow its progress, download its results.")
    app.state.settings = settings
    app.state.rate_limiter = (RateLimiter(settings.rate_limit, settings.rate_burst)
                              if settings.rate_limit > 0 else None)
    app.state.auth_failures = RateLimiter(settings.auth_failures / 60.0, settings.auth_failures)
    app.state.metrics = CollectorRegistry(auto_describe=False)  # one per app (tests run many)
    app.openapi = openapi_builder(app)  # type: ignore[method-assign]
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins),
                           allow_methods=["GET", "HEAD", "POST", "DELETE"],
                           allow_headers=["Content-Type", "Content-Encoding", "X-API-Key",
                                          "Idempotency-Key", "Range"],
                           expose_headers=["Location", "Retry-After", "Idempotent-Replayed",
                                           "Content-Range", "X-PolyDDA-Recovered"])
    # added innermost first: the security headers wrap them all (the error boundary's
    # 500 has them too), the client's address is derived before any route reads it
    app.add_middleware(HeadAsGet)
    app.add_middleware(ClientAddress, trusted=parse_networks(settings.trusted_proxies))
    app.add_middleware(RequestMetrics, registry=app.state.metrics)
    app.add_middleware(ErrorBoundary)
    app.add_middleware(SecurityHeaders)
    app.mount("/static", StaticFiles(directory=STATIC_DIR, check_dir=False), name="static")
    app.include_router(router)
    app.include_router(builder_router)
    install_handlers(app)
    _service_routes(app, settings)
    return app


def _service_routes(app: FastAPI, settings: Settings) -> None:
    """Landing page, conformance, health, metrics, docs: open without an API key."""

    @app.get("/", tags=["service"], operation_id="landing", response_model=None,
             summary="Landing page (JSON; a browser asking for text/html, or ?f=html, gets "
                     "the home page listing its jobs)",
             responses={200: {"content": {"application/json": {},
                                          "text/html": {"schema": {"type": "string"}}}}})
    def landing(request: Request, root: RootDep, store: StoreDep,
                f: Literal["json", "html"] | None = None) -> dict[str, Any] | HTMLResponse:
        if f == "html" or (f is None and "text/html" in request.headers.get("accept", "")):
            return HTMLResponse(home_page(request, settings, store, root))
        return {"title": "PolyDDA", "description": app.description, "links": [
            {"href": f"{root}/openapi.json", "rel": "service-desc",
             "type": "application/vnd.oai.openapi+json;version=3.1"},
            {"href": f"{root}/docs", "rel": "service-doc", "type": "text/html"},
            {"href": f"{root}/conformance",
             "rel": "http://www.opengis.net/def/rel/ogc/1.0/conformance"},
            {"href": f"{root}/processes",
             "rel": "http://www.opengis.net/def/rel/ogc/1.0/processes"},
            {"href": f"{root}/jobs", "rel": "http://www.opengis.net/def/rel/ogc/1.0/job-list"},
            {"href": f"{root}/?f=html", "rel": "alternate", "type": "text/html",
             "title": "home page: your jobs with their viewers and reports"},
        ]}

    @app.get("/conformance", tags=["service"], summary="OGC conformance classes",
             operation_id="conformance")
    def conformance() -> dict[str, Any]:
        base = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
        return {"conformsTo": [base + c for c in ("core", "json", "oas30", "job-list",
                                                  "dismiss")]}

    @app.get("/health", tags=["service"], operation_id="health",
             summary="Health: the queue (Redis), live workers and job counts; 503 when jobs "
                     "cannot be queued",
             responses={503: {"description": "the job queue is unreachable"}})
    async def health(request: Request) -> JSONResponse:
        # on threads of its own: a flood of other requests cannot hold up the answer
        body = await asyncio.get_running_loop().run_in_executor(
            _HEALTH_THREADS, _health, request.app.state.store, request.app.state.backend)
        status = body["status"]
        return JSONResponse(body, status_code=503 if status == "unavailable" else 200)

    def _health(store: JobStore, backend: Backend) -> dict[str, Any]:
        checks = backend.health()
        status = checks.pop("status")
        try:
            counts = store.counts()
        except sqlite3.Error as exc:  # a full disk: SQLite cannot even read its table
            return {"status": "unavailable", "backend": settings.backend,
                    "version": VERSION, "accepted": None, "running": None, **checks,
                    "job_table": f"unreadable: {exc}"}
        return {"status": status, "backend": settings.backend, "version": VERSION,
                "accepted": counts["accepted"], "running": counts["running"], **checks}

    @app.get("/metrics", tags=["service"], operation_id="metrics",
             summary="Prometheus metrics: jobs by state, queue wait, run time, workers; "
                     "HTTP requests and their latency by route and status, 5xx answers",
             response_class=Response,
             responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
    def metrics() -> Response:
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

        return Response(generate_latest(app.state.metrics), media_type=CONTENT_TYPE_LATEST)

    @app.get("/docs", include_in_schema=False)
    def docs(root: RootDep) -> HTMLResponse:
        return HTMLResponse(_DOCS_HTML.format(root=root))


def over_tls(request: Request) -> bool:
    """True when the browser talks to the service over TLS: the request's scheme, which a
    trusted TLS-terminating proxy's X-Forwarded-Proto sets (service.api.addresses)."""
    return request.url.scheme in ("https", "wss")


def home_page(request: Request, settings: Settings, store: JobStore, root: str) -> str:
    """The home page HTML: the caller's newest jobs, or a key form when keys are needed
    (the key cookie marked Secure when the page came over TLS)."""
    from service.api.pages import home_html

    try:
        client = _client(request, settings, request.headers.get("x-api-key"))
    except Problem as exc:
        if exc.status != 401:
            raise
        html = home_html(root, None)
        if over_tls(request):
            html = html.replace(";SameSite=Strict'", ";SameSite=Strict;Secure'")
        return html
    jobs, total = store.list((), None, 100, 0, client=None if client.admin else client.id)
    return home_html(root, jobs, total, names=store.scene_names([j.id for j in jobs]))


def is_loopback(host: str) -> bool:
    """True if `host` (an address or a name) listens on loopback only."""
    import ipaddress

    if host.strip("[]").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def serve(host: str = "127.0.0.1", port: int = 8000, settings: Settings | None = None) -> int:
    """Run the service with uvicorn until interrupted (`polydda serve`); exit code 1 (one
    line on stderr) when another server owns the data directory, 2 when the app factory
    refuses `host` without keys (:func:`network_guard`)."""
    import uvicorn

    settings = settings or Settings()
    try:
        lock = DataDirLock(settings.data_dir).acquire()
    except DataDirBusy as exc:
        print(f"polydda serve: {exc}", file=sys.stderr)
        return 1
    try:
        app = create_app(settings, lock=lock, listen=host)
    except OpenNetworkRefused as exc:
        lock.release()
        print(f"polydda serve: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        uvicorn.run(app, host=host, port=port,
                    timeout_graceful_shutdown=5, timeout_keep_alive=int(settings.keep_alive),
                    log_level="info", proxy_headers=False)  # the app reads them itself
    finally:
        lock.release()
    return 0
