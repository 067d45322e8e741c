"""Sweeps fanned out over the queue: a parent job of K child `sweep` jobs, one per share.

`POST /jobs?process=sweep&shares=K` creates a parent job and K accepted children (each the
scene with its share in `sweep.realisations`, see :func:`engine.analyses.sweep.share_parts`) in one
transaction; the children go to the backend's queue like any job (embedded workers, or
`polydda worker`s through Redis). The parent runs nothing: its state is derived from its
children's rows by :func:`refresh`, which the supervisor thread of either backend calls
every tick and every read of the parent calls too, so there is no process to lose and a
restarted server carries on. A refresh submits again, once, a share whose child failed for
a system reason (:func:`service.sweep.should_resubmit`, shared with the client's
`sweep_jobs`), and when every child has ended writes the parent's `sweep.json`, the
children's documents merged (:func:`engine.analyses.sweep.merge_documents`).
"""

from __future__ import annotations

import json
import logging
import time
from collections import Counter
from typing import Any, Protocol

from service.documents import write_json_atomic
from service.jobs.processes import SWEEPS_DIR
from service.jobs.store import (
    ACCEPTED,
    ACTIVE,
    DISMISSED,
    FAILED,
    RUNNING,
    SUCCESSFUL,
    JobRecord,
    JobStore,
)
from service.settings import Settings

log = logging.getLogger(__name__)


class JobQueue(Protocol):
    """What a refresh needs of a backend (service.jobs.backend.Backend, which calls into
    this module: it is named here by what it does, so neither module imports the other's
    type): its settings, to queue a job, to cancel one."""

    settings: Settings

    def submitted(self, job: JobRecord) -> None: ...

    def cancel(self, job_id: str) -> None: ...

#: the most shares a sweep may be fanned out in
MAX_SHARES = 256


def child_scenes(scene: dict[str, Any], shares: int) -> list[str]:
    """The scene texts of the children of a sweep in `shares` shares (ValueError when
    there are more shares than realisations)."""
    from engine.analyses.sweep import share_parts
    from service.sweep import share_scene, spec_of_scene

    indices = spec_of_scene(scene).indices()
    if shares > len(indices):
        raise ValueError(f"{shares} shares of {len(indices)} realisations: give at most "
                         f"{len(indices)}")
    return [json.dumps(share_scene(scene, p), ensure_ascii=False, separators=(",", ":"))
            for p in share_parts(indices, shares)]


def _share_size(store: JobStore, child: JobRecord) -> int:
    return len(json.loads(store.scene(child.id))["sweep"]["realisations"])


def _resubmit_lost(store: JobStore, backend: JobQueue, parent: JobRecord,
                   kids: list[JobRecord]) -> list[JobRecord]:
    """The parent's current children, a share whose child failed for a system reason
    submitted again (unless the parent is being cancelled)."""
    from service.sweep import should_resubmit

    if parent.cancel_requested is not None:
        return kids
    tries = Counter(c.share for c in store.children(parent.id))
    out = []
    for kid in kids:
        if should_resubmit(kid.status, kid.error_kind, tries[kid.share]):
            new = store.resubmit_child(parent.id, int(kid.share or 0), kid.id)
            if new is not None:
                log.warning("share %s of sweep job %s failed (%s); submitted again as job %s",
                            kid.share, parent.id, kid.message, new.id)
                try:
                    backend.submitted(new)
                except Exception as exc:  # the backend recorded it as failed
                    log.warning("share %s of sweep job %s not queued: %s", kid.share,
                                parent.id, exc)
                kid = store.get(new.id) or new
        out.append(kid)
    return out


def _merged(store: JobStore, backend: JobQueue, kids: list[JobRecord]) -> dict[str, Any] | None:
    """The children's sweep documents merged (those that have one), with the list of
    jobs; None when no child left one."""
    from engine.analyses.sweep import merge_documents
    from service.jobs.objectstore import ResultStore

    objects = ResultStore.of(backend.settings)
    docs = []
    for kid in kids:
        path = backend.settings.job_dir(kid.id) / "sweep.json"
        if not path.is_file() and objects is not None and kid.is_final:
            objects.fetch_job(kid.id, path.parent)  # ran on a worker of another host
        if path.is_file():
            docs.append(json.loads(path.read_text(encoding="utf-8")))
    if not docs:
        return None
    doc = merge_documents(docs)
    doc["jobs"] = [{"jobID": k.id, "status": k.status, "message": k.message,
                    "realisations": _share_size(store, k)} for k in kids]
    return doc


def _state(store: JobStore, backend: JobQueue, parent: JobRecord,
           kids: list[JobRecord]) -> dict[str, Any]:
    """The parent's status, progress and message from its current children."""
    sizes = [_share_size(store, k) for k in kids]
    n = sum(sizes)
    done = sum(s if k.status == SUCCESSFUL else int(k.step or 0)
               for k, s in zip(kids, sizes, strict=True))
    counts = Counter(k.status for k in kids)
    states = ", ".join(f"{v} {s}" for s, v in counts.items())
    started = [k.started for k in kids if k.started is not None]
    values: dict[str, Any] = {"progress": 100.0 * done / n, "step": done,
                              "started": min(started) if started else None,
                              "message": f"{done} of {n} realisations done ({states})"}
    if any(k.status in ACTIVE for k in kids):
        busy = any(k.status != ACCEPTED for k in kids)
        return values | {"status": RUNNING if busy else ACCEPTED}
    failed = [k for k in kids if k.status == FAILED]
    values["finished"] = max(k.finished or time.time() for k in kids)
    if failed:
        kinds = {k.error_kind for k in failed}
        kept = "; the other shares' results are kept" if len(failed) < len(kids) else ""
        return values | {"status": FAILED, "error_kind": "system" if kinds == {"system"}
                         else "model", "message": f"{len(failed)} of {len(kids)} shares "
                         f"failed: " + "; ".join(k.message for k in failed) + kept}
    if counts[DISMISSED]:
        return values | {"status": DISMISSED, "message": f"cancelled after {done} of {n} "
                         "realisations; partial aggregate kept"}
    return values | {"status": SUCCESSFUL, "progress": 100.0}


def refresh(store: JobStore, backend: JobQueue, parent: JobRecord) -> JobRecord:
    """Bring a parent job's row up to date with its children (see the module); the row."""
    if not parent.is_parent or parent.is_final:
        return parent
    kids = [store.get(c) for c in parent.child_ids]
    if any(k is None for k in kids):  # a child removed by hand: the share is lost
        kids = [k for k in kids if k is not None]
        if not kids:
            store.update(parent.id, only_if=ACTIVE, status=FAILED, error_kind="system",
                         finished=time.time(), message="its child jobs were removed")
            return store.get(parent.id) or parent
    current = _resubmit_lost(store, backend, parent, [k for k in kids if k is not None])
    values = _state(store, backend, parent, current)
    if values["status"] not in ACTIVE:
        doc = _merged(store, backend, current)
        if doc is not None:  # written before the final status, so a reader finds it
            write_json_atomic(backend.settings.job_dir(parent.id) / "sweep.json", doc)
            if values["status"] == SUCCESSFUL:
                a = doc[doc["spec"]["mode"]]
                values["message"] = (f"{doc['spec']['mode']}: probability of failure "
                                     f"{100 * a['probability_of_failure']:.2f} % over "
                                     f"{a['n']} realisations ({len(current)} shares)")
    if any(getattr(parent, k) != v for k, v in values.items()):
        store.update(parent.id, only_if=ACTIVE, **values)
        return store.get(parent.id) or parent
    return parent


def refresh_all(store: JobStore, backend: JobQueue) -> None:
    """Refresh every unfinished parent job (the supervisor's round)."""
    for parent in store.active_parents():
        try:
            refresh(store, backend, parent)
        except Exception:  # one bad parent must not stop the others' bookkeeping
            log.exception("sweep job %s not refreshed", parent.id)


def current(store: JobStore, backend: JobQueue, job_id: str) -> JobRecord | None:
    """A job's row now (a parent's refreshed first)."""
    job = store.get(job_id)
    return None if job is None else refresh(store, backend, job)


def cancel(store: JobStore, backend: JobQueue, job: JobRecord) -> None:
    """Cancel a job; for a parent, every unfinished child (it ends when they have)."""
    if not job.is_parent:
        backend.cancel(job.id)
        return
    store.update(job.id, only_if=ACTIVE, cancel_requested=time.time())
    for child_id in job.child_ids:
        child = store.get(child_id)
        if child is not None and child.status in ACTIVE:
            backend.cancel(child_id)


def so_far(store: JobStore, backend: JobQueue, job: JobRecord) -> dict[str, Any]:
    """The aggregate of a running parent's realisations recorded so far."""
    from service.sweep import document_so_far

    return document_so_far(json.loads(store.scene(job.id)),
                           backend.settings.data_dir / SWEEPS_DIR)
