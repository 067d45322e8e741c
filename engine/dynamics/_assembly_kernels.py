"""Compiled per-contact kernels of the assembly and the open-close iteration: the
block-sparse pattern of K (once per step), K's blocks for the modes of a cycle (each
contact's unit terms computed where they are summed), and the relative displacement of the
contact points from the solution.

Each open-close cycle runs several of them (~10 cycles per step); as numpy they were
dozens of einsum / bincount / sparse calls per cycle. Compiled with numba (cached on disk).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def relative_displacement(x: np.ndarray, dof_map: np.ndarray, bi: np.ndarray,
                          bj: np.ndarray, ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
    """Tᵢ Dᵢ − Tⱼ Dⱼ `(c, 3)`: displacement of contact point i relative to point j for
    the solution `x` (fixed dofs are zero)."""
    c, _, d = ti.shape
    out = np.zeros((c, 3))
    for k in range(c):
        a, b = bi[k], bj[k]
        for q in range(d):
            ia = dof_map[a, q]
            if ia >= 0:
                xa = x[ia]
                for r in range(3):
                    out[k, r] += ti[k, r, q] * xa
            ib = dof_map[b, q]
            if ib >= 0:
                xb = x[ib]
                for r in range(3):
                    out[k, r] -= tj[k, r, q] * xb
    return out


@nb.njit(cache=True)
def _unit_terms_into(ti: np.ndarray, tj: np.ndarray, normal: np.ndarray, k: int,
                     a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Contact `k`'s unit-stiffness terms into `out (6, d, d)` (`a`, `b (d,)`: scratch):
    :func:`unit_contact_terms` for one contact, computed where they are summed so that no
    `(c, 6, d, d)` array is stored (224 MB at 5,000 blocks)."""
    d = ti.shape[2]
    n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
    for p in range(d):
        a[p] = n0 * ti[k, 0, p] + n1 * ti[k, 1, p] + n2 * ti[k, 2, p]
        b[p] = n0 * tj[k, 0, p] + n1 * tj[k, 1, p] + n2 * tj[k, 2, p]
    for p in range(d):
        for q in range(d):
            nii = a[p] * a[q]
            nij = -a[p] * b[q]
            njj = b[p] * b[q]
            out[0, p, q] = nii
            out[1, p, q] = nij
            out[2, p, q] = njj
            out[3, p, q] = (ti[k, 0, p] * ti[k, 0, q] + ti[k, 1, p] * ti[k, 1, q]
                            + ti[k, 2, p] * ti[k, 2, q]) - nii
            out[4, p, q] = -(ti[k, 0, p] * tj[k, 0, q] + ti[k, 1, p] * tj[k, 1, q]
                             + ti[k, 2, p] * tj[k, 2, q]) - nij
            out[5, p, q] = (tj[k, 0, p] * tj[k, 0, q] + tj[k, 1, p] * tj[k, 1, q]
                            + tj[k, 2, p] * tj[k, 2, q]) - njj


@nb.njit(cache=True)
def unit_contact_terms(ti: np.ndarray, tj: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Unit-stiffness contact terms `(c, 6, d, d)`: `(n_ii, n_ij, n_jj, s_ii, s_ij, s_jj)`
    for kn = 1 (P = n nᵀ) and ks = 1 (P = I − n nᵀ) (paper eqs. 24, 29); `ti`, `tj (c, 3,
    d)`, `normal (c, 3)`. The contact's terms are `kn·n_* + ks·s_*`."""
    c, _, d = ti.shape
    out = np.empty((c, 6, d, d))
    a = np.empty(d)
    b = np.empty(d)
    for k in range(c):
        _unit_terms_into(ti, tj, normal, k, a, b, out[k])
    return out


@nb.njit(cache=True)
def bsr_pattern(m: int, fi: np.ndarray, fj: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                           np.ndarray, np.ndarray]:
    """Block-sparse pattern of K for `m` block rows and contacts between block rows `fi`,
    `fj (c,)` (-1: fixed block). Returns `(indptr (m+1,), indices (nnz,), diag_slot (m,),
    slot_ii, slot_jj, slot_ij, slot_ji (c,))`: the BSR block each contact term lands on
    (-1 where it has none); every row holds its diagonal block, columns sorted."""
    c = len(fi)
    # distinct partners per row: sort the (row, column) keys of both orientations
    keys = np.empty(2 * c, dtype=np.int64)
    nk = 0
    for k in range(c):
        if fi[k] >= 0 and fj[k] >= 0 and fi[k] != fj[k]:
            keys[nk] = fi[k] * m + fj[k]
            keys[nk + 1] = fj[k] * m + fi[k]
            nk += 2
    allk = np.empty(nk + m, dtype=np.int64)
    allk[:nk] = keys[:nk]
    for r in range(m):
        allk[nk + r] = r * m + r
    allk = np.unique(allk)
    nnz = len(allk)
    indptr = np.zeros(m + 1, dtype=np.int64)
    indices = np.empty(nnz, dtype=np.int64)
    diag_slot = np.empty(m, dtype=np.int64)
    for s in range(nnz):
        r, col = allk[s] // m, allk[s] % m
        indptr[r + 1] += 1
        indices[s] = col
        if r == col:
            diag_slot[r] = s
    for r in range(m):
        indptr[r + 1] += indptr[r]
    slot_ii = np.full(c, -1, dtype=np.int64)
    slot_jj = np.full(c, -1, dtype=np.int64)
    slot_ij = np.full(c, -1, dtype=np.int64)
    slot_ji = np.full(c, -1, dtype=np.int64)
    for k in range(c):
        a, b = fi[k], fj[k]
        if a >= 0:
            slot_ii[k] = diag_slot[a]
        if b >= 0:
            slot_jj[k] = diag_slot[b]
        if a >= 0 and b >= 0 and a != b:
            slot_ij[k] = np.searchsorted(allk, a * m + b)
            slot_ji[k] = np.searchsorted(allk, b * m + a)
    return indptr, indices, diag_slot, slot_ii, slot_jj, slot_ij, slot_ji


@nb.njit(cache=True)
def fill_bsr(base: np.ndarray, ti: np.ndarray, tj: np.ndarray, normal: np.ndarray,
             slot_ii: np.ndarray, slot_jj: np.ndarray, slot_ij: np.ndarray,
             slot_ji: np.ndarray, kn: np.ndarray, ks: np.ndarray) -> np.ndarray:
    """BSR data `(nnz, d, d)`: the block terms `base` plus every contact's
    `kn·n_* + ks·s_*` of :func:`unit_contact_terms` on its blocks (the ji block gets the
    transpose of the ij term). Contacts with kn = ks = 0 (open) add nothing."""
    data = base.copy()
    acting = np.flatnonzero((kn != 0.0) | (ks != 0.0))
    update_bsr(data, ti, tj, normal, slot_ii, slot_jj, slot_ij, slot_ji, acting, kn[acting],
               ks[acting])
    return data


@nb.njit(cache=True)
def update_bsr(data: np.ndarray, ti: np.ndarray, tj: np.ndarray, normal: np.ndarray,
               slot_ii: np.ndarray, slot_jj: np.ndarray, slot_ij: np.ndarray,
               slot_ji: np.ndarray, changed: np.ndarray, dkn: np.ndarray,
               dks: np.ndarray) -> None:
    """Add to the BSR data `data` (in place) the terms `dkn·n_* + dks·s_*` of
    :func:`unit_contact_terms` of the contacts `changed (r,)` on their blocks (the ji block
    gets the transpose of the ij term): K filled from the block terms (:func:`fill_bsr`),
    or the next open-close cycle's K from the last one by the stiffness changes `dkn`,
    `dks (r,)` of the contacts that changed mode. Contacts: `ti`, `tj (c, 3, d)`,
    `normal (c, 3)`; their unit terms are computed here (:func:`_unit_terms_into`)."""
    d = data.shape[1]
    a, b = np.empty(d), np.empty(d)
    unit = np.empty((6, d, d))
    for t in range(len(changed)):
        k = changed[t]
        wn, ws = dkn[t], dks[t]
        _unit_terms_into(ti, tj, normal, k, a, b, unit)
        si, sj, sij, sji = slot_ii[k], slot_jj[k], slot_ij[k], slot_ji[k]
        for p in range(d):
            for q in range(d):
                if si >= 0:
                    data[si, p, q] += wn * unit[0, p, q] + ws * unit[3, p, q]
                if sj >= 0:
                    data[sj, p, q] += wn * unit[2, p, q] + ws * unit[5, p, q]
                if sij >= 0:
                    v = wn * unit[1, p, q] + ws * unit[4, p, q]
                    data[sij, p, q] += v
                    data[sji, q, p] += v


@nb.njit(cache=True)
def _root(parent: np.ndarray, r: int) -> int:
    """Root of `r` in the union-find forest `parent`, halving the path on the way."""
    while parent[r] != r:
        parent[r] = parent[parent[r]]
        r = parent[r]
    return r


@nb.njit(cache=True)
def coupled_components(m: int, slot_ij: np.ndarray, fi: np.ndarray, fj: np.ndarray,
                       kn: np.ndarray, ks: np.ndarray) -> np.ndarray:
    """The connected component of every block row through contacts with nonzero stiffness
    `(m,) int`, numbered from 0 in the order of their first rows; -1 for a row that shares
    no such contact with another free block (conjugate gradients need not iterate on it)."""
    parent = np.arange(m)
    hit = np.zeros(m, dtype=np.bool_)
    for k in range(len(kn)):
        if slot_ij[k] >= 0 and (kn[k] != 0.0 or ks[k] != 0.0):
            hit[fi[k]] = True
            hit[fj[k]] = True
            a, b = _root(parent, fi[k]), _root(parent, fj[k])
            if a != b:  # the smaller row is the root: a component's root is its first row
                parent[max(a, b)] = min(a, b)
    label = np.full(m, -1, dtype=np.int64)
    count = 0
    for r in range(m):
        if hit[r]:
            root = _root(parent, r)
            if root == r:
                label[r] = count
                count += 1
            else:
                label[r] = label[root]
    return label


@nb.njit(cache=True)
def bsr_to_dense(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Dense `(m d, m d)` matrix of a BSR matrix given by its arrays."""
    m = len(indptr) - 1
    d = data.shape[1]
    out = np.zeros((m * d, m * d))
    for r in range(m):
        for s in range(indptr[r], indptr[r + 1]):
            col = indices[s]
            for p in range(d):
                for q in range(d):
                    out[r * d + p, col * d + q] = data[s, p, q]
    return out


# --------------------------------------------------------------------------- on threads
# The same sums on numba's threads, each output written by one thread and summed in the
# serial kernels' order (contacts in order per BSR block, per unknown), so that the values
# are the same bits whatever the number of threads.


@nb.njit(cache=True)
def row_contacts(m: int, fi: np.ndarray, fj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The contacts of each of `m` rows (block rows, or blocks) as `(ptr (m + 1,), entries)`:
    row r's are `entries[ptr[r]:ptr[r + 1]]`, each `2 k` (the row is contact k's `fi`) or
    `2 k + 1` (its `fj`), in contact order; rows < 0 (fixed blocks) have none."""
    ptr = np.zeros(m + 1, dtype=np.int64)
    for k in range(len(fi)):
        if fi[k] >= 0:
            ptr[fi[k] + 1] += 1
        if fj[k] >= 0:
            ptr[fj[k] + 1] += 1
    for r in range(m):
        ptr[r + 1] += ptr[r]
    fill = ptr[:-1].copy()
    entries = np.empty(ptr[m], dtype=np.int64)
    for k in range(len(fi)):
        if fi[k] >= 0:
            entries[fill[fi[k]]] = 2 * k
            fill[fi[k]] += 1
        if fj[k] >= 0:
            entries[fill[fj[k]]] = 2 * k + 1
            fill[fj[k]] += 1
    return ptr, entries


@nb.njit(cache=True, inline="always")
def _row_terms(data: np.ndarray, ti: np.ndarray, tj: np.ndarray, normal: np.ndarray,
               slot_ii: np.ndarray, slot_jj: np.ndarray, slot_ij: np.ndarray,
               slot_ji: np.ndarray, kn: np.ndarray, ks: np.ndarray, ptr: np.ndarray,
               entries: np.ndarray, r: int) -> None:
    """Add to block row `r`'s BSR blocks the terms :func:`update_bsr` adds there for every
    contact with stiffness (the diagonal block and, as block i, the ij block; as block j,
    the ji block), in contact order, with its expressions."""
    d = data.shape[1]
    a, b = np.empty(d), np.empty(d)
    for t in range(ptr[r], ptr[r + 1]):
        k, role = entries[t] >> 1, entries[t] & 1
        wn, ws = kn[k], ks[k]
        if wn == 0.0 and ws == 0.0:
            continue
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        for p in range(d):
            a[p] = n0 * ti[k, 0, p] + n1 * ti[k, 1, p] + n2 * ti[k, 2, p]
            b[p] = n0 * tj[k, 0, p] + n1 * tj[k, 1, p] + n2 * tj[k, 2, p]
        own, cross = (slot_ii[k], slot_ij[k]) if role == 0 else (slot_jj[k], slot_ji[k])
        for p in range(d):
            for q in range(d):
                if role == 0:
                    nii = a[p] * a[q]
                    sii = (ti[k, 0, p] * ti[k, 0, q] + ti[k, 1, p] * ti[k, 1, q]
                           + ti[k, 2, p] * ti[k, 2, q]) - nii
                    data[own, p, q] += wn * nii + ws * sii
                else:
                    njj = b[p] * b[q]
                    sjj = (tj[k, 0, p] * tj[k, 0, q] + tj[k, 1, p] * tj[k, 1, q]
                           + tj[k, 2, p] * tj[k, 2, q]) - njj
                    data[own, p, q] += wn * njj + ws * sjj
                if cross >= 0:
                    nij = -a[p] * b[q]
                    sij = -(ti[k, 0, p] * tj[k, 0, q] + ti[k, 1, p] * tj[k, 1, q]
                            + ti[k, 2, p] * tj[k, 2, q]) - nij
                    v = wn * nij + ws * sij
                    if role == 0:
                        data[cross, p, q] += v
                    else:
                        data[cross, q, p] += v


@nb.njit(cache=True, parallel=True)
def fill_bsr_threads(base: np.ndarray, ti: np.ndarray, tj: np.ndarray, normal: np.ndarray,
                     slot_ii: np.ndarray, slot_jj: np.ndarray, slot_ij: np.ndarray,
                     slot_ji: np.ndarray, kn: np.ndarray, ks: np.ndarray,
                     ptr: np.ndarray, entries: np.ndarray) -> np.ndarray:
    """:func:`fill_bsr` with the block rows on numba's threads; `ptr`, `entries`: each
    block row's contacts (:func:`row_contacts` of the contacts' block rows)."""
    data = base.copy()
    for r in nb.prange(len(ptr) - 1):
        _row_terms(data, ti, tj, normal, slot_ii, slot_jj, slot_ij, slot_ji, kn, ks, ptr,
                   entries, r)
    return data


@nb.njit(cache=True, parallel=True)
def relative_displacement_threads(x: np.ndarray, dof_map: np.ndarray, bi: np.ndarray,
                                  bj: np.ndarray, ti: np.ndarray,
                                  tj: np.ndarray) -> np.ndarray:
    """:func:`relative_displacement` with the contacts on numba's threads."""
    c, _, d = ti.shape
    out = np.zeros((c, 3))
    for k in nb.prange(c):
        a, b = bi[k], bj[k]
        for q in range(d):
            ia = dof_map[a, q]
            if ia >= 0:
                xa = x[ia]
                for r in range(3):
                    out[k, r] += ti[k, r, q] * xa
            ib = dof_map[b, q]
            if ib >= 0:
                xb = x[ib]
                for r in range(3):
                    out[k, r] -= tj[k, r, q] * xb
    return out
