"""ASGI middleware of the API, outermost first: an error boundary (an unexpected error is a
500 problem and the connection stays usable), request metrics (count and latency by route
and status), HEAD on every GET route, and security headers (a Content-Security-Policy
whose script hashes are those of the page's own inline scripts)."""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram

log = logging.getLogger("service.api")

Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGI = Callable[[MutableMapping[str, Any], Receive, Send], Awaitable[None]]

#: headers on every response
SECURITY_HEADERS = {"x-content-type-options": "nosniff", "x-frame-options": "DENY",
                    "referrer-policy": "no-referrer"}
#: the policy of everything that is not a page (JSON, files): nothing may run or be framed
CSP_NONE = "default-src 'none'; frame-ancestors 'none'"
#: the policy of pages; {scripts} are the hashes of the page's inline scripts
CSP_PAGE = ("default-src 'self'; script-src 'self'{scripts}; style-src 'self' 'unsafe-inline'; "
            "img-src 'self' data: blob:; connect-src 'self'; object-src 'none'; "
            "base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
_INLINE_SCRIPT = re.compile(rb"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.S | re.I)


def page_csp(html: bytes) -> str:
    """The page policy allowing exactly the inline scripts of `html` (by SHA-256)."""
    hashes = sorted({"'sha256-" + base64.b64encode(hashlib.sha256(body).digest()).decode()
                     + "'" for body in _INLINE_SCRIPT.findall(html)})
    return CSP_PAGE.format(scripts="".join(" " + h for h in hashes))


class SecurityHeaders:
    """nosniff, no framing, no referrer on every response; a CSP on each (a page's made
    from its own inline scripts, so pages need no change to keep working under it)."""

    def __init__(self, app: ASGI) -> None:
        self.app = app

    async def __call__(self, scope: MutableMapping[str, Any], receive: Receive,
                       send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start: Message | None = None
        body: list[bytes] = []

        async def send_wrapper(message: Message) -> None:
            nonlocal start
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", [])
                           if k.lower().decode() not in SECURITY_HEADERS]
                headers += [(k.encode(), v.encode()) for k, v in SECURITY_HEADERS.items()]
                message["headers"] = headers
                ctype = dict(headers).get(b"content-type", b"")
                if ctype.startswith(b"text/html"):
                    start = message  # held until the page is read
                    return
                headers.append((b"content-security-policy", CSP_NONE.encode()))
                await send(message)
            elif start is not None and message["type"] == "http.response.body":
                body.append(message.get("body", b""))
                if message.get("more_body", False):
                    return
                html = b"".join(body)
                start["headers"].append((b"content-security-policy", page_csp(html).encode()))
                await send(start)
                await send({"type": "http.response.body", "body": html, "more_body": False})
            else:
                await send(message)

        await self.app(scope, receive, send_wrapper)


class HeadAsGet:
    """HEAD of any GET route: run it as GET and send the headers only (a streamed
    response is told the client left once its headers are out)."""

    def __init__(self, app: ASGI) -> None:
        self.app = app

    async def __call__(self, scope: MutableMapping[str, Any], receive: Receive,
                       send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            return await self.app(scope, receive, send)
        started = False

        async def head_receive() -> Message:
            if started:
                return {"type": "http.disconnect"}
            return await receive()

        async def head_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                await send(message)
                await send({"type": "http.response.body", "body": b"", "more_body": False})

        await self.app(dict(scope, method="GET"), head_receive, head_send)


_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class RequestMetrics:
    """Prometheus metrics of the HTTP requests: count and latency by method, route
    (its template, e.g. /jobs/{job_id}) and status, and server errors (5xx) by route."""

    def __init__(self, app: ASGI, registry: CollectorRegistry) -> None:
        self.app = app
        self.requests = Counter("polydda_http_requests", "HTTP requests answered",
                                ["method", "route", "status"], registry=registry)
        self.latency = Histogram("polydda_http_request_duration_seconds",
                                 "time to answer an HTTP request (to its last byte)",
                                 ["method", "route", "status"], registry=registry,
                                 buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
                                          2.5, 5.0, 10.0, 30.0, 60.0))
        self.errors = Counter("polydda_http_server_errors", "HTTP answers with a 5xx status",
                              ["method", "route", "status"], registry=registry)

    async def __call__(self, scope: MutableMapping[str, Any], receive: Receive,
                       send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = 500

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = getattr(scope.get("route"), "path", None)
            if route is None:
                route = "/static" if scope["path"].startswith("/static/") else "unmatched"
            method = scope["method"] if scope["method"] in _METHODS else "other"
            labels = (method, route, str(status))  # bounded: no label a client can invent
            self.requests.labels(*labels).inc()
            self.latency.labels(*labels).observe(time.perf_counter() - t0)
            if status >= 500:
                self.errors.labels(*labels).inc()


class ErrorBoundary:
    """An error nothing else handled: logged once, answered as a 500 problem when no
    answer had started, and not raised on (so the server keeps the client's keep-alive
    connection instead of resetting it)."""

    def __init__(self, app: ASGI) -> None:
        self.app = app

    async def __call__(self, scope: MutableMapping[str, Any], receive: Receive,
                       send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = False

        async def send_wrapper(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        except Exception:
            log.exception("internal error on %s %s", scope["method"], scope["path"])
            if started:
                raise  # half an answer: the connection cannot be reused
            body = json.dumps({"type": "/problems/internal-error", "title": "Internal error",
                               "status": 500, "detail": "the service failed to answer; the "
                               "error was logged", "instance": scope["path"]}).encode()
            await send({"type": "http.response.start", "status": 500, "headers": [
                (b"content-type", b"application/problem+json"),
                (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})
