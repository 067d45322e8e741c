"""Compiled per-contact loops of one open-close cycle: the contact loads of the cycle's modes
and the mode update of the paper's Table 2 (with first entrance for contacts that close).

Each cycle of a step's open-close iteration (~10 per step) ran these as some sixty numpy
calls over the contact arrays; for a few contacts the calls' overhead was the whole cost,
for thousands a fifth of the step. Compiled with numba (cached on disk). The rules are
those documented in :mod:`engine.contact.solvers.open_close`.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine.contact.constraints import LOCKED, OPEN, SLIDING
from engine.geometry._transform_kernels import point_motion

#: a contact's switch count that marks it sliding for the rest of the step
FINAL_SLIDE = 1 << 30


@nb.njit(cache=True)
def contact_loads(f: np.ndarray, dof_map: np.ndarray, bi: np.ndarray, bj: np.ndarray,
                  ti: np.ndarray, tj: np.ndarray, normal: np.ndarray, d0: np.ndarray,
                  mode: np.ndarray, shear0: np.ndarray, offset: np.ndarray,
                  tangent: np.ndarray, nstar: np.ndarray, tan_phi: np.ndarray, kn: float,
                  ks: float, cn: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Add the contact forces of the cycle's modes to the load vector `f` (in place):
    the normal spring's start-of-step force `−kn d0 n` of closed contacts (and the normal
    dashpot's `−cn max(d0, 0) / Δt n`: a contact entering in the step damps from the entrance
    on, like a spring of `cn / Δt` from zero gap), the locked
    shear spring's `−ks (I − n nᵀ)(shear0 + offset)` and the explicit friction
    `−tan φ N* t` of sliding ones (eqs. 24, 29, 32; N* the contact's normal force, spring
    and dashpot, of the last cycle), as Tᵢᵀ F on block i and −Tⱼᵀ F on block j (the
    dashpots act through K: they rest at the start of the step). Returns the friction
    magnitudes `(c,)` and vectors `(c, 3)`."""
    c, _, d = ti.shape
    fric_mag = np.zeros(c)
    fric = np.zeros((c, 3))
    force = np.zeros(3)
    for k in range(c):
        m = mode[k]
        if m == OPEN:
            continue
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        fn = -kn * d0[k] - cn[k] * max(d0[k], 0.0) / dt
        force[0], force[1], force[2] = fn * n0, fn * n1, fn * n2
        if m == LOCKED:
            r0 = shear0[k, 0] + offset[k, 0]
            r1 = shear0[k, 1] + offset[k, 1]
            r2 = shear0[k, 2] + offset[k, 2]
            rn = r0 * n0 + r1 * n1 + r2 * n2
            force[0] -= ks * (r0 - rn * n0)
            force[1] -= ks * (r1 - rn * n1)
            force[2] -= ks * (r2 - rn * n2)
        else:
            fm = tan_phi[k] * nstar[k]
            fric_mag[k] = fm
            for r in range(3):
                fric[k, r] = fm * tangent[k, r]
                force[r] -= fric[k, r]
        a, b = bi[k], bj[k]
        for q in range(d):
            ia = dof_map[a, q]
            if ia >= 0:
                f[ia] += ti[k, 0, q] * force[0] + ti[k, 1, q] * force[1] + ti[k, 2, q] * force[2]
            ib = dof_map[b, q]
            if ib >= 0:
                f[ib] -= tj[k, 0, q] * force[0] + tj[k, 1, q] * force[1] + tj[k, 2, q] * force[2]
    return fric_mag, fric


@nb.njit(cache=True, inline="always")
def _contact_force(k: int, normal: np.ndarray, d0: np.ndarray, mode: np.ndarray,
                   shear0: np.ndarray, offset: np.ndarray, tangent: np.ndarray,
                   nstar: np.ndarray, tan_phi: np.ndarray, kn: float, ks: float,
                   cn: np.ndarray, dt: float, force: np.ndarray, fric_mag: np.ndarray,
                   fric: np.ndarray) -> None:
    """Contact `k`'s force on block i into `force[k]` and its friction into `fric_mag[k]`,
    `fric[k]` (a closed contact; :func:`contact_loads`'s expressions)."""
    n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
    fn = -kn * d0[k] - cn[k] * max(d0[k], 0.0) / dt
    force[k, 0], force[k, 1], force[k, 2] = fn * n0, fn * n1, fn * n2
    if mode[k] == LOCKED:
        r0 = shear0[k, 0] + offset[k, 0]
        r1 = shear0[k, 1] + offset[k, 1]
        r2 = shear0[k, 2] + offset[k, 2]
        rn = r0 * n0 + r1 * n1 + r2 * n2
        force[k, 0] -= ks * (r0 - rn * n0)
        force[k, 1] -= ks * (r1 - rn * n1)
        force[k, 2] -= ks * (r2 - rn * n2)
    else:
        fm = tan_phi[k] * nstar[k]
        fric_mag[k] = fm
        for r in range(3):
            fric[k, r] = fm * tangent[k, r]
            force[k, r] -= fric[k, r]


@nb.njit(cache=True, parallel=True)
def contact_loads_threads(f: np.ndarray, dof_map: np.ndarray, bi: np.ndarray,
                          bj: np.ndarray, ti: np.ndarray, tj: np.ndarray, normal: np.ndarray,
                          d0: np.ndarray, mode: np.ndarray, shear0: np.ndarray,
                          offset: np.ndarray, tangent: np.ndarray, nstar: np.ndarray,
                          tan_phi: np.ndarray, kn: float, ks: float, cn: np.ndarray,
                          dt: float, ptr: np.ndarray, entries: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`contact_loads` on numba's threads: each contact's force, then each block's
    loads from its contacts in contact order (`ptr`, `entries`: each block's contacts,
    :func:`engine.dynamics._assembly_kernels.row_contacts` of `bi`, `bj`), so that every
    unknown's sum is the serial one, bit for bit."""
    c, _, d = ti.shape
    fric_mag = np.zeros(c)
    fric = np.zeros((c, 3))
    force = np.zeros((c, 3))
    for k in nb.prange(c):
        if mode[k] != OPEN:
            _contact_force(k, normal, d0, mode, shear0, offset, tangent, nstar, tan_phi, kn,
                           ks, cn, dt, force, fric_mag, fric)
    for blk in nb.prange(len(ptr) - 1):
        for t in range(ptr[blk], ptr[blk + 1]):
            k, role = entries[t] >> 1, entries[t] & 1
            if mode[k] == OPEN:
                continue
            for q in range(d):
                i = dof_map[blk, q]
                if i < 0:
                    continue
                if role == 0:
                    f[i] += ti[k, 0, q] * force[k, 0] + ti[k, 1, q] * force[k, 1] + ti[
                        k, 2, q] * force[k, 2]
                else:
                    f[i] -= tj[k, 0, q] * force[k, 0] + tj[k, 1, q] * force[k, 1] + tj[
                        k, 2, q] * force[k, 2]
    return fric_mag, fric


@nb.njit(cache=True)
def patch_bonds(d0: np.ndarray, normal: np.ndarray, dr: np.ndarray, shear0: np.ndarray,
                offset: np.ndarray, mode: np.ndarray, tangent: np.ndarray,
                broken: np.ndarray, tan_phi: np.ndarray, tension_force: np.ndarray,
                cohesion_force: np.ndarray, fric_mag: np.ndarray, kn: float, ks: float,
                cn: np.ndarray, dt: float, patch: np.ndarray, n_patch: int) -> np.ndarray:
    """Which bonded patches hold `(n_patch,) bool` after a solve with relative
    displacements `dr (c, 3)`: a patch with unbroken closed contacts holds while the total
    shear force of its closed contacts (locked springs, sliding friction) is within
    `Σ tan φ N + Σ c A` (friction of all its closed contacts, cohesion of the unbroken
    ones); one that exceeds it loses its whole bond (`broken` set in place for every
    contact of the patch). Normal forces as :func:`update_modes` takes them."""
    held = np.zeros(n_patch, dtype=np.bool_)
    if n_patch == 0:
        return held
    shear = np.zeros((n_patch, 3))
    capacity = np.zeros(n_patch)
    bond = np.zeros(n_patch)
    for k in range(len(d0)):
        p = patch[k]
        if p < 0 or mode[k] == OPEN:
            continue
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        g1 = d0[k] + dr[k, 0] * n0 + dr[k, 1] * n1 + dr[k, 2] * n2
        normal_force = -kn * g1 - cn[k] * (g1 - min(d0[k], 0.0)) / dt
        allow = 0.0 if broken[k] else tension_force[k]
        if -kn * g1 >= -allow and normal_force < -allow and cn[k] > 0.0:
            normal_force = -kn * g1  # the dashpot lets go (as update_modes decides)
        capacity[p] += tan_phi[k] * max(normal_force, 0.0)
        if not broken[k]:
            bond[p] += cohesion_force[k]
        if mode[k] == LOCKED:
            s = np.empty(3)
            for r in range(3):
                s[r] = shear0[k, r] + offset[k, r] + dr[k, r]
            sn = s[0] * n0 + s[1] * n1 + s[2] * n2
            shear[p, 0] += ks * (s[0] - sn * n0)
            shear[p, 1] += ks * (s[1] - sn * n1)
            shear[p, 2] += ks * (s[2] - sn * n2)
        else:
            for r in range(3):
                shear[p, r] += fric_mag[k] * tangent[k, r]
    for p in range(n_patch):
        if bond[p] <= 0.0:
            continue
        ts = np.sqrt(shear[p, 0] ** 2 + shear[p, 1] ** 2 + shear[p, 2] ** 2)
        held[p] = ts <= (capacity[p] + bond[p]) * (1 + 1e-9)
    for k in range(len(d0)):
        p = patch[k]
        if p >= 0 and bond[p] > 0.0 and not held[p]:
            broken[k] = True
    return held


# One compiled loop by design: Table 2's branches for a contact share its relative
# displacement, shear stretch and friction limit, computed once; split into several kernels
# they would pass a dozen per-contact arrays back and forth every open-close cycle.
@nb.njit(cache=True)
def update_modes(d0: np.ndarray, normal: np.ndarray, dr: np.ndarray, shear0: np.ndarray,
                 offset: np.ndarray, mode: np.ndarray, tangent: np.ndarray,
                 broken: np.ndarray, reopenings: np.ndarray, switches: np.ndarray,
                 tan_phi: np.ndarray, tension_force: np.ndarray,
                 cohesion_force: np.ndarray, fric_mag: np.ndarray, fric_prev: np.ndarray,
                 kn: float, ks: float, cn: np.ndarray, dt: float,
                 open_close_gap: float, resolution: np.ndarray, max_reopenings: int,
                 max_switches: int, patch: np.ndarray,
                 n_patch: int):  # noqa: ANN201 (a long tuple, see docstring)
    """Table 2 for every contact after a solve with relative displacements `dr (c, 3)`.

    Contact forces are the penalty springs' and the normal dashpots' (`cn (c,)` N·s/m, on
    the step's normal motion, from the entrance on for a contact entering in the step),
    compression positive; the shear force is the spring's alone (a shear dashpot on a locked
    contact would be viscous static friction: it held Goodman–Bray's C10 up). A closed
    contact whose spring presses while its normal dashpot pulls loses the dashpot for the
    rest of the step (`cn` set to 0 in place); one whose normal force, or whose spring
    across a gap, is tensile beyond its tensile strength opens (at most `max_reopenings`
    times per step) and its bond breaks (a gap within `resolution (c,)` m, the round-off of
    its force, is no tension: exactly touching cut faces would flip on it); a locked one
    whose shear force exceeds `tan φ N + c A` slides along that force, a sliding one whose
    slip reverses or that a locked spring could hold locks again, continuing from its
    friction force. After `max_switches` locked <-> sliding changes in a step a contact sits
    at its friction limit: it stays locked and its spring's anchor (`offset`) slides back
    until the shear force is the friction (return mapping), unless the iteration set it
    sliding for good (`switches` = FINAL_SLIDE). An open contact that penetrates (deeper
    than `open_close_gap` plus its `resolution`) and would press (the force law of the
    opening test, so a contact at rest on the boundary does not chatter) closes at its first
    entrance (eqs. 42-47), sliding if the shear after entrance exceeds friction. A contact
    of a bonded patch (`patch (c,)`, -1 none; `n_patch` patches; engine.contact.patches)
    slips by the patch as a whole: while the patch's total shear force is within `Σ tan φ N
    + Σ c A` of its closed contacts (cohesion of the unbroken ones) its bonded contacts stay
    locked whatever each carries; beyond it the whole bond breaks (:func:`patch_bonds`). Updates
    `offset`, `broken`, `reopenings`, `switches` in place. Returns `(mode, tangent, nstar,
    d1, dr_t, along, fn, changed, closed_changed, fric_change, anchored)`: the new modes,
    sliding directions and friction normal forces N*, the end gaps, tangential slips, slips
    along the old tangent, normal forces, whether any mode / any open-closed state changed,
    the largest change of the friction forces relative to their largest value, and how far
    each capped lock's anchor slid (m).
    """
    c = len(d0)
    new_mode = mode.copy()
    new_tangent = tangent.copy()
    new_nstar = np.zeros(c)
    d1 = np.empty(c)
    dr_t = np.empty((c, 3))
    along = np.empty(c)
    fn = np.zeros(c)
    changed = False
    closed_changed = False
    fric_top = 0.0
    fric_diff = 0.0
    anchored = np.zeros(c)
    held = patch_bonds(d0, normal, dr, shear0, offset, mode, tangent, broken, tan_phi,
                       tension_force, cohesion_force, fric_mag, kn, ks, cn, dt, patch,
                       n_patch)
    for k in range(c):
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        dn = dr[k, 0] * n0 + dr[k, 1] * n1 + dr[k, 2] * n2
        g1 = d0[k] + dn
        d1[k] = g1
        t0, t1, t2 = dr[k, 0] - dn * n0, dr[k, 1] - dn * n1, dr[k, 2] - dn * n2
        dr_t[k, 0], dr_t[k, 1], dr_t[k, 2] = t0, t1, t2
        s0 = shear0[k, 0] + offset[k, 0] + dr[k, 0]
        s1 = shear0[k, 1] + offset[k, 1] + dr[k, 1]
        s2 = shear0[k, 2] + offset[k, 2] + dr[k, 2]
        sn = s0 * n0 + s1 * n1 + s2 * n2
        s0, s1, s2 = s0 - sn * n0, s1 - sn * n1, s2 - sn * n2  # the shear spring's stretch
        al = t0 * tangent[k, 0] + t1 * tangent[k, 1] + t2 * tangent[k, 2]
        along[k] = al
        m = mode[k]
        closed = m != OPEN
        nm = m
        # the dashpot works on the normal motion since the start, or since the entrance
        normal_force = -kn * g1 - cn[k] * (g1 - min(d0[k], 0.0)) / dt
        allow = 0.0 if broken[k] else tension_force[k]
        if closed and -kn * g1 >= -allow and normal_force < -allow and cn[k] > 0.0:
            # the spring presses but its dashpot pulls (the blocks part): a dashpot holds
            # nothing together, so the contact goes on without it for the rest of the step
            cn[k] = 0.0
            normal_force = -kn * g1
            changed = True
        fn[k] = normal_force if closed else 0.0
        pull = allow + kn * resolution[k]
        if (closed and (normal_force < -pull or -kn * g1 < -pull)
                and reopenings[k] < max_reopenings):
            reopenings[k] += 1
            nm = OPEN
            broken[k] = True
        elif closed:
            limit = tan_phi[k] * max(normal_force, 0.0) + (0.0 if broken[k]
                                                           else cohesion_force[k])
            f0, f1, f2 = ks * s0, ks * s1, ks * s2
            ts = np.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
            free = switches[k] < max_switches
            # a bonded contact of a patch whose bond holds stays locked (the patch slips as
            # one, patch_bonds)
            bonded = patch[k] >= 0 and not broken[k] and held[patch[k]]
            if m == LOCKED and not bonded and free and ts > limit * (1 + 1e-9):
                nm = SLIDING
                switches[k] += 1
                new_tangent[k, 0], new_tangent[k, 1], new_tangent[k, 2] = (
                    f0 / ts, f1 / ts, f2 / ts)
                broken[k] = True
            elif m == LOCKED and not bonded and ts > limit * (1 + 1e-9):
                # a contact that chatters between locked and sliding sits at its friction
                # limit: it stays locked, and its spring's anchor slides back until the
                # shear force is the friction (return mapping; loads change, K does not)
                scale = limit / ts - 1.0
                offset[k, 0] += scale * f0 / ks
                offset[k, 1] += scale * f1 / ks
                offset[k, 2] += scale * f2 / ks
                broken[k] = True
                anchored[k] = (ts - limit) / ks  # how far the anchor slid (m)
                fric_top = max(fric_top, limit)
                fric_diff = max(fric_diff, ts - limit)
            elif m == SLIDING and switches[k] < FINAL_SLIDE and (
                    al < 0 or ks * al <= tan_phi[k] * normal_force):
                # after the switch cap a slider may still lock, never slide again (unless
                # the iteration set it sliding for good: FINAL_SLIDE)
                nm = LOCKED
                switches[k] += 1
                # the re-locked spring continues from the friction force (no jump)
                for r in range(3):
                    offset[k, r] = (fric_mag[k] / ks * tangent[k, r] - dr_t[k, r]
                                    - shear0[k, r])
        elif g1 < -open_close_gap - resolution[k] and normal_force > 0.0:
            # penetrating and pressed (spring and dashpot): it closes at its first entrance
            # within the step, and the contact point is revised (eq. 47)
            tstar = d0[k] / (d0[k] - g1) if d0[k] > 0 else 0.0
            for r in range(3):
                offset[k, r] = -tstar * dr_t[k, r]
            a0, a1, a2 = (1 - tstar) * t0, (1 - tstar) * t1, (1 - tstar) * t2
            an = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            nm = SLIDING if ks * an > tan_phi[k] * normal_force else LOCKED
            if an > 0:
                new_tangent[k, 0], new_tangent[k, 1], new_tangent[k, 2] = (
                    a0 / an, a1 / an, a2 / an)
            else:
                new_tangent[k, 0] = new_tangent[k, 1] = new_tangent[k, 2] = 0.0
            # no normal spring acted in this cycle: no friction until the next solve
        new_mode[k] = nm
        if nm != OPEN and closed:
            new_nstar[k] = max(normal_force, 0.0)
        fm = tan_phi[k] * new_nstar[k] if nm == SLIDING else 0.0
        for r in range(3):
            v = fm * new_tangent[k, r]
            fric_top = max(fric_top, abs(v))
            fric_diff = max(fric_diff, abs(v - fric_prev[k, r]))
        if nm != m:
            changed = True
        if (nm != OPEN) != closed:
            closed_changed = True
    fric_change = fric_diff / max(fric_top, 1e-300)
    return (new_mode, new_tangent, new_nstar, d1, dr_t, along, fn, changed, closed_changed,
            fric_change, anchored)


@nb.njit(cache=True)
def initial_modes(bi: np.ndarray, bj: np.ndarray, point_i: np.ndarray,
                  point_j: np.ndarray, normal: np.ndarray, gap: np.ndarray,
                  centroid: np.ndarray, velocity: np.ndarray, row: np.ndarray,
                  mem_mode: np.ndarray, mem_shear: np.ndarray, mem_tangent: np.ndarray,
                  mem_broken: np.ndarray, tan_phi: np.ndarray, bonded_joint: np.ndarray,
                  first_step: bool, touch_gap: float, bond_gap: float, dt: float, kn: float,
                  ks: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Modes, accumulated shear, tangents and broken bonds `(mode (c,), shear (c, 3),
    tangent (c, 3), broken (c,))` at the start of a step.

    A closed contact found again (`row >= 0` into the previous step's memory) inherits its
    mode, its shear (in its new plane) and sliding direction; a new contact between
    blocks that touch (gap ≤ `touch_gap`) follows Table 1: sliding when the shear spring
    of its relative tangential velocity over Δt would beat friction, else locked, sliding
    along that velocity. On the first step, touching contacts of joints with cohesion or
    tensile strength (`bonded_joint`) are bonded and locked; contacts that form later are
    born broken (friction only), as are those found at the start farther apart than
    `bond_gap`."""
    c = len(gap)
    mode = np.zeros(c, dtype=np.int8)
    shear = np.zeros((c, 3))
    tangent = np.zeros((c, 3))
    broken = np.zeros(c, dtype=np.bool_)
    ui = np.empty(3)
    uj = np.empty(3)
    for k in range(c):
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        r = row[k]
        if r >= 0:
            broken[k] = mem_broken[r]
        elif not first_step or gap[k] > bond_gap:
            broken[k] = True
        if first_step and bonded_joint[k] and gap[k] <= touch_gap:
            mode[k] = LOCKED
        if r >= 0 and mem_mode[r] != OPEN:
            mode[k] = mem_mode[r]
            sn = mem_shear[r, 0] * n0 + mem_shear[r, 1] * n1 + mem_shear[r, 2] * n2
            for j in range(3):
                shear[k, j] = mem_shear[r, j] - sn * normal[k, j]
            tn = mem_tangent[r, 0] * n0 + mem_tangent[r, 1] * n1 + mem_tangent[r, 2] * n2
            t0 = mem_tangent[r, 0] - tn * n0
            t1 = mem_tangent[r, 1] - tn * n1
            t2 = mem_tangent[r, 2] - tn * n2
            tl = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            if tl > 0:
                tangent[k, 0], tangent[k, 1], tangent[k, 2] = t0 / tl, t1 / tl, t2 / tl
        elif gap[k] <= touch_gap and mode[k] == OPEN:
            a, b = bi[k], bj[k]
            point_motion(velocity[a], point_i[k, 0] - centroid[a, 0],
                            point_i[k, 1] - centroid[a, 1], point_i[k, 2] - centroid[a, 2], ui)
            point_motion(velocity[b], point_j[k, 0] - centroid[b, 0],
                            point_j[k, 1] - centroid[b, 1], point_j[k, 2] - centroid[b, 2], uj)
            w0, w1, w2 = ui[0] - uj[0], ui[1] - uj[1], ui[2] - uj[2]
            wn = w0 * n0 + w1 * n1 + w2 * n2
            w0, w1, w2 = w0 - wn * n0, w1 - wn * n1, w2 - wn * n2
            vt = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            mode[k] = SLIDING if vt * dt * ks > abs(gap[k]) * kn * tan_phi[k] else LOCKED
            if vt > 0:
                tangent[k, 0], tangent[k, 1], tangent[k, 2] = w0 / vt, w1 / vt, w2 / vt
    return mode, shear, tangent, broken


@nb.njit(cache=True)
def step_results(d0: np.ndarray, d1: np.ndarray, normal: np.ndarray, shear0: np.ndarray,
                 offset: np.ndarray, dr: np.ndarray, dr_t: np.ndarray, mode: np.ndarray,
                 tangent: np.ndarray, fric: np.ndarray, fric_mag: np.ndarray, kn: float,
                 ks: float, cn: np.ndarray, dt: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """Forces and energies of a converged step: `(normal_force (c,), shear_force (c, 3),
    shear (c, 3), friction_work, spring_dissipation, damping_dissipation)`: normal force
    −kn d1 − cn e/Δt (compression positive; e the normal motion since the start or since the
    entrance) of closed contacts; shear force on block i,
    −ks × the shear spring (locked) minus the friction force; the
    shear spring stretch of locked contacts; the work of the friction forces over the
    slips; what the implicit penalty springs dissipated, ½ k Δ² of each spring's change
    (β = ½, γ = 1) plus what springs that opened had stored; and what the dashpots took,
    ½ (c / Δt) (e² − a² + Δ²) with a, e their start and end stretch."""
    c = len(d0)
    nf = np.zeros(c)
    sf = np.zeros((c, 3))
    stretch = np.zeros((c, 3))
    fw = 0.0
    num = 0.0
    damp = 0.0
    for k in range(c):
        m = mode[k]
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        fw += fric_mag[k] * (dr_t[k, 0] * tangent[k, 0] + dr_t[k, 1] * tangent[k, 1]
                             + dr_t[k, 2] * tangent[k, 2])
        s00, s01, s02 = shear0[k, 0], shear0[k, 1], shear0[k, 2]
        ss0 = s00 * s00 + s01 * s01 + s02 * s02
        for j in range(3):
            sf[k, j] = -fric[k, j]
        if m == OPEN:  # a spring that opened gives up what it stored
            num += 0.5 * kn * min(d0[k], 0.0) ** 2 + 0.5 * ks * ss0
            continue
        if m == SLIDING:  # a shear spring that let go gives up what it stored
            num += 0.5 * ks * ss0
        dd = d1[k] - d0[k]
        a, e = max(d0[k], 0.0), d1[k] - min(d0[k], 0.0)  # the dashpot's start and end
        nf[k] = -kn * d1[k] - cn[k] * e / dt
        num += 0.5 * kn * (dd * dd - a * a)
        damp += 0.5 * cn[k] * (e * e - a * a + dd * dd) / dt
        if m == LOCKED:
            r0, r1, r2 = s00 + offset[k, 0], s01 + offset[k, 1], s02 + offset[k, 2]
            rn = r0 * n0 + r1 * n1 + r2 * n2
            a0, a1, a2 = r0 - rn * n0, r1 - rn * n1, r2 - rn * n2  # tangential start
            t0, t1, t2 = r0 + dr[k, 0], r1 + dr[k, 1], r2 + dr[k, 2]
            tn = t0 * n0 + t1 * n1 + t2 * n2
            stretch[k, 0], stretch[k, 1], stretch[k, 2] = t0 - tn * n0, t1 - tn * n1, \
                t2 - tn * n2
            slip2 = dr_t[k, 0] ** 2 + dr_t[k, 1] ** 2 + dr_t[k, 2] ** 2
            for j in range(3):
                sf[k, j] -= ks * stretch[k, j]
            num += 0.5 * ks * (slip2 + ss0 - (a0 * a0 + a1 * a1 + a2 * a2))
    return nf, sf, stretch, fw, num, damp
