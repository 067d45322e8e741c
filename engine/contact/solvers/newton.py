"""The step as one minimisation (`analysis.contact_solver: "newton"`): Shi's DDA derives a
step from the minimum of its total potential energy; here that minimum is found by Newton's
method instead of the open-close iteration (docs/contact-solvers.md).

The step's block displacements x minimise

    E(x) = ½ xᵀ K_b x − fᵀ x                  (inertia, elasticity, loads: Shi's block terms)
         + Σ ½ kn ⟨−g(x)⟩² + ½ c' ⟨a − g(x)⟩²  (normal spring on a closing gap; its dashpot)
         + Σ ψ(w(x))                           (DDA's anchored shear spring capped at μN + cA)
         + Σ ½ drᵀ P dr                        (bolts between two free blocks)

with the terms of :mod:`._newton_kernels`: every term convex, K_b positive definite, so E
has one minimum and Newton's method with an exact line search (the slope of E along a
direction is a sum over contacts) reaches it from anywhere. The modes (open, locked,
sliding) are read off the minimum instead of guessed and corrected. The Hessian K_b +
Σ Jᵀ D J (D a 3 × 3 block per contact) is assembled on the engine's block-sparse pattern
(:mod:`engine.dynamics.assembly`) and solved by its Cholesky when small and block-Jacobi
conjugate gradients (warm, to a relative tolerance that tightens as Newton converges) when
large. Newton stops on the force residual: every block's out-of-balance force, and moment
and strain forces over its radius, below `contact_tolerance` × the median block weight.

The cap's normal force N is lagged, so that the step stays one convex problem: a contact
found again takes the normal force it ended the last step with (exact wherever N does not
change over a step: a block sliding, a wedge, a body at rest); a new contact takes the
force its block pair's lost contacts carried, then the first round's (a lag of one round,
as a contact found again has one of a step). (Measured on the collapsing 134-block mass:
every contact's N iterated to a fixed point, 40-50 Newton iterations a step; lagged, 15;
semi-smooth Newton with the cap following N in the Jacobian, 12, but it stalls at 854
blocks: docs/contact-solvers.md.) Bonds are updated between rounds too: a bonded patch
holds its shear as one, uncapped, until its total shear exceeds Σ μN + Σ cA, and a bonded
contact holds tension up to its share σt·A; a break is solved again. Each contact's gap
carries the second-order correction of the blocks' exact rotation over the step, updated
at every iterate (Gauss–Newton). The energy ledger is taken from the same terms
(:func:`._newton_kernels.step_ends`): what the springs store, the friction's and the
dashpots' work, and the springs' numerical dissipation (the Bregman divergence of their
energy over the step: ½ k Δ² of DDA's implicit springs), so the energy watchdog judges what
was solved. Rings and rebounds are damped after the step (:mod:`.damping`), as for the
open-close iteration: a dashpot on the step's mean velocity cannot reach a ring.
"""

from __future__ import annotations

import dataclasses
import time as _time
from dataclasses import dataclass

import numpy as np

from engine.contact.constraints import OPEN, ContactSet
from engine.contact.patches import ContactPatches, bond_breaks, bonded_at_start
from engine.contact.solution import StepResult
from engine.contact.solvers import _newton_kernels as kern
from engine.contact.solvers.newton_systems import NewtonSystems
from engine.contact.solvers.open_close import contact_damping
from engine.dynamics import assembly as asm
from engine.dynamics.block_terms import block_dissipation, block_terms, bolt_links
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.status import StepFailure

#: Newton iterations of one solve, and outer rounds of a step, at most
MAX_NEWTON = 60
MAX_ROUNDS = 25
#: the line search stops when the slope along the direction is this fraction of its start
LINE_TOLERANCE = 1e-4
LINE_EVALUATIONS = 40
#: the Krylov solves of the Newton systems reach this relative residual at most (tighter as
#: the force residual falls: inexact Newton, Eisenstat–Walker)
KRYLOV_RTOL_MAX = 0.1
KRYLOV_RTOL_MIN = 1e-10
#: semi-smooth Newton steps (the caps following N) of a round, at most; a step cut below
#: MIN_STEP ends them (a cap's kink between x and the solution) and the round is solved
#: with its caps lagged
SEMI_SMOOTH_STEPS = 30
MIN_STEP = 0.2


@dataclass
class _Step:
    """What holds during the step's solve. Shapes: `m` moving blocks, `c` contacts, `k`
    bolts between moving blocks, `d` unknowns a block."""

    free: np.ndarray  # (m,) the moving blocks
    row: np.ndarray  # (n,) each block's row (-1: fixed or asleep)
    kb: np.ndarray  # (m, d, d) block terms
    fb: np.ndarray  # (m, d) block forces
    bi: np.ndarray
    bj: np.ndarray
    ti: np.ndarray  # (c, 3, d)
    tj: np.ndarray
    normal: np.ndarray
    point_i: np.ndarray  # (c, 3) the contact points at the step's start (m)
    point_j: np.ndarray
    centroid: np.ndarray  # (n, 3) the blocks' centroids at the step's start (m)
    d0: np.ndarray  # (c,) start gaps (m)
    a: np.ndarray  # (c,) where each dashpot starts: min(d0, 0)
    cprime: np.ndarray  # (c,) dashpots cn / Δt (N/m)
    shear0: np.ndarray  # (c, 3) the shear springs' anchored stretch (m)
    mu: np.ndarray  # (c,) tan φ
    cohesion: np.ndarray  # (c,) c · share (N)
    tension: np.ndarray  # (c,) σt · share (N)
    patch: np.ndarray  # (c,) bonded patch (-1: none)
    n_patch: int
    link: tuple[np.ndarray, ...] | None  # bolts: bi, bj, ti, tj, P (k, 3, 3)
    plan: asm.SystemPlan
    ftol: float  # N: the force residual that is converged
    radius: np.ndarray  # (m,) m
    kn: float
    ks: float


@dataclass
class _Round:
    """What a round holds: each contact's normal force `nlag` (N) for the cap of its
    friction, its gap's rotation correction `delta` (m), whether its bond is `broken`, and
    whether its shear spring has no cap (`stick`: its bonded patch holds)."""

    nlag: np.ndarray
    delta: np.ndarray
    broken: np.ndarray
    stick: np.ndarray

    def law(self, st: _Step) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`(base (c,), cap (c,), tension (c,))`: the gap at x = 0 (with its rotation
        correction), the shear springs' caps μN + cA (N) and the tension each bond holds
        (N)."""
        bonded = ~self.broken
        cap = st.mu * np.maximum(self.nlag, 0.0) + np.where(bonded, st.cohesion, 0.0)
        return st.d0 + self.delta, cap, np.where(bonded, st.tension, 0.0)


def _setup(system: BlockSystem, state: State, contacts: ContactSet, patches: ContactPatches,
           dt: float) -> tuple[_Step, np.ndarray]:
    """The step's fixed terms and its block masses `(n, 12, 12)`."""
    nd = system.ndof
    kb, fb, mass = block_terms(system, state, dt)
    free = np.flatnonzero(state.awake(system.fixed))
    row = np.full(system.n, -1, dtype=np.int64)
    row[free] = np.arange(len(free))
    bi, bj = contacts.block_i, contacts.block_j
    ti = np.ascontiguousarray(asm.displacement_matrices(contacts.point_i,
                                                        state.centroid[bi])[:, :, :nd])
    tj = np.ascontiguousarray(asm.displacement_matrices(contacts.point_j,
                                                        state.centroid[bj])[:, :, :nd])
    jm = contacts.joint_material
    mem = state.memory
    rows = mem.find(contacts.key)
    again = rows >= 0
    shear0 = np.zeros((len(contacts), 3))
    if np.any(again):  # the anchored stretch, in the contact's plane now
        s = mem.shear[rows[again]]
        n = contacts.normal[again]
        shear0[again] = s - np.einsum("ij,ij->i", s, n)[:, None] * n
    cn, _ = contact_damping(system, state, bi, bj)
    links = bolt_links(system, state)
    link = None
    pi, pj, pti, ptj, pn = bi, bj, ti, tj, contacts.normal
    if links is not None:
        lbi, lbj, lti, ltj, axis, ka, ksb = links
        ee = np.einsum("ki,kj->kij", axis, axis)
        p = ka[:, None, None] * ee + ksb[:, None, None] * (np.eye(3)[None] - ee)
        link = (lbi, lbj, lti, ltj, p)
        pi, pj = np.concatenate([bi, lbi]), np.concatenate([bj, lbj])
        pti, ptj = np.concatenate([ti, lti]), np.concatenate([tj, ltj])
        pn = np.concatenate([contacts.normal, axis])
    kfull = np.zeros((system.n, nd, nd))
    kfull[free] = kb[free, :nd, :nd]
    plan = asm.plan_system(row, kfull, pi, pj, pti, ptj, pn)
    g = max(float(np.linalg.norm(system.gravity)), 1.0)
    weight = (system.density * system.volume0)[free] * g
    wmed = float(np.median(weight)) if len(weight) else 1.0
    d0 = contacts.gap.astype(float)
    st = _Step(free=free, row=row, kb=np.ascontiguousarray(kb[free, :nd, :nd]),
               fb=np.ascontiguousarray(fb[free, :nd]), bi=bi, bj=bj, ti=ti, tj=tj,
               normal=np.ascontiguousarray(contacts.normal, dtype=float),
               point_i=contacts.point_i, point_j=contacts.point_j, centroid=state.centroid,
               d0=d0,
               a=np.minimum(d0, 0.0), cprime=cn / dt, shear0=shear0,
               mu=system.tan_phi[jm].astype(float),
               cohesion=system.cohesion[jm] * patches.share,
               tension=system.tension[jm] * patches.share, patch=patches.patch,
               n_patch=len(patches), link=link, plan=plan,
               ftol=system.controls.contact_tolerance * wmed,
               radius=np.maximum(system.radius[free], 1e-12), kn=system.kn, ks=system.ks)
    return st, mass


def _first_round(system: BlockSystem, state: State, contacts: ContactSet, st: _Step
                 ) -> _Round:
    """The first round: each contact's normal spring force from the last step (by key; a
    new one from its start gap, or its block pair's share), no rotation correction, its
    bond as it starts the step."""
    mem = state.memory
    rows = mem.find(contacts.key)
    nlag = system.kn * np.maximum(-st.d0, 0.0)
    again = rows >= 0
    old = system.kn * np.maximum(-mem.gap, 0.0) * (mem.mode != OPEN)  # the springs' N
    if np.any(again):
        nlag[again] = old[rows[again]]
    _share_pairs(system, mem, contacts, rows, old, nlag)
    strong, bonded = bonded_at_start(system, state, contacts)
    broken = strong & ~bonded
    stick = (st.patch >= 0) & ~broken & (st.cohesion > 0)
    return _Round(nlag, np.zeros(len(contacts)), broken, stick)


def _share_pairs(system: BlockSystem, mem: object, contacts: ContactSet, rows: np.ndarray,
                 old: np.ndarray, nlag: np.ndarray) -> None:
    """A new contact of a block pair the last step had takes an equal share of what the
    pair's contacts that were not found again carried (the pair's force, re-detected on
    other features), in place: a first guess its rounds then correct."""
    n = system.n
    gone = np.ones(len(mem.key), dtype=bool)
    gone[rows[rows >= 0]] = False
    pair_old = mem.key[:, 0] * n + mem.key[:, 2]
    fresh = rows < 0
    pair_new = contacts.block_i * n + contacts.block_j
    if not (np.any(gone) and np.any(fresh)):
        return
    keys, inv = np.unique(np.concatenate([pair_old[gone], pair_new[fresh]]),
                          return_inverse=True)
    carried = np.bincount(inv[:int(gone.sum())], weights=old[gone], minlength=len(keys))
    count = np.bincount(inv[int(gone.sum()):], minlength=len(keys))
    share = carried[inv[int(gone.sum()):]] / np.maximum(count[inv[int(gone.sum()):]], 1)
    nlag[fresh] = np.maximum(nlag[fresh], share)


def _links_terms(st: _Step, x: np.ndarray) -> tuple[np.ndarray, float]:
    """The bolts' forces on block i `(k, 3)` N and energy (J) for the step `x`."""
    lbi, lbj, lti, ltj, p = st.link
    dr = kern.relative_motion(x, st.row, lbi, lbj, lti, ltj)
    f = -np.einsum("kij,kj->ki", p, dr)
    return f, -0.5 * float(np.sum(f * dr))


def _gradient(st: _Step, rnd: _Round, x: np.ndarray, want_jac: bool, coupled: bool = False
              ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """E(x), its gradient `(m, d)` (the step's out-of-balance forces, negated), the
    contacts' 3 × 3 blocks `(c, 3, 3)` of the energy's Hessian (with the caps held), or of
    the forces' Jacobian with each cap following its contact's normal force (`coupled`: not
    symmetric where a contact slides), and their relative displacements `(c, 3)`."""
    base, cap, tension = rnd.law(st)
    dr = kern.relative_motion(x, st.row, st.bi, st.bj, st.ti, st.tj)
    force, jac, energy = kern.contact_terms(dr, st.normal, base, st.a, st.cprime, st.shear0,
                                            cap, st.kn, st.ks, tension, rnd.stick, want_jac,
                                            st.mu if coupled else np.zeros(0))
    kx = np.einsum("mij,mj->mi", st.kb, x)
    energy += 0.5 * float(np.sum(kx * x)) - float(np.sum(st.fb * x))
    total = st.fb - kx  # the forces on the blocks; the gradient is their negative
    kern.scatter_forces(force, st.row, st.bi, st.bj, st.ti, st.tj, total)
    if st.link is not None:
        lf, le = _links_terms(st, x)
        kern.scatter_forces(lf, st.row, st.link[0], st.link[1], st.link[2], st.link[3], total)
        energy += le
    return energy, -total, jac, dr


def _rotation(st: _Step, rnd: _Round, x: np.ndarray) -> None:
    """Set the round's gap corrections for the blocks' exact rotation to those of the
    step `x`, in place (second order: left out of the Hessian, Gauss–Newton); none where
    no block turns enough for its correction, ~θ² r, to move a spring's force by the force
    residual."""
    turn = np.einsum("mi,mi->m", x[:, 3:6], x[:, 3:6]) * st.radius if len(x) else x[:, 0]
    if float(turn.max(initial=0.0)) * st.kn <= st.ftol:
        rnd.delta = np.zeros(len(st.bi))
        return
    dr = kern.relative_motion(x, st.row, st.bi, st.bj, st.ti, st.tj)
    rnd.delta = kern.rotation_correction(x, st.row, st.bi, st.bj, st.point_i, st.point_j,
                                         st.centroid, st.normal, dr)


def _normal_forces(st: _Step, rnd: _Round, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The contacts' forces on block i `(c, 3)` N and normal forces `(c,)` N at `x`."""
    base, cap, tension = rnd.law(st)
    dr = kern.relative_motion(x, st.row, st.bi, st.bj, st.ti, st.tj)
    force, _, _ = kern.contact_terms(dr, st.normal, base, st.a, st.cprime, st.shear0, cap,
                                     st.kn, st.ks, tension, rnd.stick, False, np.zeros(0))
    return force, np.einsum("ij,ij->i", force, st.normal)


def _scaled(st: _Step, grad: np.ndarray) -> np.ndarray:
    """The out-of-balance forces `(m, d)` in newtons: forces, moments and strain forces
    over the block's radius."""
    out = grad.copy()
    out[:, 3:] /= st.radius[:, None]
    return out


def _residual(st: _Step, grad: np.ndarray) -> float:
    """The largest out-of-balance force of a block (N): its force, its moment over its
    radius and its strain forces over its radius."""
    if not len(grad):
        return 0.0
    g = _scaled(st, grad)
    out = np.linalg.norm(g[:, :3], axis=1)
    out = np.maximum(out, np.linalg.norm(g[:, 3:6], axis=1))
    if grad.shape[1] > 6:
        out = np.maximum(out, np.abs(g[:, 6:]).max(axis=1))
    return float(out.max())


def _line_search(st: _Step, rnd: _Round, x: np.ndarray, p: np.ndarray, dr: np.ndarray
                 ) -> float:
    """The step α along `p` that minimises E(x + α p): the root of its slope, which grows
    with α (E is convex), by safeguarded Newton on the slope and its curvature. The block
    terms' and the bolts' slope is linear in α; the contacts' is summed by the kernel."""
    base, cap, tension = rnd.law(st)
    dp = kern.relative_motion(p, st.row, st.bi, st.bj, st.ti, st.tj)
    kx = np.einsum("mij,mj->mi", st.kb, x)
    kp = np.einsum("mij,mj->mi", st.kb, p)
    b0 = float(np.sum(p * (kx - st.fb)))
    b1 = float(np.sum(kp * p))
    if st.link is not None:
        lbi, lbj, lti, ltj, lp = st.link
        l0 = kern.relative_motion(x, st.row, lbi, lbj, lti, ltj)
        l1 = kern.relative_motion(p, st.row, lbi, lbj, lti, ltj)
        b0 += float(np.einsum("ki,kij,kj->", l1, lp, l0))
        b1 += float(np.einsum("ki,kij,kj->", l1, lp, l1))

    def slope(alpha: float) -> tuple[float, float]:
        s, c = kern.line_slope(alpha, dr, dp, st.normal, base, st.a, st.cprime, st.shear0,
                               cap, st.kn, st.ks, tension, rnd.stick)
        return b0 + alpha * b1 + s, b1 + c

    s0, _ = slope(0.0)
    if s0 >= 0.0:
        return 0.0
    lo, hi, alpha = 0.0, np.inf, 1.0
    for _ in range(LINE_EVALUATIONS):
        s, c = slope(alpha)
        if abs(s) <= LINE_TOLERANCE * abs(s0):
            return alpha
        if s < 0.0:
            lo = alpha
        else:
            hi = alpha
        step = alpha - s / c if c > 0.0 else np.inf
        if np.isfinite(hi):
            alpha = step if lo < step < hi else 0.5 * (lo + hi)
        else:
            alpha = min(step, 4.0 * alpha) if step > alpha else 2.0 * alpha
    return lo if lo > 0.0 else alpha


def _potential_step(st: _Step, rnd: _Round, x: np.ndarray, ls: NewtonSystems, rtol: float,
                    terms: tuple) -> np.ndarray:
    """A Newton step of the step potential from `x`, whose gradient, Hessian blocks and
    relative displacements are `terms` (an exact line search): E is convex, so it always
    descends."""
    _, grad, hess, dr = terms
    p = ls.solve(hess, -grad, rtol, None)
    return x + _line_search(st, rnd, x, p, dr) * p


def _newton(st: _Step, rnd: _Round, x: np.ndarray, ls: NewtonSystems) -> tuple[np.ndarray, int]:
    """x minimising the step potential of the round `rnd` (its caps held) from `x`: Newton
    steps with an exact line search until every block's out-of-balance force is below
    `st.ftol` (the gaps' rotation corrections following each iterate); StepFailure when
    they do not get there."""
    _rotation(st, rnd, x)
    terms = _gradient(st, rnd, x, True)
    res = first = max(_residual(st, terms[1]), 1e-300)
    for it in range(MAX_NEWTON + 1):
        if res <= st.ftol:
            return x, it
        if it == MAX_NEWTON:
            break
        rtol = min(KRYLOV_RTOL_MAX, max(KRYLOV_RTOL_MIN, 0.5 * res / first))
        x = _potential_step(st, rnd, x, ls, rtol, terms)
        _rotation(st, rnd, x)
        terms = _gradient(st, rnd, x, True)
        res = _residual(st, terms[1])
    raise StepFailure(f"Newton's method did not reach the force residual {st.ftol:.3g} N in "
                      f"{MAX_NEWTON} iterations (residual {res:.3g} N)", "newton")


def _follow(st: _Step, rnd: _Round, x: np.ndarray) -> _Round:
    """The round with every cap's normal force, and the gaps' rotation corrections, those
    at `x`: the whole normal force, spring and dashpot (Coulomb bounds friction by all the
    faces carry, as the complementarity solve's impulses do; capped by the spring's part
    alone, the toppling train's toes slid on impact and T1 turned 0.117 rad at Δt 0.1 ms
    and 0.129 at 0.03 ms, away from the other solvers' 0.104-0.106)."""
    out = dataclasses.replace(rnd)
    _rotation(st, out, x)
    out.nlag = np.maximum(_normal_forces(st, out, x)[1], 0.0)
    return out


def _merit(st: _Step, grad: np.ndarray) -> float:
    """The squared out-of-balance forces (N²): what a semi-smooth Newton step must lower."""
    return float(np.sum(_scaled(st, grad) ** 2))


def _polish(st: _Step, rnd: _Round, x: np.ndarray, ls: NewtonSystems
            ) -> tuple[np.ndarray, _Round, int, bool]:
    """Semi-smooth Newton from `x` on the step's equations with each cap following its
    contact's normal force (the Jacobian with the cap's dependence on N, a backtracking
    line search on the squared out-of-balance forces): `(x, its round, iterations,
    converged)`, converged once every block's out-of-balance force is below `st.ftol`; it
    stops unconverged where a step descends poorly (cut below MIN_STEP: a cap's kink
    between x and the solution) or after SEMI_SMOOTH_STEPS."""
    cur = _follow(st, rnd, x)
    _, grad, jac, _ = _gradient(st, cur, x, True, coupled=True)
    res = first = max(_residual(st, grad), 1e-300)
    p = None
    for it in range(SEMI_SMOOTH_STEPS + 1):
        if res <= st.ftol:
            return x, cur, it, True
        if it == SEMI_SMOOTH_STEPS:
            break
        rtol = min(KRYLOV_RTOL_MAX, max(KRYLOV_RTOL_MIN, 0.5 * res / first))
        p = ls.solve(jac, -grad, rtol, p, symmetric=False)
        merit0, alpha = _merit(st, grad), 1.0
        while True:
            trial = _follow(st, cur, x + alpha * p)
            out = _gradient(st, trial, x + alpha * p, True, coupled=True)
            if _merit(st, out[1]) <= (1.0 - 2e-4 * alpha) * merit0:
                break
            alpha *= 0.5
            if alpha < MIN_STEP:
                return x, cur, it + 1, False
        x, cur, p = x + alpha * p, trial, alpha * p
        _, grad, jac, _ = out
        res = _residual(st, grad)
    return x, cur, SEMI_SMOOTH_STEPS, False


def _solve_round(st: _Step, rnd: _Round, x: np.ndarray, ls: NewtonSystems
                 ) -> tuple[np.ndarray, _Round, int]:
    """The round's solution, `(x, the round it solves, Newton iterations)`: semi-smooth
    Newton with the caps following N (:func:`_polish`); where that does not converge, the
    convex step potential minimised with the caps held at the normal forces where it
    stopped, and the polish again from there; where that does not converge either, the
    potential once more with the caps of its last iterate (a lag of one round, counted in
    `Diagnostics.lagged_caps`)."""
    x, cur, its, converged = _polish(st, rnd, x, ls)
    for attempt in range(2):
        if converged:
            return x, cur, its
        x, more = _newton(st, cur, x, ls)
        its += more
        if attempt == 0:
            x, cur, more, converged = _polish(st, cur, x, ls)
            its += more
    ls.lagged += 1
    return x, cur, its


def _patch_bonds(st: _Step, rnd: _Round, force: np.ndarray, fnorm: np.ndarray
                 ) -> np.ndarray:
    """The contacts whose bonds break `(c,) bool`: a bonded contact pulled beyond its share
    of the tensile strength (it alone), and every contact of a bonded patch whose closed
    contacts' total shear exceeds Σ μN + Σ cA (the patch whole)."""
    bonded = ~rnd.broken
    breaking = bonded & (st.tension > 0) & (-fnorm > st.tension * (1 + 1e-9))
    inside = (st.patch >= 0) & bonded & (st.cohesion > 0)
    if np.any(inside):
        p = st.patch
        use = p >= 0
        shear = force - fnorm[:, None] * st.normal
        total = np.zeros((st.n_patch, 3))
        np.add.at(total, p[use], shear[use])
        capacity = np.bincount(p[use], weights=st.mu[use] * np.maximum(fnorm[use], 0.0),
                               minlength=st.n_patch)
        capacity += np.bincount(p[inside], weights=st.cohesion[inside], minlength=st.n_patch)
        over = np.linalg.norm(total, axis=1) > capacity * (1 + 1e-9)
        breaking |= inside & over[np.maximum(p, 0)]
    return breaking


def _next_round(st: _Step, rnd: _Round, x: np.ndarray) -> tuple[_Round, bool]:
    """The next round from the solution `x` of `rnd`, and whether `rnd` already held: no
    bond broke (a bonded contact pulled beyond its tension, a bonded patch's shear beyond
    its strength)."""
    force, fnorm = _normal_forces(st, rnd, x)
    breaking = _patch_bonds(st, rnd, force, fnorm)
    broken = rnd.broken | breaking
    return (dataclasses.replace(rnd, broken=broken, stick=rnd.stick & ~broken),
            not np.any(breaking))


def _warm(system: BlockSystem, state: State, st: _Step, dt: float) -> np.ndarray:
    """The first guess: the last step's displacement scaled to this Δt (zero at the start)."""
    nd = system.ndof
    if state.last_d is None or state.last_dt <= 0:
        return np.zeros((len(st.free), nd))
    return state.last_d[st.free, :nd] * (dt / state.last_dt)


def _reseat(state: State, st: _Step, bonded: np.ndarray, fixed: np.ndarray) -> float:
    """Energy (J) the springs held at the end of the last step that the step's contacts do
    not start with (re-detected shallower, on another plane or not at all), booked as
    numerical dissipation (:func:`.open_close.reseat_loss`, with the tension a bonded
    spring holds; the springs of sleeping blocks keep theirs); a spring that starts with
    more is not booked: the watchdog sees it."""
    g = np.where(bonded, st.d0, np.minimum(st.d0, 0.0))
    start = 0.5 * st.kn * float(np.sum(g ** 2)) + 0.5 * st.ks * float(np.sum(st.shear0 ** 2))
    resting = state.memory.spring_energy(st.kn, st.ks, state.resting_contacts(fixed))
    return max(state.contact_energy - resting - start, 0.0)


def newton_step(system: BlockSystem, state: State, contacts: ContactSet,
                patches: ContactPatches, dt: float) -> StepResult:
    """The step of `dt` s from `state` with its `contacts` (and their bonded `patches`) as
    the minimum of the step potential (module docstring); StepFailure when Newton's method
    or its outer rounds do not converge."""
    diag = state.diagnostics
    clock = _time.perf_counter()
    st, mass = _setup(system, state, contacts, patches, dt)
    rnd = _first_round(system, state, contacts, st)
    broken0 = rnd.broken.copy()
    ls = NewtonSystems(st.plan, None if st.link is None else st.link[4])
    clock = diag.tick("assembly", clock)
    x = _warm(system, state, st, dt)
    iterations = 0
    for _ in range(MAX_ROUNDS):
        x, rnd, its = _solve_round(st, rnd, x, ls)
        iterations += its
        nxt, held = _next_round(st, rnd, x)
        if held:
            break
        rnd = nxt
    else:
        raise StepFailure(f"the step's bonds did not settle in {MAX_ROUNDS} rounds", "newton")
    diag.solves += iterations
    clock = diag.tick("solve", clock)
    out = _result(system, state, contacts, patches, st, rnd, x, iterations, dt, broken0)
    out.linear_iterations = ls.krylov_iterations
    diag.lagged_caps += ls.lagged
    diag.tick("open_close", clock)
    return out


def _result(system: BlockSystem, state: State, contacts: ContactSet, patches: ContactPatches,
            st: _Step, rnd: _Round, x: np.ndarray, iterations: int, dt: float,
            broken0: np.ndarray) -> StepResult:
    """The step's StepResult from its solution `x` in the round `rnd`."""
    base, cap, tension = rnd.law(st)
    dr = kern.relative_motion(x, st.row, st.bi, st.bj, st.ti, st.tj)
    (gap1, fnorm, force, stretch, slip, mode, tforce, stored, friction, damping,
     numerical) = kern.step_ends(dr, st.normal, st.d0, base, st.a, st.cprime, st.shear0, cap,
                                 st.kn, st.ks, tension, rnd.stick)
    d = np.zeros((system.n, 12))
    d[st.free, :system.ndof] = x
    numerical += block_dissipation(system, state, d)  # (the bolts' own: engine.loads.bolts)
    reseat = _reseat(state, st, tension > 0, system.fixed)
    slip_len = np.linalg.norm(slip, axis=1)
    tangent = np.where((slip_len > 0)[:, None], slip / np.maximum(slip_len, 1e-300)[:, None],
                       contacts.tangent)
    out = dataclasses.replace(contacts, mode=mode, tangent=tangent)
    return StepResult(
        d=d, contacts=out, gap1=gap1, shear=np.where((mode != OPEN)[:, None], stretch, 0.0),
        slip=slip, normal_force=fnorm, shear_force=tforce, friction_work=friction,
        iterations=iterations, numerical_dissipation=numerical + reseat,
        damping_dissipation=damping, broken=rnd.broken.copy(), reseat_dissipation=reseat,
        bond_breaks=bond_breaks(patches, broken0, rnd.broken), force=force,
        contact_energy=stored)
