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


def sweep_parent(client: httpx.Client, scene: dict[str, Any], shares: int, out: Path, *,
                 retries: int = 5, poll: float = 0.5,
                 on_progress: Callable[[int, int, list[dict[str, Any]]], None] | None = None,
                 ) -> dict[str, Any]:
    """Run the scene's sweep on the server behind `client` as ONE parent job fanned out in
    `shares` child jobs (`POST /jobs?process=sweep&shares=K`; at most one share per
    realisation) and follow it; the server spreads the children over its workers, reports
    the progress of the whole, resubmits a share whose worker died and merges the results.

    `on_progress(done, n, children's statuses)` after each poll; Ctrl-C cancels the parent
    (and so every child); `out/jobs.json` remembers the parent, so a re-run follows it
    again while it runs (or takes its results) instead of submitting a new one. Writes and
    returns `out/sweep.json` (raises ServiceError when no share left results).
    """
    from service.sweep import spec_of_scene

    n = len(spec_of_scene(scene).indices())
    shares = max(1, min(shares, n))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "jobs.json"
    url = None
    if state_path.is_file():
        state = json.loads(state_path.read_text())
        if state.get("scene") == scene and state.get("shares") == shares:
            r = client.get(state["url"])
            if r.status_code == 200 and r.json()["status"] in ("successful", "accepted",
                                                                "running"):
                url = state["url"]
    if url is None:
        r = _check(post_with_retries(client, "/jobs", json.dumps(scene).encode(),
                                     {"process": "sweep", "shares": str(shares)}, retries))
        url = r.headers["Location"]
        state_path.write_text(json.dumps({"scene": scene, "shares": shares, "url": url}))
    try:
        while True:
            status = _check(client.get(url)).json()
            if on_progress is not None:
                children = [_check(client.get(lk["href"])).json()
                            for lk in status["links"] if lk["rel"] == "item"]
                on_progress(int(status.get("step") or 0), n, children)
            if status["status"] in FINAL:
                break
            time.sleep(poll)
    except KeyboardInterrupt:
        client.delete(url)
        raise
    r = client.get(url + "/results")
    if r.status_code != 200:
        raise ServiceError({"detail": f"the sweep job {status['status']}: "
                                      f"{status.get('message') or 'no results'}"})
    doc = r.json()["sweep"]
    base = url.rsplit("/", 1)[0]
    doc["job"] = {"url": url, "status": status["status"], "message": status.get("message")}
    doc["jobs"] = [{"url": f"{base}/{j['jobID']}", "status": j["status"],
                    "message": j["message"], "realisations": j["realisations"]}
                   for j in doc.get("jobs", [])]
    (out / "sweep.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    return doc


def sweep_jobs(client: httpx.Client, scene: dict[str, Any], shares: int, out: Path, *,
               retries: int = 5, poll: float = 0.5, resubmit: int = 2,
               on_progress: Callable[[int, int, list[dict[str, Any]]], None] | None = None,
               ) -> dict[str, Any]:
    """Run the scene's sweep as `shares` jobs of process `sweep` (each a share of the
    realisations) on the server behind `client`, wherever its workers are; merge them.

    Progress of the whole is the realisations done over all jobs; Ctrl-C cancels every job;
    a job that failed for a system reason (its worker died) is submitted again up to
    `resubmit` times (:func:`service.sweep.should_resubmit`, as the server does for a
    parent job's children), and redoes none of the realisations already done (the server keeps
    them by sweep); `out/jobs.json` remembers the jobs, so a re-run keeps those that
    succeeded (or still run) and submits again only the others. Writes and returns
    `out/sweep.json`. Kept for scripts that used it: `polydda sweep --server` now submits
    one parent job (:func:`sweep_parent`).
    """
    from engine.analyses.sweep import merge_documents, share_parts
    from service.sweep import share_scene, should_resubmit, spec_of_scene

    spec = spec_of_scene(scene)
    indices = spec.indices()
    parts = share_parts(indices, shares)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "jobs.json"
    urls: list[str | None] = [None] * len(parts)
    if state_path.is_file():
        state = json.loads(state_path.read_text())
        if state.get("scene") == scene and state.get("parts") == parts:
            urls = state["urls"]

    def save() -> None:
        state_path.write_text(json.dumps({"scene": scene, "parts": parts, "urls": urls}))

    for k, part in enumerate(parts):
        if urls[k] is not None:
            r = client.get(urls[k])
            if r.status_code == 200 and r.json()["status"] in ("successful", "accepted",
                                                                "running"):
                continue
        child = share_scene(scene, part)
        r = _check(post_with_retries(client, "/jobs", json.dumps(child).encode(),
                                     {"process": "sweep"}, retries))
        urls[k] = r.headers["Location"]
        save()
    save()
    tries = [1] * len(parts)
    try:
        while True:
            statuses = [_check(client.get(u)).json() for u in urls]
            for k, st in enumerate(statuses):  # a share whose worker died: once more
                if should_resubmit(st["status"], st.get("error_kind"), tries[k], resubmit):
                    tries[k] += 1
                    child = share_scene(scene, parts[k])
                    r = _check(post_with_retries(client, "/jobs", json.dumps(child).encode(),
                                                 {"process": "sweep"}, retries))
                    urls[k] = r.headers["Location"]
                    statuses[k] = r.json()
                    save()
            done = sum(int(s.get("step") or 0) if s["status"] != "successful" else len(p)
                       for s, p in zip(statuses, parts, strict=True))
            if on_progress is not None:
                on_progress(done, len(indices), statuses)
            if all(s["status"] in FINAL for s in statuses):
                break
            time.sleep(poll)
    except KeyboardInterrupt:
        for u in urls:
            client.delete(u)
        raise
    docs = [_check(client.get(u + "/results")).json()["sweep"]
            for u, s in zip(urls, statuses, strict=True) if s["status"] == "successful"]
    if not docs:
        raise ServiceError({"detail": "no job of the sweep succeeded: " + "; ".join(
            s.get("message") or s["status"] for s in statuses)})
    doc = merge_documents(docs)
    doc["jobs"] = [{"url": u, "status": s["status"], "message": s.get("message"),
                    "realisations": len(p)} for u, s, p in zip(urls, statuses, parts,
                                                              strict=True)]
    (out / "sweep.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    return doc
