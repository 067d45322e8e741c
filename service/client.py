"""A small client of the REST service (`polydda submit SCENE.json --wait`)."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

FINAL = ("successful", "failed", "dismissed")


class ServiceError(RuntimeError):
    """The service answered with a problem document (`problem` holds it)."""

    def __init__(self, problem: dict[str, Any]) -> None:
        lines = [problem.get("detail") or problem.get("title") or "error"]
        lines += [f"{e['loc']}: {e['msg']}" if e.get("loc") else e["msg"]
                  for e in problem.get("errors") or []]
        super().__init__("\n".join(dict.fromkeys(lines)))
        self.problem = problem


def _check(r: httpx.Response) -> httpx.Response:
    if r.status_code >= 400:
        try:
            problem = r.json()
        except ValueError:
            problem = {"title": f"HTTP {r.status_code}", "detail": r.text[:500]}
        raise ServiceError(problem)
    return r


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
           on_status: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Submit a scene file to the service at `url`; with `wait`, follow it to its end.

    Returns the last statusInfo document (raises ServiceError for a problem answer).
    """
    headers = {"Content-Type": "application/json"}
    if api_key:
        headers["X-API-Key"] = api_key
    body = Path(scene_path).read_bytes()
    params = {"process": process} if process else {}
    with httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=60) as client:
        r = _check(client.post("/jobs", content=body, params=params))
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
            status = _check(client.get(job_url)).json()
        return status


def print_status(doc: dict[str, Any]) -> None:
    """One line per status document on stderr (for `polydda submit --wait`)."""
    extra = f" t={doc['simulated_time']:.4g} s" if doc.get("simulated_time") is not None else ""
    msg = f" {doc['message']}" if doc.get("message") else ""
    print(f"{doc['jobID']} {doc['status']} {doc['progress']}%{extra}{msg}", file=sys.stderr)
