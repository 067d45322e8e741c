"""The job table: one SQLite file (WAL mode), the single record of every job.

Every API thread and every embedded job process opens its own short-lived connection;
writes that change a job's state are conditional on its current status, so two writers
(a job process and the supervisor) can never move a job backwards.
"""

from __future__ import annotations

import contextlib
import errno
import json
import sqlite3
import time
import uuid
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

ACCEPTED, RUNNING = "accepted", "running"
SUCCESSFUL, FAILED, DISMISSED = "successful", "failed", "dismissed"
ACTIVE = (ACCEPTED, RUNNING)
FINAL = (SUCCESSFUL, FAILED, DISMISSED)
STATUSES = ACTIVE + FINAL

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    process TEXT NOT NULL,
    status TEXT NOT NULL,
    client TEXT NOT NULL,
    idempotency_key TEXT,
    request_hash TEXT,
    scene TEXT NOT NULL,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    updated REAL NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    step INTEGER,
    simulated_time REAL,
    duration REAL,
    message TEXT NOT NULL DEFAULT '',
    error_kind TEXT,
    cancel_requested REAL,
    attempts INTEGER NOT NULL DEFAULT 0,
    worker_pid INTEGER
);
CREATE UNIQUE INDEX IF NOT EXISTS jobs_idempotency ON jobs(client, idempotency_key)
    WHERE idempotency_key IS NOT NULL;
CREATE INDEX IF NOT EXISTS jobs_status ON jobs(status, created);
CREATE INDEX IF NOT EXISTS jobs_client ON jobs(client, status);
"""
#: columns added since the first schema (added to an older job table on first use): a
#: sweep job fanned out in shares is a parent (`shares`, `children`: the JSON list of its
#: current child per share) of child jobs (`parent`, `share`)
_ADDED = {"parent": "TEXT", "share": "INTEGER", "shares": "INTEGER", "children": "TEXT"}


@dataclass
class JobRecord:
    """One row of the job table (without the scene text)."""

    id: str
    process: str
    status: str
    client: str
    idempotency_key: str | None
    request_hash: str | None
    created: float
    started: float | None
    finished: float | None
    updated: float
    progress: float
    step: int | None
    simulated_time: float | None
    duration: float | None
    message: str
    error_kind: str | None
    cancel_requested: float | None
    attempts: int
    worker_pid: int | None
    #: a child job: its parent's id and its share (0 .. shares-1)
    parent: str | None = None
    share: int | None = None
    #: a parent job: its number of shares and its current children (JSON list of ids)
    shares: int | None = None
    children: str | None = None

    @property
    def is_final(self) -> bool:
        return self.status in FINAL

    @property
    def is_parent(self) -> bool:
        """A job fanned out in child jobs (it runs nothing itself)."""
        return self.shares is not None

    @property
    def child_ids(self) -> list[str]:
        """A parent's current child per share (empty for other jobs)."""
        return json.loads(self.children) if self.children else []


_COLUMNS = ", ".join(f.name for f in fields(JobRecord))
#: fields a job's progress and outcome may change (the rest are fixed at submission)
UPDATABLE = frozenset({"status", "started", "finished", "updated", "progress", "step",
                       "simulated_time", "duration", "message", "error_kind",
                       "cancel_requested", "attempts", "worker_pid"})


def disk_full(exc: BaseException) -> bool:
    """True for the errors of a disk that takes no more writes: SQLite's SQLITE_FULL (13)
    and SQLITE_IOERR (10: its write-ahead log could not grow), OSError ENOSPC or EDQUOT
    (HDF5 and file writes)."""
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
        return (code is not None and code & 0xFF in (10, 13)) or "disk is full" in str(exc) \
            or "disk I/O error" in str(exc)
    if isinstance(exc, OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT) or "No space left" in str(exc)
    return False


class QuotaExceeded(Exception):
    """The client already has its quota of unfinished jobs."""

    def __init__(self, active: int, quota: int) -> None:
        super().__init__(f"{active} unfinished jobs; the quota is {quota}")
        self.active, self.quota = active, quota


class IdempotencyConflict(Exception):
    """An Idempotency-Key was reused with a different request."""


class JobStore:
    """Access to the job table at `path` (created with its schema on first use)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(_SCHEMA)
            have = {row[1] for row in db.execute("PRAGMA table_info(jobs)")}
            for name, kind in _ADDED.items():
                if name not in have:
                    db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {kind}")
            db.execute("CREATE INDEX IF NOT EXISTS jobs_parent ON jobs(parent)")

    @contextlib.contextmanager
    def connect(self) -> Iterator[sqlite3.Connection]:
        """A connection in autocommit mode; use `with db:`-less BEGIN IMMEDIATE for writes."""
        db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        try:
            db.execute("PRAGMA busy_timeout=30000")
            db.execute("PRAGMA synchronous=NORMAL")
            yield db
        finally:
            db.close()

    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE ... COMMIT, rolled back on error).

        SQLite rolls a transaction back by itself on some errors (a full disk); the
        ROLLBACK is then skipped, so the caller sees the error itself ("database or disk is
        full"), not "cannot rollback - no transaction is active".
        """
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        db.execute("ROLLBACK")
                raise

    # ------------------------------------------------------------------ reading
    @staticmethod
    def _record(row: Sequence[Any] | None) -> JobRecord | None:
        return None if row is None else JobRecord(*row)

    def get(self, job_id: str) -> JobRecord | None:
        with self.connect() as db:
            row = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return self._record(row)

    def scene(self, job_id: str) -> str:
        """The scene JSON text of a job (KeyError if there is no such job)."""
        with self.connect() as db:
            row = db.execute("SELECT scene FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise KeyError(job_id)
        return str(row[0])

    def scene_names(self, job_ids: Sequence[str]) -> dict[str, tuple[str, str]]:
        """(name, description) of each job's scene, read by SQLite from the stored JSON in
        one query (the home page's job names)."""
        if not job_ids:
            return {}
        marks = ", ".join("?" * len(job_ids))
        with self.connect() as db:
            rows = db.execute(
                "SELECT id, json_extract(scene, '$.name'), "
                "substr(json_extract(scene, '$.description'), 1, 200) FROM jobs "
                f"WHERE id IN ({marks}) AND json_valid(scene)", list(job_ids)).fetchall()
        return {str(i): (str(n) if isinstance(n, str) else "",
                         str(d) if isinstance(d, str) else "") for i, n, d in rows}

    def list(self, statuses: Iterable[str] = (), process: str | None = None, limit: int = 50,
             offset: int = 0, client: str | None = None) -> tuple[list[JobRecord], int]:
        """Jobs newest first, filtered by status, process and owner (`client`; None: every
        client's), and how many match in all."""
        where: list[str] = []
        args: list[Any] = []
        if client is not None:
            where.append("client = ?")
            args.append(client)
        statuses = list(statuses)
        if statuses:
            where.append(f"status IN ({', '.join('?' * len(statuses))})")
            args.extend(statuses)
        if process is not None:
            where.append("process = ?")
            args.append(process)
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        with self.connect() as db:
            total = db.execute(f"SELECT COUNT(*) FROM jobs{clause}", args).fetchone()[0]
            rows = db.execute(
                f"SELECT {_COLUMNS} FROM jobs{clause} ORDER BY created DESC, rowid DESC "
                "LIMIT ? OFFSET ?", [*args, limit, offset]).fetchall()
        return [JobRecord(*r) for r in rows], int(total)

    def active_count(self, client: str) -> int:
        """Unfinished jobs of a client that count against its quota (not parents)."""
        with self.connect() as db:
            return int(db.execute("SELECT COUNT(*) FROM jobs WHERE client = ? AND status IN "
                                  "(?, ?) AND shares IS NULL", (client, *ACTIVE)).fetchone()[0])

    def by_key(self, client: str, idempotency_key: str) -> JobRecord | None:
        """The client's job created with this Idempotency-Key, if any."""
        with self.connect() as db:
            row = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE client = ? AND "
                             "idempotency_key = ?", (client, idempotency_key)).fetchone()
        return self._record(row)

    def active(self) -> list[JobRecord]:
        """Accepted and running jobs that run something (not parents), oldest first."""
        with self.connect() as db:
            rows = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE status IN (?, ?) AND "
                              "shares IS NULL ORDER BY created, rowid", ACTIVE).fetchall()
        return [JobRecord(*r) for r in rows]

    def active_parents(self) -> list[JobRecord]:
        """Accepted and running parent jobs, oldest first."""
        with self.connect() as db:
            rows = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE status IN (?, ?) AND "
                              "shares IS NOT NULL ORDER BY created, rowid", ACTIVE).fetchall()
        return [JobRecord(*r) for r in rows]

    def children(self, parent_id: str) -> list[JobRecord]:
        """Every child job of a parent (resubmitted shares too), oldest first."""
        with self.connect() as db:
            rows = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE parent = ? "
                              "ORDER BY created, rowid", (parent_id,)).fetchall()
        return [JobRecord(*r) for r in rows]

    def expired(self, finished_before: float) -> list[JobRecord]:
        """Finished jobs that ended before `finished_before` (epoch s), oldest first."""
        with self.connect() as db:
            rows = db.execute(
                f"SELECT {_COLUMNS} FROM jobs WHERE status IN (?, ?, ?) AND finished IS NOT "
                "NULL AND finished < ? ORDER BY finished", (*FINAL, finished_before)).fetchall()
        return [JobRecord(*r) for r in rows]

    def counts(self) -> dict[str, int]:
        """Number of jobs in each status (every status present, 0 when none)."""
        with self.connect() as db:
            rows = db.execute("SELECT status, COUNT(*) FROM jobs GROUP BY status").fetchall()
        return {s: 0 for s in STATUSES} | {str(s): int(n) for s, n in rows}

    def durations(self, column: str) -> list[float]:
        """`queue_wait` (started - created) or `run_time` (finished - started) in s of every
        job that has both times."""
        expr = {"queue_wait": "started - created", "run_time": "finished - started"}[column]
        with self.connect() as db:
            rows = db.execute(f"SELECT {expr} FROM jobs WHERE {expr} IS NOT NULL").fetchall()
        return [float(r[0]) for r in rows]

    # ------------------------------------------------------------------ writing
    def submit(self, *, process: str, scene: str, client: str, quota: int,
               idempotency_key: str | None = None, request_hash: str | None = None,
               children: Sequence[str] = ()) -> tuple[JobRecord, bool]:
        """Create an accepted job in one transaction; `(job, created)`.

        With `children` (one scene text per share), the job is a parent of as many
        accepted child jobs, created in the same transaction; the quota counts the
        children, not the parent (which runs nothing).

        With an idempotency key already used by this client, the earlier job is returned
        (`created` False); a different request under the same key raises
        IdempotencyConflict. An earlier job that failed for a cause of ours (error kind
        `system`: queue unreachable, worker lost) does not hold its key: the retry creates a
        new job and the failed one keeps its record without the key. A client at its quota
        of unfinished jobs gets QuotaExceeded.
        """
        now = time.time()
        with self.transaction() as db:
            if idempotency_key is not None:
                row = db.execute(
                    f"SELECT {_COLUMNS} FROM jobs WHERE client = ? AND idempotency_key = ?",
                    (client, idempotency_key)).fetchone()
                if row is not None:
                    job = JobRecord(*row)
                    if job.request_hash != request_hash:
                        raise IdempotencyConflict(idempotency_key)
                    if not (job.status == FAILED and job.error_kind == "system"):
                        return job, False
                    db.execute("UPDATE jobs SET idempotency_key = NULL WHERE id = ?",
                               (job.id,))
            active = db.execute("SELECT COUNT(*) FROM jobs WHERE client = ? AND status IN "
                                "(?, ?) AND shares IS NULL", (client, *ACTIVE)).fetchone()[0]
            if active + max(1, len(children)) > quota:
                raise QuotaExceeded(int(active), quota)
            job_id = str(uuid.uuid4())
            ids = [str(uuid.uuid4()) for _ in children]
            db.execute(
                "INSERT INTO jobs (id, process, status, client, idempotency_key, request_hash, "
                "scene, created, updated, shares, children) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (job_id, process, ACCEPTED, client, idempotency_key, request_hash, scene, now,
                 now, len(children) or None, json.dumps(ids) if children else None))
            for k, (child_id, text) in enumerate(zip(ids, children, strict=True)):
                self._insert_child(db, child_id, job_id, k, process, client, text, now)
            row = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return JobRecord(*row), True

    @staticmethod
    def _insert_child(db: sqlite3.Connection, child_id: str, parent_id: str, share: int,
                      process: str, client: str, scene: str, now: float) -> None:
        db.execute("INSERT INTO jobs (id, process, status, client, scene, created, updated, "
                   "parent, share) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                   (child_id, process, ACCEPTED, client, scene, now, now, parent_id, share))

    def resubmit_child(self, parent_id: str, share: int, old_id: str) -> JobRecord | None:
        """A new accepted child for a parent's share in place of `old_id` (same scene);
        None when `old_id` is no longer the share's current child (another caller
        resubmitted it already) or the parent is final."""
        now = time.time()
        with self.transaction() as db:
            row = db.execute("SELECT children, status FROM jobs WHERE id = ?",
                             (parent_id,)).fetchone()
            if row is None or row[1] in FINAL:
                return None
            ids = json.loads(row[0] or "[]")
            if not 0 <= share < len(ids) or ids[share] != old_id:
                return None
            old = db.execute("SELECT process, client, scene FROM jobs WHERE id = ?",
                             (old_id,)).fetchone()
            if old is None:
                return None
            ids[share] = str(uuid.uuid4())
            self._insert_child(db, ids[share], parent_id, share, *old, now)
            db.execute("UPDATE jobs SET children = ? WHERE id = ?", (json.dumps(ids), parent_id))
            row = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE id = ?",
                             (ids[share],)).fetchone()
        return JobRecord(*row)

    def update(self, job_id: str, only_if: Iterable[str] | None = None, **values: Any) -> bool:
        """Set fields of a job (only while its status is in `only_if`); True if it changed."""
        bad = set(values) - UPDATABLE
        if bad:
            raise ValueError(f"cannot update {sorted(bad)}")
        values.setdefault("updated", time.time())
        sets = ", ".join(f"{k} = ?" for k in values)
        sql, args = f"UPDATE jobs SET {sets} WHERE id = ?", [*values.values(), job_id]
        if only_if is not None:
            allowed = list(only_if)
            sql += f" AND status IN ({', '.join('?' * len(allowed))})"
            args.extend(allowed)
        with self.transaction() as db:
            return db.execute(sql, args).rowcount == 1

    def claim(self, job_id: str, pid: int | None = None) -> bool:
        """Move an accepted job to running (False if it is no longer accepted)."""
        now = time.time()
        with self.transaction() as db:
            cur = db.execute(
                "UPDATE jobs SET status = ?, started = ?, updated = ?, attempts = attempts + 1, "
                "worker_pid = ?, progress = 0, step = NULL, simulated_time = NULL, message = '' "
                "WHERE id = ? AND status = ?", (RUNNING, now, now, pid, job_id, ACCEPTED))
            return cur.rowcount == 1

    def delete(self, job_id: str) -> bool:
        """Remove a finished job's row (True if one was removed)."""
        with self.transaction() as db:
            cur = db.execute(f"DELETE FROM jobs WHERE id = ? AND status IN ({', '.join('?' * 3)})",
                             (job_id, *FINAL))
            return cur.rowcount == 1
