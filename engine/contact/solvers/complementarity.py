"""The complementarity contact solve of one step: open, stuck and sliding come out of one
solve of the step's frictional contact problem, with no contact springs (CONTACT-SOLVERS
route; Moreau–Jean / LMGC90's non-smooth contact dynamics on DDA's integrator).

Without penalty springs each free block's own matrix `K_b` (inertia `2 M / Δt²`, elasticity,
fixed points, bolts to the ground) is block-diagonal, so the step's displacements are
`d = K⁻¹ (F + Σ Hᵀ r)`: the contacts' forces `r` alone couple the blocks. Two stages:

1. **Position** (the DDA step): every contact keeps its end-of-step gap `g0 + u_n ≥ g_min`
   (0, or an earlier penetration that is not made deeper; at most `DEPENETRATION` of it is
   pushed out per step) ⊥ `r_n ≥ −T`, and Coulomb's law with cohesion,
   `‖r_t‖ ≤ C + μ max(r_n, 0)`, stuck or sliding. T and C are the tensile and cohesive
   capacities of an intact bond over the contact's share of its patch (the points of one
   block pair on one plane); a bonded patch where any point moves breaks as a whole (no
   distribution of its forces within the points' capacities holds it), and the step is
   solved again without it.
2. **Velocity** (the impact law): on the contacts closed at the step's end, the end
   velocities solve the same law at the velocity level, `v_n ≥ −e v_n⁻` ⊥ the impulse,
   from the velocities the step would have without its contact forces. For a contact that
   stays closed this gives DDA's own `2 d / Δt − v0`; at an impact it replaces the
   rebound DDA's integrator would make (restitution 1) by the stated restitution `e`.

Both stages are solved by non-smooth Gauss–Seidel over contacts, warm-started from the last
step's forces (matched by the contact's key). Rigid blocks on hard contacts leave the force
split between a face's corners statically indeterminate: the motion is unique, the forces
are one admissible set. Energy is booked exactly: the integrator conserves it, so the
contact forces' normal work, their friction work and the impact's loss are what the step
dissipates.
"""

from __future__ import annotations

import dataclasses
import time as _time
from dataclasses import dataclass

import numpy as np

import engine.contact.solvers._complementarity_kernels as kern
from engine.contact.constraints import LOCKED, OPEN, SLIDING, ContactSet
from engine.contact.patches import (
    ContactPatches,
    bond_breaks,
    bonded_at_start,
    patch_ids,
    sweep_order,
)
from engine.contact.solution import StepResult
from engine.contact.solvers.active_set import Primal, active_set_step
from engine.dynamics.block_terms import block_dissipation, block_terms, bolt_links
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.geometry.transforms import displacement_matrices
from engine.status import StepFailure

#: a bonded patch breaks when a point moves by more than this many times the resolution of
#: the sweeps (`contact_tolerance` × the motion the contacts cause)
BOND_RESOLUTION = 10.0
#: fraction of an earlier penetration pushed out in one step (the rest stays; a penetration
#: is never made deeper)
DEPENETRATION = 0.2
#: sweeps allowed per stage before the step fails ("contact_solve": Δt is cut)
MAX_SWEEPS = 600
#: passes over a patch's points in a row within a sweep, and alternations of a contact's
#: normal and tangential sub-problems within a visit
PATCH_PASSES = 8
LOCAL_ALTERNATIONS = 4
#: sweeps that crawl: the law's violation fell by less than this factor in SWEEPS_PER_NEWTON
CRAWL = 0.5
#: sweeps that do not converge before an active-set (Newton) step
SWEEPS_PER_NEWTON = 40
#: passes of the position stage in one step while bonds break (each breaks at least one
#: patch; what is still moving after them breaks in the next step)
MAX_BOND_PASSES = 5


@dataclass
class _Frame:
    """The step's contacts in their local frames and the blocks' matrices on the free
    blocks' unknowns (`m` free blocks, `d` unknowns each): rows `bi`, `bj` (-1: fixed),
    operators `hi`, `hj`, `b_i`, `b_j`, `w` (:func:`kern.operators`), frames `(c, 3, 3)`,
    `kmat`, `kinv`, `mass`, `minv (m, d, d)`, each free block's `radius (m,)` m."""

    free: np.ndarray
    bi: np.ndarray
    bj: np.ndarray
    frames: np.ndarray
    hi: np.ndarray
    hj: np.ndarray
    b_i: np.ndarray
    b_j: np.ndarray
    w: np.ndarray
    kmat: np.ndarray
    kinv: np.ndarray
    mass: np.ndarray
    minv: np.ndarray
    radius: np.ndarray
    ti: np.ndarray | None = None
    tj: np.ndarray | None = None


def _spd_inverse(a: np.ndarray) -> np.ndarray:
    """Inverses `(m, d, d)` of SPD blocks through their Cholesky factors (StepFailure when
    a block is not positive definite)."""
    if not len(a):
        return np.zeros_like(a)
    try:
        low = np.linalg.cholesky(a)
    except np.linalg.LinAlgError as exc:
        raise StepFailure("a block's matrix is not positive definite", "solve") from exc
    eye = np.broadcast_to(np.eye(a.shape[1]), a.shape)
    li = np.linalg.solve(low, eye)
    return np.transpose(li, (0, 2, 1)) @ li


def _frame(system: BlockSystem, state: State, contacts: ContactSet, kmat: np.ndarray,
           mass: np.ndarray) -> _Frame:
    nd = system.ndof
    free = np.flatnonzero(state.awake(system.fixed))
    kinv = _spd_inverse(kmat)
    mfree = np.ascontiguousarray(mass[free][:, :nd, :nd])
    minv = _spd_inverse(mfree)
    row = np.full(system.n, -1, dtype=np.int64)
    row[free] = np.arange(len(free))
    bi, bj = row[contacts.block_i], row[contacts.block_j]
    ti = displacement_matrices(contacts.point_i, state.centroid[contacts.block_i])[:, :, :nd]
    tj = displacement_matrices(contacts.point_j, state.centroid[contacts.block_j])[:, :, :nd]
    frames = kern.contact_frames(np.ascontiguousarray(contacts.normal, dtype=float))
    hi, hj, b_i, b_j, w = kern.operators(frames, np.ascontiguousarray(ti),
                                         np.ascontiguousarray(tj), bi, bj, kinv)
    return _Frame(free, bi, bj, frames, hi, hj, b_i, b_j, w, kmat, kinv, mfree, minv,
                  np.ascontiguousarray(system.radius[free]), np.ascontiguousarray(ti),
                  np.ascontiguousarray(tj))


@dataclass
class _Links:
    """Bolts between two free blocks as compliant two-point constraints: rows `li`, `lj`,
    `gi`, `gj (k, 3, d)` (T at the ends; j's with its sign), `ci`, `cj (k, d, 3)`
    (K⁻¹ Gᵀ), `lw (k, 3, 3)` and the spring matrices `lp (k, 3, 3)` N/m."""

    li: np.ndarray
    lj: np.ndarray
    gi: np.ndarray
    gj: np.ndarray
    ci: np.ndarray
    cj: np.ndarray
    lw: np.ndarray
    lp: np.ndarray

    @staticmethod
    def none(nd: int) -> _Links:
        z = np.zeros
        return _Links(z(0, np.int64), z(0, np.int64), z((0, 3, nd)), z((0, 3, nd)),
                      z((0, nd, 3)), z((0, nd, 3)), z((0, 3, 3)), z((0, 3, 3)))


def _links(system: BlockSystem, state: State, fr: _Frame) -> _Links:
    """The step's bolts between free blocks (:func:`bolt_links`) as compliant constraints."""
    links = bolt_links(system, state)
    if links is None:
        return _Links.none(system.ndof)
    bi, bj, ti, tj, axis, ka, ks = links
    row = np.full(system.n, -1, dtype=np.int64)
    row[fr.free] = np.arange(len(fr.free))
    li, lj = row[bi], row[bj]
    if np.any(li < 0) | np.any(lj < 0):  # a bolt to a sleeping block (never: they stay awake)
        raise StepFailure("a bolt's block is asleep", "contact_solve")
    gi, gj = np.ascontiguousarray(ti), np.ascontiguousarray(-tj)
    ci = np.einsum("kpq,keq->kpe", fr.kinv[li], gi)
    cj = np.einsum("kpq,keq->kpe", fr.kinv[lj], gj)
    lw = np.einsum("kep,kpf->kef", gi, ci) + np.einsum("kep,kpf->kef", gj, cj)
    ee = np.einsum("ki,kj->kij", axis, axis)
    lp = ka[:, None, None] * ee + ks[:, None, None] * (np.eye(3)[None] - ee)
    return _Links(li, lj, gi, gj, ci, cj, lw, lp)


def _warm_start(state: State, contacts: ContactSet, frames: np.ndarray) -> np.ndarray:
    """Each contact's force in its frame `(c, 3)` N from the last step (by key; 0 if new)."""
    mem = state.memory
    row = mem.find(contacts.key)
    r = np.zeros((len(contacts), 3))
    again = row >= 0
    if np.any(again):
        r[again] = np.einsum("cij,cj->ci", frames[again], mem.force[row[again]])
    return r


@dataclass
class _Law:
    """Each contact's law: the lower bound `bn` of its normal motion (m, or m/s), its
    friction coefficient `mu` and its bond's tensile and cohesive capacities `tension`,
    `cohesion` (N, or N·s)."""

    bn: np.ndarray
    mu: np.ndarray
    tension: np.ndarray
    cohesion: np.ndarray


@dataclass
class _Problem:
    """One stage's problem: the contacts' operators (`fr`; `b_i`, `b_j` and `w` those of
    the stage), their law, the sweep order by patch (`order`, `pptr`), the block norm
    `kmat` the convergence is judged in, the motion without contact forces `xfree`, the
    bolts (`links`, forces `f`) and the tolerances: `tol` (relative), `floor` (a sweep's
    motion) and `slack` (the law's violation; m or m/s)."""

    fr: _Frame
    law: _Law
    order: np.ndarray
    pptr: np.ndarray
    kmat: np.ndarray
    xfree: np.ndarray
    links: _Links
    f: np.ndarray
    tol: float
    floor: float
    slack: float
    #: the problem in the blocks' unknowns, for the active-set step (None: no such step)
    primal: Primal | None = None


def _solve(pb: _Problem, r: np.ndarray, x: np.ndarray, stage: str) -> int:
    """Patch NSGS on `r`, `x` in place, with an active-set step after every
    SWEEPS_PER_NEWTON sweeps that do not converge; the sweeps it took. Sweeps that crawl
    while the contact law already holds to within the model's geometric resolution
    (`slack`; rigid blocks wedged on sliding joints, many contacts at their friction limit)
    are stopped there; StepFailure after MAX_SWEEPS."""
    fr, law, ln = pb.fr, pb.law, pb.links
    done, violation = 0, np.inf
    while done < MAX_SWEEPS:
        budget = min(SWEEPS_PER_NEWTON, MAX_SWEEPS - done)
        sweeps, est = kern.nsgs(pb.order, pb.pptr, fr.bi, fr.bj, fr.hi, fr.hj, fr.b_i,
                                fr.b_j, fr.w, law.bn, law.mu, law.tension, law.cohesion, r,
                                x, pb.kmat, pb.xfree, ln.li, ln.lj, ln.gi, ln.gj, ln.ci,
                                ln.cj, ln.lw, ln.lp, pb.f, fr.radius, pb.tol, pb.floor,
                                budget, PATCH_PASSES, LOCAL_ALTERNATIONS)
        done += abs(sweeps)
        if sweeps > 0:
            return done
        before, violation = violation, kern.law_violation(
            fr.bi, fr.bj, fr.hi, fr.hj, x, r, law.bn, law.mu, law.tension, law.cohesion)
        if violation <= pb.slack and violation > CRAWL * before:
            return done
        if pb.primal is None:
            continue
        newton = active_set_step(pb.primal, fr.hi, fr.hj, law.bn, law.mu, law.tension,
                                 law.cohesion, r)
        if newton is not None:
            r[:] = newton
            x[:] = pb.xfree
            _add_links(ln, pb.f, x)
            kern.apply_forces(fr.bi, fr.bj, fr.b_i, fr.b_j, r, x, 1.0)
    raise StepFailure(f"the {stage} stage of the contact solve did not converge in "
                      f"{MAX_SWEEPS} sweeps (error estimate {est:.2g}, the contact law "
                      f"violated by {violation:.2g} m)", "contact_solve")


def _add_links(links: _Links, f: np.ndarray, x: np.ndarray) -> None:
    """`x += K⁻¹ Gᵀ f`: the motion the bolts' forces `f (k, 3)` cause, in place."""
    for k in range(len(f)):
        x[links.li[k]] += links.ci[k] @ f[k]
        x[links.lj[k]] += links.cj[k] @ f[k]


def _law(system: BlockSystem, state: State, contacts: ContactSet, areas: np.ndarray
         ) -> tuple[_Law, np.ndarray, np.ndarray, np.ndarray]:
    """The position stage's law, the start gaps `(c,)` m (touching ones exactly 0), and
    which contacts' joints have strength and which start bonded `(c,)`."""
    jm = contacts.joint_material
    g0 = contacts.gap.astype(float).copy()
    g0[np.abs(g0) < 1e-3 * system.touch_gap] = 0.0  # faces that touch, touch exactly
    # a penetration is pushed out by DEPENETRATION a step; one within the touch gap is held:
    # pushing it out leaves the velocity stage a separating velocity from nowhere (at Δt
    # 0.1 ms a stack of ten cubes gained energy from it step after step)
    gmin = np.where(g0 < -system.touch_gap, g0 * (1.0 - DEPENETRATION), np.minimum(0.0, g0))
    strong, bonded = bonded_at_start(system, state, contacts)
    law = _Law(bn=gmin - g0, mu=system.tan_phi[jm].astype(float),
               tension=np.where(bonded, system.tension[jm] * areas, 0.0),
               cohesion=np.where(bonded, system.cohesion[jm] * areas, 0.0))
    return law, g0, strong, bonded


def _primal(system: BlockSystem, state: State, contacts: ContactSet, fr: _Frame,
            kb: np.ndarray, fb: np.ndarray) -> Primal:
    """The position stage's problem in the blocks' unknowns (its matrix is planned only
    when an active-set step needs it)."""
    row = np.full(system.n, -1, dtype=np.int64)
    row[fr.free] = np.arange(len(fr.free))
    return Primal(kb=np.ascontiguousarray(kb[:, :system.ndof, :system.ndof]),
                  f=np.ascontiguousarray(fb[fr.free, :system.ndof]).ravel(), row=row,
                  block_i=contacts.block_i, block_j=contacts.block_j, bi=fr.bi, bj=fr.bj,
                  ti=fr.ti, tj=fr.tj, frames=fr.frames, links=bolt_links(system, state))


def _position_stage(system: BlockSystem, state: State, contacts: ContactSet,
                    areas: np.ndarray, fr: _Frame, kb: np.ndarray, fb: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, _Law, int, np.ndarray,
                               np.ndarray, float]:
    """The step's displacements `x (m, d)` and contact forces `r (c, 3)` N, which contacts
    of joints with strength end the step without their bond `(c,)`, the contacts' law as it
    ended, the sweeps, the end gaps `(c,)` m, the relative motions `(c, 3)` m in the
    contacts' frames and the residual (the law's largest violation, m). A bonded patch
    breaks as a whole when any of its points moves: then no distribution of the forces
    within the points' capacities holds it."""
    law, g0, strong, bonded = _law(system, state, contacts, areas)
    nd = system.ndof
    xfree = np.einsum("bij,bj->bi", fr.kinv, fb[fr.free, :nd])
    r = _warm_start(state, contacts, fr.frames)
    links = _links(system, state, fr)
    patch = patch_ids(contacts)
    order, pptr = sweep_order(contacts, patch, system.gravity)
    floor = 1e-12 * system.scale
    pb = _Problem(fr, law, order, pptr, fr.kmat, xfree, links, np.zeros((len(links.li), 3)),
                  system.controls.contact_tolerance, floor, system.touch_gap,
                  _primal(system, state, contacts, fr, kb, fb))
    broken = np.zeros(len(contacts), dtype=bool)
    sweeps = 0
    for _ in range(MAX_BOND_PASSES):
        x = xfree.copy()
        kern.apply_forces(fr.bi, fr.bj, fr.b_i, fr.b_j, r, x, 1.0)
        _add_links(links, pb.f, x)
        sweeps += _solve(pb, r, x, "position")
        u = kern.relative_motion(fr.bi, fr.bj, fr.hi, fr.hj, x)
        # a bond moves when its points move by more than the solve resolves: the sweeps
        # stop at `tol` of the motion the contacts cause (at Δt 10 ms that is ~1e-9 m, and
        # a bond judged on 1e-10 m broke at 4 % below its limit-equilibrium strength)
        resolved = BOND_RESOLUTION * pb.tol * kern.moved(x, xfree, fr.radius)
        breaking = _moving_bonds(u, law, patch, max(10.0 * floor, resolved))
        if not np.any(breaking):
            break
        broken |= breaking
        law.tension[breaking] = 0.0
        law.cohesion[breaking] = 0.0
    residual = kern.law_violation(fr.bi, fr.bj, fr.hi, fr.hj, x, r, law.bn, law.mu,
                                  law.tension, law.cohesion)
    return x, r, broken | (strong & ~bonded), law, sweeps, g0 + u[:, 0], u, residual


def _moving_bonds(u: np.ndarray, law: _Law, patch: np.ndarray, eps: float) -> np.ndarray:
    """The contacts `(c,)` of the bonded patches where some point opens or slips by more
    than `eps` m (those patches break whole)."""
    bonded = (law.tension > 0) | (law.cohesion > 0)
    moving = bonded & ((u[:, 0] - law.bn > eps) | (np.hypot(u[:, 1], u[:, 2]) > eps))
    if not np.any(moving):
        return moving
    return bonded & np.isin(patch, patch[moving])


def _velocity_stage(system: BlockSystem, state: State, contacts: ContactSet, fr: _Frame,
                    law: _Law, x: np.ndarray, r: np.ndarray, u: np.ndarray, dt: float
                    ) -> tuple[np.ndarray, int]:
    """The end velocities `(m, d)` of the free blocks by the impact law on the contacts
    closed at the step's end, and the sweeps."""
    nd = system.ndof
    v0 = state.velocity[fr.free, :nd]
    v_dda = 2.0 * x / dt - v0
    if not len(contacts):
        return v_dda, 0
    # the velocities without the contacts' impulses r Δt: v = v_free + M⁻¹ Σ Hᵀ P
    b_i = np.einsum("cpq,ceq->cpe", fr.minv[np.maximum(fr.bi, 0)], fr.hi)
    b_j = np.einsum("cpq,ceq->cpe", fr.minv[np.maximum(fr.bj, 0)], fr.hj)
    b_i[fr.bi < 0] = 0.0
    b_j[fr.bj < 0] = 0.0
    vfree = v_dda.copy()
    kern.apply_forces(fr.bi, fr.bj, b_i, b_j, r, vfree, -dt)
    closed = (u[:, 0] <= law.bn + system.touch_gap) | np.any(r != 0.0, axis=1)
    idx = np.flatnonzero(closed)
    if not len(idx):
        return vfree, 0
    w2 = np.einsum("cep,cpf->cef", fr.hi[idx], b_i[idx]) + np.einsum(
        "cep,cpf->cef", fr.hj[idx], b_j[idx])
    sub = _Frame(fr.free, fr.bi[idx], fr.bj[idx], fr.frames[idx], fr.hi[idx], fr.hj[idx],
                 b_i[idx], b_j[idx], np.ascontiguousarray(w2), fr.kmat, fr.kinv, fr.mass,
                 fr.minv, fr.radius)
    approach = kern.relative_motion(sub.bi, sub.bj, sub.hi, sub.hj,
                                    np.ascontiguousarray(v0))[:, 0]
    e = system.controls.restitution
    law2 = _Law(bn=-e * np.minimum(approach, 0.0), mu=law.mu[idx],
                tension=law.tension[idx] * dt, cohesion=law.cohesion[idx] * dt)
    closed_set = contacts.subset(idx)
    order, pptr = sweep_order(closed_set, patch_ids(closed_set), system.gravity)
    p = np.ascontiguousarray(r[idx] * dt)
    v = vfree.copy()
    kern.apply_forces(sub.bi, sub.bj, sub.b_i, sub.b_j, p, v, 1.0)
    pb = _Problem(sub, law2, order, pptr, fr.mass, vfree, _Links.none(nd), np.zeros((0, 3)),
                  system.controls.contact_tolerance, 1e-12 * system.scale / dt,
                  system.touch_gap / dt)
    return v, _solve(pb, p, v, "velocity")


def _modes(law: _Law, r: np.ndarray, u: np.ndarray, gap1: np.ndarray,
           touch: float) -> np.ndarray:
    """Each contact's mode as the solve left it: open (no force and a gap), sliding (on
    its friction rim and slipping by more than the geometric resolution `touch` m) or
    locked."""
    shear = np.hypot(r[:, 1], r[:, 2])
    rim = law.cohesion + law.mu * np.maximum(r[:, 0], 0.0)
    slip = np.hypot(u[:, 1], u[:, 2])
    mode = np.full(len(r), LOCKED, dtype=np.int8)
    mode[(shear >= rim * (1.0 - 1e-9)) & (slip > touch)] = SLIDING
    mode[np.all(r == 0.0, axis=1) & (gap1 > touch)] = OPEN
    return mode


def complementarity_step(system: BlockSystem, state: State, contacts: ContactSet,
                         patches: ContactPatches, dt: float) -> StepResult:
    """The step of `dt` s from `state` with its `contacts` (and their bonded `patches`)
    solved as one frictional contact problem (module docstring); StepFailure when a stage
    does not converge."""
    diag = state.diagnostics
    clock = _time.perf_counter()
    kb, fb, mass = block_terms(system, state, dt)
    fr = _frame(system, state, contacts,
                np.ascontiguousarray(kb[state.awake(system.fixed)]), mass)
    clock = diag.tick("assembly", clock)
    x, r, broken, law, sweeps1, gap1, u, residual = _position_stage(
        system, state, contacts, patches.share, fr, kb, fb)
    strong, bonded = bonded_at_start(system, state, contacts)
    clock = diag.tick("solve", clock)
    v, sweeps2 = _velocity_stage(system, state, contacts, fr, law, x, r, u, dt)
    clock = diag.tick("open_close", clock)
    diag.solves += 2
    n, nd = system.n, system.ndof
    d = np.zeros((n, 12))
    d[fr.free, :nd] = x
    v1 = np.zeros((n, 12))
    v1[fr.free, :nd] = v
    v_dda = np.zeros((n, 12))
    v_dda[fr.free, :nd] = 2.0 * x / dt - state.velocity[fr.free, :nd]
    m = mass[:, :nd, :nd]
    kinetic = 0.5 * float(np.einsum("ni,nij,nj->", v_dda[:, :nd], m, v_dda[:, :nd])
                          - np.einsum("ni,nij,nj->", v1[:, :nd], m, v1[:, :nd]))
    force = np.einsum("cji,cj->ci", fr.frames, r)  # world axes (Rᵀ r)
    slip = np.einsum("cji,cj->ci", fr.frames[:, 1:, :], u[:, 1:])
    friction = -float(np.sum(r[:, 1:] * u[:, 1:]))
    normal = -float(np.sum(r[:, 0] * u[:, 0]))
    mode = _modes(law, r, u, gap1, system.touch_gap)
    tangent = np.where(np.linalg.norm(slip, axis=1)[:, None] > 0,
                       slip / np.maximum(np.linalg.norm(slip, axis=1), 1e-300)[:, None],
                       contacts.tangent)
    out = dataclasses.replace(contacts, mode=mode, tangent=tangent)
    return StepResult(
        d=d, contacts=out, gap1=gap1, shear=np.zeros((len(contacts), 3)), slip=slip,
        normal_force=r[:, 0].copy(), shear_force=force - r[:, :1] * contacts.normal,
        friction_work=friction, iterations=sweeps1 + sweeps2,
        numerical_dissipation=normal + kinetic + block_dissipation(system, state, d),
        broken=broken, velocity=v1, force=force, contact_energy=0.0, springs=False,
        residual=residual,
        bond_breaks=bond_breaks(patches, strong & ~bonded, broken))
