"""Compiled per-contact loops of the step as one minimisation (:mod:`.newton`): each
contact's force, energy and Hessian block at a relative displacement, the slope and
curvature of the step potential along a Newton direction (the exact line search), forces
scattered onto the blocks, the Hessian's block-sparse values, and the second-order gap
correction of the step's exact rotation.

A contact's terms (docs/theory.md, docs/contact-solvers.md): the gap `g = d0 + δ + n·dr`
of its relative displacement `dr` (δ: the exact rotation's correction, held during a
Newton solve); a normal spring `½ kn ⟨−g⟩²` (`½ kn g²` while its bond holds tension) and a
dashpot `½ c' ⟨a − g⟩²` that resists the approach since the step's start or entrance
(`a = min(d0, 0)`, `c' = cn / Δt`); the shear spring anchored at `shear0`, `w = shear0 +
dr − (n·dr) n`, capped at `C = μ N + c A` (a Huber function: `½ ks |w|²` inside, `C |w| −
C² / (2 ks)` beyond), or uncapped while the contact's bonded patch holds. Every term is
convex in `dr`, so the step potential is convex and its minimum unique. Compiled with numba
(cached on disk).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine.contact.constraints import LOCKED, OPEN, SLIDING
from engine.dynamics._solver_kernels import _block_apply, _bsr_matvec


@nb.njit(cache=True)
def _contact(k: int, dr0: float, dr1: float, dr2: float, normal: np.ndarray,
             base: np.ndarray, a: np.ndarray, cprime: np.ndarray, shear0: np.ndarray,
             cap: np.ndarray, kn: float, ks: float, tension: np.ndarray, stick: np.ndarray,
             force: np.ndarray, hess: np.ndarray, want_hess: bool, mu: np.ndarray) -> float:
    """Contact `k` at relative displacement `dr`: its force on block i into `force (3,)`
    (world axes), its Hessian block into `hess (3, 3)` when `want_hess`, and its energy
    (J). `base[k] = d0 + δ`; `tension[k] > 0` marks a bond that holds tension; `stick[k]`
    a shear spring without a cap (its bonded patch holds). With friction coefficients `mu`
    (an empty array: none), the block is the Jacobian of the force with the cap μN + cA
    following the normal force N at `dr` (−μ ∂N ŵ nᵀ on a sliding contact: not symmetric),
    else the Hessian of the energy with the cap held."""
    n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
    dn = dr0 * n0 + dr1 * n1 + dr2 * n2
    g = base[k] + dn
    energy = 0.0
    fn = 0.0
    hn = 0.0
    if tension[k] > 0.0:
        fn = -kn * g
        hn = kn
        energy += 0.5 * kn * g * g
    elif g < 0.0:
        fn = -kn * g
        hn = kn
        energy += 0.5 * kn * g * g
    e = a[k] - g
    if e > 0.0 and cprime[k] > 0.0:
        fn += cprime[k] * e
        hn += cprime[k]
        energy += 0.5 * cprime[k] * e * e
    w0 = shear0[k, 0] + dr0 - dn * n0
    w1 = shear0[k, 1] + dr1 - dn * n1
    w2 = shear0[k, 2] + dr2 - dn * n2
    wn = w0 * n0 + w1 * n1 + w2 * n2  # shear0 lies in the plane: round-off only
    w0, w1, w2 = w0 - wn * n0, w1 - wn * n1, w2 - wn * n2
    wl = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    c = cap[k]
    if stick[k] or ks * wl <= c:
        t0, t1, t2 = -ks * w0, -ks * w1, -ks * w2
        ht = ks
        hw = 0.0
        energy += 0.5 * ks * wl * wl
    else:
        s = c / wl
        t0, t1, t2 = -s * w0, -s * w1, -s * w2
        ht = s
        hw = s
        energy += c * wl - 0.5 * c * c / ks
    force[0] = fn * n0 + t0
    force[1] = fn * n1 + t1
    force[2] = fn * n2 + t2
    if want_hess:
        u0, u1, u2 = 0.0, 0.0, 0.0
        if hw > 0.0:
            u0, u1, u2 = w0 / wl, w1 / wl, w2 / wl
        nn = (n0, n1, n2)
        uu = (u0, u1, u2)
        # the cap's dependence on the normal force (sliding, pressed, coupled Newton)
        cn = mu[k] * hn if (hw > 0.0 and len(mu) > 0 and fn > 0.0) else 0.0
        for p in range(3):
            for q in range(3):
                eye = 1.0 if p == q else 0.0
                hess[p, q] = (hn * nn[p] * nn[q] + ht * (eye - nn[p] * nn[q])
                              - hw * uu[p] * uu[q] - cn * uu[p] * nn[q])
    return energy


@nb.njit(cache=True)
def contact_terms(dr: np.ndarray, normal: np.ndarray, base: np.ndarray, a: np.ndarray,
                  cprime: np.ndarray, shear0: np.ndarray, cap: np.ndarray, kn: float,
                  ks: float, tension: np.ndarray, stick: np.ndarray, want_hess: bool,
                  mu: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Every contact's force on block i `(c, 3)` N, Jacobian block `(c, 3, 3)` N/m (zeros
    unless `want_hess`; see :func:`_contact` for `mu`) and their total energy (J) at
    relative displacements `dr (c, 3)`."""
    c = dr.shape[0]
    force = np.zeros((c, 3))
    hess = np.zeros((c, 3, 3)) if want_hess else np.zeros((0, 3, 3))
    scratch = np.zeros((3, 3))
    total = 0.0
    for k in range(c):
        h = hess[k] if want_hess else scratch
        total += _contact(k, dr[k, 0], dr[k, 1], dr[k, 2], normal, base, a, cprime, shear0,
                          cap, kn, ks, tension, stick, force[k], h, want_hess, mu)
    return force, hess, total


@nb.njit(cache=True)
def line_slope(alpha: float, dr0: np.ndarray, dp: np.ndarray, normal: np.ndarray,
               base: np.ndarray, a: np.ndarray, cprime: np.ndarray, shear0: np.ndarray,
               cap: np.ndarray, kn: float, ks: float, tension: np.ndarray,
               stick: np.ndarray) -> tuple[float, float]:
    """The contacts' part of the step potential's slope and curvature along a direction at
    `alpha`: `Σ −F(dr0 + α dp)·dp` and `Σ dpᵀ H dp` (relative displacements `dr0`, their
    change `dp (c, 3)` per unit α). The terms of :func:`_contact`, written for one
    direction (no 3 × 3 block is formed)."""
    slope = 0.0
    curve = 0.0
    for k in range(dr0.shape[0]):
        p0, p1, p2 = dp[k, 0], dp[k, 1], dp[k, 2]
        if p0 == 0.0 and p1 == 0.0 and p2 == 0.0:
            continue
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        d0, d1, d2 = dr0[k, 0] + alpha * p0, dr0[k, 1] + alpha * p1, dr0[k, 2] + alpha * p2
        dn = d0 * n0 + d1 * n1 + d2 * n2
        pn = p0 * n0 + p1 * n1 + p2 * n2
        g = base[k] + dn
        fn = 0.0
        hn = 0.0
        if tension[k] > 0.0 or g < 0.0:
            fn = -kn * g
            hn = kn
        e = a[k] - g
        if e > 0.0 and cprime[k] > 0.0:
            fn += cprime[k] * e
            hn += cprime[k]
        w0 = shear0[k, 0] + d0 - dn * n0
        w1 = shear0[k, 1] + d1 - dn * n1
        w2 = shear0[k, 2] + d2 - dn * n2
        wn = w0 * n0 + w1 * n1 + w2 * n2
        w0, w1, w2 = w0 - wn * n0, w1 - wn * n1, w2 - wn * n2
        wl = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        t0, t1, t2 = p0 - pn * n0, p1 - pn * n1, p2 - pn * n2  # dp in the plane
        tt = t0 * t0 + t1 * t1 + t2 * t2
        if stick[k] or ks * wl <= cap[k]:
            slope += ks * (w0 * t0 + w1 * t1 + w2 * t2)
            curve += ks * tt
        else:
            s = cap[k] / wl
            wt = (w0 * t0 + w1 * t1 + w2 * t2) / wl
            slope += s * wl * wt
            curve += s * (tt - wt * wt)
        slope -= fn * pn
        curve += hn * pn * pn
    return slope, curve


@nb.njit(cache=True)
def scatter_forces(force: np.ndarray, row: np.ndarray, bi: np.ndarray, bj: np.ndarray,
                   ti: np.ndarray, tj: np.ndarray, out: np.ndarray) -> None:
    """Add each contact's force `force (c, 3)` on block i as Tᵢᵀ F to block i's row and
    −Tⱼᵀ F to block j's (`out (m, d)`, in place; `row (n,)` each block's row, -1: not an
    unknown)."""
    d = ti.shape[2]
    for k in range(force.shape[0]):
        f0, f1, f2 = force[k, 0], force[k, 1], force[k, 2]
        ri, rj = row[bi[k]], row[bj[k]]
        if ri >= 0:
            for q in range(d):
                out[ri, q] += ti[k, 0, q] * f0 + ti[k, 1, q] * f1 + ti[k, 2, q] * f2
        if rj >= 0:
            for q in range(d):
                out[rj, q] -= tj[k, 0, q] * f0 + tj[k, 1, q] * f1 + tj[k, 2, q] * f2


@nb.njit(cache=True)
def relative_motion(x: np.ndarray, row: np.ndarray, bi: np.ndarray, bj: np.ndarray,
                    ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
    """Tᵢ xᵢ − Tⱼ xⱼ `(c, 3)`: each contact's relative displacement for block unknowns
    `x (m, d)` (a block without a row does not move)."""
    c, _, d = ti.shape
    out = np.zeros((c, 3))
    for k in range(c):
        ri, rj = row[bi[k]], row[bj[k]]
        for r in range(3):
            s = 0.0
            if ri >= 0:
                for q in range(d):
                    s += ti[k, r, q] * x[ri, q]
            if rj >= 0:
                for q in range(d):
                    s -= tj[k, r, q] * x[rj, q]
            out[k, r] = s
    return out


@nb.njit(cache=True)
def fill_jacobian(base: np.ndarray, ti: np.ndarray, tj: np.ndarray, jac: np.ndarray,
                  slot_ii: np.ndarray, slot_jj: np.ndarray, slot_ij: np.ndarray,
                  slot_ji: np.ndarray) -> np.ndarray:
    """BSR values `(nnz, d, d)` of the step's Jacobian: the block terms `base` plus every
    contact's `Tᵢᵀ D Tᵢ`, `Tⱼᵀ D Tⱼ`, `−Tᵢᵀ D Tⱼ` and `−Tⱼᵀ D Tᵢ` on its slots (-1: the
    block is not an unknown), D its 3 × 3 block `jac (c, 3, 3)` (not always symmetric)."""
    data = base.copy()
    d = ti.shape[2]
    dti = np.empty((3, d))
    dtj = np.empty((3, d))
    for k in range(jac.shape[0]):
        h = jac[k]
        if h[0, 0] == 0.0 and h[1, 1] == 0.0 and h[2, 2] == 0.0:
            continue
        for p in range(3):
            for q in range(d):
                dti[p, q] = h[p, 0] * ti[k, 0, q] + h[p, 1] * ti[k, 1, q] + h[p, 2] * ti[k, 2, q]
                dtj[p, q] = h[p, 0] * tj[k, 0, q] + h[p, 1] * tj[k, 1, q] + h[p, 2] * tj[k, 2, q]
        si, sj, sij, sji = slot_ii[k], slot_jj[k], slot_ij[k], slot_ji[k]
        for p in range(d):
            for q in range(d):
                if si >= 0:
                    data[si, p, q] += (ti[k, 0, p] * dti[0, q] + ti[k, 1, p] * dti[1, q]
                                       + ti[k, 2, p] * dti[2, q])
                if sj >= 0:
                    data[sj, p, q] += (tj[k, 0, p] * dtj[0, q] + tj[k, 1, p] * dtj[1, q]
                                       + tj[k, 2, p] * dtj[2, q])
                if sij >= 0:
                    data[sij, p, q] -= (ti[k, 0, p] * dtj[0, q] + ti[k, 1, p] * dtj[1, q]
                                        + ti[k, 2, p] * dtj[2, q])
                    data[sji, p, q] -= (tj[k, 0, p] * dti[0, q] + tj[k, 1, p] * dti[1, q]
                                        + tj[k, 2, p] * dti[2, q])
    return data


@nb.njit(cache=True)
def bicgstab_bsr(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray,
                 inv: np.ndarray, f: np.ndarray, x0: np.ndarray, rtol: float,
                 maxiter: int) -> tuple[np.ndarray, int]:
    """Block-Jacobi preconditioned BiCGSTAB for K x = f, K in BSR form (`indptr`,
    `indices`, `data (nnzb, b, b)`; not symmetric), the preconditioner's blocks `inv (m,
    b, b)`: `(x, iterations)`, iterations -1 when ‖f − K x‖ ≤ rtol ‖f‖ was not reached."""
    n = f.shape[0]
    m = inv.shape[0]
    rows = np.arange(m)
    x = x0.copy()
    q = np.zeros(n)
    _bsr_matvec(indptr, indices, data, rows, x, q)
    r = f - q
    stop = rtol * np.sqrt(np.sum(f * f))
    if np.sqrt(np.sum(r * r)) <= stop:
        return x, 0
    rhat = r.copy()
    rho, alpha, omega = 1.0, 1.0, 1.0
    v = np.zeros(n)
    p = np.zeros(n)
    y = np.zeros(n)
    z = np.zeros(n)
    t = np.zeros(n)
    for it in range(1, maxiter + 1):
        rho_new = np.sum(rhat * r)
        if rho_new == 0.0 or omega == 0.0:
            return x, -1
        beta = (rho_new / rho) * (alpha / omega)
        rho = rho_new
        p = r + beta * (p - omega * v)
        _block_apply(inv, rows, p, y)
        _bsr_matvec(indptr, indices, data, rows, y, v)
        alpha = rho / np.sum(rhat * v)
        s = r - alpha * v
        if np.sqrt(np.sum(s * s)) <= stop:
            return x + alpha * y, it
        _block_apply(inv, rows, s, z)
        _bsr_matvec(indptr, indices, data, rows, z, t)
        tt = np.sum(t * t)
        omega = np.sum(t * s) / tt if tt > 0.0 else 0.0
        x = x + alpha * y + omega * z
        r = s - omega * t
        rn = np.sqrt(np.sum(r * r))
        if not np.isfinite(rn):
            return x, -1
        if rn <= stop:
            return x, it
    return x, -1


@nb.njit(cache=True)
def _rotated(v: np.ndarray, rx: float, ry: float, rz: float, out: np.ndarray) -> None:
    """`out = R v` with R the exact rotation of the rotation vector (rx, ry, rz)."""
    t2 = rx * rx + ry * ry + rz * rz
    if t2 < 1e-8:
        s = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        t = np.sqrt(t2)
        s = np.sin(t) / t
        h = np.sin(0.5 * t)
        b = 2.0 * h * h / t2
    c = 1.0 - b * t2
    dot = rx * v[0] + ry * v[1] + rz * v[2]
    out[0] = c * v[0] + s * (ry * v[2] - rz * v[1]) + b * dot * rx
    out[1] = c * v[1] + s * (rz * v[0] - rx * v[2]) + b * dot * ry
    out[2] = c * v[2] + s * (rx * v[1] - ry * v[0]) + b * dot * rz


@nb.njit(cache=True)
def _moved_point(x: np.ndarray, r: int, p: np.ndarray, c: np.ndarray, out: np.ndarray
                 ) -> None:
    """Where the point `p` of a block with centroid `c` is after the step `x[r]` (exact
    rotation of its strained offset, as the update moves it; `r < 0`: it stays)."""
    if r < 0:
        out[:] = p
        return
    d = x.shape[1]
    rel = np.empty(3)
    for i in range(3):
        rel[i] = p[i] - c[i]
    if d > 6:  # (I + ε) first, as engine.geometry._transform_kernels.move_blocks
        e = x[r]
        s0 = (1.0 + e[6]) * rel[0] + 0.5 * e[11] * rel[1] + 0.5 * e[10] * rel[2]
        s1 = 0.5 * e[11] * rel[0] + (1.0 + e[7]) * rel[1] + 0.5 * e[9] * rel[2]
        s2 = 0.5 * e[10] * rel[0] + 0.5 * e[9] * rel[1] + (1.0 + e[8]) * rel[2]
        rel[0], rel[1], rel[2] = s0, s1, s2
    _rotated(rel, x[r, 3], x[r, 4], x[r, 5], out)
    for i in range(3):
        out[i] += c[i] + x[r, i]


@nb.njit(cache=True)
def rotation_correction(x: np.ndarray, row: np.ndarray, bi: np.ndarray, bj: np.ndarray,
                        point_i: np.ndarray, point_j: np.ndarray, centroid: np.ndarray,
                        normal: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """Each contact's gap at the step's end with the blocks' exact motion less its
    linearisation `(c,)` m: `(Rⱼ n)·(pᵢ' − pⱼ') − n·(pᵢ − pⱼ) − n·dr`, the points moved
    by the exact rotation of the step `x (m, d)` and the normal turned with block j (the
    face's block for a vertex-face contact). Second order in the step's rotation: what a
    linearised contact overlaps by when columns turn against each other."""
    c = bi.shape[0]
    out = np.zeros(c)
    pi = np.empty(3)
    pj = np.empty(3)
    nj = np.empty(3)
    for k in range(c):
        ri, rj = row[bi[k]], row[bj[k]]
        if ri < 0 and rj < 0:
            continue
        _moved_point(x, ri, point_i[k], centroid[bi[k]], pi)
        _moved_point(x, rj, point_j[k], centroid[bj[k]], pj)
        if rj >= 0:
            _rotated(normal[k], x[rj, 3], x[rj, 4], x[rj, 5], nj)
        else:
            nj[:] = normal[k]
        g1 = nj[0] * (pi[0] - pj[0]) + nj[1] * (pi[1] - pj[1]) + nj[2] * (pi[2] - pj[2])
        g0 = 0.0
        lin = 0.0
        for i in range(3):
            g0 += normal[k, i] * (point_i[k, i] - point_j[k, i])
            lin += normal[k, i] * dr[k, i]
        out[k] = g1 - g0 - lin
    return out


# One compiled loop by design: a contact's end-of-step quantities (gap, forces, springs'
# stretch, slip, mode and each part of its energy) share its gap, stretch and cap.
@nb.njit(cache=True)
def step_ends(dr: np.ndarray, normal: np.ndarray, d0: np.ndarray, base: np.ndarray,
              a: np.ndarray, cprime: np.ndarray, shear0: np.ndarray, cap: np.ndarray,
              kn: float, ks: float, tension: np.ndarray, stick: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                         np.ndarray, np.ndarray, float, float, float, float]:
    """The converged step's contacts: `(gap1 (c,), normal force (c,), force on i (c, 3),
    shear spring stretch (c, 3), slip (c, 3), mode (c,), shear force (c, 3), stored energy,
    friction work, dashpot work, springs' numerical dissipation)` (J). The springs'
    dissipation is the Bregman divergence of their energy between the step's start and
    end (convex energies, forces taken at the end: DDA's implicit springs lose ½ k Δ²); the
    friction work is the cap times the slip beyond the spring, the dashpot's the force
    times the approach."""
    c = dr.shape[0]
    gap1 = np.zeros(c)
    fnorm = np.zeros(c)
    force = np.zeros((c, 3))
    stretch = np.zeros((c, 3))
    slip = np.zeros((c, 3))
    mode = np.zeros(c, dtype=np.int8)
    tforce = np.zeros((c, 3))
    stored = 0.0
    friction = 0.0
    damping = 0.0
    numerical = 0.0
    for k in range(c):
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        dn = dr[k, 0] * n0 + dr[k, 1] * n1 + dr[k, 2] * n2
        g = base[k] + dn
        gs = d0[k]  # the spring's start; the blocks' forces work through n·dr only
        gap1[k] = g
        bonded = tension[k] > 0.0
        fs = -kn * g if (bonded or g < 0.0) else 0.0
        es = 0.5 * kn * g * g if (bonded or g < 0.0) else 0.0
        e0 = 0.5 * kn * gs * gs if (bonded or gs < 0.0) else 0.0
        # S(start) − S(end) − S'(end)·(linear motion): ½ kn Δ² for a closed spring, and the
        # exact rotation's second-order change of the gap (δ) that no force worked through
        numerical += e0 - es - fs * dn
        stored += es
        e = a[k] - g
        fd = cprime[k] * e if e > 0.0 else 0.0
        damping -= fd * dn
        fnorm[k] = fs + fd
        for r in range(3):
            slip[k, r] = dr[k, r] - dn * normal[k, r]
        w = np.empty(3)
        for r in range(3):
            w[r] = shear0[k, r] + slip[k, r]
        wn = w[0] * n0 + w[1] * n1 + w[2] * n2
        for r in range(3):
            w[r] -= wn * normal[k, r]
        wl = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        s0 = np.sqrt(shear0[k, 0] ** 2 + shear0[k, 1] ** 2 + shear0[k, 2] ** 2)
        cp = cap[k]
        if stick[k] or ks * wl <= cp:
            scale = 1.0
            sliding = False
        else:
            scale = cp / (ks * wl)
            sliding = True
            friction += cp * (wl - cp / ks)
        for r in range(3):
            stretch[k, r] = scale * w[r]
            tforce[k, r] = -ks * stretch[k, r]
        stored += 0.5 * ks * (scale * wl) ** 2
        # the shear spring's start energy, less its end energy and the work its end force
        # did against the elastic part of the motion (Bregman divergence of ½ ks |w_el|²)
        el = 0.0
        for r in range(3):
            el += tforce[k, r] * (shear0[k, r] - stretch[k, r])
        numerical += 0.5 * ks * s0 * s0 - 0.5 * ks * (scale * wl) ** 2 + el
        for r in range(3):
            force[k, r] = fnorm[k] * normal[k, r] + tforce[k, r]
        if fnorm[k] == 0.0 and g > 0.0 and not bonded:
            mode[k] = OPEN
        elif sliding:
            mode[k] = SLIDING
        else:
            mode[k] = LOCKED
    return (gap1, fnorm, force, stretch, slip, mode, tforce, stored, friction, damping,
            numerical)
