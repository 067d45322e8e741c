"""Compiled loops of the complementarity contact solve (:mod:`.complementarity`):
each contact's operators in its local frame (normal, two tangents), the local 3 × 3
frictional contact problem, and the non-smooth Gauss–Seidel sweeps over contacts.

Notation (CONTACT-SOLVERS route): per contact c, `H_i (3, d)` maps block i's unknowns to
the contact's relative displacement in its frame (`H_j` carries the minus sign of block j),
`B_i = K_i⁻¹ H_iᵀ (d, 3)` and `W = H_i B_i + H_j B_j (3, 3)` (the Delassus block). The
local problem is `u = W r + q` with the law of one contact: `u_n ≥ bn ⊥ r_n + T ≥ 0` and
`‖r_t‖ ≤ C + μ max(r_n, 0)`, stuck (`u_t = 0`) inside the disc and `r_t ∥ −u_t` on its
rim (T the tensile and C the cohesive capacity of an intact bond, 0 once broken).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def contact_frames(normal: np.ndarray) -> np.ndarray:
    """Rows n, t1, t2 of each contact's frame `(c, 3, 3)`: t1 from the axis least aligned
    with n, t2 = n × t1."""
    c = normal.shape[0]
    out = np.empty((c, 3, 3))
    for k in range(c):
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        if abs(n0) < 0.9:  # e = x: t1 = n × x
            a0, a1, a2 = 0.0, n2, -n1
        else:  # e = y: t1 = n × y
            a0, a1, a2 = -n2, 0.0, n0
        s = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        a0, a1, a2 = a0 / s, a1 / s, a2 / s
        out[k, 0, 0], out[k, 0, 1], out[k, 0, 2] = n0, n1, n2
        out[k, 1, 0], out[k, 1, 1], out[k, 1, 2] = a0, a1, a2
        out[k, 2, 0] = n1 * a2 - n2 * a1
        out[k, 2, 1] = n2 * a0 - n0 * a2
        out[k, 2, 2] = n0 * a1 - n1 * a0
    return out


@njit(cache=True)
def operators(frames: np.ndarray, ti: np.ndarray, tj: np.ndarray, bi: np.ndarray,
              bj: np.ndarray, kinv: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`H_i`, `H_j (c, 3, d)`, `B_i`, `B_j (c, d, 3)` and `W (c, 3, 3)` of each contact from
    its frame, T at its two points `ti`, `tj (c, 3, d)`, its free blocks' rows `bi`, `bj`
    (-1: a fixed block, no unknowns) and the blocks' inverse matrices `kinv (m, d, d)`."""
    c, d = ti.shape[0], ti.shape[2]
    hi = np.zeros((c, 3, d))
    hj = np.zeros((c, 3, d))
    b_i = np.zeros((c, d, 3))
    b_j = np.zeros((c, d, 3))
    w = np.zeros((c, 3, 3))
    for k in range(c):
        for a in range(3):
            for p in range(d):
                s1 = 0.0
                s2 = 0.0
                for e in range(3):
                    s1 += frames[k, a, e] * ti[k, e, p]
                    s2 += frames[k, a, e] * tj[k, e, p]
                hi[k, a, p] = s1
                hj[k, a, p] = -s2
        for side in range(2):
            blk = bi[k] if side == 0 else bj[k]
            if blk < 0:
                continue
            h = hi if side == 0 else hj
            bb = b_i if side == 0 else b_j
            for p in range(d):
                for a in range(3):
                    s = 0.0
                    for q in range(d):
                        s += kinv[blk, p, q] * h[k, a, q]
                    bb[k, p, a] = s
            for a in range(3):
                for e in range(3):
                    s = 0.0
                    for p in range(d):
                        s += h[k, a, p] * bb[k, p, e]
                    w[k, a, e] += s
    return hi, hj, b_i, b_j, w


@njit(cache=True)
def disc_qp(w00: float, w01: float, w11: float, c0: float, c1: float,
            rad: float) -> tuple[float, float]:
    """argmin ½ rᵀ W r + cᵀ r over ‖r‖ ≤ rad (W 2 × 2 SPD): the tangential problem of one
    contact at a fixed friction radius; its optimality conditions are Coulomb's sliding law
    (`W r + c = −λ r`, λ ≥ 0: the slip opposes the force). Exact: Newton on the secular
    equation in W's eigenbasis."""
    if rad <= 0.0:
        return 0.0, 0.0
    det = w00 * w11 - w01 * w01
    x0 = -(w11 * c0 - w01 * c1) / det
    x1 = -(-w01 * c0 + w00 * c1) / det
    if x0 * x0 + x1 * x1 <= rad * rad:
        return x0, x1
    half = 0.5 * (w00 - w11)
    disc = math.sqrt(half * half + w01 * w01)
    l1 = 0.5 * (w00 + w11) + disc
    l2 = 0.5 * (w00 + w11) - disc
    if disc > 0.0 and abs(w01) > 0.0:
        e10, e11 = w01, l1 - w00
        nrm = math.sqrt(e10 * e10 + e11 * e11)
        if nrm < 1e-300:
            e10, e11 = l1 - w11, w01
            nrm = math.sqrt(e10 * e10 + e11 * e11)
        e10 /= nrm
        e11 /= nrm
    elif w00 >= w11:
        e10, e11 = 1.0, 0.0
    else:
        e10, e11 = 0.0, 1.0
    e20, e21 = -e11, e10
    a1 = e10 * c0 + e11 * c1
    a2 = e20 * c0 + e21 * c1
    lam = 0.0
    for _ in range(60):
        d1 = l1 + lam
        d2 = l2 + lam
        pn = math.sqrt(a1 * a1 / (d1 * d1) + a2 * a2 / (d2 * d2))
        phi = 1.0 / rad - 1.0 / pn
        dphi = -(a1 * a1 / (d1 * d1 * d1) + a2 * a2 / (d2 * d2 * d2)) / (pn * pn * pn)
        new = lam - phi / dphi
        if new < 0.0:
            new = 0.5 * lam
        if abs(new - lam) <= 1e-15 * (new + l1):
            lam = new
            break
        lam = new
    y1 = -a1 / (l1 + lam)
    y2 = -a2 / (l2 + lam)
    r0 = e10 * y1 + e20 * y2
    r1 = e11 * y1 + e21 * y2
    s = rad / math.sqrt(r0 * r0 + r1 * r1)  # exactly on the rim
    return r0 * s, r1 * s


@njit(cache=True)
def local_solve(w: np.ndarray, q: np.ndarray, bn: float, mu: float, tension: float,
                cohesion: float, r: np.ndarray, out: np.ndarray, alternations: int) -> None:
    """One contact's problem `u = W r + q` under its law (module docstring); `r` the
    current guess, the answer into `out`. Stuck is tried first (W r = (bn − q_n, −q_t));
    else the normal and tangential sub-problems alternate, each solved exactly, at most
    `alternations` times (the sweeps around it iterate anyway)."""
    qn = q[0] - bn
    if tension <= 0.0 and cohesion <= 0.0 and qn >= 0.0:
        out[0] = 0.0
        out[1] = 0.0
        out[2] = 0.0
        return
    m00, m01, m02 = w[0, 0], w[0, 1], w[0, 2]
    m10, m11, m12 = w[1, 0], w[1, 1], w[1, 2]
    m20, m21, m22 = w[2, 0], w[2, 1], w[2, 2]
    c00 = m11 * m22 - m12 * m21
    c01 = -(m10 * m22 - m12 * m20)
    c02 = m10 * m21 - m11 * m20
    det = m00 * c00 + m01 * c01 + m02 * c02
    b0, b1, b2 = -qn, -q[1], -q[2]
    sn = (c00 * b0 - (m01 * m22 - m02 * m21) * b1 + (m01 * m12 - m02 * m11) * b2) / det
    s1 = (c01 * b0 + (m00 * m22 - m02 * m20) * b1 - (m00 * m12 - m02 * m10) * b2) / det
    s2 = (c02 * b0 - (m00 * m21 - m01 * m20) * b1 + (m00 * m11 - m01 * m10) * b2) / det
    rad = cohesion + mu * max(sn, 0.0)
    if sn >= -tension and s1 * s1 + s2 * s2 <= rad * rad * (1.0 + 1e-12):
        out[0] = sn
        out[1] = s1
        out[2] = s2
        return
    rn, r1, r2 = max(r[0], -tension), r[1], r[2]
    for it in range(alternations):
        rn_new = max(-(qn + m01 * r1 + m02 * r2) / m00, -tension)
        rad = cohesion + mu * max(rn_new, 0.0)
        t1, t2 = disc_qp(m11, m12, m22, q[1] + m10 * rn_new, q[2] + m20 * rn_new, rad)
        if it >= 50:  # damp a slow alternation between the two sub-problems
            rn_new = 0.5 * (rn_new + rn)
            t1 = 0.5 * (t1 + r1)
            t2 = 0.5 * (t2 + r2)
            rad = cohesion + mu * max(rn_new, 0.0)
            tt = math.sqrt(t1 * t1 + t2 * t2)
            if tt > rad:
                t1 *= rad / tt
                t2 *= rad / tt
        change = abs(rn_new - rn) + abs(t1 - r1) + abs(t2 - r2)
        rn, r1, r2 = rn_new, t1, t2
        if change <= 1e-14 * (abs(rn) + abs(r1) + abs(r2)) + 1e-300:
            break
    out[0] = rn
    out[1] = r1
    out[2] = r2


@njit(cache=True)
def _motion(c: int, bi: np.ndarray, bj: np.ndarray, hi: np.ndarray, hj: np.ndarray,
            x: np.ndarray, u: np.ndarray) -> None:
    """Contact c's relative motion in its frame, for block motions `x`, into `u (3,)`."""
    a, b = bi[c], bj[c]
    d = x.shape[1]
    for k in range(3):
        s = 0.0
        if a >= 0:
            for p in range(d):
                s += hi[c, k, p] * x[a, p]
        if b >= 0:
            for p in range(d):
                s += hj[c, k, p] * x[b, p]
        u[k] = s


@njit(cache=True)
def _contact(c: int, bi: np.ndarray, bj: np.ndarray, hi: np.ndarray, hj: np.ndarray,
             b_i: np.ndarray, b_j: np.ndarray, w: np.ndarray, bn: np.ndarray,
             mu: np.ndarray, tension: np.ndarray, cohesion: np.ndarray, r: np.ndarray,
             x: np.ndarray, u: np.ndarray, q: np.ndarray, old: np.ndarray,
             out: np.ndarray, alternations: int) -> float:
    """Solve contact c's local problem against the current `x` and update its blocks;
    the change's energy `Δrᵀ W Δr`."""
    a, b = bi[c], bj[c]
    d = x.shape[1]
    _motion(c, bi, bj, hi, hj, x, u)
    for k in range(3):
        q[k] = u[k] - (w[c, k, 0] * r[c, 0] + w[c, k, 1] * r[c, 1] + w[c, k, 2] * r[c, 2])
        old[k] = r[c, k]
    local_solve(w[c], q, bn[c], mu[c], tension[c], cohesion[c], old, out, alternations)
    d0, d1, d2 = out[0] - old[0], out[1] - old[1], out[2] - old[2]
    if d0 == 0.0 and d1 == 0.0 and d2 == 0.0:
        return 0.0
    if a >= 0:
        for p in range(d):
            x[a, p] += b_i[c, p, 0] * d0 + b_i[c, p, 1] * d1 + b_i[c, p, 2] * d2
    if b >= 0:
        for p in range(d):
            x[b, p] += b_j[c, p, 0] * d0 + b_j[c, p, 1] * d1 + b_j[c, p, 2] * d2
    for k in range(3):
        r[c, k] = out[k]
    return (d0 * (w[c, 0, 0] * d0 + w[c, 0, 1] * d1 + w[c, 0, 2] * d2)
            + d1 * (w[c, 1, 0] * d0 + w[c, 1, 1] * d1 + w[c, 1, 2] * d2)
            + d2 * (w[c, 2, 0] * d0 + w[c, 2, 1] * d1 + w[c, 2, 2] * d2))


@njit(cache=True)
def _link(k: int, li: np.ndarray, lj: np.ndarray, gi: np.ndarray, gj: np.ndarray,
          ci: np.ndarray, cj: np.ndarray, lw: np.ndarray, lp: np.ndarray, f: np.ndarray,
          x: np.ndarray) -> None:
    """One two-point spring between free blocks (a rock bolt): its force `f = −P u` for the
    relative displacement `u = G_i x_i + G_j x_j` of its ends, solved locally as
    `(I + P W) f = −P q` and applied to its blocks (a compliant constraint)."""
    a, b = li[k], lj[k]
    d = x.shape[1]
    q = np.zeros(3)
    for e in range(3):
        s = 0.0
        for p in range(d):
            s += gi[k, e, p] * x[a, p] + gj[k, e, p] * x[b, p]
        q[e] = s - (lw[k, e, 0] * f[k, 0] + lw[k, e, 1] * f[k, 1] + lw[k, e, 2] * f[k, 2])
    m = np.eye(3) + lp[k] @ lw[k]
    rhs = -(lp[k] @ q)
    new = np.linalg.solve(m, rhs)
    for p in range(d):
        dx = 0.0
        dy = 0.0
        for e in range(3):
            dx += ci[k, p, e] * (new[e] - f[k, e])
            dy += cj[k, p, e] * (new[e] - f[k, e])
        x[a, p] += dx
        x[b, p] += dy
    for e in range(3):
        f[k, e] = new[e]


@njit(cache=True)
def _energy_norm(kmat: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """Σ_b (x_b − y_b)ᵀ K_b (x_b − y_b) over the free blocks."""
    out = 0.0
    d = x.shape[1]
    for b in range(x.shape[0]):
        for p in range(d):
            s = 0.0
            for q in range(d):
                s += kmat[b, p, q] * (x[b, q] - y[b, q])
            out += (x[b, p] - y[b, p]) * s
    return out


@njit(cache=True)
def moved(x: np.ndarray, y: np.ndarray, radius: np.ndarray) -> float:
    """The largest displacement of any block point between `x` and `y` (a bound)."""
    out = 0.0
    for b in range(x.shape[0]):
        mt = 0.0
        mr = 0.0
        for p in range(3):
            mt = max(mt, abs(x[b, p] - y[b, p]))
            mr = max(mr, abs(x[b, p + 3] - y[b, p + 3]))
        ms = 0.0
        for p in range(6, x.shape[1]):
            ms = max(ms, abs(x[b, p] - y[b, p]))
        out = max(out, mt + radius[b] * (mr + 2.0 * ms))
    return out


# the sweep loop (patches in the given order, reversed every other sweep, each solved to
# convergence in place, then the bolt springs) and its convergence test belong together:
# split, they would pass ~25 arrays around
@njit(cache=True)
def nsgs(order: np.ndarray, pptr: np.ndarray, bi: np.ndarray, bj: np.ndarray,
         hi: np.ndarray, hj: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, w: np.ndarray,
         bn: np.ndarray, mu: np.ndarray, tension: np.ndarray, cohesion: np.ndarray,
         r: np.ndarray, x: np.ndarray, kmat: np.ndarray, xfree: np.ndarray, li: np.ndarray,
         lj: np.ndarray, gi: np.ndarray, gj: np.ndarray, ci: np.ndarray, cj: np.ndarray,
         lw: np.ndarray, lp: np.ndarray, f: np.ndarray, radius: np.ndarray, tol: float,
         floor: float, max_sweeps: int, passes: int, alternations: int
         ) -> tuple[int, float]:
    """Non-smooth Gauss–Seidel over the contacts' patches (`order[pptr[p]:pptr[p + 1]]`:
    the points of one block pair on one plane) and the bolt springs between free blocks,
    keeping `x = K⁻¹(F + Σ Hᵀ r)` current. Converged when the estimated error of `x`
    (the sweep's change over 1 − its contraction rate) is below `tol` of `x − xfree` in K's
    energy norm (scale-free, and blind to force redistributions that move nothing), or when
    no block point moved more than `floor` in the sweep.
    Each patch is swept up to `passes` times in a row before the sweep moves on (a rigid
    face's stuck corners are redundant: point by point, Gauss–Seidel crawls along their null
    space). Returns (sweeps, error estimate); sweeps < 0: not converged within
    `max_sweeps`."""
    npatch = pptr.shape[0] - 1
    u = np.empty(3)
    q = np.empty(3)
    old = np.empty(3)
    out = np.empty(3)
    start = np.empty_like(x)
    eta = 0.0
    est = 0.0
    for sweep in range(1, max_sweeps + 1):
        start[:, :] = x
        for pp in range(npatch):
            p = npatch - 1 - pp if sweep % 2 == 0 else pp
            first = 0.0
            for it in range(passes):
                e = 0.0
                for kk in range(pptr[p], pptr[p + 1]):
                    e += _contact(order[kk], bi, bj, hi, hj, b_i, b_j, w, bn, mu, tension,
                                  cohesion, r, x, u, q, old, out, alternations)
                if it == 0:
                    first = e
                if e <= 1e-16 * first or pptr[p + 1] - pptr[p] == 1:
                    break
        for k in range(li.shape[0]):
            _link(k, li, lj, gi, gj, ci, cj, lw, lp, f, x)
        num = _energy_norm(kmat, x, start)
        den = _energy_norm(kmat, x, xfree)
        previous = eta
        eta = math.sqrt(num / den) if den > 0.0 else (0.0 if num == 0.0 else 1.0)
        rate = eta / previous if (sweep > 1 and previous > 0.0) else 0.0
        est = eta / max(1.0 - min(rate, 0.999), 1e-3) if rate < 1.0 else 1e3 * eta
        # one sweep tells no contraction rate: it converges alone only by moving nothing
        if (est < tol and sweep > 1) or moved(x, start, radius) <= floor:
            return sweep, est
    return -max_sweeps, est


@njit(cache=True)
def relative_motion(bi: np.ndarray, bj: np.ndarray, hi: np.ndarray, hj: np.ndarray,
                    x: np.ndarray) -> np.ndarray:
    """Each contact's relative motion `(c, 3)` in its frame for block motions `x (m, d)`."""
    out = np.zeros((hi.shape[0], 3))
    for k in range(hi.shape[0]):
        _motion(k, bi, bj, hi, hj, x, out[k])
    return out


@njit(cache=True)
def apply_forces(bi: np.ndarray, bj: np.ndarray, b_i: np.ndarray, b_j: np.ndarray,
                 r: np.ndarray, x: np.ndarray, scale: float) -> None:
    """`x += scale · Σ_c B r_c` in place (the motion the contact forces `r` cause)."""
    d = x.shape[1]
    for k in range(bi.shape[0]):
        a, b = bi[k], bj[k]
        for p in range(d):
            if a >= 0:
                x[a, p] += scale * (b_i[k, p, 0] * r[k, 0] + b_i[k, p, 1] * r[k, 1]
                                    + b_i[k, p, 2] * r[k, 2])
            if b >= 0:
                x[b, p] += scale * (b_j[k, p, 0] * r[k, 0] + b_j[k, p, 1] * r[k, 1]
                                    + b_j[k, p, 2] * r[k, 2])


@njit(cache=True)
def generalized_forces(bi: np.ndarray, bj: np.ndarray, hi: np.ndarray, hj: np.ndarray,
                       r: np.ndarray, m: int) -> np.ndarray:
    """`Σ_c Hᵀ r_c` on each free block's unknowns `(m, d)` for forces `r (c, 3)` in the
    contacts' frames."""
    d = hi.shape[2]
    out = np.zeros((m, d))
    for k in range(bi.shape[0]):
        a, b = bi[k], bj[k]
        for p in range(d):
            if a >= 0:
                out[a, p] += hi[k, 0, p] * r[k, 0] + hi[k, 1, p] * r[k, 1] + hi[k, 2, p] * r[k, 2]
            if b >= 0:
                out[b, p] += hj[k, 0, p] * r[k, 0] + hj[k, 1, p] * r[k, 1] + hj[k, 2, p] * r[k, 2]
    return out


@njit(cache=True)
def law_violation(bi: np.ndarray, bj: np.ndarray, hi: np.ndarray, hj: np.ndarray,
                  x: np.ndarray, r: np.ndarray, bn: np.ndarray, mu: np.ndarray,
                  tension: np.ndarray, cohesion: np.ndarray) -> float:
    """The largest violation of the contact law by the motion `x` and forces `r`, as a
    length (m, or m/s): a gap below its bound; a gap while the contact presses (or pulls
    below its tensile capacity); slip while stuck inside the friction rim; slip not
    opposed to the shear force on the rim."""
    out = 0.0
    u = np.zeros(3)
    for k in range(bi.shape[0]):
        _motion(k, bi, bj, hi, hj, x, u)
        un = u[0] - bn[k]
        out = max(out, -un)
        if r[k, 0] > -tension[k]:
            out = max(out, un)
        st = math.sqrt(r[k, 1] * r[k, 1] + r[k, 2] * r[k, 2])
        ut = math.sqrt(u[1] * u[1] + u[2] * u[2])
        rim = cohesion[k] + mu[k] * max(r[k, 0], 0.0)
        if st < rim * (1.0 - 1e-9):
            out = max(out, ut)
        elif st > 0.0:  # on the rim: the slip must oppose the shear force
            along = -(r[k, 1] * u[1] + r[k, 2] * u[2]) / st
            out = max(out, math.sqrt(max(ut * ut - along * along, 0.0)) + max(-along, 0.0))
    return out


@njit(cache=True)
def law_residual(r: np.ndarray, u: np.ndarray, w: np.ndarray, bn: np.ndarray,
                 mu: np.ndarray, tension: np.ndarray, cohesion: np.ndarray) -> float:
    """How far the forces `r` and motions `u (c, 3)` are from the contact law, as work (J):
    normal complementarity `|(r_n + T) u'_n|` (u' = u − bn), penetration
    `(min(u'_n, 0))² / W_nn`, slip against or aside the shear force
    `r_t·u_t + ‖r_t‖ ‖u_t‖`, and slip inside the rim `(rim − ‖r_t‖) ‖u_t‖`. Zero for an
    exact solution (the design note's spurious work)."""
    out = 0.0
    for k in range(r.shape[0]):
        un = u[k, 0] - bn[k]
        out += abs((r[k, 0] + tension[k]) * un)
        if un < 0.0:
            out += un * un / w[k, 0, 0]
        st = math.sqrt(r[k, 1] * r[k, 1] + r[k, 2] * r[k, 2])
        ut = math.sqrt(u[k, 1] * u[k, 1] + u[k, 2] * u[k, 2])
        out += r[k, 1] * u[k, 1] + r[k, 2] * u[k, 2] + st * ut
        rim = cohesion[k] + mu[k] * max(r[k, 0], 0.0)
        out += max(rim - st, 0.0) * ut
    return out
