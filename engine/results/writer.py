"""Writing a result file: :class:`ResultWriter`, the engine's Recorder, and the file's
publication under its name.

The writer creates the file's layout (:mod:`engine.results.layout`: root attributes, scene,
initial geometry, empty per-step datasets), turns each recorded frame into the values of
those datasets, and hands the steps to its :class:`~engine.results.batching.Batcher`, which
writes and flushes them in batches (HDF5 SWMR mode) so that a run that is killed keeps
every flushed step and its status stays "running"; :meth:`ResultWriter.end` writes the
status, message and summary. The file appears at its path (by a rename) only once its
static part is written; an existing file is replaced, never rewritten in place. The reader
is :mod:`engine.results.reader`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from engine.model import Model
from engine.results.batching import Batcher, PendingStep, append_rows
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
from engine.step.frame import ENERGY_NAMES, REMOVED, Frame

log = logging.getLogger(__name__)

#: names and the scene JSON are UTF-8 strings in the file
_STR = h5py.string_dtype("utf-8")


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


def write_stages(f: h5py.File, stages: list[dict[str, Any]]) -> None:
    """The `/stages` group of a staged run (layout: :mod:`engine.results.layout`)."""
    g = f.create_group("stages")
    g.create_dataset("names", data=[s["name"] for s in stages], dtype=_STR)
    for key in ("start_time", "end_time"):
        g[key] = np.array([s[key] for s in stages], float)
    for key in ("start_step", "end_step"):
        g[key] = np.array([s[key] for s in stages], np.int64)
    g["removed_energy"] = np.array([s["removed_energy"] for s in stages], float)
    g.create_dataset("status", data=[s["status"] for s in stages], dtype=_STR)
    g.create_dataset("removed_blocks", data=[json.dumps(s["removed_blocks"]) for s in stages],
                     dtype=_STR)
    g.create_dataset("bolts", data=[json.dumps(s["bolts"]) for s in stages], dtype=_STR)


class ResultWriter:
    """Writes one run to one HDF5 file as it goes; implements the :class:`Recorder` protocol.

    Recorded steps go to a :class:`~engine.results.batching.Batcher`, which writes them in
    batches, each flushed (durable, visible to readers): the first step at once; then every
    `flush_every` records, `flush_seconds` of wall time (checked at each record) or about
    32 MB, and everything at :meth:`flush` and :meth:`end`. Large steps are compressed by a thread
    while the run goes on (`background`, the default). A killed run keeps every flushed
    step (:attr:`n_flushed`); `flush_every=1` makes every step durable when `record`
    returns.

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
        self._batcher = Batcher(self._step_values, self._steps_written,
                                compression=compression, compression_level=compression_level,
                                flush_every=flush_every, flush_seconds=flush_seconds,
                                background=background)
        self.path = Path(path)
        self.record_contacts = record_contacts
        self.overwrite = overwrite
        self.schema_version = schema_version
        #: steps given to `record`
        self.n_recorded = 0
        self._file: h5py.File | None = None
        self._inode: tuple[int, int] | None = None
        self._static: Static | None = None
        self._ended = False
        self._n_contacts = 0
        self._ignored_energies: set[str] = set()
        self._nf = 0
        self._n_bolts = 0
        self._water = False

    @property
    def n_flushed(self) -> int:
        """Steps written and flushed to the file (durable)."""
        return self._batcher.n_flushed

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
        self._batcher.open(f)

    def _write_static(self, f: h5py.File, model: Model, scene_json: str | None) -> None:
        """Root attributes, scene, initial geometry and empty per-step datasets; SWMR on."""
        st = self._static = flatten_model(model)
        n, nv = len(model.blocks), len(st.vertices)
        growing = self._batcher.dataset

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
        growing(g, "step", (), np.int64)
        growing(g, "time", (), np.float64)
        growing(g, "dt", (), np.float64)
        growing(g, "open_close_iterations", (), np.int64)
        growing(g, "max_penetration", (), np.float64)
        e = g.create_group("energies")
        for name in ENERGY_NAMES:
            growing(e, name, (), np.float64)

        g = f.create_group("history")
        for name, tail in HISTORY_SHAPES.items():
            growing(g, name, (n, *tail), np.float64)

        g = f.create_group("contacts")
        g.attrs["recorded"] = bool(self.record_contacts)
        so = growing(g, "step_offsets", (), np.int64)
        append_rows(so, np.zeros(1, np.int64))
        if self.record_contacts:
            for name, (tail, dtype) in CONTACT_FIELDS.items():
                growing(g, name, tail, dtype, contact_blocks=n)

        self._begin_loads(f, model)
        self._begin_vtkhdf(f, n, nv)
        f.flush()
        f.swmr_mode = True

    def _begin_loads(self, f: h5py.File, model: Model) -> None:
        """The `/bolts` and `/water` groups of a model that has bolts or water."""
        n = len(model.blocks)
        growing = self._batcher.dataset
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
                growing(g, name, (nb,), dtype)

        if model.water is not None:
            self._water = True
            growing(f.create_group("water"), "resultant", (n, 3), np.float64)

    def _begin_vtkhdf(self, f: h5py.File, n: int, nv: int) -> None:
        """Static part of the VTKHDF temporal PolyData group and its per-step datasets."""
        st = self._static
        assert st is not None
        growing = self._batcher.dataset
        v = f.create_group("VTKHDF")
        v.attrs["Version"] = np.array(VTKHDF_VERSION, dtype=np.int64)
        v.attrs.create("Type", np.bytes_("PolyData"), dtype=h5py.string_dtype("ascii", 8))
        growing(v, "NumberOfPoints", (), np.int64)
        growing(v, "Points", (3,), np.float64, rows_per_step=max(nv, 1))
        nf = len(st.face_offsets) - 1
        for name in ("Vertices", "Lines", "Polygons", "Strips"):
            c = v.create_group(name)
            growing(c, "NumberOfCells", (), np.int64)
            growing(c, "NumberOfConnectivityIds", (), np.int64)
            if name == "Polygons":
                c["Offsets"] = st.face_offsets
                c["Connectivity"] = st.face_connectivity
            else:
                c["Offsets"] = np.zeros(1, np.int64)
                c["Connectivity"] = np.zeros(0, np.int64)
        pd = v.create_group("PointData")
        pd["block_id"] = st.vertex_block.astype(np.int32)
        growing(pd, "displacement", (3,), np.float64, rows_per_step=max(nv, 1))
        growing(pd, "velocity", (3,), np.float64, rows_per_step=max(nv, 1))
        cd = v.create_group("CellData")
        cd["block_id"] = np.repeat(np.arange(n), np.diff(st.face_block_offsets)).astype(np.int32)
        cd["face_tag"] = st.face_tags
        s = v.create_group("Steps")
        s.attrs["NSteps"] = np.int64(0)
        growing(s, "Values", (), np.float64)
        growing(s, "PartOffsets", (), np.int64)
        growing(s, "NumberOfParts", (), np.int64)
        growing(s, "PointOffsets", (), np.int64)
        growing(s, "CellOffsets", (4,), np.int64)
        growing(s, "ConnectivityIdOffsets", (4,), np.int64)
        po = s.create_group("PointDataOffsets")
        for name in ("block_id", "displacement", "velocity"):
            growing(po, name, (), np.int64)
        co = s.create_group("CellDataOffsets")
        for name in ("block_id", "face_tag"):
            growing(co, name, (), np.int64)
        self._nf = nf

    def record(self, frame: Frame) -> None:
        """Take one step (copied) and hand it to the batcher (written and flushed as its
        policy says)."""
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
                   tuple(frame.energies.get(name, 0.0 if name in REMOVED else np.nan)
                         for name in ENERGY_NAMES))
        nbytes = (sum(a.nbytes for a in arrays.values())
                  + sum(a.nbytes for a in contacts.values())
                  + 72 * len(st.vertices))  # VTKHDF points written per step
        self.n_recorded += 1
        self._batcher.add(PendingStep(arrays, contacts, self._n_contacts, scalars), nbytes)

    def flush(self) -> None:
        """Write every recorded step and flush: all of them durable when this returns."""
        if self._file is None or self._static is None:
            raise RuntimeError("flush() needs begin() first and no end() yet")
        self._batcher.flush()

    def _steps_written(self, n: int) -> None:
        """The VTKHDF step count follows the steps the batcher has written (`n`)."""
        f = self._file
        assert f is not None
        f["VTKHDF/Steps"].attrs.modify("NSteps", np.int64(n))

    def _step_values(self, pend: list[PendingStep], k0: int) -> list[tuple[str, np.ndarray]]:
        """The values of every growing dataset for steps `pend` (step indices from `k0`),
        in the order they are written (`steps/step` last: a reader counts the steps every
        per-step dataset holds). Runs in the batcher's thread for large steps: numpy
        only, no HDF5."""
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
        return writes

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
            self._batcher.close()
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
            if summary and summary.get("stages"):
                write_stages(f, summary["stages"])

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

