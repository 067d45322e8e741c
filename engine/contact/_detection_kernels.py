"""Compiled (numba) loops of the contact detection in :mod:`engine.contact.detection`.

Everything here works on the flat scene arrays that :mod:`engine.contact.detection` builds (one
row per piece, face, edge or piece vertex of all blocks; see its `_Scene`). The loops
run per piece pair, so the work and the memory grow with the number of nearby feature
pairs instead of with large padded temporaries, and a call costs a few microseconds
instead of hundreds of numpy calls. Conventions and the rules (vertex-face,
edge-edge, vertex-edge, vertex-vertex, shortest exit) are those of the module
docstring of :mod:`engine.contact.detection`.

Output rows of :func:`narrow_phase` are already in block i / block j orientation; their
columns are named by the `RI_*` and `RF_*` constants below, here and in Python:

- `ri (k, 10) int64`: block i, block j, kind, key feature i, key feature j, face tag,
  X vertex (global id, -1 for edge-edge), X is block j's piece (flip), number of
  candidate normals, piece pair
- `rf (k, 13) float`: point i (3), point j (3), normal (3), gap, tangent (3)
- `cand (q, 3)`: candidate normals (from j into i), rows' ranges in order
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from llvmlite import ir
from numba import njit, types, vectorize
from numba.core import cgutils
from numba.extending import intrinsic

from engine.contact.constraints import EDGE_EDGE, VERTEX_EDGE, VERTEX_FACE, VERTEX_VERTEX

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}

FEATURE_VERTEX, FEATURE_EDGE, FEATURE_FACE = 0, 1, 2

# columns of the integer rows `ri` ...
(RI_BLOCK_I, RI_BLOCK_J, RI_KIND, RI_FEATURE_I, RI_FEATURE_J, RI_TAG, RI_VERTEX, RI_FLIP,
 RI_CANDIDATES, RI_PAIR) = range(10)
# ... and the first columns of the float rows `rf` (points, normal and tangent take three)
RF_POINT_I, RF_POINT_J, RF_NORMAL, RF_GAP, RF_TANGENT = 0, 3, 6, 9, 10
_NI, _NF = 10, 13


# --------------------------------------------------------------------------- small vectors


# The dot products follow numpy's order of operations bit for bit (einsum, norm and
# matmul each have their own), so that ties in the discrete choices (largest gap, best
# plane, tangent axis) fall exactly as in a numpy implementation.


@intrinsic
def _fma(typingctx, a, b, c):  # noqa: ANN001, ANN202, ARG001
    """Fused multiply-add `a * b + c` with one rounding (what BLAS kernels use)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202, ARG001
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]),
                                            "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


@njit(**_OPTS)
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """`a . b` as `np.einsum("ij,ij->i")` adds it."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


@njit(**_OPTS)
def _dot_mm(a: np.ndarray, b: np.ndarray) -> float:
    """`a . b` as a stacked matrix product (`A @ B`, BLAS) computes it."""
    return _fma(a[2], b[2], _fma(a[1], b[1], a[0] * b[0]))


@njit(**_OPTS)
def _dot_mv(a: np.ndarray, b: np.ndarray) -> float:
    """`a . b` as a stacked matrix-vector product (`A @ v`, BLAS) computes it."""
    return _fma(a[2], b[2], _fma(a[0], b[0], a[1] * b[1]))


@njit(**_OPTS)
def _norm(a: np.ndarray) -> float:
    """`|a|` as `np.linalg.norm(axis=-1)` computes it."""
    return np.sqrt((a[0] * a[0] + a[1] * a[1]) + a[2] * a[2])


@njit(**_OPTS)
def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(**_OPTS)
def _unit_inplace(v: np.ndarray) -> None:
    n = _norm(v)
    if n > 0:
        v[0] /= n
        v[1] /= n
        v[2] /= n
    else:
        v[:] = 0.0


@vectorize(["int64(int64, int64, int64)"], cache=True)
def feature_code(piece: int, kind: int, index: int) -> int:
    """Stable int64 id of a feature: `((piece * 4 + kind) << 32) | index` (a ufunc: numbers
    or arrays). `piece` is the piece number within its block, `kind` FEATURE_VERTEX / EDGE
    / FACE, `index` the block vertex id (vertices) or the piece-local edge / face id."""
    return ((piece * 4 + kind) << 32) | index


# --------------------------------------------------------------------------- geometry


@njit(**_OPTS)
def piece_boxes(x: np.ndarray, pv_vtx: np.ndarray, pv_start: np.ndarray,
                pv_count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounding boxes `(p_lo, p_hi) (P, 3)` of all pieces at the vertex positions `x`."""
    npc = len(pv_start)
    p_lo = np.zeros((npc, 3))
    p_hi = np.zeros((npc, 3))
    for p in range(npc):
        s = pv_start[p]
        for j in range(3):
            p_lo[p, j] = x[pv_vtx[s], j]
            p_hi[p, j] = x[pv_vtx[s], j]
        for v in range(s + 1, s + pv_count[p]):
            for j in range(3):
                t = x[pv_vtx[v], j]
                p_lo[p, j] = min(p_lo[p, j], t)
                p_hi[p, j] = max(p_hi[p, j], t)
    return p_lo, p_hi


@njit(**_OPTS)
def geometry(x: np.ndarray, f_vtx: np.ndarray, f_nxt: np.ndarray, e_vtx: np.ndarray,
             e_faces: np.ndarray, pv_vtx: np.ndarray, pv_nb: np.ndarray,
             f_start: np.ndarray, f_count: np.ndarray, e_start: np.ndarray,
             e_count: np.ndarray, pv_start: np.ndarray, pv_count: np.ndarray,
             pieces: np.ndarray, parallel: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                        np.ndarray]:
    """Position-dependent quantities of the pieces marked in `pieces (P,) bool` (the ones
    in a pair the narrow phase looks at; zeros for the others): `(f_normal (F, 3),
    f_offset (F,), e_dir (E, 3), e_in (E, 2, 3), e_flat (E,), pv_dir (V, D, 3))`."""
    nf, kk = f_vtx.shape
    f_normal = np.zeros((nf, 3))
    f_offset = np.zeros(nf)
    ne = len(e_vtx)
    e_dir = np.zeros((ne, 3))
    e_in = np.zeros((ne, 2, 3))
    e_flat = np.zeros(ne, dtype=np.bool_)
    nv, dd = pv_nb.shape
    pv_dir = np.zeros((nv, dd, 3))
    u = np.zeros(3)
    w = np.zeros(3)
    c = np.zeros(3)
    for piece in range(len(pieces)):
        if not pieces[piece]:
            continue
        for f in range(f_start[piece], f_start[piece] + f_count[piece]):
            p0 = x[f_vtx[f, 0]]
            acc = f_normal[f]
            for k in range(kk):
                a, b = x[f_vtx[f, k]], x[f_nxt[f, k]]
                for j in range(3):
                    u[j] = a[j] - p0[j]
                    w[j] = b[j] - p0[j]
                _cross(u, w, c)
                for j in range(3):
                    acc[j] += c[j]
            _unit_inplace(acc)
            f_offset[f] = _dot(acc, p0)
        for e in range(e_start[piece], e_start[piece] + e_count[piece]):
            d = e_dir[e]
            a, b = x[e_vtx[e, 0]], x[e_vtx[e, 1]]
            for j in range(3):
                d[j] = b[j] - a[j]
                w[j] = -d[j]
            n1, n2 = f_normal[e_faces[e, 0]], f_normal[e_faces[e, 1]]
            _cross(n1, d, e_in[e, 0])
            _unit_inplace(e_in[e, 0])
            _cross(n2, w, e_in[e, 1])
            _unit_inplace(e_in[e, 1])
            e_flat[e] = _dot(n1, n2) > 1.0 - parallel
        for v in range(pv_start[piece], pv_start[piece] + pv_count[piece]):
            p = x[pv_vtx[v]]
            for k in range(dd):
                q = pv_nb[v, k]
                if q >= 0:
                    r = pv_dir[v, k]
                    for j in range(3):
                        r[j] = x[q, j] - p[j]
                    _unit_inplace(r)
    return f_normal, f_offset, e_dir, e_in, e_flat, pv_dir


# --------------------------------------------------------------------------- broad phase


@njit(**_OPTS)
def sweep_pairs(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """All pairs `(k, 2)` (a < b, sorted) of boxes `lower, upper (n, 3)` that overlap
    (closed boxes): sort and sweep along the axis where the box centres spread most."""
    n = len(lower)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    centre = 0.5 * (lower + upper)
    axis, best = 0, -1.0
    for j in range(3):
        v = np.var(centre[:, j])
        if v > best:
            axis, best = j, v
    order = np.argsort(lower[:, axis], kind="mergesort")
    cap = 16 * n
    out = np.empty((cap, 2), dtype=np.int64)
    k = 0
    for s in range(n):
        a = order[s]
        top = upper[a, axis]
        for t in range(s + 1, n):
            b = order[t]
            if lower[b, axis] > top:
                break
            if (lower[a, 0] <= upper[b, 0] and lower[b, 0] <= upper[a, 0]
                    and lower[a, 1] <= upper[b, 1] and lower[b, 1] <= upper[a, 1]
                    and lower[a, 2] <= upper[b, 2] and lower[b, 2] <= upper[a, 2]):
                if k == cap:
                    cap *= 2
                    grown = np.empty((cap, 2), dtype=np.int64)
                    grown[:k] = out[:k]
                    out = grown
                out[k, 0] = min(a, b)
                out[k, 1] = max(a, b)
                k += 1
    out = out[:k]
    key = out[:, 0] * n + out[:, 1]
    return out[np.argsort(key)]


@njit(**_OPTS)
def piece_pairs(block_pairs: np.ndarray, piece_block: np.ndarray, p_lo: np.ndarray,
                p_hi: np.ndarray, inflate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Piece pairs `(pa of block i, pb of block j)` of `block_pairs (k, 2)` (j < i) whose
    boxes, each inflated by its block's `inflate (n_blocks,)`, overlap; in block pair
    order, then a, then b."""
    nb = piece_block.max() + 1 if len(piece_block) else 0
    pstart = np.zeros(nb + 1, dtype=np.int64)
    for p in range(len(piece_block)):
        pstart[piece_block[p] + 1] += 1
    for b in range(nb):
        pstart[b + 1] += pstart[b]
    cap = 0
    for k in range(len(block_pairs)):
        bi, bj = block_pairs[k, 1], block_pairs[k, 0]
        cap += (pstart[bi + 1] - pstart[bi]) * (pstart[bj + 1] - pstart[bj])
    pa = np.empty(cap, dtype=np.int64)
    pb = np.empty(cap, dtype=np.int64)
    m = 0
    for k in range(len(block_pairs)):
        bi, bj = block_pairs[k, 1], block_pairs[k, 0]
        gi, gj = inflate[bi], inflate[bj]
        for a in range(pstart[bi], pstart[bi + 1]):
            for b in range(pstart[bj], pstart[bj + 1]):
                ok = True
                for j in range(3):
                    if not (p_lo[a, j] - gi <= p_hi[b, j] + gj
                            and p_lo[b, j] - gj <= p_hi[a, j] + gi):
                        ok = False
                if ok:
                    pa[m] = a
                    pb[m] = b
                    m += 1
    return pa[:m], pb[:m]


# --------------------------------------------------------------------------- planes


@njit(**_OPTS)
def _select_planes(cand: np.ndarray, cface: np.ndarray, nc: int, dx: np.ndarray, ndx: int,
                   dy: np.ndarray, ndy: int, delta: np.ndarray, entrance: float, snap: float,
                   ang: float, adm: np.ndarray, adm_gap: np.ndarray) -> int:
    """Shortest exit among candidate planes `cand[:nc]` (normals from Y into X); fills
    `adm[:nc]` and the gaps `adm_gap[:nc]`, returns the best index or -1 when none is
    admissible.

    A plane is admissible when X's cone directions `dx[:ndx]` lie on its + side and
    Y's `dy[:ndy]` on its - side. Among admissible planes the largest gap `delta . n`
    wins; near-ties go to face planes, then to the largest clearance of the off-plane
    cone directions (the rule of :func:`engine.contact.detection` `_select_planes`).
    The candidates are all valid (written by :func:`_face_candidates` and
    :func:`_cross_candidates`), the directions those of real neighbours (the zero rows
    that pad them would change no test).
    """
    gap = adm_gap
    top = -np.inf
    found = False
    for c in range(nc):
        ok = True
        for k in range(ndx):
            if _dot_mm(cand[c], dx[k]) < -entrance:
                ok = False
                break
        if ok:
            for k in range(ndy):
                if -_dot_mm(cand[c], dy[k]) < -entrance:
                    ok = False
                    break
        adm[c] = ok
        if ok:
            found = True
            gap[c] = _dot_mv(cand[c], delta)
            top = max(top, gap[c])
        else:
            gap[c] = -np.inf
    if not found:
        return -1
    best, best_score = 0, -np.inf
    for c in range(nc):
        score = -1.0
        if adm[c] and gap[c] >= top - snap:
            clear = np.inf
            for k in range(ndx):
                v = _dot_mm(cand[c], dx[k])
                if v > ang and v < clear:
                    clear = v
            for k in range(ndy):
                v = -_dot_mm(cand[c], dy[k])
                if v > ang and v < clear:
                    clear = v
            clear = min(clear, 1.0) if np.isfinite(clear) else 0.0
            score = 4.0 + (2.0 if cface[c] else 0.0) + clear
        if score > best_score:
            best, best_score = c, score
    return best


@njit(**_OPTS)
def _cross_candidates(dx: np.ndarray, ndx: int, rx: np.ndarray, ey: np.ndarray,
                      ry: np.ndarray, ney: int, parallel: float, cand: np.ndarray,
                      cface: np.ndarray, ctag: np.ndarray, at: int) -> int:
    """Planes through one real edge direction of X (`dx[:ndx]`, mask `rx`) and one of
    Y (`ey[:ney]`, mask `ry`), signed so X is on +; the valid ones (not through parallel
    edges) written from `cand[at]` in (X direction, Y direction) order. Returns the next
    free index."""
    s0 = s1 = s2 = 0.0
    for k in range(ndx):
        s0 += dx[k, 0]
        s1 += dx[k, 1]
        s2 += dx[k, 2]
    lim = np.sqrt(2.0 * parallel)
    for a in range(ndx):
        if not rx[a]:
            continue
        for b in range(ney):
            if not ry[b]:
                continue
            c = cand[at]
            _cross(dx[a], ey[b], c)
            n = _norm(c)
            if not n > lim:
                continue
            cface[at] = False
            ctag[at] = -1
            for j in range(3):
                c[j] /= n
            if (c[0] * s0 + c[2] * s2) + c[1] * s1 < 0:
                for j in range(3):
                    c[j] = -c[j]
            at += 1
    return at


@njit(**_OPTS)
def _face_candidates(pv_faces: np.ndarray, pv_nfaces: np.ndarray, f_normal: np.ndarray,
                     f_tag: np.ndarray, pv: int, sign: float, cand: np.ndarray,
                     cface: np.ndarray, ctag: np.ndarray, at: int) -> int:
    """Normals (times `sign`) of the real faces at piece vertex `pv`, from `cand[at]`."""
    for k in range(pv_nfaces[pv]):
        f = pv_faces[pv, k]
        cface[at] = True
        for j in range(3):
            cand[at, j] = f_normal[f, j] * sign
        ctag[at] = f_tag[f]
        at += 1
    return at


@njit(**_OPTS)
def _inside_edge(v_surface: np.ndarray, e_vtx: np.ndarray, e: int, t: float, length: float,
                 snap: float) -> bool:
    """Parameter `t` is inside edge `e`: beyond snap from ends that are surface vertices,
    up to (and within snap past) ends that are only seam points."""
    along = t * length
    lo = snap if v_surface[e_vtx[e, 0]] else -snap
    hi = snap if v_surface[e_vtx[e, 1]] else -snap
    return along > lo and along < length - hi


@njit(**_OPTS)
def _in_box(p: np.ndarray, lo: np.ndarray, hi: np.ndarray, r: float) -> bool:
    for j in range(3):
        if not (p[j] >= lo[j] - r and p[j] <= hi[j] + r):
            return False
    return True


@njit(**_OPTS)
def _near_edges(p: int, side: int, other: int, x: np.ndarray, e_start: np.ndarray,
                e_count: np.ndarray, e_vtx: np.ndarray, e_slot: np.ndarray,
                e_real: np.ndarray, e_flat: np.ndarray, vbound: np.ndarray, within: float,
                p_lo: np.ndarray, p_hi: np.ndarray, r: float, out: np.ndarray,
                kept: np.ndarray) -> int:
    """Real convex edges of piece `p` (on `side`) with a distance bound `vbound[side]` of
    at most `within` at one of their ends and whose box meets the box of piece `other`
    inflated by `r`, into `out`; returns how many. `kept[side]`: the piece's edges a skin
    keeps for the pair (all of them without a skin)."""
    n = 0
    lo, hi = p_lo[other], p_hi[other]
    for e in range(e_start[p], e_start[p] + e_count[p]):
        if not e_real[e] or e_flat[e] or not kept[side, e - e_start[p]]:
            continue
        if not (vbound[side, e_slot[e, 0]] <= within or vbound[side, e_slot[e, 1]] <= within):
            continue
        a, b = x[e_vtx[e, 0]], x[e_vtx[e, 1]]
        ok = True
        for j in range(3):
            if not (min(a[j], b[j]) <= hi[j] + r and max(a[j], b[j]) >= lo[j] - r):
                ok = False
                break
        if ok:
            out[n] = e
            n += 1
    return n


@njit(**_OPTS)
def _separating_face(a_p: int, b_p: int, x: np.ndarray, pv_start: np.ndarray,
                     pv_count: np.ndarray, pv_vtx: np.ndarray, f_start: np.ndarray,
                     f_count: np.ndarray, f_real: np.ndarray, f_normal: np.ndarray,
                     f_offset: np.ndarray) -> tuple[float, int, int, float]:
    """The face plane of either convex piece with the largest clearance of the other
    piece: `(clearance, face, side, exit)`, side 0 when the face belongs to `b_p` (the
    vertices of `a_p` lie at least `clearance` outside it), 1 when it belongs to `a_p`.
    Negative clearance: the pieces overlap (by at least that much along every face
    normal). `exit` is the same maximum over the real (block) faces only: how far the
    pieces must move apart to separate through a block face."""
    best, best_f, best_side, best_real = -np.inf, -1, 0, -np.inf
    for side in range(2):
        xp, yp = (a_p, b_p) if side == 0 else (b_p, a_p)
        for f in range(f_start[yp], f_start[yp] + f_count[yp]):
            n = f_normal[f]
            if n[0] == 0.0 and n[1] == 0.0 and n[2] == 0.0:
                continue  # degenerate face
            real = f_real[f]
            stop = best_real if real else best
            mn = np.inf
            for pv in range(pv_start[xp], pv_start[xp] + pv_count[xp]):
                mn = min(mn, _dot(x[pv_vtx[pv]], n) - f_offset[f])
                if mn <= stop:
                    break
            if real and mn > best_real:
                best_real = mn
            if mn > best:
                best, best_f, best_side = mn, f, side
    return best, best_f, best_side, best_real


# --------------------------------------------------------------------------- output rows


@njit(**_OPTS)
def _reserve(ri: np.ndarray, rf: np.ndarray, cand: np.ndarray, k: int, q: int, rows: int,
             cands: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Output arrays with room for `rows` more rows and `cands` more candidate normals."""
    if k + rows > len(ri):
        cap = max(2 * len(ri), k + rows)
        r2 = np.empty((cap, _NI), dtype=np.int64)
        r2[:k] = ri[:k]
        f2 = np.empty((cap, _NF))
        f2[:k] = rf[:k]
        ri, rf = r2, f2
    if q + cands > len(cand):
        cap = max(2 * len(cand), q + cands)
        c2 = np.empty((cap, 3))
        c2[:q] = cand[:q]
        cand = c2
    return ri, rf, cand


@njit(**_OPTS)
def _emit(ri: np.ndarray, rf: np.ndarray, k: int, bi: int, bj: int, kind: int, fx: int,
          fy: int, tag: int, vx: int, flip: bool, ncand: int, pair: int, px: np.ndarray,
          py: np.ndarray, n: np.ndarray, gap: float) -> None:
    """Write row `k` in block i / j orientation (X is block j's piece when `flip`)."""
    s = -1.0 if flip else 1.0
    ri[k, RI_BLOCK_I] = bi
    ri[k, RI_BLOCK_J] = bj
    ri[k, RI_KIND] = kind
    ri[k, RI_FEATURE_I] = fy if flip else fx
    ri[k, RI_FEATURE_J] = fx if flip else fy
    ri[k, RI_TAG] = tag
    ri[k, RI_VERTEX] = vx
    ri[k, RI_FLIP] = 1 if flip else 0
    ri[k, RI_CANDIDATES] = ncand
    ri[k, RI_PAIR] = pair
    for j in range(3):
        rf[k, RF_POINT_I + j] = py[j] if flip else px[j]
        rf[k, RF_POINT_J + j] = px[j] if flip else py[j]
        rf[k, RF_NORMAL + j] = s * n[j]
    rf[k, RF_GAP] = gap
    # tangent: normal x the coordinate axis least aligned with it
    nn = rf[k, RF_NORMAL:RF_NORMAL + 3]
    ax = 0
    for j in range(1, 3):
        if abs(nn[j]) < abs(nn[ax]):
            ax = j
    e0, e1, e2 = (1.0 if ax == 0 else 0.0), (1.0 if ax == 1 else 0.0), (1.0 if ax == 2 else 0.0)
    t = rf[k, RF_TANGENT:RF_TANGENT + 3]
    t[0] = nn[1] * e2 - nn[2] * e1
    t[1] = nn[2] * e0 - nn[0] * e2
    t[2] = nn[0] * e1 - nn[1] * e0
    _unit_inplace(t)


# --------------------------------------------------------------------------- narrow phase


class SceneTopology(NamedTuple):
    """The flat topology arrays of all blocks' pieces that :func:`narrow_phase` reads (built
    by :mod:`engine.contact.detection`, whose `_Scene` documents each)."""

    v_surface: np.ndarray
    v_local: np.ndarray
    piece_block: np.ndarray
    piece_local: np.ndarray
    f_start: np.ndarray
    f_count: np.ndarray
    e_start: np.ndarray
    e_count: np.ndarray
    pv_start: np.ndarray
    pv_count: np.ndarray
    f_vtx: np.ndarray
    f_nxt: np.ndarray
    f_edge: np.ndarray
    f_valid: np.ndarray
    f_local: np.ndarray
    f_tag: np.ndarray
    f_real: np.ndarray
    e_vtx: np.ndarray
    e_faces: np.ndarray
    e_local: np.ndarray
    e_real: np.ndarray
    e_slot: np.ndarray
    pv_vtx: np.ndarray
    pv_surface: np.ndarray
    pv_nb_real: np.ndarray
    pv_faces: np.ndarray
    pv_ndir: np.ndarray
    pv_nfaces: np.ndarray


class SceneGeometry(NamedTuple):
    """The position-dependent arrays of :func:`geometry`."""

    f_normal: np.ndarray
    f_offset: np.ndarray
    e_dir: np.ndarray
    e_in: np.ndarray
    e_flat: np.ndarray
    pv_dir: np.ndarray
    p_lo: np.ndarray
    p_hi: np.ndarray


class SkinLists(NamedTuple):
    """What a skin (:mod:`engine.contact.skin`) keeps of the piece pairs given to
    :func:`narrow_phase`: pair k's candidate piece vertices are `v_list[v_ptr[k]:v_ptr[k +
    1]]` and its candidate edges `e_list[e_ptr[k]:e_ptr[k + 1]]` (global ids); a pair is
    only searched when one of its blocks is `active` and their piece boxes, each grown by
    its block's `inflate (n_blocks,)` (reach + snap), overlap: the broad phase of the step.
    Empty `v_ptr`: no skin, every pair and feature is searched."""

    v_ptr: np.ndarray
    v_list: np.ndarray
    e_ptr: np.ndarray
    e_list: np.ndarray
    inflate: np.ndarray
    active: np.ndarray


@njit(**_OPTS)
def _kept_pair(a_p: int, b_p: int, bi: int, bj: int, p_lo: np.ndarray, p_hi: np.ndarray,
               keep: SkinLists) -> bool:
    """Whether a pair a skin keeps is one this step's broad phase finds: a block awake and
    the piece boxes, grown by their blocks' reach and snap, overlapping (the test of
    :func:`piece_pairs`, so that the pairs are exactly its pairs)."""
    if not (keep.active[bi] or keep.active[bj]):
        return False
    gi, gj = keep.inflate[bi], keep.inflate[bj]
    for j in range(3):
        if not (p_lo[a_p, j] - gi <= p_hi[b_p, j] + gj and p_lo[b_p, j] - gj <= p_hi[a_p, j] + gi):
            return False
    return True


@njit(**_OPTS)
def _mark_kept(pair: int, a_p: int, b_p: int, pv_start: np.ndarray, e_start: np.ndarray,
               keep: SkinLists, v_kept: np.ndarray, e_kept: np.ndarray, on: bool) -> None:
    """Set (`on`) or clear the marks `v_kept`, `e_kept (2, ·)` of the candidate vertices
    and edges a skin keeps for `pair` (side 0: piece `a_p`, side 1: `b_p`)."""
    for t in range(keep.v_ptr[pair], keep.v_ptr[pair + 1]):
        pv = keep.v_list[t]
        if _in_piece(pv, a_p, pv_start):
            v_kept[0, pv - pv_start[a_p]] = on
        else:
            v_kept[1, pv - pv_start[b_p]] = on
    for t in range(keep.e_ptr[pair], keep.e_ptr[pair + 1]):
        e = keep.e_list[t]
        if _in_piece(e, a_p, e_start):
            e_kept[0, e - e_start[a_p]] = on
        else:
            e_kept[1, e - e_start[b_p]] = on


@njit(**_OPTS)
def _in_piece(k: int, p: int, start: np.ndarray) -> bool:
    """Whether global id `k` (a piece vertex, or an edge) belongs to piece `p`, given each
    piece's first id `start` (ids are consecutive by piece)."""
    return k >= start[p] and (p + 1 >= len(start) or k < start[p + 1])


def no_skin() -> SkinLists:
    """The :class:`SkinLists` of a search without a skin."""
    z = np.zeros(0, dtype=np.int64)
    return SkinLists(z, z, z, z, np.zeros(0), np.zeros(0, dtype=np.bool_))


# One long compiled loop by design: the four contact types of a piece pair share the pair's
# separating plane, near-edge lists and scratch buffers, and splitting it into separate
# kernels would pass those between calls for every pair (measured slower on piles).
@njit(**_OPTS)
def narrow_phase(pa: np.ndarray, pb: np.ndarray, x: np.ndarray, topo: SceneTopology,
                 geo: SceneGeometry, reach: np.ndarray, snap: float, ang: float,
                 parallel: float, entrance: float, keep: SkinLists
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contacts of the piece pairs `(pa[k] of block i, pb[k] of block j)`, reduced to one
    per (piece pair, vertex) (v-f over v-e over v-v, then the largest gap) and without
    edge-edge contacts deeper than the pair's shallowest face exit. A pair is searched
    within `reach[i] + reach[j]` (m; `reach (n_blocks,)`). Returns `(ri, rf, cand)`
    (module docstring). `keep`: a skin's pairs and candidate features (:class:`SkinLists`;
    the same rows as a search of every pair and feature, in less time)."""
    (v_surface, v_local, piece_block, piece_local, f_start, f_count, e_start, e_count,
     pv_start, pv_count, f_vtx, f_nxt, f_edge, f_valid, f_local, f_tag, f_real, e_vtx,
     e_faces, e_local, e_real, e_slot, pv_vtx, pv_surface, pv_nb_real, pv_faces, pv_ndir,
     pv_nfaces) = topo
    f_normal, f_offset, e_dir, e_in, e_flat, pv_dir, p_lo, p_hi = geo
    dmax, dfmax = pv_dir.shape[1], pv_faces.shape[1]
    # a plane through edges lies on a face when within the entrance angle of it
    cos_tag = np.sqrt(1.0 - entrance * entrance)
    cmax = max(2 + dfmax + dmax, 2 * dfmax + dmax * dmax)
    cand = np.zeros((cmax, 3))
    cface = np.zeros(cmax, dtype=np.bool_)
    ctag = np.zeros(cmax, dtype=np.int64)
    adm = np.zeros(cmax, dtype=np.bool_)
    adm_gap = np.zeros(cmax)
    ukeep = np.zeros(cmax, dtype=np.bool_)
    dy = np.zeros((max(4, dmax), 3))
    ry = np.ones(max(4, dmax), dtype=np.bool_)
    tmp = np.zeros(3)
    proj = np.zeros(3)
    delta = np.zeros(3)
    c3 = np.zeros(3)
    n_best = np.zeros(3)
    p_best = np.zeros(3)
    npairs = len(pa)
    ri = np.empty((4 * npairs + 16, _NI), dtype=np.int64)
    rf = np.empty((4 * npairs + 16, _NF))
    out_c = np.empty((4 * npairs + 16, 3))
    k = 0
    q = 0
    maxpv = pv_count.max() if len(pv_count) else 0
    maxe = e_count.max() if len(e_count) else 0
    taken = np.zeros((2, maxpv), dtype=np.bool_)
    near = np.zeros((2, maxpv), dtype=np.bool_)
    ea_list = np.zeros(maxe, dtype=np.int64)
    eb_list = np.zeros(maxe, dtype=np.int64)
    vv_a = np.zeros(maxpv, dtype=np.int64)
    vv_b = np.zeros(maxpv, dtype=np.int64)
    vv_gap = np.zeros(maxpv)
    # the winners' candidates: the vertex-edge one of the vertex at hand, the vertex-vertex
    # ones of the pair (emitted without evaluating them again)
    ve_cand, ve_adm = np.zeros((cmax, 3)), np.zeros(cmax, dtype=np.bool_)
    ve_face, ve_tag, ve_proj = np.zeros(cmax, dtype=np.bool_), np.zeros(cmax, dtype=np.int64), \
        np.zeros(3)
    vv_cand, vv_adm = np.zeros((maxpv, cmax, 3)), np.zeros((maxpv, cmax), dtype=np.bool_)
    vv_face, vv_tag = np.zeros((maxpv, cmax), dtype=np.bool_), np.zeros((maxpv, cmax),
                                                                     dtype=np.int64)
    vv_nc, vv_best = np.zeros(maxpv, dtype=np.int64), np.zeros(maxpv, dtype=np.int64)
    slab_s = np.zeros(2)
    slab_c = np.zeros(2)
    close = np.zeros((2, maxpv), dtype=np.bool_)
    vbound = np.zeros((2, maxpv))
    skin = len(keep.v_ptr) > 0
    v_kept = np.ones((2, maxpv), dtype=np.bool_)
    e_kept = np.ones((2, maxe), dtype=np.bool_)
    if skin:
        v_kept[:] = False
        e_kept[:] = False
    for pair in range(npairs):
        a_p, b_p = pa[pair], pb[pair]
        bi, bj = piece_block[a_p], piece_block[b_p]
        if skin:
            if not _kept_pair(a_p, b_p, bi, bj, p_lo, p_hi, keep):
                continue
        search = reach[bi] + reach[bj]
        r = search + snap
        na, nb_ = pv_count[a_p], pv_count[b_p]
        worst = 2 * (na + nb_) + na * nb_ + e_count[a_p] * e_count[b_p]
        # the face plane (of either convex piece) that best separates the pair gives each
        # feature a lower bound on its distance from the other piece: a vertex-face contact
        # needs a vertex within 2 r of it (its projection may overhang a non-sharp edge by
        # r), the other types a feature within r
        sep, sep_f, sep_side, exit_gap = _separating_face(
            a_p, b_p, x, pv_start, pv_count, pv_vtx, f_start, f_count, f_real, f_normal,
            f_offset)
        far, close_by = 2.0 * r + snap, r + snap
        if sep > far:
            continue
        if skin:
            _mark_kept(pair, a_p, b_p, pv_start, e_start, keep, v_kept, e_kept, True)
        # bound of a feature at height h along the face normal: s (h - offset) + c
        for side in range(2):
            if sep_f < 0:  # no face plane to go by (degenerate pieces): no bound
                slab_s[side], slab_c[side] = 0.0, -np.inf
            elif side == sep_side:  # the piece outside the face plane
                slab_s[side], slab_c[side] = 1.0, 0.0
            else:  # the piece that owns the face
                slab_s[side], slab_c[side] = -1.0, sep
        sep_n = f_normal[max(sep_f, 0)]
        sep_o = f_offset[max(sep_f, 0)]
        ri, rf, out_c = _reserve(ri, rf, out_c, k, q, worst, (na + nb_) * cmax)
        # surface vertices of each piece inside the other's inflated box, within 2 r (near,
        # for vertex-face) or r (close, for vertex-edge and vertex-vertex) by the bound
        for side in range(2):
            xp, yp = (a_p, b_p) if side == 0 else (b_p, a_p)
            for lv in range(pv_count[xp]):
                pv = pv_start[xp] + lv
                taken[side, lv] = False
                xv = x[pv_vtx[pv]]
                bound = slab_s[side] * (_dot(sep_n, xv) - sep_o) + slab_c[side]
                vbound[side, lv] = bound
                near[side, lv] = (pv_surface[pv] and v_kept[side, lv] and bound <= far
                                  and _in_box(xv, p_lo[yp], p_hi[yp], r))
                close[side, lv] = near[side, lv] and bound <= close_by
        # real convex edges of each piece within r by the bound (at one of its ends: the
        # bound is linear along the edge) whose box meets the other's inflated box
        na_e = _near_edges(a_p, 0, b_p, x, e_start, e_count, e_vtx, e_slot, e_real, e_flat,
                           vbound, close_by, p_lo, p_hi, r, ea_list, e_kept)
        nb_e = _near_edges(b_p, 1, a_p, x, e_start, e_count, e_vtx, e_slot, e_real, e_flat,
                           vbound, close_by, p_lo, p_hi, r, eb_list, e_kept)
        if skin:
            _mark_kept(pair, a_p, b_p, pv_start, e_start, keep, v_kept, e_kept, False)
        # ---- vertex-face
        for side in range(2):
            xp, yp = (a_p, b_p) if side == 0 else (b_p, a_p)
            for lv in range(pv_count[xp]):
                if not near[side, lv]:
                    continue
                pv = pv_start[xp] + lv
                xv = x[pv_vtx[pv]]
                best_f, best_d = -1, -np.inf
                exit_d = -np.inf  # shortest exit: the largest distance to any real face
                for f in range(f_start[yp], f_start[yp] + f_count[yp]):
                    if not f_real[f]:
                        continue
                    n = f_normal[f]
                    d = _dot(n, xv) - f_offset[f]
                    exit_d = max(exit_d, d)
                    if not (d < r and d > -(2 * search + snap)):
                        continue
                    ok = True
                    for kd in range(dmax):
                        if _dot(pv_dir[pv, kd], n) < -entrance:
                            ok = False
                            break
                    if not ok:
                        continue
                    for j in range(3):
                        proj[j] = xv[j] - d * n[j]
                    for kk in range(f_vtx.shape[1]):
                        if not f_valid[f, kk]:
                            continue
                        a, b = x[f_vtx[f, kk]], x[f_nxt[f, kk]]
                        for j in range(3):
                            tmp[j] = b[j] - a[j]
                            delta[j] = proj[j] - a[j]
                        length = _norm(tmp)
                        _cross(n, tmp, c3)
                        dist = _dot(delta, c3) / length if length > 0 else np.inf
                        fe = f_edge[f, kk]
                        sharp = fe >= 0 and e_real[fe] and not e_flat[fe]
                        if not dist >= (snap if sharp else -r):
                            ok = False
                            break
                    if ok and d > best_d:
                        best_f, best_d = f, d
                # a penetrating vertex belongs to the face it is closest to leaving by
                # (shortest exit); a deeper face whose projection only grazes its boundary
                # would report a false deep penetration (vertex beyond a convex edge)
                if best_f >= 0 and best_d < 0 and best_d < exit_d - snap:
                    best_f = -1
                if best_f >= 0:
                    n = f_normal[best_f]
                    for j in range(3):
                        proj[j] = xv[j] - best_d * n[j]
                    v = pv_vtx[pv]
                    _emit(ri, rf, k, bi, bj, VERTEX_FACE,
                          feature_code(piece_local[xp], FEATURE_VERTEX, v_local[v]),
                          feature_code(piece_local[yp], FEATURE_FACE, f_local[best_f]),
                          f_tag[best_f], v, side == 1, 0, pair, xv, proj, n, best_d)
                    k += 1
                    taken[side, lv] = True
        # ---- vertex-edge (vertices without a vertex-face contact)
        for side in range(2):
            xp, yp = (a_p, b_p) if side == 0 else (b_p, a_p)
            edges, ne = (eb_list, nb_e) if side == 0 else (ea_list, na_e)
            if ne == 0:
                continue
            for lv in range(pv_count[xp]):
                if not close[side, lv] or taken[side, lv]:
                    continue
                pv = pv_start[xp] + lv
                xv = x[pv_vtx[pv]]
                best_e, best_gap, best_nc, best_c = -1, -np.inf, 0, -1
                for ie in range(ne):
                    inside, length = _vertex_edge_foot(edges[ie], xv, x, v_surface, e_vtx,
                                                       e_dir, snap, proj, delta)
                    if not inside or not _within_segment(xv, x, e_vtx, e_dir, edges[ie], r):
                        continue
                    gap, nc, best = _vertex_edge_plane(
                        edges[ie], pv, length, e_dir, e_faces, e_in, f_normal, f_tag,
                        pv_faces, pv_nfaces, pv_dir, pv_ndir, pv_nb_real, r, snap, ang,
                        parallel, entrance, cand, cface, ctag, adm, adm_gap, dy, ry, delta)
                    # ties within snap go to the first edge (collinear edges split by a
                    # seam point): the choice must not depend on round-off
                    if best >= 0 and gap > best_gap + snap:
                        best_e, best_gap, best_nc, best_c = ie, gap, nc, best
                        _keep_candidates(nc, cand, adm, cface, ctag, ve_cand, ve_adm, ve_face,
                                         ve_tag)
                        for j in range(3):
                            ve_proj[j] = proj[j]
                if best_e < 0:
                    continue
                # no deeper than the pair's shallowest face exit: an edge within reach
                # whose plane the vertex is far behind (a narrow face next to the vertex
                # it touches, as on thin cut blocks) reports a false deep penetration
                if best_gap < -snap and best_gap < exit_gap - snap:
                    continue
                e = edges[best_e]
                q0 = q
                q = _copy_unique(ve_cand, ve_adm, best_nc, parallel, ukeep, out_c, q,
                                 side == 1)
                v = pv_vtx[pv]
                tag = ve_tag[best_c] if ve_face[best_c] else _plane_tag(
                    pv_faces[pv], e_faces[e], f_tag, f_normal, ve_cand[best_c], cos_tag)
                _emit(ri, rf, k, bi, bj, VERTEX_EDGE,
                      feature_code(piece_local[xp], FEATURE_VERTEX, v_local[v]),
                      feature_code(piece_local[yp], FEATURE_EDGE, e_local[e]),
                      tag, v, side == 1, q - q0, pair, xv, ve_proj, ve_cand[best_c],
                      best_gap)
                k += 1
                taken[side, lv] = True
        # ---- crossing edge-edge
        for i1 in range(na_e):
            e1 = ea_list[i1]
            a1, b1 = x[e_vtx[e1, 0]], x[e_vtx[e1, 1]]
            for i2 in range(nb_e):
                e2 = eb_list[i2]
                a2, b2 = x[e_vtx[e2, 0]], x[e_vtx[e2, 1]]
                ok = True
                for j in range(3):
                    if not (min(a1[j], b1[j]) <= max(a2[j], b2[j]) + r
                            and min(a2[j], b2[j]) <= max(a1[j], b1[j]) + r):
                        ok = False
                        break
                if not ok:
                    continue
                u, w = e_dir[e1], e_dir[e2]
                for j in range(3):
                    delta[j] = a1[j] - a2[j]
                aa, bb, cc = _dot(u, u), _dot(u, w), _dot(w, w)
                dd, ee = _dot(u, delta), _dot(w, delta)
                den = aa * cc - bb * bb
                # nearly parallel edges: a parallel edge-edge contact (v-e at the ends)
                sin2 = den / (aa * cc)
                if not (sin2 > 2.0 * parallel and sin2 * min(aa, cc) > search * search):
                    continue
                sp = (bb * ee - cc * dd) / den
                tq = (aa * ee - bb * dd) / den
                if not (_inside_edge(v_surface, e_vtx, e1, sp, np.sqrt(aa), snap)
                        and _inside_edge(v_surface, e_vtx, e2, tq, np.sqrt(cc), snap)):
                    continue
                for j in range(3):
                    proj[j] = a1[j] + sp * u[j]
                    p_best[j] = a2[j] + tq * w[j]
                    tmp[j] = proj[j] - p_best[j]
                _cross(u, w, n_best)
                _unit_inplace(n_best)
                if not _norm(tmp) < r:
                    continue
                ina0, ina1 = _dot(e_in[e1, 0], n_best), _dot(e_in[e1, 1], n_best)
                inb0, inb1 = _dot(e_in[e2, 0], n_best), _dot(e_in[e2, 1], n_best)
                m_plus = min(min(ina0, ina1), -max(inb0, inb1))
                m_minus = min(-max(ina0, ina1), min(inb0, inb1))
                if not max(m_plus, m_minus) >= -entrance:
                    continue
                if not m_plus >= m_minus:
                    for j in range(3):
                        n_best[j] = -n_best[j]
                gap = _dot(tmp, n_best)
                if gap < -snap:
                    # deeper than the shallowest face exit of the pair: edges that passed
                    # each other sideways in an overlap of corners; the face is the exit
                    if not gap >= exit_gap - snap:
                        continue
                _emit(ri, rf, k, bi, bj, EDGE_EDGE,
                      feature_code(piece_local[a_p], FEATURE_EDGE, e_local[e1]),
                      feature_code(piece_local[b_p], FEATURE_EDGE, e_local[e2]),
                      _plane_tag(e_faces[e1], e_faces[e2], f_tag, f_normal, n_best,
                                 cos_tag),
                      -1, False, 0, pair, proj, p_best, n_best, gap)
                k += 1
        # ---- vertex-vertex (vertices without a vertex-face or vertex-edge contact)
        m = 0
        for la in range(na):
            if not close[0, la] or taken[0, la]:
                continue
            va = pv_start[a_p] + la
            best_b, best_gap = -1, -np.inf
            for lb in range(nb_):
                if not close[1, lb] or taken[1, lb]:
                    continue
                vb = pv_start[b_p] + lb
                gap, nc, best = _vertex_vertex_plane(
                    va, vb, x, pv_vtx, f_normal, f_tag, pv_faces, pv_nfaces, pv_dir, pv_ndir,
                    pv_nb_real, r, snap, ang, parallel, entrance, cand, cface, ctag, adm,
                    adm_gap, delta)
                if best >= 0 and gap > best_gap + snap:  # ties: the first vertex
                    best_b, best_gap = vb, gap
                    vv_nc[m], vv_best[m] = nc, best
                    _keep_candidates(nc, cand, adm, cface, ctag, vv_cand[m], vv_adm[m],
                                     vv_face[m], vv_tag[m])
            # no deeper than the pair's shallowest face exit (as vertex-edge)
            if best_b >= 0 and not (best_gap < -snap and best_gap < exit_gap - snap):
                vv_a[m], vv_b[m], vv_gap[m] = va, best_b, best_gap
                m += 1
        # one contact per vertex of block j's piece too: the largest gap, first on ties
        for s_ in range(m):
            alone = True
            for t in range(m):
                if t != s_ and vv_b[t] == vv_b[s_] and (
                        vv_gap[t] > vv_gap[s_] or (vv_gap[t] == vv_gap[s_] and t < s_)):
                    alone = False
                    break
            if not alone:
                continue
            va, vb, nc, best = vv_a[s_], vv_b[s_], vv_nc[s_], vv_best[s_]
            ri, rf, out_c = _reserve(ri, rf, out_c, k, q, 1, nc)
            q0 = q
            q = _copy_unique(vv_cand[s_], vv_adm[s_], nc, parallel, ukeep, out_c, q, False)
            tag = vv_tag[s_, best] if vv_face[s_, best] else _plane_tag(
                pv_faces[va], pv_faces[vb], f_tag, f_normal, vv_cand[s_, best], cos_tag)
            _emit(ri, rf, k, bi, bj, VERTEX_VERTEX,
                  feature_code(piece_local[a_p], FEATURE_VERTEX, v_local[pv_vtx[va]]),
                  feature_code(piece_local[b_p], FEATURE_VERTEX, v_local[pv_vtx[vb]]),
                  tag, pv_vtx[va], False, q - q0, pair,
                  x[pv_vtx[va]], x[pv_vtx[vb]], vv_cand[s_, best], vv_gap[s_])
            k += 1
    return ri[:k], rf[:k], out_c[:q]


@njit(**_OPTS)
def _copy_unique(cand: np.ndarray, adm: np.ndarray, nc: int, parallel: float,
                 keep: np.ndarray, out: np.ndarray, q: int, flip: bool) -> int:
    """Append the admissible candidates without repeats (an earlier admissible one
    parallel) to `out[q:]`, negated when `flip`; returns the new end."""
    s = -1.0 if flip else 1.0
    for c in range(nc):
        ok = adm[c]
        if ok:
            for d in range(c):
                if adm[d] and _dot_mm(cand[c], cand[d]) > 1.0 - parallel:
                    ok = False
                    break
        if ok:
            for j in range(3):
                out[q, j] = s * cand[c, j]
            q += 1
    return q


@njit(**_OPTS)
def _plane_tag(fx: np.ndarray, fy: np.ndarray, f_tag: np.ndarray, f_normal: np.ndarray,
               n: np.ndarray, cos_min: float) -> int:
    """Joint tag of a contact plane through edges (normal `n`): the tag of the face
    among `fx` and `fy` (the faces at the two contact features, -1 pads) most nearly
    parallel to the plane, within `cos_min`; a tag found on both sides wins a tie. -1
    when no tagged face lies along the plane."""
    best, score = -1, -np.inf
    for side in range(2):
        faces, other = (fx, fy) if side == 0 else (fy, fx)
        for a in range(len(faces)):
            f = faces[a]
            if f < 0 or f_tag[f] < 0:
                continue
            c = abs(_dot(f_normal[f], n))
            if c < cos_min:
                continue
            shared = False
            for b in range(len(other)):
                if other[b] >= 0 and f_tag[other[b]] == f_tag[f]:
                    shared = True
                    break
            sc = c + (1e-9 if shared else 0.0)
            if sc > score:
                best, score = f_tag[f], sc
    return best


@njit(**_OPTS)
def _within_segment(p: np.ndarray, x: np.ndarray, e_vtx: np.ndarray, e_dir: np.ndarray,
                    e: int, r: float) -> bool:
    """Point `p` is within about `r` of edge `e` (a cheap test before
    :func:`_vertex_edge_plane`, which decides exactly)."""
    a, u = x[e_vtx[e, 0]], e_dir[e]
    uu = _dot(u, u)
    t = ((p[0] - a[0]) * u[0] + (p[1] - a[1]) * u[1] + (p[2] - a[2]) * u[2]) / uu
    t = min(max(t, 0.0), 1.0)
    d0 = p[0] - a[0] - t * u[0]
    d1 = p[1] - a[1] - t * u[1]
    d2 = p[2] - a[2] - t * u[2]
    return d0 * d0 + d1 * d1 + d2 * d2 < 1.0001 * r * r


@njit(**_OPTS)
def _vertex_edge_foot(e: int, xv: np.ndarray, x: np.ndarray, v_surface: np.ndarray,
                      e_vtx: np.ndarray, e_dir: np.ndarray, snap: float, proj: np.ndarray,
                      delta: np.ndarray) -> tuple[bool, float]:
    """The foot of the point `xv` on edge `e`'s line: fills `proj` and `delta = xv − proj`;
    returns whether the foot is inside the edge (:func:`_inside_edge`) and the edge's
    length. The cheap first test of a vertex against an edge."""
    a, u = x[e_vtx[e, 0]], e_dir[e]
    length = _norm(u)
    for j in range(3):
        delta[j] = xv[j] - a[j]
    t = _dot(delta, u) / (length * length)
    for j in range(3):
        proj[j] = a[j] + t * u[j]
        delta[j] = xv[j] - proj[j]
    return _inside_edge(v_surface, e_vtx, e, t, length, snap), length


@njit(**_OPTS)
def _vertex_edge_plane(e: int, pv: int, length: float, e_dir: np.ndarray,
                       e_faces: np.ndarray, e_in: np.ndarray, f_normal: np.ndarray,
                       f_tag: np.ndarray, pv_faces: np.ndarray, pv_nfaces: np.ndarray,
                       pv_dir: np.ndarray, pv_ndir: np.ndarray, pv_nb_real: np.ndarray,
                       r: float, snap: float, ang: float, parallel: float, entrance: float,
                       cand: np.ndarray, cface: np.ndarray, ctag: np.ndarray,
                       adm: np.ndarray, adm_gap: np.ndarray, dy: np.ndarray,
                       ry: np.ndarray, delta: np.ndarray) -> tuple[float, int, int]:
    """Vertex `pv` (of X) against the interior of edge `e` (of Y) of `length`, its foot
    inside the edge at `delta` from the vertex (:func:`_vertex_edge_foot`): `(gap,
    candidates, best)` with best = -1 when it is no contact; fills the candidate scratch
    arrays."""
    if not _norm(delta) < r:
        return -np.inf, 0, -1
    for c in range(2):
        f = e_faces[e, c]
        cand[c] = f_normal[f]
        cface[c] = True
        ctag[c] = f_tag[f]
    nc = _face_candidates(pv_faces, pv_nfaces, f_normal, f_tag, pv, -1.0, cand, cface, ctag,
                          2)
    u = e_dir[e]
    for j in range(3):
        dy[0, j] = u[j] / length
        dy[1, j] = -dy[0, j]
        dy[2, j] = e_in[e, 0, j]
        dy[3, j] = e_in[e, 1, j]
    ry[0] = True
    nd = pv_ndir[pv]
    nc = _cross_candidates(pv_dir[pv], nd, pv_nb_real[pv], dy, ry, 1, parallel, cand, cface,
                           ctag, nc)
    best = _select_planes(cand, cface, nc, pv_dir[pv], nd, dy, 4, delta, entrance, snap, ang,
                          adm, adm_gap)
    if best < 0:
        return -np.inf, nc, -1
    return _dot(delta, cand[best]), nc, best


@njit(**_OPTS)
def _vertex_vertex_plane(va: int, vb: int, x: np.ndarray, pv_vtx: np.ndarray,
                         f_normal: np.ndarray, f_tag: np.ndarray, pv_faces: np.ndarray,
                         pv_nfaces: np.ndarray, pv_dir: np.ndarray, pv_ndir: np.ndarray,
                         pv_nb_real: np.ndarray, r: float, snap: float, ang: float,
                         parallel: float, entrance: float, cand: np.ndarray,
                         cface: np.ndarray, ctag: np.ndarray, adm: np.ndarray,
                         adm_gap: np.ndarray, delta: np.ndarray) -> tuple[float, int, int]:
    """Vertex `va` (of block i's piece) against vertex `vb` (of block j's): `(gap,
    candidates, best)` with best = -1 when it is no contact."""
    xa, xb = x[pv_vtx[va]], x[pv_vtx[vb]]
    for j in range(3):
        delta[j] = xa[j] - xb[j]
    if not _norm(delta) < r:
        return -np.inf, 0, -1
    nc = _face_candidates(pv_faces, pv_nfaces, f_normal, f_tag, vb, 1.0, cand, cface, ctag, 0)
    nc = _face_candidates(pv_faces, pv_nfaces, f_normal, f_tag, va, -1.0, cand, cface, ctag,
                          nc)
    dy = pv_dir[vb]
    na, nb = pv_ndir[va], pv_ndir[vb]
    nc = _cross_candidates(pv_dir[va], na, pv_nb_real[va], dy, pv_nb_real[vb], nb, parallel,
                           cand, cface, ctag, nc)
    best = _select_planes(cand, cface, nc, pv_dir[va], na, dy, nb, delta, entrance, snap, ang,
                          adm, adm_gap)
    if best < 0:
        return -np.inf, nc, -1
    return _dot(delta, cand[best]), nc, best


@njit(**_OPTS)
def _keep_candidates(nc: int, cand: np.ndarray, adm: np.ndarray, cface: np.ndarray,
                     ctag: np.ndarray, k_cand: np.ndarray, k_adm: np.ndarray,
                     k_face: np.ndarray, k_tag: np.ndarray) -> None:
    """Copy the first `nc` candidates and what the plane selection made of them into the
    `k_*` arrays (the winner's, so that emitting it needs no second evaluation)."""
    for c in range(nc):
        for j in range(3):
            k_cand[c, j] = cand[c, j]
        k_adm[c] = adm[c]
        k_face[c] = cface[c]
        k_tag[c] = ctag[c]


@njit(**_OPTS)
def _anchor(ri: np.ndarray, rf: np.ndarray, r: int, snap: float) -> tuple[int, int, int]:
    """What makes two constraints of one block pair the same contact: the X vertex and
    side, or for edge-edge the contact point on block i rounded to the snap distance."""
    if ri[r, RI_KIND] == EDGE_EDGE:
        return (round(rf[r, RF_POINT_I] / snap), round(rf[r, RF_POINT_I + 1] / snap),
                round(rf[r, RF_POINT_I + 2] / snap))
    return ri[r, RI_VERTEX], ri[r, RI_FLIP], 0


@njit(**_OPTS)
def _precedes(ri: np.ndarray, t: int, s: int) -> bool:
    """Row `t` comes before row `s`: lower kind, then lower key of block i, of block j."""
    for c in (RI_KIND, RI_FEATURE_I, RI_FEATURE_J):
        if ri[t, c] != ri[s, c]:
            return ri[t, c] < ri[s, c]
    return t < s


@njit(**_OPTS)
def _key_after(ri: np.ndarray, t: int, s: int) -> bool:
    """Row `t` has a larger key (feature i, then feature j) than row `s`."""
    if ri[t, RI_FEATURE_I] != ri[s, RI_FEATURE_I]:
        return ri[t, RI_FEATURE_I] > ri[s, RI_FEATURE_I]
    return ri[t, RI_FEATURE_J] > ri[s, RI_FEATURE_J]


@njit(**_OPTS)
def merge_and_order(ri: np.ndarray, rf: np.ndarray, snap: float, parallel: float,
                    n_blocks: int) -> np.ndarray:
    """Rows of :func:`narrow_phase` output to keep, in key order `(block i, feature i,
    block j, feature j)`.

    A row is dropped when an earlier row (lower kind, then lower key) of the same block
    pair has the same anchor (:func:`_anchor`), normal and gap - e.g. a vertex on a seam
    found from two pieces. The rows of one block pair are consecutive in the input.
    """
    k = len(ri)
    # runs of one block pair
    nrun = 0
    run_start = np.empty(k + 1, dtype=np.int64)
    for r in range(k):
        if (r == 0 or ri[r, RI_BLOCK_I] != ri[r - 1, RI_BLOCK_I]
                or ri[r, RI_BLOCK_J] != ri[r - 1, RI_BLOCK_J]):
            run_start[nrun] = r
            nrun += 1
    run_start[nrun] = k
    keep = np.ones(k, dtype=np.bool_)
    anchors = np.empty((k, 3), dtype=np.int64)
    for r in range(k):
        anchors[r, 0], anchors[r, 1], anchors[r, 2] = _anchor(ri, rf, r, max(snap, 1e-300))
    for g in range(nrun):
        for s in range(run_start[g], run_start[g + 1]):
            for t in range(run_start[g], run_start[g + 1]):
                if (t == s or (ri[t, RI_KIND] == EDGE_EDGE) != (ri[s, RI_KIND] == EDGE_EDGE)
                        or anchors[t, 0] != anchors[s, 0] or anchors[t, 1] != anchors[s, 1]
                        or anchors[t, 2] != anchors[s, 2] or not _precedes(ri, t, s)):
                    continue
                if (_dot(rf[s, RF_NORMAL:RF_NORMAL + 3], rf[t, RF_NORMAL:RF_NORMAL + 3])
                        > 1.0 - parallel and abs(rf[s, RF_GAP] - rf[t, RF_GAP]) < snap):
                    keep[s] = False
                    break
    # block pairs by (i, j), rows of a pair by (feature i, feature j)
    run_key = np.empty(nrun, dtype=np.int64)
    for g in range(nrun):
        r = run_start[g]
        run_key[g] = ri[r, RI_BLOCK_I] * n_blocks + ri[r, RI_BLOCK_J]
    out = np.empty(k, dtype=np.int64)
    m = 0
    for g in np.argsort(run_key, kind="mergesort"):
        m0 = m
        for r in range(run_start[g], run_start[g + 1]):
            if not keep[r]:
                continue
            p = m
            while p > m0 and _key_after(ri, out[p - 1], r):
                out[p] = out[p - 1]
                p -= 1
            out[p] = r
            m += 1
    return out[:m]


@njit(**_OPTS)
def gather_candidates(counts: np.ndarray, cand: np.ndarray, rows: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Ragged gather: `(indptr (len(rows)+1,), normals)` of the candidate ranges of
    `rows`, where row k owns `counts[k]` consecutive normals of `cand`."""
    start = np.zeros(len(counts) + 1, dtype=np.int64)
    for k in range(len(counts)):
        start[k + 1] = start[k] + counts[k]
    ptr = np.zeros(len(rows) + 1, dtype=np.int64)
    for k in range(len(rows)):
        ptr[k + 1] = ptr[k] + counts[rows[k]]
    out = np.empty((ptr[-1], 3))
    for k in range(len(rows)):
        s = start[rows[k]]
        for t in range(ptr[k + 1] - ptr[k]):
            out[ptr[k] + t] = cand[s + t]
    return ptr, out
