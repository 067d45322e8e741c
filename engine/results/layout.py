"""The layout of a result file: what the writer and the reader of the HDF5 file agree on.

One HDF5 file per run (:mod:`engine.results.writer` writes it, :mod:`engine.results.reader`
reads it): the format's name and versions, the statuses a run ends with, the HDF5 format
bounds, the tables of per-step datasets (history, contacts, bolts), the initial geometry
flattened into global arrays, and the transforms that turn the stored block motions into
moved points and point velocities (the writer's VTKHDF points, the reader's vertices).
Layout (K steps, n blocks, V surface vertices, F faces, C contacts in all):

- root attrs: `format` "polydda-result", `format_version`, `engine_version`,
  `schema_version` (when known), `status`, `message`, `summary` (JSON text, set by end)
- `/scene`: `json` (scalar text) with attr `sha256` (hex digest of the UTF-8 text)
- `/blocks`: `vertices (V,3)` initial surface vertices of all blocks, `vertex_offsets (n+1,)`,
  `face_offsets (F+1,)`, `face_connectivity` global indices into `/blocks/vertices`,
  `face_block_offsets (n+1,)` (block b owns faces `face_block_offsets[b]:[b+1]`),
  `face_tags (F,)`, `names (n,)`, `material (n,)`, `fixed (n,)`, `centroid (n,3)`,
  `volume (n,)`
- `/steps`: `step`, `time`, `dt`, `open_close_iterations`, `max_penetration` `(K,)` and
  `energies/<name> (K,)` J
- `/history`: `centroid (K,n,3)`, `rotation (K,n,3)`, `affine (K,n,3,3)`,
  `velocity (K,n,12)`, `stress (K,n,6)`; vertices are `centroid + affine @ (X0 - c0)`
- `/contacts` (attr `recorded`): `step_offsets (K+1,)`, step k is rows
  `step_offsets[k]:step_offsets[k+1]` of `block_i`, `block_j`, `kind`, `mode`,
  `point_i (C,3)`, `point_j`, `normal`, `tangent`, `gap (C,)`, `normal_force (C,)`,
  `shear_force (C,3)`
- `/bolts` (only for a model with rock bolts, b of them): `names (b,)`, `block (b,)`,
  `anchor_block (b,)` (-1: the ground), `head (b,3)`, `anchor (b,3)` m, `pretension (b,)`,
  `capacity (b,)` N; per step `axial_force (K,b)` N (tension positive), `shear_force (K,b)` N,
  `status (K,b)` (0 elastic, 1 yielded, 2 broken)
- `/water` (only for a model with water in its joints): per step `resultant (K,n,3)` N, the
  resultant water force on each block
- `/stages` (only for a staged run, S stages, written at its end): `names (S,)`,
  `start_time`, `end_time (S,)` s, `start_step`, `end_step (S,)` (the steps of
  `/steps/step` where each begins and ends), `status (S,)`, `removed_energy (S,)` J,
  `removed_blocks (S,)` and `bolts (S,)` (JSON lists of the block names removed as the
  stage starts and of the bolts acting in it). A removed block stays in `/history`
  frozen where it was removed
- `/VTKHDF`: VTKHDF 2.2 temporal PolyData for ParaView (block faces as polygons, points
  written per step, connectivity shared by all steps; point data `block_id`,
  `displacement`, `velocity`; cell data `block_id`, `face_tag`)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.geometry._transform_kernels import block_vertices, point_motions
from engine.model import Model

FORMAT = "polydda-result"
FORMAT_VERSION = 1
VTKHDF_VERSION = (2, 2)
STATUSES = ("completed", "failed", "cancelled", "stopped")
#: HDF5 file-format bounds: 1.10 is the oldest that has SWMR; ParaView >= 5.x reads it
LIBVER = ("v110", "v110")
#: per-step block histories under /history: the shape of one block's row
HISTORY_SHAPES = {"centroid": (3,), "rotation": (3,), "affine": (3, 3),
                  "velocity": (12,), "stress": (6,)}
#: per-step bolt datasets under /bolts: frame attribute and dtype
BOLT_FIELDS: dict[str, tuple[str, type]] = {
    "axial_force": ("bolt_axial_force", np.float64),
    "shear_force": ("bolt_shear_force", np.float64),
    "status": ("bolt_status", np.int8),
}
#: contact datasets under /contacts (one row per contact): row shape and dtype
CONTACT_FIELDS: dict[str, tuple[tuple[int, ...], type]] = {
    "block_i": ((), np.int32), "block_j": ((), np.int32), "kind": ((), np.int8),
    "mode": ((), np.int8), "point_i": ((3,), np.float64), "point_j": ((3,), np.float64),
    "normal": ((3,), np.float64), "tangent": ((3,), np.float64), "gap": ((), np.float64),
    "normal_force": ((), np.float64), "shear_force": ((3,), np.float64),
}


def engine_version() -> str:
    """The installed polydda version, "unknown" in a source checkout (a root attribute)."""
    try:
        from importlib.metadata import version

        return version("polydda")
    except Exception:  # not installed (source checkout)
        return "unknown"


def json_default(obj: Any) -> Any:
    """JSON encoding of numpy scalars and arrays (summaries carry them)."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


@dataclass
class Static:
    """Initial geometry of all blocks, flattened (what the writer and plots need)."""

    vertices: np.ndarray  # (V, 3)
    vertex_offsets: np.ndarray  # (n+1,)
    vertex_block: np.ndarray  # (V,) block of each vertex
    face_offsets: np.ndarray  # (F+1,)
    face_connectivity: np.ndarray  # global vertex ids
    face_block_offsets: np.ndarray  # (n+1,)
    face_tags: np.ndarray  # (F,)
    centroid: np.ndarray  # (n, 3) initial centroids


def flatten_model(model: Model) -> Static:
    """Surface vertices and faces of all blocks renumbered into global arrays."""
    verts, vcount, fptr, fconn, fcount, tags, cents = [], [], [], [], [], [], []
    base = 0
    for block in model.blocks:
        poly = block.polyhedron
        used = poly.surface_vertex_ids
        remap = np.full(len(poly.vertices), -1, dtype=np.int64)
        remap[used] = np.arange(len(used)) + base
        verts.append(poly.vertices[used])
        vcount.append(len(used))
        fptr.append(np.diff(poly.face_indptr))
        fconn.append(remap[poly.face_indices])
        fcount.append(poly.n_faces)
        tags.append(np.asarray(poly.face_tags, dtype=np.int64))
        cents.append(poly.centroid)
        base += len(used)
    n = len(model.blocks)

    def offsets(counts: list[int] | np.ndarray) -> np.ndarray:
        out = np.zeros(len(counts) + 1, dtype=np.int64)
        np.cumsum(counts, out=out[1:])
        return out

    face_sizes = np.concatenate(fptr) if fptr else np.zeros(0, np.int64)
    vo = offsets(vcount)
    return Static(
        vertices=np.concatenate(verts) if verts else np.zeros((0, 3)),
        vertex_offsets=vo,
        vertex_block=np.repeat(np.arange(n), np.diff(vo)),
        face_offsets=offsets(face_sizes),
        face_connectivity=np.concatenate(fconn) if fconn else np.zeros(0, np.int64),
        face_block_offsets=offsets(fcount),
        face_tags=np.concatenate(tags) if tags else np.zeros(0, np.int64),
        centroid=np.array(cents, dtype=float).reshape(n, 3),
    )


def point_velocities(
    points: np.ndarray, centroids: np.ndarray, velocity: np.ndarray
) -> np.ndarray:
    """Velocity `(p, 3)` of points `(p, 3)` from their block's `centroids (p, 3)` and rates
    `velocity (p, 12)`: T(x) v (:func:`engine.geometry._transform_kernels.point_motion`)."""
    return point_motions(np.ascontiguousarray(points, dtype=float),
                         np.ascontiguousarray(centroids, dtype=float),
                         np.ascontiguousarray(velocity, dtype=float))


def transform_points(rel0: np.ndarray, vertex_block: np.ndarray, centroids: np.ndarray,
                     affine: np.ndarray) -> np.ndarray:
    """Moved points `c + A (X0 − c0)` `(..., p, 3)` of points `rel0 = X0 − c0 (p, 3)` of
    blocks `vertex_block (p,)`, for block `centroids (..., n, 3)` and `affine (..., n, 3,
    3)`; leading axes (steps) broadcast
    (:func:`engine.geometry._transform_kernels.block_vertices`)."""
    lead = centroids.shape[:-2]
    cent = np.ascontiguousarray(centroids, dtype=float).reshape(-1, *centroids.shape[-2:])
    aff = np.ascontiguousarray(affine, dtype=float).reshape(-1, *affine.shape[-3:])
    rel = np.ascontiguousarray(rel0, dtype=float)
    vb = np.ascontiguousarray(vertex_block, dtype=np.int64)
    out = np.stack([block_vertices(c, a, vb, rel) for c, a in zip(cent, aff, strict=True)])
    return out.reshape(*lead, len(rel), 3)

