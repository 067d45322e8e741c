"""Contact detection: broad phase on bounding boxes, narrow phase between convex pieces.

Concave blocks are handled through their convex pieces (paper section 2.2.2): every
convex piece of one block is tested against every nearby convex piece of another, so a
vertex in a concave corner gets one constraint per convex sub-angle. The narrow phase
finds the four basic types (paper Fig. 2) - vertex-face, crossing edge-edge,
vertex-edge and vertex-vertex - vectorised over all piece pairs at once, and picks the
plane of vertex-edge and vertex-vertex contacts by the shortest exit rule (paper eq. 4).

Conventions: `block_i > block_j`; the normal points from block j into block i;
`gap = (point_i - point_j) . normal`. Feature codes: see :func:`feature_code`.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.contacts import (
    EDGE_EDGE,
    LOCKED,
    OPEN,
    VERTEX_EDGE,
    VERTEX_FACE,
    VERTEX_VERTEX,
    ContactSet,
)
from engine.geometry import ConvexPiece, Polyhedron, edge_topology
from engine.tolerances import DEFAULT_TOLERANCES, Tolerances

FEATURE_VERTEX, FEATURE_EDGE, FEATURE_FACE = 0, 1, 2

#: sine of the angle a cone edge may dip through a contact plane and still count as
#: entering / not overlapping: a block tilted by up to ~3 degrees in a step (paper
#: section 5.2, theta = 1-3 deg) keeps its face-to-face contacts
ENTRANCE_TOLERANCE = 0.05

_I64 = np.int64


# --------------------------------------------------------------------------- feature codes


def feature_code(piece: np.ndarray | int, kind: np.ndarray | int,
                 index: np.ndarray | int) -> np.ndarray:
    """Stable int64 id of a feature: `((piece * 4 + kind) << 32) | index`.

    `piece` is the piece number within its block, `kind` FEATURE_VERTEX / EDGE / FACE,
    `index` the block vertex id (vertices) or the piece-local edge / face id.
    """
    p, k, i = (np.asarray(x, dtype=_I64) for x in (piece, kind, index))
    return ((p * 4 + k) << 32) | i


def decode_feature(code: np.ndarray | int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`feature_code`: `(piece, kind, index)`."""
    c = np.asarray(code, dtype=_I64)
    return (c >> 32) // 4, (c >> 32) % 4, c & 0xFFFFFFFF


# --------------------------------------------------------------------------- broad phase


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ragged expansion: `(owner, local)` with `owner` repeated `counts` times."""
    counts = np.asarray(counts, dtype=_I64)
    owner = np.repeat(np.arange(len(counts), dtype=_I64), counts)
    start = np.cumsum(counts) - counts
    return owner, np.arange(owner.size, dtype=_I64) - start[owner]


def aabb_pairs(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """All pairs `(k, 2)` (a < b, sorted) of boxes `lower, upper (n, 3)` that overlap.

    Uniform-grid hashing, linear in the number of boxes for boxes of similar size:
    each pair is reported only from the cell holding the lower corner of its overlap.
    """
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    n = len(lower)
    if n < 2:
        return np.zeros((0, 2), dtype=_I64)
    size = (upper - lower).max(axis=1)
    h = max(float(np.median(size)), 1e-12 * max(float(np.ptp(upper.max(0) - lower.min(0))), 1.0))
    origin = lower.min(axis=0)
    while True:
        c0 = np.floor((lower - origin) / h).astype(_I64)
        c1 = np.floor((upper - origin) / h).astype(_I64)
        span = c1 - c0 + 1
        counts = span.prod(axis=1)
        if counts.sum() <= 27 * n + 1000:
            break
        h *= 2.0
    box, local = _expand(counts)
    sy, sz = span[box, 1], span[box, 2]
    cell = c0[box] + np.stack([local // (sy * sz), (local // sz) % sy, local % sz], axis=1)
    m = int(c1.max()) + 2
    key = (cell[:, 0] * m + cell[:, 1]) * m + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key, box, cell = key[order], box[order], cell[order]
    brk = np.flatnonzero(np.diff(key)) + 1
    gstart = np.r_[0, brk]
    gend = np.r_[brk, len(key)]
    glen = gend - gstart
    end_of = np.repeat(gend, glen)
    after = end_of - np.arange(len(key)) - 1
    first, off = _expand(after)
    second = first + 1 + off
    a, b = box[first], box[second]
    ok = np.all(lower[a] <= upper[b], axis=1) & np.all(lower[b] <= upper[a], axis=1)
    corner = np.maximum(lower[a], lower[b])
    ccell = np.floor((corner - origin) / h).astype(_I64)
    ok &= np.all(ccell == cell[first], axis=1)
    pairs = np.stack([np.minimum(a, b)[ok], np.maximum(a, b)[ok]], axis=1)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


# --------------------------------------------------------------------------- piece topology


@dataclass(frozen=True)
class _PieceTopo:
    """Position-independent data of one convex piece (block-local vertex ids)."""

    face_vtx: np.ndarray  # (m, K) face vertices, padded by repeating the last one
    face_nxt: np.ndarray  # (m, K) next vertex of each face edge (pad: same as face_vtx)
    face_edge: np.ndarray  # (m, K) piece edge id of each face edge (pad: -1)
    face_valid: np.ndarray  # (m, K) bool
    face_surface: np.ndarray  # (m,) block face or -1
    edges: np.ndarray  # (e, 2) block vertex ids
    edge_faces: np.ndarray  # (e, 2) piece face ids
    edge_real: np.ndarray  # (e,) both faces are real block faces
    verts: np.ndarray  # (k,) block vertex ids of the piece
    vert_surface: np.ndarray  # (k,) vertex is a surface vertex of the block
    vert_nb: np.ndarray  # (k, D) neighbour vertex ids along piece edges (pad -1)
    vert_nb_real: np.ndarray  # (k, D) that edge is real
    vert_faces: np.ndarray  # (k, Df) incident real piece faces (pad -1)


_TOPO_CACHE: dict[tuple[int, int, int], _PieceTopo] = {}


def _pad_rows(rows: list[list[int]], fill: int = -1) -> np.ndarray:
    width = max((len(r) for r in rows), default=0)
    out = np.full((len(rows), max(width, 1)), fill, dtype=_I64)
    for k, r in enumerate(rows):
        out[k, : len(r)] = r
    return out


def _piece_topology(piece: ConvexPiece, block: Polyhedron) -> _PieceTopo:
    """Topology of `piece`, cached while its face arrays live (blocks keep them when moved)."""
    key = (id(piece.face_indptr), id(piece.face_indices), id(block.face_indices))
    hit = _TOPO_CACHE.get(key)
    if hit is not None:
        return hit
    indptr, indices = piece.face_indptr, piece.face_indices
    surface = np.asarray(piece.face_surface, dtype=_I64)
    edges, edge_faces, _, _ = edge_topology(indptr, indices)
    m = len(indptr) - 1
    emap = {(int(min(a, b)), int(max(a, b))): k for k, (a, b) in enumerate(edges)}
    faces = [indices[indptr[f]:indptr[f + 1]].tolist() for f in range(m)]
    width = max(len(f) for f in faces)
    fv = np.zeros((m, width), dtype=_I64)
    fn = np.zeros((m, width), dtype=_I64)
    fe = np.full((m, width), -1, dtype=_I64)
    valid = np.zeros((m, width), dtype=bool)
    for f, poly in enumerate(faces):
        c = len(poly)
        nxt = poly[1:] + poly[:1]
        fv[f, :c], fv[f, c:] = poly, poly[-1]
        fn[f, :c], fn[f, c:] = nxt, poly[-1]
        fe[f, :c] = [emap[(min(a, b), max(a, b))] for a, b in zip(poly, nxt, strict=True)]
        valid[f, :c] = True
    real_face = surface >= 0
    edge_real = real_face[edge_faces[:, 0]] & real_face[edge_faces[:, 1]] & (edge_faces.min(1) >= 0)
    verts = np.unique(indices)
    slot = {int(v): k for k, v in enumerate(verts)}
    nb: list[list[int]] = [[] for _ in verts]
    nb_real: list[list[int]] = [[] for _ in verts]
    for (a, b), r in zip(edges.tolist(), edge_real.tolist(), strict=True):
        nb[slot[a]].append(b)
        nb[slot[b]].append(a)
        nb_real[slot[a]].append(int(r))
        nb_real[slot[b]].append(int(r))
    vf: list[list[int]] = [[] for _ in verts]
    for f, poly in enumerate(faces):
        if real_face[f]:
            for v in poly:
                vf[slot[v]].append(f)
    topo = _PieceTopo(
        fv, fn, fe, valid, surface, edges, edge_faces, edge_real, verts,
        np.isin(verts, block.surface_vertex_ids), _pad_rows(nb),
        _pad_rows(nb_real, 0).astype(bool), _pad_rows(vf),
    )
    _TOPO_CACHE[key] = topo
    weakref.finalize(piece.face_indices, _TOPO_CACHE.pop, key, None)
    return topo


# --------------------------------------------------------------------------- scene arrays


def _pad_to(a: np.ndarray, width: int, fill: int | bool) -> np.ndarray:
    if a.shape[1] >= width:
        return a
    pad = np.full((a.shape[0], width - a.shape[1]), fill, dtype=a.dtype)
    return np.concatenate([a, pad], axis=1)


def _cat_padded(parts: list[np.ndarray], fill: int | bool, offsets: list[int] | None = None,
                repeat_last: bool = False) -> np.ndarray:
    """Concatenate 2-D int tables of differing widths (padding) and add row offsets."""
    width = max(p.shape[1] for p in parts)
    out = []
    for k, p in enumerate(parts):
        q = p + offsets[k] if offsets is not None else p
        if offsets is not None and not repeat_last:
            q = np.where(p < 0, -1, q)
        if repeat_last:
            q = np.concatenate([q, np.repeat(q[:, -1:], width - q.shape[1], axis=1)], axis=1)
        else:
            q = _pad_to(q, width, fill)
        out.append(q)
    return np.concatenate(out)


@dataclass
class _Scene:
    """All blocks' pieces flattened into global arrays (g = global vertex ids)."""

    x: np.ndarray  # (nv, 3)
    v_surface: np.ndarray  # (nv,)
    v_local: np.ndarray  # (nv,) block-local vertex id
    v_block: np.ndarray  # (nv,)
    piece_block: np.ndarray  # (P,)
    piece_local: np.ndarray  # (P,)
    f_start: np.ndarray  # (P,)
    f_count: np.ndarray
    e_start: np.ndarray
    e_count: np.ndarray
    pv_start: np.ndarray
    pv_count: np.ndarray
    f_vtx: np.ndarray  # (F, K) g
    f_nxt: np.ndarray  # (F, K) g
    f_edge: np.ndarray  # (F, K) global edge (-1 pad)
    f_valid: np.ndarray
    f_local: np.ndarray  # (F,)
    f_tag: np.ndarray  # (F,) block face tag, -1 for fictitious faces
    f_real: np.ndarray
    e_vtx: np.ndarray  # (E, 2) g
    e_faces: np.ndarray  # (E, 2) global faces
    e_local: np.ndarray
    e_real: np.ndarray
    pv_vtx: np.ndarray  # (V,) g
    pv_surface: np.ndarray
    pv_nb: np.ndarray  # (V, D) g, -1 pad
    pv_nb_real: np.ndarray
    pv_faces: np.ndarray  # (V, Df) global faces, -1 pad


def _build_scene(blocks: Sequence[Polyhedron]) -> _Scene:
    """Gather topology of every piece of every block into flat global arrays."""
    xs, vsurf, vloc, vblk = [], [], [], []
    pblock, plocal = [], []
    fv, fn, fe, fval, floc, ftag, freal = [], [], [], [], [], [], []
    ev, ef, eloc, ereal = [], [], [], []
    pvv, pvs, pvnb, pvnbr, pvf = [], [], [], [], []
    voffs, foffs, eoffs = [], [], []
    f_count, e_count, pv_count = [], [], []
    vo = fo = eo = 0
    for b, block in enumerate(blocks):
        nv = len(block.vertices)
        xs.append(block.vertices)
        surf = np.zeros(nv, dtype=bool)
        surf[block.surface_vertex_ids] = True
        vsurf.append(surf)
        vloc.append(np.arange(nv, dtype=_I64))
        vblk.append(np.full(nv, b, dtype=_I64))
        for p, piece in enumerate(block.convex_pieces()):
            t = _piece_topology(piece, block)
            m, ne = len(t.face_surface), len(t.edges)
            pblock.append(b)
            plocal.append(p)
            fv.append(t.face_vtx)
            fn.append(t.face_nxt)
            fe.append(t.face_edge)
            fval.append(t.face_valid)
            floc.append(np.arange(m, dtype=_I64))
            ftag.append(np.where(t.face_surface >= 0,
                                 block.face_tags[np.maximum(t.face_surface, 0)], -1))
            freal.append(t.face_surface >= 0)
            ev.append(t.edges + vo)
            ef.append(t.edge_faces + fo)
            eloc.append(np.arange(ne, dtype=_I64))
            ereal.append(t.edge_real)
            pvv.append(t.verts + vo)
            pvs.append(t.vert_surface)
            pvnb.append(t.vert_nb)
            pvnbr.append(t.vert_nb_real)
            pvf.append(t.vert_faces)
            voffs.append(vo)
            foffs.append(fo)
            eoffs.append(eo)
            f_count.append(m)
            e_count.append(ne)
            pv_count.append(len(t.verts))
            fo += m
            eo += ne
        vo += nv

    def starts(c: list[int]) -> tuple[np.ndarray, np.ndarray]:
        cnt = np.asarray(c, dtype=_I64)
        return np.cumsum(cnt) - cnt, cnt

    fs, fc = starts(f_count)
    es, ec = starts(e_count)
    ps, pc = starts(pv_count)
    return _Scene(
        x=np.concatenate(xs).astype(float), v_surface=np.concatenate(vsurf),
        v_local=np.concatenate(vloc), v_block=np.concatenate(vblk),
        piece_block=np.asarray(pblock, dtype=_I64), piece_local=np.asarray(plocal, dtype=_I64),
        f_start=fs, f_count=fc, e_start=es, e_count=ec, pv_start=ps, pv_count=pc,
        f_vtx=_cat_padded(fv, 0, voffs, repeat_last=True),
        f_nxt=_cat_padded(fn, 0, voffs, repeat_last=True),
        f_edge=_cat_padded(fe, -1, eoffs),
        f_valid=_cat_padded(fval, False),
        f_local=np.concatenate(floc), f_tag=np.concatenate(ftag).astype(_I64),
        f_real=np.concatenate(freal),
        e_vtx=np.concatenate(ev), e_faces=np.concatenate(ef), e_local=np.concatenate(eloc),
        e_real=np.concatenate(ereal),
        pv_vtx=np.concatenate(pvv), pv_surface=np.concatenate(pvs),
        pv_nb=_cat_padded(pvnb, -1, voffs), pv_nb_real=_cat_padded(pvnbr, False),
        pv_faces=_cat_padded(pvf, -1, foffs),
    )


@dataclass
class _Geom:
    """Position-dependent quantities of a scene."""

    f_normal: np.ndarray  # (F, 3) outward unit normals
    f_offset: np.ndarray  # (F,)
    e_dir: np.ndarray  # (E, 3) b - a
    e_in: np.ndarray  # (E, 2, 3) unit in-face directions perpendicular to the edge
    e_flat: np.ndarray  # (E,) the two faces are coplanar
    pv_dir: np.ndarray  # (V, D, 3) unit edge directions at each piece vertex (0 pad)
    p_lo: np.ndarray  # (P, 3)
    p_hi: np.ndarray
    e_lo: np.ndarray  # (E, 3) edge boxes
    e_hi: np.ndarray


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def _geometry(s: _Scene, parallel: float) -> _Geom:
    """Normals, offsets, edge wedges, vertex cones and piece boxes at current positions."""
    x = s.x
    a, b = x[s.f_vtx], x[s.f_nxt]
    c = x[s.f_vtx[:, 0]][:, None, :]
    normal = _unit(np.cross(a - c, b - c).sum(axis=1))
    offset = np.einsum("ij,ij->i", normal, x[s.f_vtx[:, 0]])
    d = x[s.e_vtx[:, 1]] - x[s.e_vtx[:, 0]]
    n1, n2 = normal[s.e_faces[:, 0]], normal[s.e_faces[:, 1]]
    e_in = np.stack([_unit(np.cross(n1, d)), _unit(np.cross(n2, -d))], axis=1)
    flat = np.einsum("ij,ij->i", n1, n2) > 1.0 - parallel
    nb = s.pv_nb
    pv_dir = np.where((nb >= 0)[..., None],
                      _unit(x[np.maximum(nb, 0)] - x[s.pv_vtx][:, None, :]), 0.0)
    px = x[s.pv_vtx]
    lo = np.minimum.reduceat(px, s.pv_start, axis=0)
    hi = np.maximum.reduceat(px, s.pv_start, axis=0)
    ea, eb = x[s.e_vtx[:, 0]], x[s.e_vtx[:, 1]]
    return _Geom(normal, offset, d, e_in, flat, pv_dir, lo, hi,
                 np.minimum(ea, eb), np.maximum(ea, eb))


# --------------------------------------------------------------------------- narrow phase


@dataclass
class _Raw:
    """Contacts found in one pass, in the roles X (vertex side) and Y, before mapping to i/j."""

    pair: np.ndarray
    flip: np.ndarray  # X is the piece of block j
    kind: np.ndarray
    fx: np.ndarray  # feature codes
    fy: np.ndarray
    px: np.ndarray
    py: np.ndarray
    normal: np.ndarray  # from Y into X
    gap: np.ndarray
    tag: np.ndarray
    vx: np.ndarray  # global vertex of X (-1 for edge-edge)
    vy: np.ndarray  # global vertex of Y (-1 unless vertex-vertex)
    cand_count: np.ndarray
    cand: np.ndarray  # (sum cand_count, 3)


def _empty_raw() -> _Raw:
    z = np.zeros(0, dtype=_I64)
    z3 = np.zeros((0, 3))
    return _Raw(z, z.astype(bool), z, z, z, z3, z3, z3, np.zeros(0), z, z, z, z, z3)


def _cat_raw(parts: list[_Raw]) -> _Raw:
    return _Raw(*(np.concatenate([getattr(p, f) for p in parts])
                  for f in _Raw.__dataclass_fields__))


@dataclass
class _Ctx:
    """What every narrow-phase pass needs."""

    s: _Scene
    g: _Geom
    search: float
    snap: float
    ang: float
    parallel: float
    entrance: float = 0.0


def _vertices_near(ctx: _Ctx, xp: np.ndarray, yp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(pair, pv)`: surface vertices of piece `xp[pair]` inside the inflated box of `yp[pair]`."""
    s, g = ctx.s, ctx.g
    own, loc = _expand(s.pv_count[xp])
    pv = s.pv_start[xp][own] + loc
    x = s.x[s.pv_vtx[pv]]
    r = ctx.search + ctx.snap
    ok = s.pv_surface[pv]
    ok &= np.all(x >= g.p_lo[yp[own]] - r, axis=1) & np.all(x <= g.p_hi[yp[own]] + r, axis=1)
    return own[ok], pv[ok]


def _edges_near(ctx: _Ctx, ep: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(pair, edge)`: real convex edges of piece `ep[pair]` whose box meets `other[pair]`'s."""
    s, g = ctx.s, ctx.g
    own, loc = _expand(s.e_count[ep])
    e = s.e_start[ep][own] + loc
    a, b = s.x[s.e_vtx[e, 0]], s.x[s.e_vtx[e, 1]]
    r = ctx.search + ctx.snap
    ok = s.e_real[e] & ~g.e_flat[e]
    ok &= np.all(np.minimum(a, b) <= g.p_hi[other[own]] + r, axis=1)
    ok &= np.all(np.maximum(a, b) >= g.p_lo[other[own]] - r, axis=1)
    return own[ok], e[ok]


def _codes(s: _Scene, piece: np.ndarray, kind: int, index: np.ndarray) -> np.ndarray:
    return feature_code(s.piece_local[piece], kind, index)


def _vertex_face(ctx: _Ctx, xp: np.ndarray, yp: np.ndarray, flip: bool) -> _Raw:
    """Vertices of pieces `xp` strictly inside real faces of pieces `yp` (entrance-checked)."""
    s, g = ctx.s, ctx.g
    own, pv = _vertices_near(ctx, xp, yp)
    o2, loc = _expand(s.f_count[yp[own]])
    pair, pv = own[o2], pv[o2]
    f = s.f_start[yp[pair]] + loc
    x = s.x[s.pv_vtx[pv]]
    n = g.f_normal[f]
    d = np.einsum("ij,ij->i", n, x) - g.f_offset[f]
    ok = s.f_real[f] & (d < ctx.search + ctx.snap) & (d > -(2 * ctx.search + ctx.snap))
    ok &= np.einsum("ikj,ij->ik", g.pv_dir[pv], n).min(axis=1) >= -ctx.entrance
    pair, pv, f, x, n, d = pair[ok], pv[ok], f[ok], x[ok], n[ok], d[ok]
    proj = x - d[:, None] * n
    a, b = s.x[s.f_vtx[f]], s.x[s.f_nxt[f]]
    t = b - a
    length = np.linalg.norm(t, axis=2)
    inward = np.einsum("ikj,ikj->ik", proj[:, None, :] - a, np.cross(n[:, None, :], t))
    dist = np.divide(inward, length, out=np.full_like(inward, np.inf), where=length > 0)
    fe = s.f_edge[f]
    sharp = (fe >= 0) & s.e_real[np.maximum(fe, 0)] & ~ctx.g.e_flat[np.maximum(fe, 0)]
    # beyond a seam edge (fictitious neighbour: concave corner or flat seam) the face
    # plane continues as the plane of its convex sub-angle, up to the search distance
    thr = np.where(sharp, ctx.snap, -(ctx.search + ctx.snap))
    dist = np.where(s.f_valid[f], dist, np.inf)
    ok = np.all(dist >= thr, axis=1)
    pair, pv, f, x, n, d, proj = pair[ok], pv[ok], f[ok], x[ok], n[ok], d[ok], proj[ok]
    xpc, ypc = xp[pair], yp[pair]
    k = len(pair)
    return _Raw(
        pair, np.full(k, flip), np.full(k, VERTEX_FACE, dtype=_I64),
        _codes(s, xpc, FEATURE_VERTEX, s.v_local[s.pv_vtx[pv]]),
        _codes(s, ypc, FEATURE_FACE, s.f_local[f]),
        x, proj, n, d, s.f_tag[f], s.pv_vtx[pv], np.full(k, -1, dtype=_I64),
        np.zeros(k, dtype=_I64), np.zeros((0, 3)),
    )


def _edge_edge(ctx: _Ctx, ap: np.ndarray, bp: np.ndarray) -> _Raw:
    """Crossing edge-edge contacts between real convex edges of pieces `ap` (i) and `bp` (j)."""
    s, g = ctx.s, ctx.g
    pa, ea = _edges_near(ctx, ap, bp)
    pb, eb = _edges_near(ctx, bp, ap)
    if len(pa) == 0 or len(pb) == 0:
        return _empty_raw()
    cnt_b = np.bincount(pb, minlength=len(ap))
    start_b = np.cumsum(cnt_b) - cnt_b
    o, loc = _expand(cnt_b[pa])
    pair, e1, e2 = pa[o], ea[o], eb[start_b[pa[o]] + loc]
    r = ctx.search + ctx.snap
    lo1, hi1 = g.e_lo[e1], g.e_hi[e1]
    lo2, hi2 = g.e_lo[e2], g.e_hi[e2]
    near = np.all(lo1 <= hi2 + r, axis=1) & np.all(lo2 <= hi1 + r, axis=1)
    pair, e1, e2 = pair[near], e1[near], e2[near]
    p0, u = s.x[s.e_vtx[e1, 0]], g.e_dir[e1]
    q0, v = s.x[s.e_vtx[e2, 0]], g.e_dir[e2]
    w0 = p0 - q0
    aa, bb, cc = (np.einsum("ij,ij->i", *uv) for uv in ((u, u), (u, v), (v, v)))
    dd, ee = np.einsum("ij,ij->i", u, w0), np.einsum("ij,ij->i", v, w0)
    den = aa * cc - bb * bb
    # nearly parallel edges (they drift apart by less than the search distance over
    # the shorter one) are a parallel edge-edge contact: v-e at the overlap ends
    sin2 = den / (aa * cc)
    ok = (sin2 > 2.0 * ctx.parallel) & (sin2 * np.minimum(aa, cc) > ctx.search**2)
    den = np.where(ok, den, 1.0)
    sp = (bb * ee - cc * dd) / den
    tq = (aa * ee - bb * dd) / den
    ok &= _inside_edge(ctx, e1, sp, np.sqrt(aa)) & _inside_edge(ctx, e2, tq, np.sqrt(cc))
    pi = p0 + sp[:, None] * u
    pj = q0 + tq[:, None] * v
    n0 = _unit(np.cross(u, v))
    ok &= np.linalg.norm(pi - pj, axis=1) < ctx.search + ctx.snap
    ina = np.einsum("ikj,ij->ik", g.e_in[e1], n0)
    inb = np.einsum("ikj,ij->ik", g.e_in[e2], n0)
    m_plus = np.minimum(ina.min(1), -inb.max(1))
    m_minus = np.minimum(-ina.max(1), inb.min(1))
    plus = m_plus >= m_minus
    ok &= np.maximum(m_plus, m_minus) >= -ctx.entrance
    sign = np.where(plus, 1.0, -1.0)[:, None]
    n = (n0 * sign)[ok]
    pair, e1, e2, pi, pj = pair[ok], e1[ok], e2[ok], pi[ok], pj[ok]
    k = len(pair)
    return _Raw(
        pair, np.zeros(k, dtype=bool), np.full(k, EDGE_EDGE, dtype=_I64),
        _codes(s, ap[pair], FEATURE_EDGE, s.e_local[e1]),
        _codes(s, bp[pair], FEATURE_EDGE, s.e_local[e2]),
        pi, pj, n, np.einsum("ij,ij->i", pi - pj, n), np.full(k, -1, dtype=_I64),
        np.full(k, -1, dtype=_I64), np.full(k, -1, dtype=_I64),
        np.zeros(k, dtype=_I64), np.zeros((0, 3)),
    )


def _inside_edge(ctx: _Ctx, e: np.ndarray, t: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Parameter `t` is inside edge `e`: beyond the snap distance from ends that are
    surface vertices, up to (and within snap past) ends that are only seam points."""
    s = ctx.s
    along = t * length
    lo = np.where(s.v_surface[s.e_vtx[e, 0]], ctx.snap, -ctx.snap)
    hi = np.where(s.v_surface[s.e_vtx[e, 1]], ctx.snap, -ctx.snap)
    return (along > lo) & (along < length - hi)


def _select_planes(ctx: _Ctx, cand: np.ndarray, cvalid: np.ndarray, cface: np.ndarray,
                   dx: np.ndarray, dy: np.ndarray, delta: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shortest exit among candidate planes `cand (m, c, 3)` (normals from Y into X).

    A plane is admissible when X's cone directions `dx (m, kx, 3)` lie on its + side
    and Y's `dy (m, ky, 3)` on its - side (no overlap). Among admissible planes the
    largest gap `delta . n` wins; near-ties go to face planes, then to the largest
    clearance of the off-plane cone directions. Returns `(best (m,), admissible (m, c),
    found (m,))`.
    """
    vx = cand @ dx.transpose(0, 2, 1)
    vy = -(cand @ dy.transpose(0, 2, 1))
    adm = cvalid & (vx.min(axis=2) >= -ctx.entrance) & (vy.min(axis=2) >= -ctx.entrance)
    gap = np.where(adm, (cand @ delta[:, :, None])[:, :, 0], -np.inf)
    top = gap.max(axis=1, initial=-np.inf)
    near = adm & (gap >= top[:, None] - ctx.snap)
    vals = np.concatenate([vx, vy], axis=2)
    clear = np.where(vals > ctx.ang, vals, np.inf).min(axis=2)
    clear = np.where(np.isfinite(clear), np.minimum(clear, 1.0), 0.0)
    score = np.where(near, 4.0 + 2.0 * cface + clear, -1.0)
    return score.argmax(axis=1), adm, adm.any(axis=1)


def _unique_candidates(cand: np.ndarray, adm: np.ndarray, parallel: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Admissible candidates without repeats: `(count (m,), normals (q, 3))`."""
    dots = cand @ cand.transpose(0, 2, 1)
    earlier = np.tril(np.ones(dots.shape[1:], dtype=bool), -1)
    dup = (dots > 1.0 - parallel) & earlier & adm[:, None, :]
    keep = adm & ~dup.any(axis=2)
    return keep.sum(axis=1), cand[keep]


def _face_normals_at(ctx: _Ctx, pv: np.ndarray, sign: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Real faces at piece vertices `pv`: `(normals*sign (m, k, 3), valid, tags)`."""
    f = ctx.s.pv_faces[pv]
    valid = f >= 0
    fn = np.where(valid[..., None], ctx.g.f_normal[np.maximum(f, 0)] * sign, 0.0)
    return fn, valid, np.where(valid, ctx.s.f_tag[np.maximum(f, 0)], -1)


def _cross_candidates(ctx: _Ctx, dx: np.ndarray, rx: np.ndarray, ey: np.ndarray,
                      ry: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planes through one real edge direction of X and one of Y, signed so X is on +.

    `dx (m, a, 3)`, `ey (m, b, 3)`, masks `rx (m, a)`, `ry (m, b)` -> `(m, a*b, 3)`, valid.
    """
    c = np.cross(dx[:, :, None, :], ey[:, None, :, :])
    norm = np.linalg.norm(c, axis=3)
    valid = rx[:, :, None] & ry[:, None, :] & (norm > np.sqrt(2.0 * ctx.parallel))
    c = np.divide(c, norm[..., None], out=np.zeros_like(c), where=valid[..., None])
    side = np.einsum("mabk,mk->mab", c, dx.sum(axis=1))
    c = np.where((side < 0)[..., None], -c, c)
    m = len(dx)
    return c.reshape(m, -1, 3), valid.reshape(m, -1)


def _vertex_codes(s: _Scene, pair: np.ndarray, side: int | np.ndarray,
                  pv: np.ndarray) -> np.ndarray:
    """Code of (piece pair, side 0 = vertex of block i's piece / 1 = of j's, vertex)."""
    return (pair * 2 + side) * len(s.x) + s.pv_vtx[pv]


def _vertex_edge(ctx: _Ctx, xp: np.ndarray, yp: np.ndarray, flip: bool,
                 taken: np.ndarray) -> _Raw:
    """Vertices of pieces `xp` near the interior of real convex edges of pieces `yp`,
    except vertices whose codes are in `taken` (they already have a v-f contact)."""
    s, g = ctx.s, ctx.g
    own, pv = _vertices_near(ctx, xp, yp)
    free = ~np.isin(_vertex_codes(s, own, int(flip), pv), taken)
    own, pv = own[free], pv[free]
    pe, e = _edges_near(ctx, yp, xp)
    if len(own) == 0 or len(pe) == 0:
        return _empty_raw()
    cnt = np.bincount(pe, minlength=len(xp))
    start = np.cumsum(cnt) - cnt
    o, loc = _expand(cnt[own])
    pair, pv, e = own[o], pv[o], e[start[own[o]] + loc]
    x = s.x[s.pv_vtx[pv]]
    a, u = s.x[s.e_vtx[e, 0]], g.e_dir[e]
    length = np.linalg.norm(u, axis=1)
    t = np.einsum("ij,ij->i", x - a, u) / length**2
    proj = a + t[:, None] * u
    ok = _inside_edge(ctx, e, t, length)
    ok &= np.linalg.norm(x - proj, axis=1) < ctx.search + ctx.snap
    pair, pv, e, x, proj, u = pair[ok], pv[ok], e[ok], x[ok], proj[ok], u[ok] / length[ok, None]
    m = len(pair)
    if m == 0:
        return _empty_raw()
    ef = s.e_faces[e]
    yn = g.f_normal[ef]
    fxn, fxv, fxt = _face_normals_at(ctx, pv, -1.0)
    dx = g.pv_dir[pv]
    cr, crv = _cross_candidates(ctx, dx, s.pv_nb_real[pv], u[:, None, :],
                                np.ones((m, 1), dtype=bool))
    cand = np.concatenate([yn, fxn, cr], axis=1)
    cvalid = np.concatenate([np.ones((m, 2), dtype=bool), fxv, crv], axis=1)
    cface = np.concatenate([np.ones((m, 2), dtype=bool), fxv, np.zeros_like(crv)], axis=1)
    ctag = np.concatenate([s.f_tag[ef], fxt, np.full(crv.shape, -1, dtype=_I64)], axis=1)
    dy = np.concatenate([u[:, None, :], -u[:, None, :], g.e_in[e]], axis=1)
    return _finish_pairwise(ctx, VERTEX_EDGE, pair, flip, xp, yp, pv, e, -1, x, proj,
                            cand, cvalid, cface, ctag, dx, dy)


def _vertex_vertex(ctx: _Ctx, ap: np.ndarray, bp: np.ndarray, taken: np.ndarray) -> _Raw:
    """Surface vertices of pieces `ap` (i) near surface vertices of pieces `bp` (j),
    except vertices whose codes are in `taken` (they have a v-f or v-e contact)."""
    s, g = ctx.s, ctx.g
    pa, va = _vertices_near(ctx, ap, bp)
    pb, vb = _vertices_near(ctx, bp, ap)
    fa = ~np.isin(_vertex_codes(s, pa, 0, va), taken)
    fb = ~np.isin(_vertex_codes(s, pb, 1, vb), taken)
    pa, va, pb, vb = pa[fa], va[fa], pb[fb], vb[fb]
    if len(pa) == 0 or len(pb) == 0:
        return _empty_raw()
    cnt = np.bincount(pb, minlength=len(ap))
    start = np.cumsum(cnt) - cnt
    o, loc = _expand(cnt[pa])
    pair, va, vb = pa[o], va[o], vb[start[pa[o]] + loc]
    x, y = s.x[s.pv_vtx[va]], s.x[s.pv_vtx[vb]]
    ok = np.linalg.norm(x - y, axis=1) < ctx.search + ctx.snap
    pair, va, vb, x, y = pair[ok], va[ok], vb[ok], x[ok], y[ok]
    m = len(pair)
    if m == 0:
        return _empty_raw()
    fyn, fyv, fyt = _face_normals_at(ctx, vb, 1.0)
    fxn, fxv, fxt = _face_normals_at(ctx, va, -1.0)
    dx, dy = g.pv_dir[va], g.pv_dir[vb]
    cr, crv = _cross_candidates(ctx, dx, s.pv_nb_real[va], dy, s.pv_nb_real[vb])
    cand = np.concatenate([fyn, fxn, cr], axis=1)
    cvalid = np.concatenate([fyv, fxv, crv], axis=1)
    cface = np.concatenate([fyv, fxv, np.zeros_like(crv)], axis=1)
    ctag = np.concatenate([fyt, fxt, np.full(crv.shape, -1, dtype=_I64)], axis=1)
    return _finish_pairwise(ctx, VERTEX_VERTEX, pair, False, ap, bp, va, -1, vb, x, y,
                            cand, cvalid, cface, ctag, dx, dy)


def _finish_pairwise(ctx: _Ctx, kind: int, pair: np.ndarray, flip: bool, xp: np.ndarray,
                     yp: np.ndarray, pv: np.ndarray, e: np.ndarray | int, pw: np.ndarray | int,
                     x: np.ndarray, y: np.ndarray, cand: np.ndarray, cvalid: np.ndarray,
                     cface: np.ndarray, ctag: np.ndarray, dx: np.ndarray, dy: np.ndarray
                     ) -> _Raw:
    """Pick the plane of v-e / v-v contacts and pack them (drops those with no plane)."""
    s = ctx.s
    best, adm, found = _select_planes(ctx, cand, cvalid, cface, dx, dy, x - y)
    rows = np.arange(len(pair))
    n = cand[rows, best]
    tag = np.where(cface[rows, best], ctag[rows, best], -1)
    count, normals = _unique_candidates(cand[found], adm[found], ctx.parallel)
    sel = found
    pair, pv, x, y, n, tag = pair[sel], pv[sel], x[sel], y[sel], n[sel], tag[sel]
    k = len(pair)
    fx = _codes(s, xp[pair], FEATURE_VERTEX, s.v_local[s.pv_vtx[pv]])
    if kind == VERTEX_EDGE:
        e = np.asarray(e)[sel]
        fy = _codes(s, yp[pair], FEATURE_EDGE, s.e_local[e])
        vy = np.full(k, -1, dtype=_I64)
    else:
        pw = np.asarray(pw)[sel]
        fy = _codes(s, yp[pair], FEATURE_VERTEX, s.v_local[s.pv_vtx[pw]])
        vy = s.pv_vtx[pw]
    return _Raw(pair, np.full(k, flip), np.full(k, kind, dtype=_I64), fx, fy, x, y, n,
                np.einsum("ij,ij->i", x - y, n), tag, s.pv_vtx[pv], vy, count, normals)


# --------------------------------------------------------------------------- reduction


def _face_separation(ctx: _Ctx, xp: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """`(k,)`: max over real faces f of piece `yp` of min over vertices a of `xp` of the
    signed distance of a from f - how far `xp` must move to exit `yp` through a face."""
    s, g = ctx.s, ctx.g
    own, loc = _expand(s.f_count[yp])
    f = s.f_start[yp][own] + loc
    o2, loc2 = _expand(s.pv_count[xp[own]])
    x = s.x[s.pv_vtx[s.pv_start[xp[own]][o2] + loc2]]
    d = np.einsum("ij,ij->i", x, g.f_normal[f[o2]]) - g.f_offset[f[o2]]
    per_face = np.full(len(f), np.inf)
    np.minimum.at(per_face, o2, d)
    per_face[~s.f_real[f]] = -np.inf
    out = np.full(len(xp), -np.inf)
    np.maximum.at(out, own, per_face)
    return out


def _edge_edge_not_deeper(ctx: _Ctx, raw: _Raw, pa: np.ndarray, pb: np.ndarray
                          ) -> np.ndarray:
    """Mask dropping penetrating edge-edge contacts deeper than the shallowest face exit
    of their piece pair (edges that passed each other sideways in an overlap of corners:
    the overlap leaves through a face, the true exit, and these would push it sideways)."""
    keep = np.ones(len(raw.pair), dtype=bool)
    deep = np.flatnonzero((raw.kind == EDGE_EDGE) & (raw.gap < -ctx.snap))
    if len(deep) == 0:
        return keep
    pairs, inv = np.unique(raw.pair[deep], return_inverse=True)
    exit_gap = np.maximum(_face_separation(ctx, pa[pairs], pb[pairs]),
                          _face_separation(ctx, pb[pairs], pa[pairs]))
    keep[deep] = raw.gap[deep] >= exit_gap[inv.ravel()] - ctx.snap
    return keep


def _first_per_group(group: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Boolean mask of the row with the largest `score` in each `group` value."""
    order = np.lexsort((-score, group))
    g = group[order]
    first = np.r_[True, g[1:] != g[:-1]] if len(g) else np.zeros(0, dtype=bool)
    keep = np.zeros(len(group), dtype=bool)
    keep[order[first]] = True
    return keep


def _one_per_vertex(raw: _Raw, nv: int) -> np.ndarray:
    """Mask keeping one contact per (piece pair, vertex): v-f over v-e over v-v, then the
    largest gap (the shortest exit from a convex piece). Edge-edge rows are all kept."""
    side_x = raw.flip.astype(_I64)
    gx = (raw.pair * 2 + side_x) * nv + raw.vx
    gy = (raw.pair * 2 + (1 - side_x)) * nv + raw.vy
    keep = raw.kind == EDGE_EDGE
    taken = np.zeros(0, dtype=_I64)
    for kind in (VERTEX_FACE, VERTEX_EDGE, VERTEX_VERTEX):
        rows = np.flatnonzero(raw.kind == kind)
        ok = ~np.isin(gx[rows], taken)
        if kind == VERTEX_VERTEX:
            ok &= ~np.isin(gy[rows], taken)
        rows = rows[ok]
        rows = rows[_first_per_group(gx[rows], raw.gap[rows])]
        if kind == VERTEX_VERTEX:
            rows = rows[_first_per_group(gy[rows], raw.gap[rows])]
        keep[rows] = True
        taken = np.concatenate([taken, gx[rows]])
    return keep


def _merge_duplicates(c: ContactSet, anchor: np.ndarray, snap: float,
                      parallel: float) -> np.ndarray:
    """Mask dropping constraints equal to an earlier one with the same anchor (block pair
    and contact point), normal and gap; earlier = lower kind, then lower key."""
    order = np.lexsort((c.key[:, 3], c.key[:, 1], c.kind, anchor))
    a = anchor[order]
    brk = np.r_[True, a[1:] != a[:-1]]
    gid = np.cumsum(brk) - 1
    gstart = np.flatnonzero(brk)
    rank = np.arange(len(a)) - gstart[gid]
    width = int(rank.max()) + 1 if len(a) else 1
    table = np.full((len(gstart), width), -1, dtype=_I64)
    table[gid, rank] = order
    valid = table >= 0
    t = np.maximum(table, 0)
    n, gap = c.normal[t], c.gap[t]
    same = (np.einsum("gak,gbk->gab", n, n) > 1.0 - parallel)
    same &= np.abs(gap[:, :, None] - gap[:, None, :]) < snap
    same &= valid[:, :, None] & valid[:, None, :]
    same &= np.tril(np.ones((width, width), dtype=bool), -1)
    dup = same.any(axis=2)
    keep = np.ones(len(c), dtype=bool)
    keep[table[dup]] = False
    return keep


# --------------------------------------------------------------------------- public API


def _scene_scale(lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.max(hi.max(axis=0) - lo.min(axis=0))) if len(lo) else 1.0


def _piece_pairs(s: _Scene, g: _Geom, block_pairs: np.ndarray, inflate: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Piece pairs `(a of block i, b of block j)` of the block pairs with overlapping boxes."""
    nb = int(s.piece_block.max()) + 1
    pcount = np.bincount(s.piece_block, minlength=nb)
    pstart = np.cumsum(pcount) - pcount
    bi, bj = block_pairs[:, 1], block_pairs[:, 0]
    o, la = _expand(pcount[bi])
    o2, lb = _expand(pcount[bj[o]])
    pa = pstart[bi[o]][o2] + la[o2]
    pb = pstart[bj[o[o2]]] + lb
    ok = np.all(g.p_lo[pa] - inflate <= g.p_hi[pb] + inflate, axis=1)
    ok &= np.all(g.p_lo[pb] - inflate <= g.p_hi[pa] + inflate, axis=1)
    return pa[ok], pb[ok]


def _subset(c: ContactSet, index: np.ndarray) -> ContactSet:
    """Vectorised :meth:`ContactSet.subset` (ragged gather of the candidate normals)."""
    idx = np.arange(len(c))[index]
    counts = np.diff(c.cand_indptr)[idx]
    own, loc = _expand(counts)
    ptr = np.zeros(len(idx) + 1, dtype=_I64)
    np.cumsum(counts, out=ptr[1:])
    out = {f: getattr(c, f)[idx] for f in ContactSet.__dataclass_fields__
           if f not in ("cand_indptr", "cand_normals")}
    return ContactSet(**out, cand_indptr=ptr,
                      cand_normals=c.cand_normals[c.cand_indptr[idx][own] + loc])


def _tangents(n: np.ndarray) -> np.ndarray:
    """Some unit vector `(c, 3)` perpendicular to each normal."""
    axis = np.eye(3)[np.argmin(np.abs(n), axis=1)] if len(n) else np.zeros((0, 3))
    return _unit(np.cross(n, axis))


def detect_contacts(blocks: Sequence[Polyhedron], search_distance: float,
                    active: np.ndarray | None = None,
                    tol: Tolerances = DEFAULT_TOLERANCES) -> ContactSet:
    """All generalized contact constraints between blocks within `search_distance` (m).

    Penetrating contacts (gap down to about -2 x search) are kept. `active (n,) bool`:
    pairs of two inactive (fixed) blocks are skipped. `block_i > block_j`, normal from j
    into i, key = (block i, feature i, block j, feature j) with :func:`feature_code`.
    """
    if len(blocks) < 2:
        return ContactSet()
    s = _build_scene(blocks)
    scale0 = float(np.ptp(s.x, axis=0).max())
    g = _geometry(s, tol.parallel)
    ctx = _Ctx(s, g, float(search_distance), tol.length("feature_snap", scale0),
               float(np.sqrt(2.0 * tol.parallel)), tol.parallel, ENTRANCE_TOLERANCE)
    # broad phase on block boxes
    nb = len(blocks)
    bcount = np.bincount(s.piece_block, minlength=nb)
    bstart = np.cumsum(bcount) - bcount
    blo = np.minimum.reduceat(g.p_lo, bstart, axis=0)
    bhi = np.maximum.reduceat(g.p_hi, bstart, axis=0)
    inflate = 0.5 * ctx.search + ctx.snap
    pairs = aabb_pairs(blo - inflate, bhi + inflate)
    if active is not None:
        act = np.asarray(active, dtype=bool)
        pairs = pairs[act[pairs[:, 0]] | act[pairs[:, 1]]]
    if len(pairs) == 0:
        return ContactSet()
    pa, pb = _piece_pairs(s, g, pairs, inflate)
    vf = _cat_raw([_vertex_face(ctx, pa, pb, False), _vertex_face(ctx, pb, pa, True)])
    taken = _taken(vf, len(s.x))
    ve = _cat_raw([_vertex_edge(ctx, pa, pb, False, taken),
                   _vertex_edge(ctx, pb, pa, True, taken)])
    taken = np.concatenate([taken, _taken(ve, len(s.x))])
    raw = _cat_raw([vf, ve, _edge_edge(ctx, pa, pb), _vertex_vertex(ctx, pa, pb, taken)])
    keep = _one_per_vertex(raw, len(s.x)) & _edge_edge_not_deeper(ctx, raw, pa, pb)
    return _to_contact_set(ctx, raw, keep, pa, pb)


def _taken(raw: _Raw, nv: int) -> np.ndarray:
    """Sorted codes (see :func:`_vertex_codes`) of the X vertices of contacts in `raw`."""
    return np.unique((raw.pair * 2 + raw.flip) * nv + raw.vx)


def _to_contact_set(ctx: _Ctx, raw: _Raw, keep: np.ndarray, pa: np.ndarray,
                    pb: np.ndarray) -> ContactSet:
    """Map X/Y roles to blocks i/j, merge duplicates, order by key."""
    s = ctx.s
    cptr = np.r_[0, np.cumsum(raw.cand_count)]
    owner = np.repeat(np.arange(len(raw.pair)), raw.cand_count)
    flip = raw.flip
    f = flip[:, None]
    bi, bj = s.piece_block[pa[raw.pair]], s.piece_block[pb[raw.pair]]
    normal = np.where(f, -raw.normal, raw.normal)
    cand = np.where(flip[owner][:, None], -raw.cand, raw.cand)
    c = ContactSet(
        block_i=bi, block_j=bj, kind=raw.kind.astype(np.int8),
        point_i=np.where(f, raw.py, raw.px), point_j=np.where(f, raw.px, raw.py),
        normal=normal, tangent=_tangents(normal),
        mode=np.where(raw.gap < 0, LOCKED, OPEN).astype(np.int8), gap=raw.gap,
        key=np.stack([bi, np.where(flip, raw.fy, raw.fx), bj,
                      np.where(flip, raw.fx, raw.fy)], axis=1),
        face_tag=raw.tag, joint_material=np.zeros(len(bi), dtype=_I64),
        cand_indptr=cptr, cand_normals=cand,
    )
    c = _subset(c, keep)
    if len(c) == 0:
        return c
    ee = c.kind == EDGE_EDGE
    q = np.round(c.point_i / max(ctx.snap, 1e-300)).astype(_I64)
    rows = np.stack([c.block_i, c.block_j, ee.astype(_I64),
                     np.where(ee, q[:, 0], raw.vx[keep]),
                     np.where(ee, q[:, 1], raw.flip[keep].astype(_I64)),
                     np.where(ee, q[:, 2], 0)], axis=1)
    anchor = np.unique(rows, axis=0, return_inverse=True)[1].ravel()
    c = _subset(c, _merge_duplicates(c, anchor, ctx.snap, ctx.parallel))
    order = np.lexsort((c.key[:, 3], c.key[:, 2], c.key[:, 1], c.key[:, 0]))
    return _subset(c, order)

