"""Shi's block terms and the penalty contact terms of the global system `K D = F`.

Everything is vectorised over blocks or contacts. Each block has 12 local columns
`(u, v, w, rx, ry, rz, εx, εy, εz, γyz, γzx, γxy)`; rigid blocks use the first 6, fixed
blocks none. `dof_map (n, 12) int` gives the global unknown of each column, -1 where the
column is not an unknown. The global K is assembled block-sparse (:class:`SystemPlan`):
contact terms are first summed per block and per block pair, so its size follows the
blocks and pairs in contact, not the number of contact points.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from engine.dynamics._assembly_kernels import (
    bsr_pattern,
    bsr_to_dense,
    coupled_components,
    fill_bsr,
    fill_bsr_threads,
    relative_displacement,
    relative_displacement_threads,
    row_contacts,
    update_bsr,
)
from engine.geometry._transform_kernels import TA, contact_matrices, contact_matrices_threads
from engine.geometry.transforms import displacement_matrices  # noqa: F401 (asm.)

#: the T_aᵀ T_b of the second moments C_ab, flattened (9, 144)
_CROSS = np.einsum("aki,bkj->abij", TA, TA).reshape(9, 144)


def mass_matrices(density: np.ndarray, volume: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Block mass matrices `(n, 12, 12)`: `ρ (V T0ᵀT0 + Σ C_ab T_aᵀ T_b)`.

    `density (n,)` kg/m³, `volume (n,)` m³, `second (n, 3, 3)` = ∫ x_t x_tᵀ dV.
    """
    n = len(volume)
    m = (second.reshape(n, 9) @ _CROSS).reshape(n, 12, 12)
    for k in range(3):  # T0ᵀ T0 is the identity on the translations
        m[:, k, k] += volume
    m *= density[:, None, None]
    return m


def elastic_matrix(young_modulus: float, poisson_ratio: float) -> np.ndarray:
    """Isotropic 6×6 stiffness for Voigt strains with engineering shear (Pa)."""
    e, nu = young_modulus, poisson_ratio
    lam = e * nu / ((1 + nu) * (1 - 2 * nu))
    g = e / (2 * (1 + nu))
    d = np.zeros((6, 6))
    d[:3, :3] = lam
    d[np.arange(3), np.arange(3)] = lam + 2 * g
    d[np.arange(3, 6), np.arange(3, 6)] = g
    return d


def scatter_vector(dof_map: np.ndarray, block: np.ndarray, values: np.ndarray,
                   n: int) -> np.ndarray:
    """Global vector `(n,)` from per-block 12-vectors `values (p, 12)` of blocks `block (p,)`."""
    idx = dof_map[block]
    keep = idx >= 0
    return np.bincount(idx[keep], weights=values[keep], minlength=n)


#: systems with at most this many unknowns are assembled and factorized dense: for a few
#: blocks the sparse machinery costs more than the arithmetic
DENSE_MAX_UNKNOWNS = 120

#: per-contact loops run on numba's threads (NUMBA_NUM_THREADS, the cores by default) from
#: this many contacts on, when a core is spare (:func:`spare_core`); each output is summed
#: by one thread in the serial order, so the values do not depend on the number of threads.
#: Measured by `python -m benchmarks.bench_work` (benchmarks/REPORT.md section 8): a
#: parallel region costs ~20 µs on free cores, and beside busy processes the threads lose
#: at every size (a region waits for its slowest thread's turn on a core)
THREADS_MIN_CONTACTS = 4000
#: how long (s) a reading of the load average serves
_LOAD_TTL = 1.0
_load: list[float] = [-1.0, 0.0]  # (when, spare) of the last reading


def spare_core() -> bool:
    """Whether the machine has a core to spare for a second thread: its one-minute load
    average (this process included) at most its cores less one (read at most once a
    second)."""
    now = time.monotonic()
    if now - _load[0] > _LOAD_TTL:
        try:
            load = os.getloadavg()[0]
        except OSError:  # no load average (not a Unix): assume the cores are free
            load = 0.0
        _load[0], _load[1] = now, float(load <= (os.cpu_count() or 1) - 1)
    return bool(_load[1])


def threaded(count: int) -> bool:
    """Whether loops over `count` contacts run on numba's threads: from
    THREADS_MIN_CONTACTS on, with more than one configured and a core spare (reading
    numba's configured count does not launch its threading layer)."""
    import numba

    return (numba.config.NUMBA_NUM_THREADS > 1 and count >= THREADS_MIN_CONTACTS
            and spare_core())


def point_matrices(points: np.ndarray, centroids: np.ndarray, block: np.ndarray,
                   nd: int) -> np.ndarray:
    """T at contact points `points (c, 3)` of blocks `block (c,)` on the first `nd`
    unknowns `(c, 3, nd)` (contiguous; the values of `displacement_matrices(points,
    centroids[block])[:, :, :nd]`), on threads for many contacts."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    block = np.ascontiguousarray(block, dtype=np.int64)
    centroids = np.ascontiguousarray(centroids, dtype=np.float64)
    kernel = contact_matrices_threads if threaded(len(points)) else contact_matrices
    return kernel(points, centroids, block, nd)


def relative_motion(x: np.ndarray, dof_map: np.ndarray, bi: np.ndarray, bj: np.ndarray,
                    ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
    """Tᵢ Dᵢ − Tⱼ Dⱼ `(c, 3)` of the solution `x` at the contacts (on threads for many)."""
    kernel = relative_displacement_threads if threaded(len(bi)) else relative_displacement
    return kernel(x, dof_map, bi, bj, ti, tj)


def contact_stiffness(
    ti: np.ndarray,
    tj: np.ndarray,
    normal: np.ndarray,
    kn: np.ndarray,
    ks: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal and (locked) shear penalty springs, paper eqs. 24 and 29.

    `ti`, `tj (c, 3, 12)` are T at the two contact points, `normal (c, 3)`, `kn`, `ks (c,)`
    (set ks = 0 for sliding contacts). Returns `(kii, kij, kjj)` each `(c, 12, 12)`.
    """
    # spring matrix P = kn n nᵀ + ks (I - n nᵀ)
    nn = np.einsum("ci,cj->cij", normal, normal)
    p = kn[:, None, None] * nn + ks[:, None, None] * (np.eye(3)[None] - nn)
    pti = np.einsum("cab,cbj->caj", p, ti)
    ptj = np.einsum("cab,cbj->caj", p, tj)
    kii = np.einsum("cai,caj->cij", ti, pti)
    kij = -np.einsum("cai,caj->cij", ti, ptj)
    kjj = np.einsum("cai,caj->cij", tj, ptj)
    return kii, kij, kjj


@dataclass
class SystemPlan:
    """The global K of one step as a function of the contact modes.

    Everything that does not depend on which contacts are closed or locked (block terms,
    the block-sparse pattern and where each contact's terms land in it) is computed once
    per step by :func:`plan_system`; each open-close cycle then only weights the contacts'
    unit terms and sums them, in one compiled pass (:func:`fill_bsr`, or
    :func:`update_bsr` over the contacts that changed). A matrix :meth:`matrix` returns is
    valid until its next call, which may update it in place.
    """

    m: int
    d: int
    base: np.ndarray  # (nnz, d, d) BSR data holding the block terms of the free blocks
    indptr: np.ndarray  # (m + 1,) BSR row pointers
    indices: np.ndarray  # (nnz,) BSR block columns
    diag_slot: np.ndarray  # (m,) the diagonal block of each block row
    ti: np.ndarray  # (c, 3, d) contacts' displacement matrices on block i (contiguous)
    tj: np.ndarray  # (c, 3, d) on block j
    normal: np.ndarray  # (c, 3)
    fi: np.ndarray  # (c,) block row of block i of each contact (-1: fixed)
    fj: np.ndarray  # (c,) block row of block j
    slot_ii: np.ndarray  # (c,) BSR block of each contact term (-1: none)
    slot_jj: np.ndarray
    slot_ij: np.ndarray
    slot_ji: np.ndarray
    dense: bool
    #: the last matrix's coupled components of the block rows (:func:`coupled_components`)
    components: np.ndarray | None = None
    #: the last matrix's contact stiffnesses `kn`, `ks (c,)` and BSR data, for updates
    last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    #: the last BSR data and the matrix wrapping it (a view: an update in place shows)
    bsr: tuple[np.ndarray, sp.bsr_matrix] | None = None
    #: each block row's contacts (:func:`row_contacts`), for filling on threads
    rows: tuple[np.ndarray, np.ndarray] | None = None

    def matrix(self, kn: np.ndarray, ks: np.ndarray) -> tuple[sp.bsr_matrix | np.ndarray,
                                                               np.ndarray]:
        """K and its diagonal blocks `(m, d, d)` for per-contact normal and shear
        stiffness `kn`, `ks (c,)` (0 where the contact is open / not locked); K is dense
        for small systems, else BSR. Also sets :attr:`components`."""
        kn = np.ascontiguousarray(kn, dtype=np.float64)
        ks = np.ascontiguousarray(ks, dtype=np.float64)
        return self._wrap(self._data(kn, ks), kn, ks)

    def wrap(self, data: np.ndarray, weight: np.ndarray) -> tuple[sp.bsr_matrix | np.ndarray,
                                                                  np.ndarray]:
        """K of BSR values `data (nnz, d, d)` on this plan's pattern (filled by the caller,
        e.g. a Hessian with a 3 × 3 block per contact) and its diagonal blocks; `weight
        (c,)` is nonzero where a contact couples its blocks (for :attr:`components`)."""
        w = np.ascontiguousarray(weight, dtype=np.float64)
        return self._wrap(data, w, np.zeros_like(w))

    def _wrap(self, data: np.ndarray, kn: np.ndarray, ks: np.ndarray
              ) -> tuple[sp.bsr_matrix | np.ndarray, np.ndarray]:
        self.components = coupled_components(self.m, self.slot_ij, self.fi, self.fj, kn, ks)
        dblk = data[self.diag_slot]
        if self.dense:
            return bsr_to_dense(self.indptr, self.indices, data), dblk
        if self.bsr is None:
            n = self.m * self.d
            self.bsr = (data, sp.bsr_matrix((data, self.indices, self.indptr), shape=(n, n)))
        elif self.bsr[0] is not data:  # filled afresh (else K was updated in place): the
            self.bsr[1].data = data  # same pattern, so the matrix takes the new values
            self.bsr = (data, self.bsr[1])
        return self.bsr[1], dblk

    def pattern(self) -> SystemPlan:
        """This plan without its values (no block terms, contact matrices or K): what
        :func:`plan_system` needs of it to keep its pattern for the next step, held at the
        cost of a few integers per contact."""
        empty = np.zeros((0, 3, self.d))
        return dataclasses.replace(self, base=np.zeros((0, self.d, self.d)), ti=empty,
                                   tj=empty, normal=np.zeros((0, 3)), components=None,
                                   last=None, bsr=None)

    def _data(self, kn: np.ndarray, ks: np.ndarray) -> np.ndarray:
        """BSR data of K for `kn`, `ks`: the last K updated in place by the contacts
        whose stiffness changed when they are few (an open-close cycle changes tens of a
        rock mass's thousands of contacts), else filled afresh. In place, not on a copy:
        the copy of a 5,000-block K cost as much as the update."""
        last = self.last
        if last is not None and len(kn) >= UPDATE_MIN_CONTACTS:
            changed = np.flatnonzero((kn != last[0]) | (ks != last[1]))
            if len(changed) <= UPDATE_MAX_FRACTION * len(kn):
                data = last[2]
                update_bsr(data, self.ti, self.tj, self.normal, self.slot_ii, self.slot_jj,
                           self.slot_ij, self.slot_ji, changed,
                           kn[changed] - last[0][changed], ks[changed] - last[1][changed])
                self.last = (kn.copy(), ks.copy(), data)
                return data
        if threaded(len(kn)) and not self.dense:
            if self.rows is None:
                self.rows = row_contacts(self.m, self.fi, self.fj)
            data = fill_bsr_threads(self.base, self.ti, self.tj, self.normal, self.slot_ii,
                                    self.slot_jj, self.slot_ij, self.slot_ji, kn, ks,
                                    *self.rows)
        else:
            data = fill_bsr(self.base, self.ti, self.tj, self.normal, self.slot_ii,
                            self.slot_jj, self.slot_ij, self.slot_ji, kn, ks)
        self.last = (kn.copy(), ks.copy(), data)
        return data


#: K is updated from the last one when at most this fraction of the contacts changed
#: stiffness, else filled afresh; only from this many contacts on (a fresh fill of fewer
#: costs microseconds, and keeps small scenes' round-off exactly as it was)
UPDATE_MAX_FRACTION = 0.25
UPDATE_MIN_CONTACTS = 512


def plan_system(
    row_of: np.ndarray, diag: np.ndarray, bi: np.ndarray, bj: np.ndarray,
    ti: np.ndarray, tj: np.ndarray, normal: np.ndarray, last: SystemPlan | None = None,
) -> SystemPlan:
    """The :class:`SystemPlan` of one step. `row_of (n,) int` is each block's block row
    (-1 for fixed blocks, rows in block order), `diag (n, d, d)` the block terms; contacts
    `bi`, `bj (c,)` with `ti`, `tj (c, 3, d)` and `normal (c, 3)`. K is dense for systems
    of at most DENSE_MAX_UNKNOWNS unknowns, else block-sparse (BSR). `last`: an earlier
    plan (the last step's) whose pattern is kept when its contacts join the same block rows
    in the same order (the contact pairs a skin keeps), so only the values are filled."""
    d = diag.shape[1]
    m = int(row_of.max(initial=-1)) + 1
    fi = np.ascontiguousarray(row_of[bi], dtype=np.int64)
    fj = np.ascontiguousarray(row_of[bj], dtype=np.int64)
    if (last is not None and last.m == m and last.d == d and np.array_equal(last.fi, fi)
            and np.array_equal(last.fj, fj)):
        fi, fj, rows = last.fi, last.fj, last.rows
        indptr, indices, diag_slot = last.indptr, last.indices, last.diag_slot
        sii, sjj, sij, sji = last.slot_ii, last.slot_jj, last.slot_ij, last.slot_ji
    else:
        rows = None
        indptr, indices, diag_slot, sii, sjj, sij, sji = bsr_pattern(m, fi, fj)
    base = np.zeros((len(indices), d, d))
    base[diag_slot] = diag[row_of >= 0]
    return SystemPlan(m=m, d=d, base=base, indptr=indptr, indices=indices,
                      diag_slot=diag_slot, ti=np.ascontiguousarray(ti, dtype=np.float64),
                      tj=np.ascontiguousarray(tj, dtype=np.float64),
                      normal=np.ascontiguousarray(normal, dtype=np.float64), fi=fi, fj=fj,
                      slot_ii=sii, slot_jj=sjj, slot_ij=sij, slot_ji=sji,
                      dense=m * d <= DENSE_MAX_UNKNOWNS, rows=rows)
