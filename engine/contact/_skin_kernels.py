"""Compiled loops of the detection skin (:mod:`engine.contact.skin`): how far each block's
vertices moved since the skin's full detection, and the candidate features each kept piece
pair may ever need while no block moves further than the skin's margin."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def block_drift(x: np.ndarray, x0: np.ndarray, vertex_block: np.ndarray,
                n: int) -> np.ndarray:
    """The largest distance `(n,)` m any vertex of each block moved from `x0` to `x`
    `(V, 3)`. A block's motion is affine, so no point of its convex hull moved further."""
    out = np.zeros(n)
    for v in range(x.shape[0]):
        d0, d1, d2 = x[v, 0] - x0[v, 0], x[v, 1] - x0[v, 1], x[v, 2] - x0[v, 2]
        d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        b = vertex_block[v]
        if d > out[b]:
            out[b] = d
    return out


@nb.njit(cache=True, inline="always")
def _segment_meets(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   r: float) -> bool:
    """Whether the box of the segment `a`–`b` (a point when `a` is `b`) meets the box
    `[lo, hi]` grown by `r`."""
    for j in range(3):
        if min(a[j], b[j]) > hi[j] + r or max(a[j], b[j]) < lo[j] - r:
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _push(buf: np.ndarray, n: int, value: int) -> np.ndarray:
    """`buf` with `value` at index `n` (its first `n` entries kept), doubled when full."""
    if n == len(buf):
        grown = np.empty(2 * len(buf), dtype=buf.dtype)
        grown[:n] = buf[:n]
        buf = grown
    buf[n] = value
    return buf


@nb.njit(cache=True, nogil=True)
def candidate_features(pa: np.ndarray, pb: np.ndarray, x: np.ndarray,
                       piece_block: np.ndarray, pv_start: np.ndarray, pv_count: np.ndarray,
                       pv_vtx: np.ndarray, pv_surface: np.ndarray, e_start: np.ndarray,
                       e_count: np.ndarray, e_vtx: np.ndarray, e_real: np.ndarray,
                       p_lo: np.ndarray, p_hi: np.ndarray, grow: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each piece pair `(pa[k], pb[k])`: the surface vertices of either piece inside
    the other's box grown by `grow[i] + grow[j]` (its blocks' `grow (n,)` m), and the real
    edges whose boxes meet it, as `(v_ptr, v_list, e_ptr, e_list)` (global piece-vertex and
    edge ids, in piece then id order). Every feature the narrow phase may look at while the
    pair's search radius and motion stay within that growth is among them: it only looks at
    vertices inside, and edges meeting, the other piece's box grown by the search radius."""
    npairs = len(pa)
    v_ptr = np.zeros(npairs + 1, dtype=np.int64)
    e_ptr = np.zeros(npairs + 1, dtype=np.int64)
    v_list = np.empty(16 * npairs + 16, dtype=np.int64)
    e_list = np.empty(24 * npairs + 16, dtype=np.int64)
    nv = ne = 0
    for k in range(npairs):
        r = grow[piece_block[pa[k]]] + grow[piece_block[pb[k]]]
        for side in range(2):
            p, other = (pa[k], pb[k]) if side == 0 else (pb[k], pa[k])
            lo, hi = p_lo[other], p_hi[other]
            for pv in range(pv_start[p], pv_start[p] + pv_count[p]):
                if not pv_surface[pv] or not _segment_meets(x[pv_vtx[pv]], x[pv_vtx[pv]], lo,
                                                            hi, r):
                    continue
                v_list = _push(v_list, nv, pv)
                nv += 1
            for e in range(e_start[p], e_start[p] + e_count[p]):
                if not e_real[e]:
                    continue
                if not _segment_meets(x[e_vtx[e, 0]], x[e_vtx[e, 1]], lo, hi, r):
                    continue
                e_list = _push(e_list, ne, e)
                ne += 1
        v_ptr[k + 1] = nv
        e_ptr[k + 1] = ne
    return v_ptr, v_list[:nv].copy(), e_ptr, e_list[:ne].copy()
