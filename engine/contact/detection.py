"""Contact detection: broad phase on bounding boxes, narrow phase between convex pieces.

Concave blocks are handled through their convex pieces (paper section 2.2.2): every
convex piece of one block is tested against every nearby convex piece of another, so a
vertex in a concave corner gets one constraint per convex sub-angle. The narrow phase
finds the four basic types (paper Fig. 2) - vertex-face, crossing edge-edge,
vertex-edge and vertex-vertex - and picks the plane of vertex-edge and vertex-vertex
contacts by the shortest exit rule (paper eq. 4).

Speed: the topology of all pieces is flattened once into global arrays (`_Scene`) and
cached while the blocks keep their topology arrays (:meth:`Polyhedron.moved` does), so
a call only gathers the vertex positions; the geometry, broad phase and narrow phase
are compiled loops over piece pairs (:mod:`engine.contact._detection_kernels`, numba).

Conventions: `block_i > block_j`; the normal points from block j into block i;
`gap = (point_i - point_j) . normal`. Feature codes: see :func:`feature_code`.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np

from engine.contact import _detection_kernels as kern
from engine.contact._detection_kernels import (
    FEATURE_EDGE,
    FEATURE_FACE,
    FEATURE_VERTEX,
    feature_code,
)
from engine.contact.constraints import LOCKED, OPEN, ContactSet
from engine.dynamics.assembly import spare_core
from engine.geometry.polyhedron import ConvexPiece, Polyhedron, edge_topology
from engine.tolerances import DEFAULT_TOLERANCES, Tolerances

#: piece pairs from which the narrow phase runs in slices on threads, as many as numba is
#: configured for, when a core is spare (the kernel releases the GIL; rows are joined in
#: pair order, so the contacts are the same)
THREADED_MIN_PAIRS = 2048

_I64 = np.int64

__all__ = ["FEATURE_EDGE", "FEATURE_FACE", "FEATURE_VERTEX", "aabb_pairs", "decode_feature",
           "detect_contacts", "feature_code"]


# --------------------------------------------------------------------------- feature codes


def decode_feature(code: np.ndarray | int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`feature_code`: `(piece, kind, index)`."""
    c = np.asarray(code, dtype=_I64)
    return (c >> 32) // 4, (c >> 32) % 4, c & 0xFFFFFFFF


# --------------------------------------------------------------------------- broad phase


def aabb_pairs(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """All pairs `(k, 2)` (a < b, sorted) of closed boxes `lower, upper (n, 3)` that overlap.

    Sort and sweep along the axis where the box centres spread most (compiled).
    """
    lo = np.ascontiguousarray(lower, dtype=float)
    hi = np.ascontiguousarray(upper, dtype=float)
    return kern.sweep_pairs(lo, hi)


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
    edge_slots: np.ndarray  # (e, 2) the edges' ends as indices into verts
    vert_surface: np.ndarray  # (k,) vertex is a surface vertex of the block
    vert_nb: np.ndarray  # (k, D) neighbour vertex ids along piece edges (pad -1)
    vert_nb_real: np.ndarray  # (k, D) that edge is real
    vert_faces: np.ndarray  # (k, Df) incident real piece faces (pad -1)


#: piece topologies by content (face arrays and the block's surface vertices): blocks of
#: one shape - the boxes of a stack, the slab and the cube of an incline, a block and its
#: moved copies - share one entry; oldest first out beyond _TOPO_CACHE_SIZE entries
_TOPO_CACHE: dict[tuple[bytes, ...], _PieceTopo] = {}
_TOPO_CACHE_SIZE = 20000


def _pad_rows(rows: list[list[int]], fill: int = -1) -> np.ndarray:
    width = max((len(r) for r in rows), default=0)
    out = np.full((len(rows), max(width, 1)), fill, dtype=_I64)
    for k, r in enumerate(rows):
        out[k, : len(r)] = r
    return out


def _piece_topology(piece: ConvexPiece, block: Polyhedron) -> _PieceTopo:
    """Topology of `piece` (cached by content, see :data:`_TOPO_CACHE`)."""
    key = (piece.face_indptr.tobytes(), piece.face_indices.tobytes(),
           np.asarray(piece.face_surface).tobytes(), block.surface_vertex_ids.tobytes())
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
        np.searchsorted(verts, edges).astype(_I64),
        np.isin(verts, block.surface_vertex_ids), _pad_rows(nb),
        _pad_rows(nb_real, 0).astype(bool), _pad_rows(vf),
    )
    if len(_TOPO_CACHE) >= _TOPO_CACHE_SIZE:
        _TOPO_CACHE.pop(next(iter(_TOPO_CACHE)))
    _TOPO_CACHE[key] = topo
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

    nv: int  # vertices of all blocks
    v_surface: np.ndarray  # (nv,)
    v_local: np.ndarray  # (nv,) block-local vertex id
    v_block: np.ndarray  # (nv,)
    block_piece0: np.ndarray  # (nb,) first piece of each block
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
    e_slot: np.ndarray  # (E, 2) the edge's ends as piece vertex slots (0..pv_count)
    pv_vtx: np.ndarray  # (V,) g
    pv_surface: np.ndarray
    pv_nb: np.ndarray  # (V, D) g, -1 pad
    pv_nb_real: np.ndarray
    pv_faces: np.ndarray  # (V, Df) global faces, -1 pad
    pv_ndir: np.ndarray  # (V,) neighbours (the first ones of pv_nb; the rest pad)
    pv_nfaces: np.ndarray  # (V,) real faces (the first ones of pv_faces)

    @cached_property
    def topology(self) -> kern.SceneTopology:
        """The arrays the narrow phase reads, as one record."""
        return kern.SceneTopology(*(getattr(self, name) for name in kern.SceneTopology._fields))


def _build_scene(blocks: Sequence[Polyhedron]) -> _Scene:
    """Gather topology of every piece of every block into flat global arrays."""
    vsurf, vloc, vblk = [], [], []
    pblock, plocal = [], []
    fv, fn, fe, fval, floc, ftag, freal = [], [], [], [], [], [], []
    ev, ef, eloc, ereal, eslot = [], [], [], [], []
    pvv, pvs, pvnb, pvnbr, pvf = [], [], [], [], []
    voffs, foffs, eoffs = [], [], []
    f_count, e_count, pv_count = [], [], []
    vo = fo = eo = 0
    for b, block in enumerate(blocks):
        nv = len(block.vertices)
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
            eslot.append(t.edge_slots)
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
    pv_nb = _cat_padded(pvnb, -1, voffs)
    pv_faces = _cat_padded(pvf, -1, foffs)
    return _Scene(
        nv=vo, block_piece0=np.searchsorted(np.asarray(pblock, dtype=_I64),
                                            np.arange(len(blocks))),
        v_surface=np.concatenate(vsurf),
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
        e_real=np.concatenate(ereal), e_slot=np.concatenate(eslot),
        pv_vtx=np.concatenate(pvv), pv_surface=np.concatenate(pvs),
        pv_nb=pv_nb, pv_nb_real=_cat_padded(pvnbr, False), pv_faces=pv_faces,
        pv_ndir=(pv_nb >= 0).sum(axis=1).astype(_I64),
        pv_nfaces=(pv_faces >= 0).sum(axis=1).astype(_I64),
    )


#: recently used scenes: identity of the blocks -> (scene, the blocks)
_SCENE_CACHE: dict[tuple[int, ...], tuple[_Scene, list]] = {}
_SCENE_CACHE_SIZE = 8


def _scene(blocks: Sequence[Polyhedron]) -> _Scene:
    """The flat topology arrays of `blocks`, cached on the identity of the blocks (a
    Polyhedron's topology never changes; the entry holds the blocks, so their ids cannot be
    reused while it lives)."""
    key = tuple(map(id, blocks))
    hit = _SCENE_CACHE.get(key)
    if hit is not None:
        return hit[0]
    s = _build_scene(blocks)
    if len(_SCENE_CACHE) >= _SCENE_CACHE_SIZE:
        _SCENE_CACHE.pop(next(iter(_SCENE_CACHE)))
    _SCENE_CACHE[key] = (s, list(blocks))
    return s


# --------------------------------------------------------------------------- public API


@dataclass
class Search:
    """One contact search's inputs: the scene's flat topology, the vertex positions `x
    (V, 3)`, each block's reach `(n,)` m, the piece boxes `p_lo`, `p_hi (P, 3)` and the
    feature snap (m) of the scene's current size."""

    scene: _Scene
    x: np.ndarray
    reach: np.ndarray
    p_lo: np.ndarray
    p_hi: np.ndarray
    snap: float
    tol: Tolerances

    @property
    def extent(self) -> float:
        """The scene's size (m): the largest side of the box of all pieces."""
        return float((self.p_hi.max(axis=0) - self.p_lo.min(axis=0)).max())


def start_search(blocks: Sequence[Polyhedron], search_distance: float | np.ndarray,
                 tol: Tolerances = DEFAULT_TOLERANCES, vertices: np.ndarray | None = None
                 ) -> Search:
    """The :class:`Search` of `blocks` at `vertices` (default: the blocks' own) within
    `search_distance` (one distance, or each block's reach; see :func:`detect_contacts`)."""
    s = _scene(blocks)
    if vertices is None:
        x = np.concatenate([b.vertices for b in blocks]).astype(float, copy=False)
    else:
        x = np.ascontiguousarray(vertices, dtype=float)
        if x.shape != (s.nv, 3):
            raise ValueError(f"vertices has shape {x.shape}, expected one row per block "
                             "vertex")
    if np.ndim(search_distance) == 0:
        reach = np.full(len(blocks), 0.5 * float(search_distance))
    else:
        reach = np.ascontiguousarray(search_distance, dtype=float)
        if reach.shape != (len(blocks),):
            raise ValueError(f"search_distance has shape {reach.shape}, expected a number "
                             "or one reach per block")
    p_lo, p_hi = kern.piece_boxes(x, s.pv_vtx, s.pv_start, s.pv_count)
    # the scene's size from the piece boxes (every vertex belongs to a piece)
    snap = tol.lengths(float((p_hi.max(axis=0) - p_lo.min(axis=0)).max())).feature_snap
    return Search(s, x, reach, p_lo, p_hi, snap, tol)


def broad_phase(search: Search, grow: np.ndarray, active: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """The piece pairs `(pa of block i, pb of block j)` whose boxes, each grown by its
    block's `grow (n,)` m, overlap, with one block `active` (all when None): block boxes
    swept first, then their pieces; in block pair order, then piece order."""
    s = search.scene
    blo = np.minimum.reduceat(search.p_lo, s.block_piece0, axis=0)
    bhi = np.maximum.reduceat(search.p_hi, s.block_piece0, axis=0)
    pairs = kern.sweep_pairs(blo - grow[:, None], bhi + grow[:, None])
    if active is not None:
        act = np.asarray(active, dtype=bool)
        pairs = np.ascontiguousarray(pairs[act[pairs[:, 0]] | act[pairs[:, 1]]])
    if len(pairs) == 0:
        return np.zeros(0, dtype=_I64), np.zeros(0, dtype=_I64)
    return kern.piece_pairs(pairs, s.piece_block, search.p_lo, search.p_hi, grow)


def narrow(search: Search, pa: np.ndarray, pb: np.ndarray,
           keep: kern.SkinLists | None = None) -> ContactSet:
    """The contacts of the piece pairs `pa`, `pb` (:func:`broad_phase`; or a skin's pairs
    and candidate features `keep`, which finds the same ones), duplicates merged, ordered
    by key. The geometry (normals, edge and neighbour directions) is computed for the
    pieces of the pairs only."""
    if len(pa) == 0:
        return ContactSet()
    s, x = search.scene, search.x
    parallel = float(search.tol.parallel)
    pieces = np.zeros(len(s.pv_start), dtype=bool)
    pieces[pa] = True
    pieces[pb] = True
    geo = kern.SceneGeometry(*kern.geometry(
        x, s.f_vtx, s.f_nxt, s.e_vtx, s.e_faces, s.pv_vtx, s.pv_nb, s.f_start, s.f_count,
        s.e_start, s.e_count, s.pv_start, s.pv_count, pieces, parallel),
        search.p_lo, search.p_hi)
    ri, rf, cand = _narrow_phase(pa, pb, x, s.topology, geo, search.reach, search.snap,
                                 parallel, search.tol.entrance,
                                 kern.no_skin() if keep is None else keep)
    return _to_contact_set(ri, rf, cand, search.snap, parallel, len(s.block_piece0))


def detect_contacts(blocks: Sequence[Polyhedron], search_distance: float | np.ndarray,
                    active: np.ndarray | None = None,
                    tol: Tolerances = DEFAULT_TOLERANCES,
                    vertices: np.ndarray | None = None) -> ContactSet:
    """All generalized contact constraints between blocks within `search_distance` (m).

    `search_distance` is one distance for every block pair, or each block's reach `(n,)`:
    blocks a and b are then searched within `reach[a] + reach[b]` (how far each can move
    in a step), so a fast block does not widen the search of the whole scene.
    Penetrating contacts (gap down to about -2 x search) are kept. `active (n,) bool`:
    pairs of two inactive (fixed) blocks are skipped. `block_i > block_j`, normal from j
    into i, key = (block i, feature i, block j, feature j) with :func:`feature_code`.
    `vertices (V, 3)`: current positions of all blocks' vertices stacked in block order
    (default: the blocks' own), so a caller can move blocks without new polyhedra.
    """
    if len(blocks) < 2:
        return ContactSet()
    search = start_search(blocks, search_distance, tol, vertices)
    pa, pb = broad_phase(search, search.reach + search.snap, active)
    return narrow(search, pa, pb)


def _narrow_phase(pa: np.ndarray, pb: np.ndarray, x: np.ndarray, topo: kern.SceneTopology,
                  geo: kern.SceneGeometry, reach: np.ndarray, snap: float, parallel: float,
                  entrance: float, keep: kern.SkinLists
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`engine.contact._detection_kernels.narrow_phase` of the piece pairs `pa`, `pb`, in
    as many slices as numba's configured threads when there are enough pairs, joined in
    order (`numba.get_num_threads()` would launch numba's threading layer, a thread of its
    own under TBB or workqueue)."""
    args = (x, topo, geo, reach, snap, float(np.sqrt(2.0 * parallel)), parallel, entrance)
    threads = numba.config.NUMBA_NUM_THREADS
    if threads < 2 or len(pa) < THREADED_MIN_PAIRS or not spare_core():
        return kern.narrow_phase(pa, pb, *args, keep)
    cuts = np.linspace(0, len(pa), threads + 1).astype(np.int64)

    def part(q: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo, hi = cuts[q], cuts[q + 1]
        sliced = keep if len(keep.v_ptr) == 0 else keep._replace(
            v_ptr=keep.v_ptr[lo:hi + 1], e_ptr=keep.e_ptr[lo:hi + 1])
        return kern.narrow_phase(pa[lo:hi], pb[lo:hi], *args, sliced)

    with ThreadPoolExecutor(threads) as pool:
        parts = list(pool.map(part, range(threads)))
    for q, (ri, _, _) in enumerate(parts):
        ri[:, kern.RI_PAIR] += cuts[q]
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


def _to_contact_set(ri: np.ndarray, rf: np.ndarray, cand: np.ndarray, snap: float,
                    parallel: float, n_blocks: int) -> ContactSet:
    """The ContactSet of the rows `ri (k, 10)`, `rf (k, 13)`, `cand (q, 3)` of
    :func:`engine.contact._detection_kernels.narrow_phase`, duplicates merged, ordered by key."""
    if len(ri) == 0:
        return ContactSet()
    rows = kern.merge_and_order(ri, rf, snap, parallel, n_blocks)
    ptr, normals = kern.gather_candidates(ri[:, kern.RI_CANDIDATES], cand, rows)
    g, f = ri[rows], rf[rows]
    gap = f[:, kern.RF_GAP].copy()

    def vec(col: int) -> np.ndarray:
        return f[:, col:col + 3].copy()

    return ContactSet(
        block_i=g[:, kern.RI_BLOCK_I].copy(), block_j=g[:, kern.RI_BLOCK_J].copy(),
        kind=g[:, kern.RI_KIND].astype(np.int8), point_i=vec(kern.RF_POINT_I),
        point_j=vec(kern.RF_POINT_J), normal=vec(kern.RF_NORMAL), tangent=vec(kern.RF_TANGENT),
        mode=np.where(gap < 0, LOCKED, OPEN).astype(np.int8), gap=gap,
        key=g[:, [kern.RI_BLOCK_I, kern.RI_FEATURE_I, kern.RI_BLOCK_J, kern.RI_FEATURE_J]],
        face_tag=g[:, kern.RI_TAG].copy(), joint_material=np.zeros(len(rows), dtype=_I64),
        cand_indptr=ptr, cand_normals=normals,
    )
