"""Request dependencies as `Annotated` aliases: settings, job table, backend, who is asking
(API key, admin, rate limit), the job asked for (owned by the caller, else 404), the scene
body (size-checked before it is read, JSON only)."""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import re
import threading
import time
import zlib
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Header, Request, Security
from fastapi.security import APIKeyHeader

from schemas.errors import unicode_problems
from service.api.problems import Problem, invalid_scene, no_such_job
from service.jobs.backend import Backend
from service.jobs.store import JobRecord, JobStore
from service.settings import Settings


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

api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                              description="needed when the service has API keys configured")


@dataclass(frozen=True)
class Client:
    """Who is asking: `id` owns the jobs it creates (`key:<hash>` or `ip:<address>`);
    `admin` sees every job. Without configured keys every client is its address: it sees,
    downloads and dismisses only the jobs of its address, and quotas and rate limits count
    per address (docs/service-security.md)."""

    id: str
    admin: bool

    def owns(self, job: JobRecord) -> bool:
        return self.admin or job.client == self.id


class RateLimiter:
    """Token buckets per client: `rate` requests per second, bursts of up to `burst`."""

    def __init__(self, rate: float, burst: int) -> None:
        self.rate, self.burst = rate, burst
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def wait_for(self, client: str) -> float:
        """Take one token; 0 if there was one, else the seconds until there is one."""
        now = time.monotonic()
        with self._lock:
            tokens, last = self._buckets.get(client, (float(self.burst), now))
            tokens = min(float(self.burst), tokens + (now - last) * self.rate)
            if tokens >= 1.0:
                self._buckets[client] = (tokens - 1.0, now)
                return 0.0
            self._buckets[client] = (tokens, now)
            if len(self._buckets) > 100_000:  # forget idle clients (their buckets are full)
                self._buckets = {k: v for k, v in self._buckets.items()
                                 if now - v[1] < self.burst / self.rate}
            return (1.0 - tokens) / self.rate

    def peek(self, client: str) -> float:
        """0 if the client has a token now (none is taken), else the seconds until it has."""
        now = time.monotonic()
        with self._lock:
            tokens, last = self._buckets.get(client, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - last) * self.rate)
        return 0.0 if tokens >= 1.0 else (1.0 - tokens) / self.rate


def _matches(key: str, keys: frozenset[str]) -> bool:
    return any(hmac.compare_digest(key.encode(), k.encode()) for k in keys)


#: the cookie a browser keeps the API key in (set by the home page; GET requests only)
KEY_COOKIE = "polydda_key"


def _address(request: Request) -> str:
    """The client's address as service.api.addresses derived it (a trusted proxy's
    X-Forwarded-For, else the connection's peer)."""
    return request.client.host if request.client else "unknown"


def _keyed_client(request: Request, settings: Settings, key: str | None) -> Client:
    """The client of a valid key; 401 for a missing or wrong one, 429 for an address that
    sent more than `auth_failures` wrong keys in a minute (checked before the key, so
    guessing cannot go faster)."""
    failures: RateLimiter = request.app.state.auth_failures
    address = _address(request)
    if key is not None:
        wait = failures.peek(address)
        if wait > 0:
            raise Problem(429, "too-many-wrong-keys", "Too many wrong API keys",
                          f"this address sent more than {settings.auth_failures} wrong API "
                          f"keys in a minute; retry in {wait:.0f} s",
                          headers={"Retry-After": str(max(1, math.ceil(wait)))})
    admin = key is not None and _matches(key, settings.admin_keys)
    if key is None or not (admin or _matches(key, settings.api_keys)):
        if key is not None:
            failures.wait_for(address)
        raise Problem(401, "unauthorized", "API key missing or wrong",
                      "send a valid key in the X-API-Key header (in a browser: enter it "
                      "on the home page)",
                      headers={"WWW-Authenticate": 'ApiKey header="X-API-Key"'})
    return Client("key:" + hashlib.sha256(key.encode()).hexdigest()[:16], admin)


def _client(request: Request, settings: SettingsDep,
            key: Annotated[str | None, Security(api_key_header)] = None) -> Client:
    """Who is asking (a valid key is required when keys are configured: the X-API-Key
    header, or for GET requests the browser's key cookie; without keys, the address);
    rate-limited."""
    if key is None and request.method in ("GET", "HEAD"):
        key = request.cookies.get(KEY_COOKIE)
    if settings.keys_required:
        client = _keyed_client(request, settings, key)
    else:
        client = Client("ip:" + _address(request), False)
    limiter: RateLimiter | None = request.app.state.rate_limiter
    if limiter is not None:
        wait = limiter.wait_for(client.id)
        if wait > 0:
            raise Problem(429, "rate-limited", "Too many requests",
                          f"this client may send {settings.rate_limit:g} requests per second "
                          f"(bursts of {settings.rate_burst}); retry in {wait:.2f} s",
                          headers={"Retry-After": str(max(1, math.ceil(wait)))})
    return client


ClientDep = Annotated[Client, Depends(_client)]


def _job(job_id: str, store: StoreDep, client: ClientDep, backend: BackendDep) -> JobRecord:
    """The job asked for, as it is now (a parent job refreshed from its children)."""
    from service.jobs.fanout import refresh

    job = store.get(job_id)
    if job is None or not client.owns(job):
        raise no_such_job(job_id)
    return refresh(store, backend, job)


JobDep = Annotated[JobRecord, Depends(_job)]


#: a media type: type "/" subtype, both RFC 9110 tokens
_MEDIA_TYPE = re.compile(r"^[!#$%&'*+.^_`|~0-9a-z-]+/[!#$%&'*+.^_`|~0-9a-z-]+$")


def _is_json(content_type: str | None) -> bool:
    """True for no Content-Type (JSON is assumed) and for application/json or
    application/*+json with well-formed parameters; False for anything else (`;;;===`)."""
    if content_type is None:
        return True
    media, _, params = content_type.partition(";")
    media = media.strip().lower()
    if not _MEDIA_TYPE.match(media):
        return False
    for param in params.split(";") if params else ():
        name, eq, value = param.strip().partition("=")
        if not (eq and name.strip() and value.strip()):
            return False
    return media == "application/json" or (media.startswith("application/")
                                           and media.endswith("+json"))


def _decode(raw: bytes, encoding: str | None, limit: int) -> bytes:
    """The body without its Content-Encoding (identity or gzip; 415 for others, 400 for a
    body that is not what its encoding says, 413 when it inflates beyond `limit`)."""
    codings = [c.strip().lower() for c in (encoding or "").split(",") if c.strip()]
    codings = [c for c in codings if c != "identity"]
    if not codings:
        return raw
    if codings != ["gzip"] and codings != ["x-gzip"]:
        raise Problem(415, "unsupported-content-encoding", "Unsupported content encoding",
                      f"send the body plain or gzip-compressed, not {encoding!r}",
                      headers={"Accept-Encoding": "gzip, identity"})
    inflate = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        out = inflate.decompress(raw, limit + 1)
        complete = inflate.eof and not inflate.unconsumed_tail
    except zlib.error as exc:
        raise Problem(400, "malformed-body", "Malformed body",
                      f"the body is not gzip data as its Content-Encoding says: {exc}") from None
    if len(out) > limit:
        raise Problem(413, "body-too-large", "Request body too large",
                      f"the body may have at most {limit:,} bytes (decompressed)")
    if not complete:
        raise Problem(400, "malformed-body", "Malformed body",
                      "the gzip data of the body is truncated")
    return out


async def _scene_body(request: Request, settings: SettingsDep) -> Any:
    """The request body as parsed JSON: 415 unless JSON, 413 above the size limit (checked
    before reading), 422 for malformed JSON (including numbers Python refuses to read)."""
    content_type = request.headers.get("content-type")
    if not _is_json(content_type):
        raise Problem(415, "unsupported-media-type", "Unsupported media type",
                      f"send the scene as application/json, not {content_type!r}",
                      headers={"Accept-Post": "application/json"})
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
    raw = _decode(b"".join(chunks), request.headers.get("content-encoding"), limit)
    if not raw.strip():
        raise invalid_scene([{"loc": "", "msg": "the request body is empty: send the scene "
                                                "as a JSON object"}])
    try:
        data = json.loads(raw)
    except UnicodeDecodeError:
        raise invalid_scene([{"loc": "", "msg": "not valid JSON: the body is not UTF-8"}]) \
            from None
    except json.JSONDecodeError as exc:
        raise invalid_scene([{"loc": "", "msg": f"not valid JSON: {exc.msg} at line "
                                                f"{exc.lineno} column {exc.colno}"}]) from None
    except ValueError as exc:  # e.g. an integer of more than 4,300 digits
        raise invalid_scene([{"loc": "", "msg": f"not a number this service reads: {exc}"}]) \
            from None
    except RecursionError:
        raise invalid_scene([{"loc": "", "msg": "not valid JSON: nested too deeply"}]) \
            from None
    problems = unicode_problems(data)  # "\ud800" alone: JSON, but no text to store
    if problems:
        raise invalid_scene(problems)
    return data


SceneBody = Annotated[Any, Depends(_scene_body)]
IdempotencyKey = Annotated[str | None, Header(
    alias="Idempotency-Key", max_length=200,
    description="a retry with the same key returns the job the first request created (a "
                "job that failed for a cause of the service's does not hold its key)")]
