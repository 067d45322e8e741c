"""How a result file's steps reach the disk: batches, flushes, chunks and compression.

The writer (:mod:`engine.results.writer`) decides what a step holds and where each value
goes (:mod:`engine.results.layout`); a :class:`Batcher` it owns decides when and how the
values are written. Steps are appended to resizable, chunked datasets in HDF5
single-writer/multiple-reader (SWMR) mode, in batches, each followed by a flush (at the
first step, then at least every `flush_seconds` of wall time, or every `flush_every`
steps), so a run that is killed keeps every flushed step. Large steps are compressed
(HDF5's shuffle + deflate, done here) by a background thread while the run goes on and
written as whole-step chunks.

The chunk policy lives here too: which datasets are compressed, their chunk shapes, and
which are written chunk by chunk, since whole-step chunks are what the thread compresses.
"""

from __future__ import annotations

import time
import zlib
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import h5py
import numpy as np

#: Chunking policy. HDF5 in SWMR mode does not reuse freed file space, so a compressed chunk
#: that is rewritten (it grew) leaks its old copy. Steps of at least _COMPRESS_MIN bytes get
#: their own compressed chunks, written once; smaller ones share uncompressed chunks of about
#: _SHARED_CHUNK bytes, rewritten in place.
_COMPRESS_MIN = 4096
_SHARED_CHUNK = 8 * 1024
_CHUNK_MAX = 8 * 1024 * 1024
#: pending steps are written and flushed once they hold about this many bytes
_FLUSH_BYTES = 32 * 1024 * 1024
#: batches of large steps that may wait for the writer's thread (which derives the VTKHDF
#: points and compresses while the run goes on) before `record` waits too
_MAX_INFLIGHT = 2
#: contacts (a variable count per step) are compressed in models of at least this many
#: blocks, in chunks of `n_blocks` rows (a rewritten partial chunk leaks < 1 chunk per step)
_CONTACT_COMPRESS_BLOCKS = 100


@dataclass
class PendingStep:
    """One recorded step held in memory until the next flush."""

    arrays: dict[str, np.ndarray]  # history arrays by name, (n, *tail) each
    contacts: dict[str, np.ndarray]  # contact fields (empty: no contacts this step)
    contact_end: int  # contact rows of all steps up to this one
    scalars: tuple[Any, ...]  # step, time, dt, open_close_iterations, max_penetration, energies


#: The values of every growing dataset by its path for pending steps (step indices from the
#: second argument on), in the order they are written. Called by the writer's thread for
#: large steps: numpy only, no HDF5.
StepValues = Callable[[list[PendingStep], int], list[tuple[str, np.ndarray]]]


@dataclass
class _Batch:
    """Steps prepared for writing: values per dataset path, in write order, and the
    compressed whole-step chunks of the datasets written chunk by chunk."""

    m: int
    writes: list[tuple[str, np.ndarray]]
    chunks: dict[str, list[bytes]]


@dataclass
class _Job:
    """Pending steps handed over for writing (from step index `k0`), and the thread's
    :class:`_Batch` being prepared from them (None: prepared when written)."""

    pend: list[PendingStep]
    k0: int
    future: Future[_Batch] | None = None

    def ready(self) -> bool:
        return self.future is None or self.future.done()


def _deflate(values: np.ndarray, level: int) -> bytes:
    """One chunk through HDF5's shuffle + deflate filters (what H5Z would store)."""
    raw = np.ascontiguousarray(values)
    size = raw.dtype.itemsize
    shuffled = np.ascontiguousarray(raw.view(np.uint8).reshape(-1, size).T)
    return zlib.compress(shuffled, level)


def append_rows(ds: h5py.Dataset, values: np.ndarray) -> None:
    """Append rows `values (m, *tail)` (or one row `(*tail)`) to a growing dataset.

    Uses the low-level API: h5py's high-level resize and slicing cost ~10x more.
    """
    dsid = ds.id
    space = dsid.get_space()
    shape = space.shape
    values = np.ascontiguousarray(values, dtype=ds.dtype)
    if values.ndim == len(shape) - 1:
        values = values[None]
    n, m = shape[0], len(values)
    dsid.set_extent((n + m, *shape[1:]))
    if m:
        fspace = dsid.get_space()
        fspace.select_hyperslab((n,) + (0,) * (len(shape) - 1), values.shape)
        dsid.write(h5py.h5s.create_simple(values.shape), fspace, values)


class Batcher:
    """Writes one result file's recorded steps in batches and flushes them.

    Recorded steps are buffered and written together, then flushed (durable, visible to
    readers): the first step at once; then a batch is started whenever `flush_every`
    records are pending, `flush_seconds` of wall time have passed since the last one
    (checked at each record) or about `_FLUSH_BYTES` are pending, and everything at
    :meth:`flush`. Whole-step chunks of large, compressed datasets are compressed by a
    thread while the run goes on (`background`, the default; the engine mostly uses one
    core); such a batch is written and flushed at the first :meth:`add` after its
    compression is done. Writing per batch removes the per-step cost that does not scale
    with the data (~50 datasets grow per step).

    `values` gives what a batch writes (the writer's layout); `written(n)` is called with
    the number of steps written after each batch, before its flush.
    """

    def __init__(
        self,
        values: StepValues,
        written: Callable[[int], None],
        *,
        compression: str | None,
        compression_level: int,
        flush_every: int,
        flush_seconds: float | None,
        background: bool,
    ) -> None:
        if compression not in ("gzip", None):
            raise ValueError(f"compression must be 'gzip' or None (ParaView reads both), "
                             f"not {compression!r}")
        if flush_every < 1:
            raise ValueError("flush_every must be >= 1")
        if flush_seconds is not None and not flush_seconds >= 0:
            raise ValueError("flush_seconds must be >= 0 (or None: by count only)")
        self.compression = compression
        self.compression_level = int(compression_level)
        self.flush_every = int(flush_every)
        self.flush_seconds = flush_seconds
        self.background = background
        #: steps written and flushed to the file (durable)
        self.n_flushed = 0
        self._values = values
        self._written = written
        self._file: h5py.File | None = None
        self._h: dict[str, h5py.Dataset] | None = None
        self._pending: list[PendingStep] = []
        self._pending_bytes = 0
        self._last_flush = 0.0
        #: datasets whose chunks are whole steps, compressed off the main thread
        self._direct: dict[str, np.dtype] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._inflight: deque[_Job] = deque()

    def dataset(self, group: h5py.Group, name: str, tail: tuple[int, ...], dtype: Any,
                rows_per_step: int = 1, contact_blocks: int | None = None) -> h5py.Dataset:
        """An empty dataset `(0, *tail)` growing along axis 0, chunked by the policy above;
        `contact_blocks`: a contacts dataset (a variable number of rows per step) of a model
        of that many blocks."""
        item = np.dtype(dtype).itemsize
        row_bytes = int(np.prod(tail, dtype=np.int64)) * item
        step_bytes = max(1, row_bytes * rows_per_step)
        tail_chunk = tail
        if contact_blocks is not None:
            compress = bool(self.compression) and contact_blocks >= _CONTACT_COMPRESS_BLOCKS
            rows = max(256, contact_blocks) if compress else max(1, _SHARED_CHUNK // row_bytes)
        else:
            compress = bool(self.compression) and step_bytes >= _COMPRESS_MIN
            if not compress:
                rows = rows_per_step * max(1, _SHARED_CHUNK // step_bytes)
            elif step_bytes <= _CHUNK_MAX:
                rows = rows_per_step  # exactly one step per chunk, written once
            elif rows_per_step > 1:  # a huge flat step: chunks straddle steps
                rows = max(1, _CHUNK_MAX // row_bytes)
            else:  # one huge (n, ...) row: one step, split along the block axis
                rows = 1
                tail_chunk = (max(1, _CHUNK_MAX // (row_bytes // tail[0])), *tail[1:])
        kw: dict[str, Any] = {}
        if compress:
            kw = {"compression": "gzip", "compression_opts": self.compression_level,
                  "shuffle": True}
        ds = group.create_dataset(name, shape=(0, *tail), maxshape=(None, *tail),
                                  dtype=dtype, chunks=(rows, *tail_chunk), **kw)
        if (compress and contact_blocks is None and rows == rows_per_step
                and tail_chunk == tail):
            self._direct[ds.name.lstrip("/")] = ds.dtype  # whole-step chunks: _deflate
        return ds

    def open(self, f: h5py.File) -> None:
        """Start writing steps to `f` (its datasets made by :meth:`dataset`, SWMR on); the
        wall-time clock of the flush policy starts now."""
        self._file = f
        self._last_flush = time.monotonic()

    def add(self, step: PendingStep, nbytes: int) -> None:
        """Take one step of about `nbytes`; write and flush pending steps as the policy says."""
        self._pending.append(step)
        self._pending_bytes += nbytes
        self._commit_ready(wait=False)
        now = time.monotonic()
        if self.flush_every == 1 or self.n_flushed + len(self._inflight) == 0:
            self.flush()  # every step durable on return; the first step at once
        elif (len(self._pending) >= self.flush_every or self._pending_bytes >= _FLUSH_BYTES
              or (self.flush_seconds is not None
                  and now - self._last_flush >= self.flush_seconds)):
            self._launch()
            self._commit_ready(wait=False)  # at once unless its chunks are compressing

    def flush(self) -> None:
        """Write every pending step and flush: all of them durable when this returns."""
        self._launch()
        self._commit_ready(wait=True)

    def close(self) -> None:
        """Drop the batches not written and stop the thread (the file is the writer's)."""
        self._inflight.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._file = None

    def _handles(self) -> dict[str, h5py.Dataset]:
        """Every growing dataset by its path (looked up once; lookups cost per step)."""
        if self._h is None:
            f = self._file
            assert f is not None
            out: dict[str, h5py.Dataset] = {}
            f.visititems(lambda name, obj: out.__setitem__(name, obj) if isinstance(
                obj, h5py.Dataset) and obj.maxshape[:1] == (None,) else None)
            self._h = out
        return self._h

    def _launch(self) -> None:
        """Hand the pending steps over as one batch (large steps: prepared and compressed by
        the writer's thread from now on); :meth:`_commit_ready` writes batches in order."""
        self._last_flush = time.monotonic()
        if not self._pending:
            return
        while len(self._inflight) >= _MAX_INFLIGHT:  # the thread is behind: wait
            self._commit(self._inflight.popleft())
        pend, self._pending, self._pending_bytes = self._pending, [], 0
        job = _Job(pend, self.n_flushed + sum(len(j.pend) for j in self._inflight))
        if self._direct and self.background:  # large steps: prepared by the thread
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=1,
                                                thread_name_prefix="polydda-result")
            job.future = self._pool.submit(self._prepare, job.pend, job.k0)
        self._inflight.append(job)

    def _commit_ready(self, wait: bool) -> None:
        """Write and flush the batches that are prepared (all of them if `wait`)."""
        while self._inflight and (wait or self._inflight[0].ready()):
            self._commit(self._inflight.popleft())

    def _prepare(self, pend: list[PendingStep], k0: int) -> _Batch:
        """The values of every growing dataset for steps `pend` (step indices from `k0`), in
        write order, with the whole-step chunks of compressed datasets compressed. Runs in
        the writer's thread for large steps: numpy and zlib only, no HDF5."""
        m = len(pend)
        writes = self._values(pend, k0)
        chunks: dict[str, list[bytes]] = {}
        for path, values in writes:
            if path in self._direct and len(values):
                steps = np.ascontiguousarray(values, dtype=self._direct[path]).reshape(m, -1)
                chunks[path] = [_deflate(row, self.compression_level) for row in steps]
        return _Batch(m, writes, chunks)

    def _commit(self, job: _Job) -> None:
        """Append one batch to the datasets (compressed chunks as they are) and flush."""
        f = self._file
        assert f is not None
        if job.future is None or job.future.cancel():  # not started: prepared here
            batch = self._prepare(job.pend, job.k0)
        else:
            batch = job.future.result()
        h = self._handles()
        for path, values in batch.writes:
            ds = h[path]
            if path not in batch.chunks:
                append_rows(ds, values)
                continue
            dsid = ds.id
            shape = dsid.get_space().shape
            rows = len(values) // batch.m  # rows of one step: one chunk
            dsid.set_extent((shape[0] + len(values), *shape[1:]))
            tail = (0,) * (len(shape) - 1)
            for j, data in enumerate(batch.chunks[path]):
                dsid.write_direct_chunk((shape[0] + j * rows, *tail), data)
        self.n_flushed += batch.m
        self._written(self.n_flushed)
        f.flush()
