"""Writing a result file: :class:`ResultWriter`, the engine's Recorder, and the file's
publication under its name.

The writer appends the recorded steps to resizable, chunked, gzip+shuffle datasets in
HDF5 single-writer/multiple-reader (SWMR) mode, in batches, each followed by a flush (at
the first step, then at least every `flush_seconds` of wall time, default 1 s, or every
`flush_every` steps), so a run that is killed keeps every flushed step and its status
stays "running". The file appears at its path (by a rename) only once its static part is
written; an existing file is replaced, never rewritten in place. The layout is
:mod:`engine.results.layout`; the reader is :mod:`engine.results.reader`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
import time
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from engine.model import Model
from engine.results.layout import (
    BOLT_FIELDS,
    CONTACT_FIELDS,
    FORMAT,
    FORMAT_VERSION,
    HISTORY_SHAPES,
    LIBVER,
    STATUSES,
    VTKHDF_VERSION,
    Static,
    engine_version,
    flatten_model,
    json_default,
    point_velocities,
    transform_points,
)
from engine.step.frame import ENERGY_NAMES, Frame

log = logging.getLogger(__name__)

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
#: names and the scene JSON are UTF-8 strings in the file
_STR = h5py.string_dtype("utf-8")


@dataclass
class _PendingStep:
    """One recorded step held in memory until the next flush."""

    arrays: dict[str, np.ndarray]  # history arrays by name, (n, *tail) each
    contacts: dict[str, np.ndarray]  # contact fields (empty: no contacts this step)
    contact_end: int  # contact rows of all steps up to this one
    scalars: tuple[Any, ...]  # step, time, dt, open_close_iterations, max_penetration, energies


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

    pend: list[_PendingStep]
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


def _inode(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the file at `path`, None if there is none."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino


def _publish(tmp: Path, path: Path, overwrite: bool) -> None:
    """Give the finished-static file `tmp` the name `path`: an atomic rename that replaces
    an existing file (`overwrite`) or a hard link that refuses to (FileExistsError)."""
    if overwrite:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists; results are never rewritten in place") from None
    except OSError:  # a file system without hard links
        if path.exists():
            raise FileExistsError(f"{path} exists; results are never rewritten in place") \
                from None
        os.replace(tmp, path)
        return
    tmp.unlink()


class ResultWriter:
    """Writes one run to one HDF5 file as it goes; implements the :class:`Recorder` protocol.

    Recorded steps are buffered and written together, then flushed (durable, visible to
    readers): the first step at once; then a batch is started whenever `flush_every`
    records are pending, `flush_seconds` of wall time have passed since the last one
    (checked at each record) or about `_FLUSH_BYTES` are pending, and everything at
    :meth:`flush` and :meth:`end`. Whole-step chunks of large, compressed datasets are
    compressed by a thread while the run goes on (`background`, the default; the engine
    mostly uses one core); such a batch is written and flushed at the first `record` after
    its compression is done. A killed run keeps every flushed step
    (:attr:`n_flushed`); `flush_every=1` makes every step durable when `record` returns.
    Writing per batch removes the per-step cost that does not scale with the data (~50
    datasets grow per step).

    The file is created under a temporary name beside `path` (`.NAME.PID.HEX.tmp`, left
    only by a process killed inside `begin`) and renamed to `path` once its static part is
    written, before the first step: `path` is never truncated or rewritten in place. With
    `overwrite`, an existing file at `path` is replaced by the rename (a reader holding it
    keeps a valid file); otherwise it must not exist.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        compression: str | None = "gzip",
        compression_level: int = 4,
        record_contacts: bool = True,
        flush_every: int = 1000,
        flush_seconds: float | None = 1.0,
        overwrite: bool = False,
        schema_version: str | None = None,
        background: bool = True,
    ) -> None:
        if compression not in ("gzip", None):
            raise ValueError(f"compression must be 'gzip' or None (ParaView reads both), "
                             f"not {compression!r}")
        if flush_every < 1:
            raise ValueError("flush_every must be >= 1")
        if flush_seconds is not None and not flush_seconds >= 0:
            raise ValueError("flush_seconds must be >= 0 (or None: by count only)")
        self.path = Path(path)
        self.compression = compression
        self.compression_level = int(compression_level)
        self.record_contacts = record_contacts
        self.flush_every = int(flush_every)
        self.flush_seconds = flush_seconds
        self.overwrite = overwrite
        self.schema_version = schema_version
        self.background = background
        #: steps given to `record`, and steps written and flushed to the file (durable)
        self.n_recorded = 0
        self.n_flushed = 0
        self._file: h5py.File | None = None
        self._inode: tuple[int, int] | None = None
        self._static: Static | None = None
        self._ended = False
        self._n_contacts = 0
        self._ignored_energies: set[str] = set()
        self._h: dict[str, h5py.Dataset] | None = None
        self._nf = 0
        self._n_blocks = 0
        self._n_bolts = 0
        self._water = False
        self._pending: list[_PendingStep] = []
        self._pending_bytes = 0
        self._last_flush = 0.0
        #: datasets whose chunks are whole steps, compressed off the main thread
        self._direct: dict[str, np.dtype] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._inflight: deque[_Job] = deque()

    # --- helpers
    def _ds(self, group: h5py.Group, name: str, tail: tuple[int, ...], dtype: Any,
            rows_per_step: int = 1, contact: bool = False) -> h5py.Dataset:
        """An empty dataset `(0, *tail)` growing along axis 0, chunked by the policy above."""
        item = np.dtype(dtype).itemsize
        row_bytes = int(np.prod(tail, dtype=np.int64)) * item
        step_bytes = max(1, row_bytes * rows_per_step)
        tail_chunk = tail
        if contact:
            compress = bool(self.compression) and self._n_blocks >= _CONTACT_COMPRESS_BLOCKS
            rows = max(256, self._n_blocks) if compress else max(1, _SHARED_CHUNK // row_bytes)
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
        if compress and not contact and rows == rows_per_step and tail_chunk == tail:
            self._direct[ds.name.lstrip("/")] = ds.dtype  # whole-step chunks: _deflate
        return ds

    @staticmethod
    def _append(ds: h5py.Dataset, values: np.ndarray) -> None:
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

    # --- Recorder protocol
    def begin(self, model: Model, scene_json: str | None = None) -> None:
        """Create the file, write the initial geometry and scene, switch to SWMR mode."""
        if self._file is not None or self._ended:
            raise RuntimeError("begin() was already called on this writer")
        if self.path.exists() and not self.overwrite:
            raise FileExistsError(f"{self.path} exists; results are never rewritten in place")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.record_contacts = self.record_contacts and model.controls.record_contacts
        # a new name beside `path` (same file system: the rename is atomic), created with
        # the permissions the umask gives, like any other output file
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
        try:
            f = h5py.File(tmp, "x", libver=LIBVER)
            self._file = f
            self._write_static(f, model, scene_json)
            _publish(tmp, self.path, self.overwrite)
        except BaseException:
            if self._file is not None:
                self._file.close()
                self._file = None
            tmp.unlink(missing_ok=True)
            raise
        self._inode = _inode(self.path)
        self._last_flush = time.monotonic()

    def _write_static(self, f: h5py.File, model: Model, scene_json: str | None) -> None:
        """Root attributes, scene, initial geometry and empty per-step datasets; SWMR on."""
        st = self._static = flatten_model(model)
        n, nv = len(model.blocks), len(st.vertices)
        self._n_blocks = n

        schema = self.schema_version
        if schema is None and scene_json:
            try:
                parsed = json.loads(scene_json)
                if isinstance(parsed, dict) and "schema_version" in parsed:
                    schema = str(parsed["schema_version"])
            except ValueError:
                pass
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["engine_version"] = engine_version()
        if schema is not None:
            f.attrs["schema_version"] = schema
        f.attrs["status"] = "running"
        f.attrs["message"] = ""

        g = f.create_group("scene")
        if scene_json is not None:
            g.create_dataset("json", data=scene_json, dtype=_STR)
            g.attrs["sha256"] = hashlib.sha256(scene_json.encode("utf-8")).hexdigest()

        g = f.create_group("blocks")
        g["vertices"] = st.vertices
        g["vertex_offsets"] = st.vertex_offsets
        g["face_offsets"] = st.face_offsets
        g["face_connectivity"] = st.face_connectivity
        g["face_connectivity"].attrs["indexing"] = "global into /blocks/vertices"
        g["face_block_offsets"] = st.face_block_offsets
        g["face_tags"] = st.face_tags
        g.create_dataset("names", data=[b.name for b in model.blocks], dtype=_STR)
        g["material"] = np.array([b.material for b in model.blocks], dtype=np.int64)
        g["fixed"] = np.array([b.fixed for b in model.blocks], dtype=bool)
        g["centroid"] = st.centroid
        g["volume"] = np.array([b.polyhedron.volume for b in model.blocks], dtype=float)

        g = f.create_group("steps")
        self._ds(g, "step", (), np.int64)
        self._ds(g, "time", (), np.float64)
        self._ds(g, "dt", (), np.float64)
        self._ds(g, "open_close_iterations", (), np.int64)
        self._ds(g, "max_penetration", (), np.float64)
        e = g.create_group("energies")
        for name in ENERGY_NAMES:
            self._ds(e, name, (), np.float64)

        g = f.create_group("history")
        for name, tail in HISTORY_SHAPES.items():
            self._ds(g, name, (n, *tail), np.float64)

        g = f.create_group("contacts")
        g.attrs["recorded"] = bool(self.record_contacts)
        so = self._ds(g, "step_offsets", (), np.int64)
        self._append(so, np.zeros(1, np.int64))
        if self.record_contacts:
            for name, (tail, dtype) in CONTACT_FIELDS.items():
                self._ds(g, name, tail, dtype, contact=True)

        self._begin_loads(f, model)
        self._begin_vtkhdf(f, n, nv)
        f.flush()
        f.swmr_mode = True

    def _begin_loads(self, f: h5py.File, model: Model) -> None:
        """The `/bolts` and `/water` groups of a model that has bolts or water."""
        n = len(model.blocks)
        if model.bolts:
            self._n_bolts = nb = len(model.bolts)
            g = f.create_group("bolts")
            g.create_dataset("names", data=[b.name or f"bolt{k + 1}"
                                            for k, b in enumerate(model.bolts)], dtype=_STR)
            g["block"] = np.array([b.block for b in model.bolts], dtype=np.int64)
            g["anchor_block"] = np.array([b.anchor_block for b in model.bolts], dtype=np.int64)
            g["head"] = np.array([b.head for b in model.bolts], float).reshape(nb, 3)
            g["anchor"] = np.array([b.anchor for b in model.bolts], float).reshape(nb, 3)
            g["pretension"] = np.array([b.pretension for b in model.bolts], float)
            g["capacity"] = np.array([b.capacity for b in model.bolts], float)
            for name, (_, dtype) in BOLT_FIELDS.items():
                self._ds(g, name, (nb,), dtype)

        if model.water is not None:
            self._water = True
            self._ds(f.create_group("water"), "resultant", (n, 3), np.float64)

    def _begin_vtkhdf(self, f: h5py.File, n: int, nv: int) -> None:
        """Static part of the VTKHDF temporal PolyData group and its per-step datasets."""
        st = self._static
        assert st is not None
        v = f.create_group("VTKHDF")
        v.attrs["Version"] = np.array(VTKHDF_VERSION, dtype=np.int64)
        v.attrs.create("Type", np.bytes_("PolyData"), dtype=h5py.string_dtype("ascii", 8))
        self._ds(v, "NumberOfPoints", (), np.int64)
        self._ds(v, "Points", (3,), np.float64, rows_per_step=max(nv, 1))
        nf = len(st.face_offsets) - 1
        for name in ("Vertices", "Lines", "Polygons", "Strips"):
            c = v.create_group(name)
            self._ds(c, "NumberOfCells", (), np.int64)
            self._ds(c, "NumberOfConnectivityIds", (), np.int64)
            if name == "Polygons":
                c["Offsets"] = st.face_offsets
                c["Connectivity"] = st.face_connectivity
            else:
                c["Offsets"] = np.zeros(1, np.int64)
                c["Connectivity"] = np.zeros(0, np.int64)
        pd = v.create_group("PointData")
        pd["block_id"] = st.vertex_block.astype(np.int32)
        self._ds(pd, "displacement", (3,), np.float64, rows_per_step=max(nv, 1))
        self._ds(pd, "velocity", (3,), np.float64, rows_per_step=max(nv, 1))
        cd = v.create_group("CellData")
        cd["block_id"] = np.repeat(np.arange(n), np.diff(st.face_block_offsets)).astype(np.int32)
        cd["face_tag"] = st.face_tags
        s = v.create_group("Steps")
        s.attrs["NSteps"] = np.int64(0)
        self._ds(s, "Values", (), np.float64)
        self._ds(s, "PartOffsets", (), np.int64)
        self._ds(s, "NumberOfParts", (), np.int64)
        self._ds(s, "PointOffsets", (), np.int64)
        self._ds(s, "CellOffsets", (4,), np.int64)
        self._ds(s, "ConnectivityIdOffsets", (4,), np.int64)
        po = s.create_group("PointDataOffsets")
        for name in ("block_id", "displacement", "velocity"):
            self._ds(po, name, (), np.int64)
        co = s.create_group("CellDataOffsets")
        for name in ("block_id", "face_tag"):
            self._ds(co, name, (), np.int64)
        self._nf = nf

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

    def record(self, frame: Frame) -> None:
        """Take one step (copied); write and flush the pending steps as the policy says."""
        st = self._static
        if self._file is None or st is None or self._ended:
            raise RuntimeError("record() needs begin() first and no end() yet")
        n = len(st.centroid)
        arrays = {name: np.array(getattr(frame, attr), dtype=float) for name, attr in
                  (("centroid", "centroids"), ("rotation", "rotation"), ("affine", "affine"),
                   ("velocity", "velocity"), ("stress", "stress"))}
        for name, tail in HISTORY_SHAPES.items():
            if arrays[name].shape != (n, *tail):
                raise ValueError(f"frame.{name} has shape {arrays[name].shape}, "
                                 f"expected {(n, *tail)}")
        for name, (attr, dtype) in BOLT_FIELDS.items() if self._n_bolts else ():
            value = getattr(frame, attr)
            arrays[f"bolts/{name}"] = (np.full(self._n_bolts, np.nan) if value is None
                                       else np.array(value, dtype=dtype))
        if self._water:
            arrays["water/resultant"] = (np.full((n, 3), np.nan) if frame.water_force is None
                                         else np.array(frame.water_force, float))
        contacts: dict[str, np.ndarray] = {}
        cs = frame.contacts
        c = 0 if cs is None or not self.record_contacts else len(cs)
        if c:
            assert cs is not None
            vals = {name: getattr(cs, name) for name in CONTACT_FIELDS
                    if name not in ("normal_force", "shear_force")}
            vals["normal_force"] = (np.full(c, np.nan) if frame.normal_force is None
                                    else frame.normal_force)
            vals["shear_force"] = (np.full((c, 3), np.nan) if frame.shear_force is None
                                   else frame.shear_force)
            for name, (tail, dtype) in CONTACT_FIELDS.items():
                contacts[name] = np.array(vals[name], dtype=dtype).reshape(c, *tail)
        self._n_contacts += c
        extra = set(frame.energies) - set(ENERGY_NAMES) - self._ignored_energies
        if extra:
            log.warning("energies %s are not in the result layout and are not stored",
                        sorted(extra))
            self._ignored_energies |= extra
        scalars = (frame.step, frame.time, frame.dt, frame.open_close_iterations,
                   frame.max_penetration,
                   tuple(frame.energies.get(name, np.nan) for name in ENERGY_NAMES))
        self._pending.append(_PendingStep(arrays, contacts, self._n_contacts, scalars))
        self._pending_bytes += (sum(a.nbytes for a in arrays.values())
                                + sum(a.nbytes for a in contacts.values())
                                + 72 * len(st.vertices))  # VTKHDF points written per step
        self.n_recorded += 1
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
        """Write every recorded step and flush: all of them durable when this returns."""
        if self._file is None or self._static is None:
            raise RuntimeError("flush() needs begin() first and no end() yet")
        self._launch()
        self._commit_ready(wait=True)

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

    def _prepare(self, pend: list[_PendingStep], k0: int) -> _Batch:
        """The values of every growing dataset for steps `pend` (step indices from `k0`),
        in the order they are written (`steps/step` last: a reader counts the steps every
        per-step dataset holds); whole-step chunks of compressed datasets compressed.
        Runs in the writer's thread for large steps: numpy and zlib only, no HDF5."""
        st = self._static
        assert st is not None
        m = len(pend)
        writes: list[tuple[str, np.ndarray]] = []
        hist = {name: np.stack([p.arrays[name] for p in pend]) for name in HISTORY_SHAPES}
        writes += [(f"history/{name}", a) for name, a in hist.items()]
        if self._n_bolts:
            writes += [(f"bolts/{name}", np.stack([p.arrays[f"bolts/{name}"] for p in pend]))
                       for name in BOLT_FIELDS]
        if self._water:
            writes.append(("water/resultant",
                           np.stack([p.arrays["water/resultant"] for p in pend])))
        if self.record_contacts:
            for name in CONTACT_FIELDS:
                parts = [p.contacts[name] for p in pend if p.contacts]
                if parts:
                    writes.append((f"contacts/{name}", np.concatenate(parts)))
        writes.append(("contacts/step_offsets",
                       np.array([p.contact_end for p in pend], np.int64)))

        # VTKHDF: points, point displacement and velocity
        nv = len(st.vertices)
        vb = st.vertex_block
        cent = hist["centroid"][:, vb]  # (m, V, 3)
        pts = transform_points(st.vertices - st.centroid[vb], vb, hist["centroid"],
                               hist["affine"])
        vel = point_velocities(pts.reshape(-1, 3), cent.reshape(-1, 3),
                               hist["velocity"][:, vb].reshape(-1, 12))
        writes += [("VTKHDF/Points", pts.reshape(-1, 3)),
                   ("VTKHDF/PointData/displacement", (pts - st.vertices).reshape(-1, 3)),
                   ("VTKHDF/PointData/velocity", vel)]
        ks = np.arange(k0, k0 + m, dtype=np.int64)
        zero, zero4 = np.zeros(m, np.int64), np.zeros((m, 4), np.int64)
        writes.append(("VTKHDF/NumberOfPoints", np.full(m, nv, np.int64)))
        for name in ("Vertices", "Lines", "Strips"):
            writes.append((f"VTKHDF/{name}/NumberOfCells", zero))
            writes.append((f"VTKHDF/{name}/NumberOfConnectivityIds", zero))
        writes.append(("VTKHDF/Polygons/NumberOfCells", np.full(m, self._nf, np.int64)))
        writes.append(("VTKHDF/Polygons/NumberOfConnectivityIds",
                       np.full(m, len(st.face_connectivity), np.int64)))
        scal = [p.scalars for p in pend]
        s = "VTKHDF/Steps/"
        writes += [
            (s + "Values", np.array([x[1] for x in scal], float)),
            (s + "PartOffsets", ks), (s + "NumberOfParts", np.ones(m, np.int64)),
            (s + "PointOffsets", ks * nv), (s + "CellOffsets", zero4),
            (s + "ConnectivityIdOffsets", zero4), (s + "PointDataOffsets/block_id", zero),
            (s + "PointDataOffsets/displacement", ks * nv),
            (s + "PointDataOffsets/velocity", ks * nv),
            (s + "CellDataOffsets/block_id", zero), (s + "CellDataOffsets/face_tag", zero),
        ]
        energies = np.array([x[5] for x in scal], float).reshape(m, len(ENERGY_NAMES))
        writes += [(f"steps/energies/{name}", energies[:, j])
                   for j, name in enumerate(ENERGY_NAMES)]
        writes += [("steps/time", np.array([x[1] for x in scal], float)),
                   ("steps/dt", np.array([x[2] for x in scal], float)),
                   ("steps/open_close_iterations", np.array([x[3] for x in scal], np.int64)),
                   ("steps/max_penetration", np.array([x[4] for x in scal], float)),
                   ("steps/step", np.array([x[0] for x in scal], np.int64))]

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
                self._append(ds, values)
                continue
            dsid = ds.id
            shape = dsid.get_space().shape
            rows = len(values) // batch.m  # rows of one step: one chunk
            dsid.set_extent((shape[0] + len(values), *shape[1:]))
            tail = (0,) * (len(shape) - 1)
            for j, data in enumerate(batch.chunks[path]):
                dsid.write_direct_chunk((shape[0] + j * rows, *tail), data)
        self.n_flushed += batch.m
        f["VTKHDF/Steps"].attrs.modify("NSteps", np.int64(self.n_flushed))
        f.flush()

    def end(self, status: str, message: str = "", summary: dict[str, Any] | None = None) -> None:
        """Write the pending steps and close the SWMR session, then write status, message
        and summary (JSON) and close."""
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, not {status!r}")
        if self._file is None or self._ended:
            raise RuntimeError("end() needs begin() first and may be called once")
        text = json.dumps(summary if summary is not None else {}, default=json_default)
        try:
            self.flush()
        finally:
            self._inflight.clear()
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
            self._file.close()
            self._file = None
            self._ended = True
        if _inode(self.path) != self._inode:
            log.warning("%s was replaced during the run; its status is not written",
                        self.path)
            return
        with h5py.File(self.path, "r+", libver=LIBVER) as f:
            f.attrs["status"] = status
            f.attrs["message"] = message
            f.attrs["summary"] = text
            f.attrs["n_steps"] = np.int64(self.n_flushed)

    # --- context manager: a writer left without end() says so in its status
    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._file is not None and not self._ended:
            if exc is not None:
                self.end("failed", f"{type(exc).__name__}: {exc}")
            else:
                self.end("stopped", "the recorder was closed before the run ended")

