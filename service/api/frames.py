"""Block motion of a result file as compact frames for the browser viewer.

One payload holds a JSON header and little-endian arrays: the block geometry once
(`geometry`: surface vertices relative to `origin`, triangles, edges, initial centroids)
and, per recorded step of a range, each block's rigid motion as float32: `displacement
(m, n, 3)` of its centroid, `rotation (m, n, 4)` a quaternion (x, y, z, w; the rotation of
the polar decomposition of the recorded affine map) and `velocity (m, n, 3)` of its
centroid. A vertex moves to `c0 + d + R (X0 - c0)`. Optional contacts: `contact_offsets
(m+1,)`, `contact_point (c, 3)` (mid-points, relative to `origin`), `contact_mode (c,)`,
`contact_normal (c, 3)` (unit, from block j into block i) and `contact_force (c,)` (normal
force N, compression positive, on block i along the normal; 0 where the run recorded none,
and header `contact_forces` false when no force of the range was recorded).

Binary layout (`encode_binary`): uint32 header length L, L bytes of UTF-8 JSON (padded with
spaces so the arrays start 8-byte aligned), then the arrays, each 8-byte aligned, array `name` at
`4 + L + header["arrays"][name]["offset"]` bytes.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from engine.results.reader import Result

FORMAT = "polydda-frames"
FORMAT_VERSION = 1
#: the motion arrays of one payload stay below this many bytes (`next_start` pages on)
MAX_MOTION_BYTES = 64 * 1024 * 1024
_MOTION_BYTES_PER_BLOCK = 10 * 4  # displacement 3 + rotation 4 + velocity 3, float32


class RangeError(ValueError):
    """A step range that the result does not have (the message says why)."""


@dataclass
class Frames:
    """A payload: its JSON header and its named arrays (in order)."""

    header: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


def ear_clip(points: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles (indices into `points`, in the polygon's winding) of a simple planar
    polygon `(k, 3)`, convex or not, by ear clipping."""
    k = len(points)
    n = np.cross(points, np.roll(points, -1, axis=0)).sum(axis=0)  # Newell normal
    ax = int(np.argmax(np.abs(n)))
    p = points[:, [(ax + 1) % 3, (ax + 2) % 3]].astype(float)
    if n[ax] < 0:
        p[:, 1] *= -1.0  # mirrored: counter-clockwise in this projection
    scale = float(np.ptp(p, axis=0).max()) ** 2 or 1.0

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    idx = list(range(k))
    tris: list[tuple[int, int, int]] = []
    while len(idx) > 3:
        for j in range(len(idx)):
            a, b, c = idx[j - 1], idx[j], idx[(j + 1) % len(idx)]
            if cross(p[a], p[b], p[c]) <= 1e-12 * scale:
                continue  # a reflex or flat corner is no ear
            if any(cross(p[a], p[b], p[q]) >= 0 and cross(p[b], p[c], p[q]) >= 0
                   and cross(p[c], p[a], p[q]) >= 0 for q in idx if q not in (a, b, c)):
                continue  # another vertex lies in the triangle
            tris.append((a, b, c))
            idx.pop(j)
            break
        else:  # degenerate (self-touching) polygon: fan what is left
            tris += [(idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1)]
            return tris
    tris.append((idx[0], idx[1], idx[2]))
    return tris


def _triangles_and_edges(result: Result) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles `(T, 3)` of all faces (global vertex ids; convex faces as fans, the others
    by ear clipping), their block `(T,)` and the unique polygon edges `(E, 2)`."""
    return triangulate(result.surface(), result.n_blocks)


def triangulate(mesh: dict[str, np.ndarray], n_blocks: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_triangles_and_edges` of a surface mesh in the result file's layout
    (`vertices`, `face_offsets`, `face_connectivity`, `face_block_offsets`): also the
    builder's preview of blocks that were never run."""
    x, foff, conn = mesh["vertices"], mesh["face_offsets"], mesh["face_connectivity"]
    fboff = mesh["face_block_offsets"]
    sizes = np.diff(foff)
    face_block = np.repeat(np.arange(n_blocks), np.diff(fboff))
    face_of = np.repeat(np.arange(len(sizes)), sizes)
    nxt = np.arange(len(conn)) + 1
    nxt[foff[1:] - 1] = foff[:-1]  # each face's last vertex closes to its first
    prv = np.arange(len(conn)) - 1
    prv[foff[:-1]] = foff[1:] - 1
    # non-convex faces: a corner that turns against the face's (Newell) normal
    pts = x[conn]
    normal = np.zeros((len(sizes), 3))
    np.add.at(normal, face_of, np.cross(pts, pts[nxt]))
    turn = np.einsum("ij,ij->i", np.cross(pts - pts[prv], pts[nxt] - pts), normal[face_of])
    size2 = float(np.ptp(x, axis=0).max()) ** 2 if len(x) else 1.0
    tol = 1e-9 * size2 * np.linalg.norm(normal, axis=1)[face_of]
    concave = np.zeros(len(sizes), bool)
    concave[face_of[turn < -tol]] = True
    ntri = np.where(concave, 0, np.maximum(sizes - 2, 0))
    tri_face = np.repeat(np.arange(len(sizes)), ntri)
    k = np.arange(len(tri_face)) - (np.cumsum(ntri) - ntri)[tri_face]
    base = foff[:-1][tri_face]  # triangle k of face f: (v0, v[k+1], v[k+2])
    tris = np.stack([conn[base], conn[base + k + 1], conn[base + k + 2]], axis=1)
    extra_tris, extra_face = [], []
    for f in np.flatnonzero(concave):
        ids = conn[foff[f]: foff[f + 1]]
        for t in ear_clip(x[ids]):
            extra_tris.append(ids[list(t)])
            extra_face.append(f)
    if extra_tris:
        tris = np.concatenate([tris, np.array(extra_tris)])
        tri_face = np.concatenate([tri_face, np.array(extra_face)])
        order = np.argsort(tri_face, kind="stable")
        tris, tri_face = tris[order], tri_face[order]
    edges = np.unique(np.sort(np.stack([conn, conn[nxt]], axis=1), axis=1), axis=0)
    return tris, face_block[tri_face], edges


def joint_planes(scene_json: str | None, origin: np.ndarray, extent: np.ndarray,
                 ) -> list[dict[str, Any]]:
    """The scene's joints as polygons relative to `origin` (one plane per joint or set: its
    extent, else a square across the blocks' bounding box `extent`); [] without a scene."""
    try:
        scene = json.loads(scene_json or "{}")
        joints = list(scene.get("joints") or [])
    except (ValueError, AttributeError):
        return []
    size = float(np.linalg.norm(extent)) or 1.0
    out = []
    for k, j in enumerate(joints):
        try:
            d, az = np.radians(float(j["dip"])), np.radians(float(j["dip_direction"]))
            point = np.asarray(j["point"], float)
            ext = j.get("extent") or {}
            n = np.array([np.sin(d) * np.sin(az), np.sin(d) * np.cos(az), np.cos(d)])
            if ext.get("polygon"):
                poly = np.asarray(ext["polygon"], float)
            else:
                u = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
                u /= np.linalg.norm(u)
                v = np.cross(n, u)
                if ext.get("disc"):
                    disc = ext["disc"]
                    c = np.asarray(disc.get("center") or point, float)
                    r, sides = float(disc["radius"]), int(disc.get("sides", 24))
                else:  # persistent: across the blocks, centred where the plane is nearest
                    c = origin - np.dot(origin - point, n) * n
                    r, sides = size / 2, 4
                a = 2 * np.pi * (np.arange(sides) + 0.5) / sides
                poly = c + r * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)
        except (KeyError, TypeError, ValueError):
            continue
        out.append({"name": j.get("name") or f"J{k + 1}", "spacing": j.get("spacing"),
                    "polygon": np.round(poly - origin, 6).tolist()})
    return out


def geometry(result: Result) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header fields and arrays of the block geometry (drawn once)."""
    x0 = result.surface()["vertices"]
    lo = x0.min(axis=0) if len(x0) else np.zeros(3)
    hi = x0.max(axis=0) if len(x0) else np.zeros(3)
    origin = geometry_origin(result)
    tris, tri_block, edges = _triangles_and_edges(result)
    head = {"extent": (hi - lo).tolist(),
            "block_names": result.block_names, "fixed": [bool(f) for f in result.fixed],
            "material": [int(m) for m in result.material],
            "volume": [float(v) for v in result.volume],
            "joints": joint_planes(result.scene_json, origin, hi - lo),
            "stages": _stages(result)}
    arrays = {
        "vertices": (x0 - origin).astype("<f4"),
        "vertex_offsets": result.surface()["vertex_offsets"].astype("<u4"),
        "triangles": tris.astype("<u4"),
        "triangle_block": tri_block.astype("<u4"),
        "edges": edges.astype("<u4"),
        "centroid0": (result.initial_centroids - origin).astype("<f4"),
    }
    return head, arrays


def _stages(result: Result) -> list[dict[str, Any]]:
    """A staged run's stages for the viewer: name, start time (s) and the blocks (indices)
    removed as each starts (empty without stages)."""
    names = list(result.block_names)
    return [{"name": st["name"], "start_time": st["start_time"],
             "removed": [names.index(b) for b in st["removed_blocks"] if b in names]}
            for st in result.stages()]


def _quaternions(affine: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) `(..., 4)` of the rotations nearest the maps `(..., 3, 3)`
    (scipy's from_matrix: the rotation of the polar decomposition, also for a map with
    strain)."""
    flat = affine.reshape(-1, 3, 3)
    if not len(flat):
        return np.zeros((*affine.shape[:-2], 4))
    return Rotation.from_matrix(flat).as_quat().reshape(*affine.shape[:-2], 4)


def frames(result: Result, start: int = 0, stop: int | None = None, stride: int = 1, *,
           with_geometry: bool = True, contacts: bool = False,
           max_motion_bytes: int = MAX_MOTION_BYTES) -> Frames:
    """Recorded steps `start:stop:stride` (stop clipped to the steps written so far) of a
    result as a :class:`Frames` payload; RangeError for a range the result cannot have."""
    n = result.refresh()
    if stride < 1 or start < 0:
        raise RangeError("start must be >= 0 and stride >= 1")
    if start > n:
        raise RangeError(f"start {start} is beyond the {n} recorded steps")
    end = n if stop is None else min(stop, n)
    if end < start:
        raise RangeError(f"stop {stop} is before start {start}")
    idx = np.arange(start, end, stride)
    per_frame = max(1, result.n_blocks * _MOTION_BYTES_PER_BLOCK)
    limit = max(1, max_motion_bytes // per_frame)
    next_start = int(idx[limit]) if len(idx) > limit else None
    idx = idx[:limit]
    sel = slice(start, int(idx[-1]) + 1, stride) if len(idx) else slice(0, 0)
    centroid = result.history("centroid", sel)
    affine = result.history("affine", sel)
    velocity = result.history("velocity", sel)[..., :3]
    out = Frames({"format": FORMAT, "format_version": FORMAT_VERSION,
                  "status": result.status, "n_blocks": result.n_blocks,
                  "n_steps": n, "start": start, "stop": end, "stride": stride,
                  "count": len(idx), "next_start": next_start,
                  "steps": [int(s) for s in result.steps[idx]],
                  "times": [float(t) for t in result.times[idx]],
                  "contacts_recorded": result.contacts_recorded})
    origin = geometry_origin(result)
    out.header["origin"] = origin.tolist()
    if with_geometry:
        head, arrays = geometry(result)
        out.header.update(head)
        out.arrays.update(arrays)
    out.arrays["displacement"] = (centroid - result.initial_centroids).astype("<f4")
    out.arrays["rotation"] = _quaternions(affine).astype("<f4")
    out.arrays["velocity"] = velocity.astype("<f4")
    if contacts and result.contacts_recorded:
        out.header["contact_forces"] = _contacts(result, idx, origin, out.arrays)
    return out


def _contacts(result: Result, idx: np.ndarray, origin: np.ndarray,
              arrays: dict[str, np.ndarray]) -> bool:
    """Put the contacts of recorded steps `idx` into `arrays` (mid-points, modes, normals,
    normal forces); whether any normal force was recorded (NaN in the file: not)."""
    offs, points, modes, normals, forces = [0], [], [], [], []
    for k in idx:
        c = result.contacts(int(k))
        points.append((c["point_i"] + c["point_j"]) / 2 - origin)
        modes.append(c["mode"])
        normals.append(c["normal"])
        forces.append(c["normal_force"])
        offs.append(offs[-1] + len(c["mode"]))

    def joined(parts: list[np.ndarray], shape: tuple[int, ...], dtype: str) -> np.ndarray:
        return (np.concatenate(parts) if parts else np.zeros(shape)).astype(dtype)

    force = joined(forces, (0,), "<f8")
    recorded = np.isfinite(force)
    arrays["contact_offsets"] = np.asarray(offs, "<u4")
    arrays["contact_point"] = joined(points, (0, 3), "<f4")
    arrays["contact_mode"] = joined(modes, (0,), "<i1")
    arrays["contact_normal"] = joined(normals, (0, 3), "<f4")
    arrays["contact_force"] = np.where(recorded, force, 0.0).astype("<f4")
    return bool(recorded.any())


def geometry_origin(result: Result) -> np.ndarray:
    """The origin the geometry's coordinates are relative to (centre of its bounding box)."""
    x0 = result.surface()["vertices"]
    return (x0.min(axis=0) + x0.max(axis=0)) / 2 if len(x0) else np.zeros(3)


def encode_binary(payload: Frames) -> bytes:
    """The binary form: uint32 header length, JSON header, 8-byte aligned arrays."""
    specs: dict[str, dict[str, Any]] = {}
    offset = 0
    for name, a in payload.arrays.items():
        specs[name] = {"dtype": a.dtype.name, "shape": list(a.shape), "offset": offset}
        offset += -(-a.nbytes // 8) * 8
    text = json.dumps({**payload.header, "arrays": specs}, separators=(",", ":"),
                      allow_nan=False).encode()
    text += b" " * (-(4 + len(text)) % 8)
    parts = [struct.pack("<I", len(text)), text]
    for a in payload.arrays.values():
        raw = np.ascontiguousarray(a).tobytes()
        parts += [raw, b"\0" * (-len(raw) % 8)]
    return b"".join(parts)


def decode_binary(data: bytes) -> Frames:
    """Inverse of encode_binary (for tests and Python clients)."""
    (size,) = struct.unpack_from("<I", data)
    header = json.loads(data[4: 4 + size])
    arrays = {name: np.frombuffer(data, dtype=np.dtype(spec["dtype"]).newbyteorder("<"),
                                  count=int(np.prod(spec["shape"], dtype=np.int64)),
                                  offset=4 + size + spec["offset"]).reshape(spec["shape"])
              for name, spec in header.pop("arrays").items()}
    return Frames(header, arrays)


def to_json(payload: Frames) -> dict[str, Any]:
    """The JSON form: the header with each array as nested lists."""
    return {**payload.header, **{k: v.tolist() for k, v in payload.arrays.items()}}
