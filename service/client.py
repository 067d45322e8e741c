"""A small client of the REST service (`polydda submit SCENE.json --wait`).

A submission carries an Idempotency-Key, so retrying it is safe: answers 429 (quota, rate)
and 503 (queue unavailable), and connections cut before an answer, are retried after the
server's Retry-After (bounded), and a retry never makes a second job.
"""

from __future__ import annotations

import json
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

FINAL = ("successful", "failed", "dismissed")
#: answers a submission is retried after
RETRY_STATUSES = (429, 503)
#: longest pause between two attempts (s), whatever Retry-After says
MAX_PAUSE = 60.0


class ServiceError(RuntimeError):
    """The service answered with a problem document (`problem` holds it)."""

    def __init__(self, problem: dict[str, Any]) -> None:
        lines = [problem.get("detail") or problem.get("title") or "error"]
        lines += [f"{e['loc']}: {e['msg']}" if e.get("loc") else e["msg"]
                  for e in problem.get("errors") or []]
        super().__init__("\n".join(dict.fromkeys(lines)))
        self.problem = problem


class Unreachable(ConnectionError):
    """No server answered at the URL."""


def _check(r: httpx.Response) -> httpx.Response:
    if r.status_code >= 400:
        try:
            problem = r.json()
        except ValueError:
            problem = {"title": f"HTTP {r.status_code}", "detail": r.text[:500]}
        raise ServiceError(problem)
    return r


def retry_after(r: httpx.Response, attempt: int) -> float:
    """Seconds to wait before the next attempt: the server's Retry-After (seconds), else
    an exponential backoff; at most MAX_PAUSE."""
    try:
        pause = float(r.headers.get("Retry-After", ""))
    except ValueError:
        pause = 2.0 ** attempt
    return max(0.0, min(pause, MAX_PAUSE))


def post_with_retries(client: httpx.Client, path: str, body: bytes, params: dict[str, str],
                      retries: int, sleep: Callable[[float], None] = time.sleep,
                      ) -> httpx.Response:
    """POST `body` under one fresh Idempotency-Key, retried up to `retries` times after
    429 / 503 answers and cut connections; the last answer (or Unreachable)."""
    headers = {"Idempotency-Key": str(uuid.uuid4())}
    for attempt in range(retries + 1):
        try:
            r = client.post(path, content=body, params=params, headers=headers)
        except httpx.ConnectError as exc:
            if attempt == 0:  # nothing listens there: say so at once
                raise Unreachable(f"cannot reach the PolyDDA server at {client.base_url} "
                                  f"({exc}); is `polydda serve` running?") from None
            if attempt == retries:
                raise Unreachable(f"the server at {client.base_url} went away: {exc}") \
                    from None
            sleep(min(2.0 ** attempt, MAX_PAUSE))
            continue
        except httpx.TransportError as exc:  # cut off: the job may exist; the key tells
            if attempt == retries:
                raise Unreachable(f"no answer from {client.base_url}: {exc}") from None
            sleep(min(2.0 ** attempt, MAX_PAUSE))
            continue
        if r.status_code not in RETRY_STATUSES or attempt == retries:
            return r
        sleep(retry_after(r, attempt))
    raise AssertionError("unreachable")


def events(client: httpx.Client, job_url: str) -> Iterator[dict[str, Any]]:
    """The statusInfo documents of a job's server-sent event stream until it ends."""
    with client.stream("GET", f"{job_url}/events", timeout=httpx.Timeout(10, read=60)) as r:
        _check(r)
        kind, data = "message", []
        for line in r.iter_lines():
            if line == "":
                if data and kind == "status":
                    yield json.loads("\n".join(data))
                kind, data = "message", []
            elif line.startswith("event:"):
                kind = line[6:].strip()
            elif line.startswith("data:"):
                data.append(line[5:].lstrip())


def submit(url: str, scene_path: str | Path, wait: bool = True, process: str | None = None,
           api_key: str | None = None,
           on_status: Callable[[dict[str, Any]], None] | None = None,
           retries: int = 5) -> dict[str, Any]:
    """Submit a scene file to the service at `url`; with `wait`, follow it to its end.

    Returns the last statusInfo document (raises ServiceError for a problem answer,
    Unreachable when no server answers).
    """
    headers = {"Content-Type": "application/json"}
    if api_key:
        headers["X-API-Key"] = api_key
    body = Path(scene_path).read_bytes()
    params = {"process": process} if process else {}
    with httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=60) as client:
        r = _check(post_with_retries(client, "/jobs", body, params, retries))
        status = r.json()
        job_url = r.headers["Location"]
        if on_status is not None:
            on_status(status)
        while wait and status["status"] not in FINAL:
            try:
                for doc in events(client, job_url):
                    status = doc
                    if on_status is not None:
                        on_status(doc)
            except httpx.TransportError:
                time.sleep(1.0)  # the stream broke: reconnect after a pause
            try:
                status = _check(client.get(job_url)).json()
            except httpx.TransportError:
                time.sleep(1.0)
        return status


def print_status(doc: dict[str, Any]) -> None:
    """One line per status document on stderr (for `polydda submit --wait`)."""
    extra = f" t={doc['simulated_time']:.4g} s" if doc.get("simulated_time") is not None else ""
    msg = f" {doc['message']}" if doc.get("message") else ""
    print(f"{doc['jobID']} {doc['status']} {doc['progress']}%{extra}{msg}", file=sys.stderr)
