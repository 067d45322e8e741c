"""Reading a result file: :class:`Result` (:func:`open_result`) and :func:`recover_result`.

A read-only view of the HDF5 file :mod:`engine.results.writer` writes (its layout:
:mod:`engine.results.layout`), finished, still being written (SWMR: :meth:`Result.refresh`
sees the steps a live writer flushed since) or left by a killed run; and the copy of a
killed run's complete steps into a closed file that ParaView and h5dump open. Kept apart
from the writer: plots, summaries and the service read results and need none of the
writing.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from engine import user_entry
from engine.results.layout import (
    BOLT_FIELDS,
    CONTACT_FIELDS,
    FORMAT,
    HISTORY_SHAPES,
    LIBVER,
    transform_points,
)


def _text(value: Any) -> str:
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


class Result:
    """Read-only view of a result file (finished, still being written, or from a killed run).

    Steps count only when every per-step dataset holds them; call :meth:`refresh` to see
    steps a live writer added since opening.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._file = self._open(self.path)
        f = self._file
        if _text(f.attrs.get("format", "")) != FORMAT:
            self._file.close()
            raise ValueError(f"{self.path} is not a {FORMAT} file")
        b = f["blocks"]
        self.format_version = int(f.attrs["format_version"])
        self.engine_version = _text(f.attrs.get("engine_version", "unknown"))
        sv = f.attrs.get("schema_version")
        self.schema_version = None if sv is None else _text(sv)
        self.block_names: list[str] = [_text(x) for x in b["names"][()]]
        self.n_blocks = len(self.block_names)
        self.material = b["material"][()]
        self.fixed = b["fixed"][()]
        self.volume = b["volume"][()]
        self.initial_centroids = b["centroid"][()]
        self._x0 = b["vertices"][()]
        self._voff = b["vertex_offsets"][()]
        self._vblock = np.repeat(np.arange(self.n_blocks), np.diff(self._voff))
        self._foff = b["face_offsets"][()]
        self._fconn = b["face_connectivity"][()]
        self._fboff = b["face_block_offsets"][()]
        self.face_tags = b["face_tags"][()]
        self.n_steps = 0
        self._cache: dict[str, np.ndarray] = {}
        self.refresh()

    @staticmethod
    def _open(path: Path) -> h5py.File:
        """Open read-only: SWMR read first (live or killed writer), then without file locks."""
        errors = []
        for kw in ({"swmr": True}, {"swmr": True, "locking": False}, {"locking": False}):
            try:
                return h5py.File(path, "r", **kw)
            except OSError as exc:
                if not path.exists():
                    raise
                if str(exc) not in errors:
                    errors.append(str(exc))
        raise OSError(f"cannot open {path}: {'; '.join(errors)}")

    # --- bookkeeping
    def _per_step(self) -> Iterator[h5py.Dataset]:
        f = self._file
        yield from (f["steps"][k] for k in ("step", "time", "dt", "open_close_iterations",
                                            "max_penetration"))
        yield from f["steps/energies"].values()
        yield from f["history"].values()
        if "bolts" in f:
            yield from (f["bolts"][name] for name in BOLT_FIELDS)
        if "water" in f:
            yield f["water/resultant"]
        yield f["VTKHDF/Steps/Values"]

    def refresh(self) -> int:
        """Re-read the number of complete steps (grows while a writer is running)."""
        f = self._file
        if f.swmr_mode:
            for ds in self._per_step():
                ds.refresh()
            for ds in f["contacts"].values():
                ds.refresh()
            f["VTKHDF/Points"].refresh()
        k = min(ds.shape[0] for ds in self._per_step())
        so = f["contacts/step_offsets"]
        k = min(k, so.shape[0] - 1)
        if self.contacts_recorded and k > 0:
            rows = min(ds.shape[0] for name, ds in f["contacts"].items()
                       if name != "step_offsets")
            k = int(np.searchsorted(so[: k + 1], rows, side="right")) - 1
        self.n_steps = max(k, 0)
        self._cache = {}
        return self.n_steps

    def _read(self, path: str) -> np.ndarray:
        """Dataset `path` cut to the complete steps (cached until refresh)."""
        if path not in self._cache:
            self._cache[path] = self._file[path][: self.n_steps]
        return self._cache[path]

    def close(self) -> None:
        """Close the file (also done by the context manager)."""
        self._file.close()

    def __enter__(self) -> Result:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- run metadata
    @property
    def status(self) -> str:
        """'running' (still going or killed), 'completed', 'failed', 'cancelled', 'stopped'."""
        return _text(self._file.attrs["status"])

    @property
    def message(self) -> str:
        """Why the run ended as it did (empty while running)."""
        return _text(self._file.attrs.get("message", ""))

    @property
    def summary(self) -> dict[str, Any] | None:
        """The run summary given to `end()`, or None while the run has not ended."""
        text = self._file.attrs.get("summary")
        return None if text is None else json.loads(_text(text))

    @property
    def scene_json(self) -> str | None:
        """The input scene JSON text (None if the run had none)."""
        g = self._file["scene"]
        return _text(g["json"][()]) if "json" in g else None

    @property
    def scene_sha256(self) -> str | None:
        """SHA-256 (hex) of the input scene JSON text (None if the run had none)."""
        value = self._file["scene"].attrs.get("sha256")
        return None if value is None else _text(value)

    @property
    def contacts_recorded(self) -> bool:
        """Whether `/contacts` holds contact rows (`record_contacts` of the writer)."""
        return bool(self._file["contacts"].attrs["recorded"])

    @property
    def times(self) -> np.ndarray:
        """Time `(K,)` s of each recorded step."""
        return self._read("steps/time")

    @property
    def steps(self) -> np.ndarray:
        """Solver step number `(K,)` of each recorded step."""
        return self._read("steps/step")

    def step_data(self) -> dict[str, np.ndarray]:
        """Per-step scalars `(K,)`: step, time, dt, open_close_iterations, max_penetration."""
        return {k: self._read(f"steps/{k}") for k in
                ("step", "time", "dt", "open_close_iterations", "max_penetration")}

    def energies(self) -> dict[str, np.ndarray]:
        """Energy and work terms `(K,)` J by name (NaN where the engine gave none)."""
        return {k: self._read(f"steps/energies/{k}") for k in self._file["steps/energies"]}

    def bolts(self) -> dict[str, Any] | None:
        """The rock bolts (None for a model without): `names`, `block`, `anchor_block`,
        `head`, `anchor`, `pretension`, `capacity`, and per step `axial_force`,
        `shear_force`, `status` `(K, b)` (see :mod:`engine.results.layout`)."""
        if "bolts" not in self._file:
            return None
        g = self._file["bolts"]
        out: dict[str, Any] = {"names": [_text(x) for x in g["names"][()]]}
        for name in ("block", "anchor_block", "head", "anchor", "pretension", "capacity"):
            out[name] = g[name][()]
        for name in BOLT_FIELDS:
            out[name] = self._read(f"bolts/{name}")
        return out

    def stages(self) -> list[dict[str, Any]]:
        """The stages of a staged run (empty otherwise): name, start and end time (s) and
        step, status, removed energy (J), the blocks removed as it starts and its bolts."""
        if "stages" not in self._file:
            return []
        g = self._file["stages"]
        names = [_text(x) for x in g["names"][()]]
        return [{"name": names[k], "start_time": float(g["start_time"][k]),
                 "end_time": float(g["end_time"][k]), "start_step": int(g["start_step"][k]),
                 "end_step": int(g["end_step"][k]), "status": _text(g["status"][k]),
                 "removed_energy": float(g["removed_energy"][k]),
                 "removed_blocks": json.loads(_text(g["removed_blocks"][k])),
                 "bolts": json.loads(_text(g["bolts"][k]))} for k in range(len(names))]

    def removed_at(self, time: float) -> set[int]:
        """Blocks gone at `time` s: those removed by a stage that started before it (the
        frame at a stage's start is the stage before's end, the blocks still there)."""
        names = list(self.block_names)
        return {names.index(n) for st in self.stages() if st["start_time"] < time
                for n in st["removed_blocks"] if n in names}

    def water_resultants(self) -> np.ndarray | None:
        """Resultant water force on each block `(K, n, 3)` N (None for a dry model)."""
        return self._read("water/resultant") if "water" in self._file else None

    # --- blocks
    def block_index(self, name_or_index: str | int) -> int:
        """Index of a block given by name (first match) or index (negative allowed)."""
        if isinstance(name_or_index, str):
            try:
                return self.block_names.index(name_or_index)
            except ValueError:
                raise KeyError(f"no block named {name_or_index!r}") from None
        i = int(name_or_index)
        if not -self.n_blocks <= i < self.n_blocks:
            raise IndexError(f"block index {i} out of range for {self.n_blocks} blocks")
        return i % self.n_blocks

    def block_history(self, name_or_index: str | int) -> dict[str, np.ndarray]:
        """One block over time: time `(K,)`, centroid, displacement, rotation `(K,3)`,
        velocity `(K,12)`, stress `(K,6)`, affine `(K,3,3)`."""
        i = self.block_index(name_or_index)
        h = self._file["history"]
        out = {"step": self.steps, "time": self.times}
        for name in HISTORY_SHAPES:
            out[name] = h[name][: self.n_steps, i]
        out["displacement"] = out["centroid"] - self.initial_centroids[i]
        return out

    def resolve_step(self, step_index: int) -> int:
        """Step index in `0..n_steps-1` (negative counts from the end); IndexError outside."""
        k = int(step_index)
        if not -self.n_steps <= k < self.n_steps:
            raise IndexError(f"step index {k} out of range for {self.n_steps} steps")
        return k % self.n_steps

    def centroids(self, step_index: int) -> np.ndarray:
        """Centroids `(n, 3)` of all blocks at a step."""
        return self._file["history/centroid"][self.resolve_step(step_index)]

    def surface(self) -> dict[str, np.ndarray]:
        """Initial surface mesh of all blocks as flat arrays (as in `/blocks`): `vertices
        (V,3)`, `vertex_offsets (n+1,)`, `face_offsets (F+1,)`, `face_connectivity` (global
        vertex ids), `face_block_offsets (n+1,)`."""
        return {"vertices": self._x0, "vertex_offsets": self._voff,
                "face_offsets": self._foff, "face_connectivity": self._fconn,
                "face_block_offsets": self._fboff}

    def history(self, name: str, steps: slice = slice(None)) -> np.ndarray:
        """`/history/<name>` (centroid, rotation, affine, velocity, stress) of all blocks at
        the complete steps `steps` (a slice of `0..n_steps`), `(k, n, ...)`."""
        if name not in HISTORY_SHAPES:
            raise KeyError(f"no history {name!r} (known: {', '.join(HISTORY_SHAPES)})")
        a, b, stride = steps.indices(self.n_steps)
        if b <= a:
            return np.zeros((0, self.n_blocks, *HISTORY_SHAPES[name]))
        return self._file[f"history/{name}"][a:b:stride]

    def initial_vertices(self) -> list[np.ndarray]:
        """Initial surface vertices `(k_b, 3)` of each block."""
        return np.split(self._x0, self._voff[1:-1])

    def faces(self, block: str | int) -> list[np.ndarray]:
        """Faces of a block as arrays of indices into that block's vertex list."""
        b = self.block_index(block)
        f0, f1 = self._fboff[b], self._fboff[b + 1]
        conn = self._fconn[self._foff[f0]: self._foff[f1]] - self._voff[b]
        return np.split(conn, self._foff[f0 + 1: f1] - self._foff[f0])

    def all_vertices(self, step_index: int) -> np.ndarray:
        """Surface vertices of all blocks `(V, 3)` at a step, in `/blocks/vertices` order."""
        k = self.resolve_step(step_index)
        h = self._file["history"]
        vb = self._vblock
        return transform_points(self._x0 - self.initial_centroids[vb], vb,
                                h["centroid"][k], h["affine"][k])

    def vertices(self, step_index: int) -> list[np.ndarray]:
        """Surface vertices `(k_b, 3)` of each block at a step, `centroid + A (X0 - c0)`."""
        return np.split(self.all_vertices(step_index), self._voff[1:-1])

    def contacts(self, step_index: int) -> dict[str, np.ndarray]:
        """Contacts of one step as arrays (`block_i (c,)`, `point_i (c,3)`, ... `shear_force`)."""
        if not self.contacts_recorded:
            raise ValueError("contacts were not recorded for this run (record_contacts=False)")
        k = self.resolve_step(step_index)
        g = self._file["contacts"]
        a, b = g["step_offsets"][k: k + 2]
        return {name: g[name][a:b] for name in CONTACT_FIELDS}


@user_entry("polydda.open_result")
def open_result(path: str | os.PathLike[str]) -> Result:
    """Open a result file read-only (also one still being written or left by a killed run)."""
    return Result(path)


def _growing_rows(name: str, n: int, nv: int, nc: int) -> int:
    """Rows the first `n` steps occupy in the growing dataset `name` (absolute HDF5 path)."""
    if name in ("/VTKHDF/Points", "/VTKHDF/PointData/displacement",
                "/VTKHDF/PointData/velocity"):
        return n * nv
    if name == "/contacts/step_offsets":
        return n + 1
    if name.startswith("/contacts/"):
        return nc
    return n


def recover_result(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> Path:
    """Copy the complete steps of a killed run's file into a new, closed file at `dst`.

    A killed SWMR writer leaves its file marked as open, which only SWMR readers (this
    module) accept; ParaView and h5dump need the copy. The status stays "running".
    """
    dst = Path(dst)
    if dst.exists():
        raise FileExistsError(f"{dst} exists")
    with open_result(src) as r, h5py.File(dst, "x", libver=LIBVER) as out:
        fin = r._file
        n = r.n_steps
        nv = len(r._x0)
        nc = int(fin["contacts/step_offsets"][n])

        def copy(name: str, obj: h5py.Group | h5py.Dataset) -> None:
            if isinstance(obj, h5py.Group):
                g = out.require_group(name)
                g.attrs.update(obj.attrs)
                return
            kw: dict[str, Any] = {"dtype": obj.dtype}
            if obj.maxshape[:1] == (None,):
                rows = _growing_rows(obj.name, n, nv, nc)
                kw.update(shape=(rows, *obj.shape[1:]), maxshape=obj.maxshape,
                          chunks=obj.chunks, compression=obj.compression,
                          compression_opts=obj.compression_opts, shuffle=obj.shuffle)
                ds = out.create_dataset(name, **kw)
                slab = max(1, (16 << 20) // max(1, obj.dtype.itemsize * int(
                    np.prod(obj.shape[1:], dtype=np.int64))))
                for a in range(0, rows, slab):
                    ds[a: min(rows, a + slab)] = obj[a: min(rows, a + slab)]
            else:
                ds = out.create_dataset(name, data=obj[()], **kw)
            ds.attrs.update(obj.attrs)

        out.attrs.update(fin.attrs)
        fin.visititems(copy)
        out["VTKHDF/Steps"].attrs["NSteps"] = np.int64(n)
        out.attrs["recovered_from"] = str(Path(src).resolve())
        out.attrs["message"] = f"recovered {n} complete steps of a run that did not end"
    return dst
