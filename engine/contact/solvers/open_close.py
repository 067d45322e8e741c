"""The open-close iteration of one step (paper section 4.3, Tables 1 and 2).

Start modes come from the previous step for contacts found again (inherited) and from
Table 1 for new ones. Each cycle adds the contact terms of the current modes to K (refactored
only when the closed or locked contacts change), solves, and updates every contact's mode by
Table 2 (with first entrance for contacts that close within the step). The iteration
converges on open / closed (paper 4.3); locked <-> sliding changes iterate too but are
bounded per contact (one that keeps switching sits at its friction limit: it stays locked
and its spring's anchor is returned to the friction force, or slides if the anchor keeps
moving), and the explicit friction forces are iterated to a fixed point without
refactoring. Rescue rules, each a named function below, keep a converged step honest:
contacts kept closed by the reopening cap must not end in tension, sliding contacts kept by
the switch cap must not slip against their friction, and no spring may release energy it
never stored. A step that breaks them raises :class:`StepFailure` (the caller cuts Δt).
"""

from __future__ import annotations

import dataclasses
import time as _time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from engine.contact.constraints import LOCKED, OPEN, SLIDING, ContactSet
from engine.contact.patches import ContactPatches, bond_breaks
from engine.contact.solution import StepResult
from engine.contact.solvers._open_close_kernels import (
    FINAL_SLIDE,
    contact_loads,
    contact_loads_threads,
    step_results,
    update_modes,
)
from engine.contact.solvers._open_close_kernels import initial_modes as _initial_modes
from engine.dynamics import assembly as asm
from engine.dynamics._assembly_kernels import row_contacts
from engine.dynamics.block_terms import block_dissipation, block_terms, bolt_links, kinetic_energy
from engine.dynamics.motion import mass_properties
from engine.dynamics.solver import BlockJacobi, SolveError, make_solver
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.status import StepFailure
from engine.tolerances import DEFAULT_TOLERANCES

#: relative change of friction forces below which the open-close iteration has converged
FRICTION_RTOL = 1e-4
#: cycles allowed per mode change for the explicit friction forces to settle (no refactor)
FRICTION_ITERATIONS_PER_CHANGE = 6
#: after that many cycles without a mode change, a friction change below this is accepted:
#: the explicit friction fixed point of a large contact system can creep instead of converge
FRICTION_RTOL_STALLED = 1e-2
#: locked <-> sliding switches a contact may make in one step; after them it is held at its
#: friction limit (its anchor returned, `update_modes`) or slides for good (ANCHOR_QUIET_CYCLES)
MAX_SHEAR_SWITCHES = 2
#: times a contact may open in one step before it is kept closed for the rest of the step
MAX_REOPENINGS = 2
#: a step whose capped sliding contact slips back against its friction by more than this
#: fraction of the step displacement limit is redone with a smaller time step (the
#: friction would push the blocks and create energy; measured on the stability map's pile)
FRICTION_REVERSAL_RATIO = 0.01
#: a converged step whose penalty springs release more than this fraction of the blocks'
#: kinetic energy (plus the round-off floor) that they never stored is redone with a
#: smaller time step
SPRING_ENERGY_RTOL = 1e-2


@dataclass
class StartModes:
    """Modes `(c,)`, accumulated shear `(c, 3)` m, sliding directions `(c, 3)` and broken
    bonds `(c,)` of a step's contacts at its start."""

    mode: np.ndarray
    shear: np.ndarray
    tangent: np.ndarray
    broken: np.ndarray


def initial_modes(system: BlockSystem, state: State, contacts: ContactSet,
                  dt: float) -> StartModes:
    """Modes at the start of a step of `dt` s: inherited from the previous step for the
    same closed contact, else the paper's Table 1 from the penetration and the relative
    tangential velocity, where blocks that already touch (cut blocks, stacked blocks) start
    closed so a resting mass carries its weight from the first cycle. Joints are bonded
    (cohesion, tensile strength) where blocks touch at the start; a contact that forms
    later has only friction."""
    mem = state.memory
    jm = contacts.joint_material
    return StartModes(*_initial_modes(
        contacts.block_i, contacts.block_j, contacts.point_i, contacts.point_j,
        contacts.normal, contacts.gap, state.centroid, state.velocity,
        mem.find(contacts.key), mem.mode, mem.shear, mem.tangent, mem.broken,
        system.tan_phi[jm], (system.cohesion[jm] > 0) | (system.tension[jm] > 0),
        state.step == 0, system.touch_gap, system.bond_gap, dt, system.kn, system.ks))


@dataclass
class _Terms:
    """The step's contacts as the compiled kernels take them (fixed during the iteration):
    blocks, normals, start gaps `d0` and shear `shear0`, T at the contact points on the
    unknown columns `ti`, `tj (c, 3, d)`, the unknowns `dmap (n, d)`, the strengths, and
    each contact's face-to-face patch (-1: none) with the number of patches."""

    bi: np.ndarray
    bj: np.ndarray
    normal: np.ndarray
    d0: np.ndarray
    shear0: np.ndarray
    ti: np.ndarray
    tj: np.ndarray
    dmap: np.ndarray
    tan_phi: np.ndarray
    cohesion_force: np.ndarray
    tension_force: np.ndarray
    cn: np.ndarray
    resolution: np.ndarray  # (c,) m: gaps within it are round-off (contact_round_off)
    patch: np.ndarray
    n_patch: int
    #: each block's contacts (row_contacts of bi, bj), when the loads run on threads
    blocks: tuple[np.ndarray, np.ndarray] | None = None


def block_masses(system: BlockSystem, state: State) -> np.ndarray:
    """Each block's mass `(n,)` kg, infinite for a fixed block."""
    return np.where(system.fixed, np.inf, system.density * mass_properties(system, state)[0])


def round_off_gaps(system: BlockSystem, state: State, contacts: ContactSet) -> np.ndarray:
    """Each contact's gap resolution `(c,)` m: the spring stretch whose force is
    `contact_round_off` of the lighter block's weight (0 between fixed blocks)."""
    lighter = np.minimum(*(block_masses(system, state)[b]
                           for b in (contacts.block_i, contacts.block_j)))
    force = np.zeros(len(lighter))
    free = np.isfinite(lighter)
    force[free] = (DEFAULT_TOLERANCES.contact_round_off * float(np.linalg.norm(system.gravity))
                   * lighter[free])
    return force / system.kn


#: below this many contacts a Python dict counts a step's block pairs faster than numpy
SMALL_PAIR_COUNT = 64


def pair_counts(pair: np.ndarray) -> np.ndarray:
    """How many of the entries `pair (c,) int` equal each one `(c,)` (np.unique's counts
    mapped back, without its cost for a few contacts)."""
    if len(pair) <= SMALL_PAIR_COUNT:
        keys = pair.tolist()
        seen: dict[int, int] = {}
        for k in keys:
            seen[k] = seen.get(k, 0) + 1
        return np.array([seen[k] for k in keys], dtype=np.int64)
    order = np.argsort(pair, kind="stable")
    sorted_pair = pair[order]
    first = np.empty(len(pair), dtype=bool)
    first[0] = True
    np.not_equal(sorted_pair[1:], sorted_pair[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, len(pair)))
    out = np.empty(len(pair), dtype=np.int64)
    out[order] = np.repeat(counts, counts)
    return out


def contact_damping(system: BlockSystem, state: State, block_i: np.ndarray,
                    block_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal and shear dashpots `(cn, cs)` `(c,)` N·s/m of contacts between blocks
    `block_i`, `block_j (c,)`: the fraction `contact_damping` of critical damping,
    2 ζ √(k m), of each contact's spring carrying its share of the block pair's reduced
    mass (a fixed block's mass is infinite; a pair's contacts share its mass equally)."""
    zeta = system.controls.contact_damping
    c = len(block_i)
    if zeta <= 0 or c == 0:
        return np.zeros(c), np.zeros(c)
    mass = block_masses(system, state)
    mi, mj = mass[block_i], mass[block_j]
    reduced = 1.0 / (1.0 / mi + 1.0 / mj)
    share = reduced / pair_counts(block_i * system.n + block_j)
    return 2.0 * zeta * np.sqrt(system.kn * share), 2.0 * zeta * np.sqrt(system.ks * share)


def _terms(system: BlockSystem, state: State, contacts: ContactSet,
           patches: ContactPatches, shear0: np.ndarray) -> _Terms:
    nd = system.ndof
    bi, bj = contacts.block_i, contacts.block_j
    jm = contacts.joint_material
    # only the normal dashpot acts inside the solve: a shear dashpot on a locked contact is
    # viscous static friction (the shear dashpots after the step, engine.contact.solvers.damping,
    # keep theirs)
    cn, _ = contact_damping(system, state, bi, bj)
    return _Terms(
        bi=bi, bj=bj, normal=contacts.normal, d0=contacts.gap, shear0=shear0,
        ti=asm.point_matrices(contacts.point_i, state.centroid, bi, nd),
        tj=asm.point_matrices(contacts.point_j, state.centroid, bj, nd),
        dmap=np.ascontiguousarray(system.dof_map[:, :nd]), tan_phi=system.tan_phi[jm],
        cohesion_force=system.cohesion[jm] * patches.share,
        tension_force=system.tension[jm] * patches.share,
        cn=cn, resolution=round_off_gaps(system, state, contacts), patch=patches.patch,
        n_patch=len(patches),
        blocks=row_contacts(system.n, bi, bj) if asm.threaded(len(bi)) else None)


@dataclass
class _Modes:
    """What the iteration changes from cycle to cycle: modes, sliding directions, friction
    normal forces N* (paper eq. 30: kn |d*|, here with the dashpot's force), revised contact
    point shifts of contacts closing (eq. 47),
    broken bonds, the per-contact caps' counters, the contacts a rescue rule changed, the
    last friction forces, and the open/closed changes and quiet cycles so far."""

    mode: np.ndarray
    tangent: np.ndarray
    nstar: np.ndarray
    offset: np.ndarray
    broken: np.ndarray
    switches: np.ndarray
    reopenings: np.ndarray
    forced: np.ndarray  # capped sliding contacts locked
    released: np.ndarray  # capped closed contacts opened
    fric_prev: np.ndarray
    cn: np.ndarray  # normal dashpots still acting (N·s/m; 0 once a dashpot let go)
    mode_changes: int = 0
    steady: int = 0


def _start(system: BlockSystem, start: StartModes, t: _Terms) -> _Modes:
    d0 = t.d0
    c = len(d0)
    return _Modes(mode=start.mode, tangent=start.tangent,
                  nstar=system.kn * np.maximum(-d0, 0.0),
                  offset=np.zeros((c, 3)), broken=start.broken,
                  switches=np.zeros(c, dtype=np.int64), reopenings=np.zeros(c, dtype=np.int64),
                  forced=np.zeros(c, dtype=bool), released=np.zeros(c, dtype=bool),
                  fric_prev=np.zeros((c, 3)), cn=t.cn.copy())


class _LinearSystem:
    """K of the step as a function of the contact modes (:class:`asm.SystemPlan`) and its
    solver, built again only when the closed or locked contacts change; the solution of the
    last cycle warm-starts the next."""

    def __init__(self, system: BlockSystem, kb: np.ndarray, t: _Terms, dt: float,
                 links: tuple[np.ndarray, ...] | None = None,
                 workspace: dict | None = None) -> None:
        self.system, self.kb, self.t, self.dt = system, kb, t, dt
        #: two-point springs between free blocks that are not contacts (rock bolts)
        self.links = links
        #: the run's workspace (`State.workspace`): the last step's plan, whose pattern the
        #: step's K keeps while its contacts join the same blocks
        self.workspace = {} if workspace is None else workspace
        self.plan: asm.SystemPlan | None = None
        self.solver = None
        self.key: tuple[bytes, bytes] | None = None
        self.jacobi = BlockJacobi()
        self.x: np.ndarray | None = None

    def update(self, mode: np.ndarray, cn: np.ndarray) -> bool:
        """Assemble and factorize K for `mode` and the normal dashpots `cn` unless they are
        the last ones; whether it did."""
        closed, locked = mode != OPEN, mode == LOCKED
        key = (closed.tobytes(), locked.tobytes(), (cn > 0).tobytes())
        if self.solver is not None and key == self.key:
            return False
        s, t = self.system, self.t
        kn, ks = (s.kn + cn / self.dt) * closed, s.ks * locked
        fresh = self.plan is None
        last = self.workspace.get("plan") if fresh else None
        if self.links is None:
            if self.plan is None:
                self.plan = asm.plan_system(s.block_row, self.kb, t.bi, t.bj, t.ti, t.tj,
                                            t.normal, last=last)
        else:
            bi, bj, ti, tj, axis, ka, ksb = self.links
            if self.plan is None:
                self.plan = asm.plan_system(
                    s.block_row, self.kb, np.concatenate([t.bi, bi]),
                    np.concatenate([t.bj, bj]), np.concatenate([t.ti, ti]),
                    np.concatenate([t.tj, tj]), np.concatenate([t.normal, axis]), last=last)
            kn, ks = np.concatenate([kn, ka]), np.concatenate([ks, ksb])
        if fresh:
            self.workspace["plan"] = self.plan.pattern()
        k, kdiag = self.plan.matrix(kn, ks)
        try:
            self.solver = make_solver(k, s.ndof, kdiag, self.jacobi, self.plan.components)
        except SolveError as exc:
            raise StepFailure(str(exc), "solve") from exc
        self.key = key
        return True

    def solve(self, f: np.ndarray) -> np.ndarray:
        try:
            self.x = self.solver(f, self.x)
        except SolveError as exc:
            raise StepFailure(str(exc), "solve") from exc
        return self.x


@dataclass
class _Cycle:
    """One cycle's solution `x`, friction forces `fric_mag (c,)`, `fric (c, 3)` N, relative
    displacements `dr (c, 3)` m, and what Table 2 made of them (:func:`update_modes`)."""

    x: np.ndarray
    fric_mag: np.ndarray
    fric: np.ndarray
    dr: np.ndarray
    mode: np.ndarray
    tangent: np.ndarray
    nstar: np.ndarray
    d1: np.ndarray
    dr_t: np.ndarray
    along: np.ndarray
    fn: np.ndarray
    changed: bool
    closed_changed: bool
    fric_change: float
    anchored: np.ndarray  # how far capped locks' anchors slid back to friction (m)


def _cycle(system: BlockSystem, state: State, t: _Terms, m: _Modes, lin: _LinearSystem,
           f_block: np.ndarray, dt: float, clock: float) -> tuple[_Cycle, float]:
    """Solve with the contact terms of the current modes, then Table 2 for every contact."""
    diag = state.diagnostics
    if lin.update(m.mode, m.cn):
        diag.factorizations += 1
        clock = diag.tick("assembly", clock)
    # contact forces on block i (on j the opposite), as generalized loads
    f = f_block.copy()
    args = (f, t.dmap, t.bi, t.bj, t.ti, t.tj, t.normal, t.d0, m.mode, t.shear0, m.offset,
            m.tangent, m.nstar, t.tan_phi, system.kn, system.ks, m.cn, dt)
    fric_mag, fric = (contact_loads(*args) if t.blocks is None
                      else contact_loads_threads(*args, *t.blocks))
    clock = diag.tick("assembly", clock)
    x = lin.solve(f)
    diag.solves += 1
    clock = diag.tick("solve", clock)
    dr = asm.relative_motion(x, t.dmap, t.bi, t.bj, t.ti, t.tj)
    out = update_modes(t.d0, t.normal, dr, t.shear0, m.offset, m.mode, m.tangent, m.broken,
                       m.reopenings, m.switches, t.tan_phi, t.tension_force,
                       t.cohesion_force, fric_mag, m.fric_prev, system.kn, system.ks, m.cn,
                       dt, system.open_close_gap, t.resolution, MAX_REOPENINGS,
                       MAX_SHEAR_SWITCHES, t.patch, t.n_patch)
    clock = diag.tick("open_close", clock)
    return _Cycle(x, fric_mag, fric, dr, *out), clock


def _settled(m: _Modes, cyc: _Cycle, was_sliding: np.ndarray) -> bool:
    """No mode changed, and the friction forces settled (or nothing slides)."""
    settled = cyc.fric_change <= FRICTION_RTOL or (
        m.steady >= FRICTION_ITERATIONS_PER_CHANGE and cyc.fric_change <= FRICTION_RTOL_STALLED)
    return not cyc.changed and (settled or not (np.any(was_sliding) or np.any(cyc.anchored > 0)))


def _rescue_once(m: _Modes, breaking: np.ndarray, rescued: np.ndarray, mode: int,
                 failure: Callable[[int], StepFailure]) -> np.ndarray | None:
    """The contacts `breaking` a rule that no rescue has changed yet, set to `mode` and
    marked in `rescued` (None when there are none); `failure(count)` is raised when a
    rescued contact breaks the rule again."""
    if not np.any(breaking):
        return None
    now = breaking & ~rescued
    if not np.any(now):
        raise failure(int(breaking.sum()))
    m.mode = m.mode.copy()
    m.mode[now] = mode
    rescued |= now
    return now


def release_held_contacts(system: BlockSystem, t: _Terms, m: _Modes, cyc: _Cycle) -> bool:
    """Contacts kept closed by the reopening cap must not end pulling their blocks together:
    that would be a bond the joint does not have. Open them once more and iterate on (True);
    a contact held again after that stops the step (StepFailure)."""
    allow_tension = np.where(m.broken, 0.0, t.tension_force)
    pull = np.minimum(cyc.fn, -system.kn * cyc.d1)  # the dashpot may not hold a gap shut
    held = (m.mode != OPEN) & (m.reopenings >= MAX_REOPENINGS) & (
        pull < -allow_tension - system.kn * (system.open_close_gap + t.resolution))
    now = _rescue_once(m, held, m.released, OPEN, lambda count: StepFailure(
        f"open-close iteration did not settle: {count} contact(s) kept closing and opening",
        "held_contacts"))
    if now is None:
        return False
    m.nstar = np.where(now, 0.0, m.nstar)
    m.reopenings[now] = 0
    return True


def lock_reversed_sliders(system: BlockSystem, t: _Terms, m: _Modes, cyc: _Cycle,
                          was_sliding: np.ndarray) -> bool:
    """A sliding contact kept by the switch cap must not slip against its friction force:
    the friction would then push the blocks and create energy. Table 2 locks a contact whose
    slip reverses; lock it for the rest of the step, continuing from its friction force, and
    iterate on (True); one that reverses again stops the step (StepFailure)."""
    driven = was_sliding & (m.switches >= MAX_SHEAR_SWITCHES) & (
        cyc.along < -FRICTION_REVERSAL_RATIO * system.max_step_displacement)
    now = _rescue_once(m, driven, m.forced, LOCKED, lambda count: StepFailure(
        f"open-close iteration did not settle: {count} sliding contact(s) reversed against "
        "their friction", "reversed_friction"))
    if now is None:
        return False
    m.offset[now] = (cyc.fric_mag[now, None] / system.ks * m.tangent[now] - cyc.dr_t[now]
                     - t.shear0[now])
    return True


#: quiet cycles (no mode change) after which capped locks whose anchors still slide are set
#: sliding: a contact at its friction limit settles in a few cycles, a real slip drags
#: its anchor on and on (the elastic stiffness converges slowly on a slip)
ANCHOR_QUIET_CYCLES = 2 * FRICTION_ITERATIONS_PER_CHANGE


def slide_dragged_anchors(t: _Terms, m: _Modes, cyc: _Cycle) -> bool:
    """Capped locked contacts whose anchors still slide after ANCHOR_QUIET_CYCLES quiet
    cycles are sliding, not at their friction limit: set them sliding along their shear
    force for the rest of the step and iterate on (True)."""
    now = (cyc.anchored > 0) & (m.steady >= ANCHOR_QUIET_CYCLES)
    if not np.any(now):
        return False
    r = t.shear0 + m.offset + cyc.dr
    stretch = r - np.einsum("ij,ij->i", r, t.normal)[:, None] * t.normal
    m.mode = m.mode.copy()
    m.mode[now] = SLIDING
    m.tangent = m.tangent.copy()
    m.tangent[now] = stretch[now] / np.maximum(np.linalg.norm(stretch[now], axis=1),
                                               1e-300)[:, None]
    m.nstar = np.where(now, np.maximum(cyc.fn, 0.0), m.nstar)
    m.switches[now] = FINAL_SLIDE
    m.steady = 0
    return True


def reseat_loss(system: BlockSystem, state: State, t: _Terms) -> float:
    """Energy (J) the springs held at the end of the last step that the step's re-detected
    contacts do not start with: a contact found shallower, on another plane, or not at all
    (never deeper: `contact_step.plausible_gaps`). The step's spring terms start from the
    new gaps `t.d0` and shears `t.shear0`; this is booked as numerical dissipation. A spring
    that starts with more than it held (a rotation's second-order shift) is not booked: that
    stays visible to the energy watchdog as created energy."""
    start = (0.5 * system.kn * float(np.sum(np.minimum(t.d0, 0.0) ** 2))
             + 0.5 * system.ks * float(np.sum(t.shear0 ** 2)))
    return max(state.contact_energy - start, 0.0)


def _converged(system: BlockSystem, state: State, contacts: ContactSet, t: _Terms,
               m: _Modes, cyc: _Cycle, mass: np.ndarray, iterations: int, dt: float,
               patches: ContactPatches, broken0: np.ndarray) -> StepResult:
    """The step's result from its last cycle; StepFailure when its implicit springs
    released energy they never stored (a spring re-locked with an offset from an earlier
    cycle of a fast step would accelerate the blocks: redo the step smaller)."""
    nf, sf, shear1, fw, num, damp = step_results(
        t.d0, cyc.d1, t.normal, t.shear0, m.offset, cyc.dr, cyc.dr_t, m.mode, m.tangent,
        cyc.fric, cyc.fric_mag, system.kn, system.ks, m.cn, dt)
    d = np.zeros((system.n, 12))
    free = system.dof_map >= 0
    d[free] = cyc.x[system.dof_map[free]]
    num += block_dissipation(system, state, d)
    kinetic = kinetic_energy(state.velocity, mass)
    if -num > SPRING_ENERGY_RTOL * kinetic + system.energy_floor:
        raise StepFailure(f"open-close iteration settled with springs that release {-num:.3g} "
                          "J they never stored", "spring_energy")
    reseat = reseat_loss(system, state, t)
    return StepResult(
        d=d, contacts=dataclasses.replace(contacts, mode=m.mode.astype(np.int8),
                                          tangent=m.tangent),
        gap1=cyc.d1, shear=shear1, slip=cyc.dr_t, normal_force=nf, shear_force=sf,
        friction_work=fw, iterations=iterations, mode_changes=m.mode_changes,
        numerical_dissipation=num + reseat, damping_dissipation=damp, broken=m.broken,
        reseat_dissipation=reseat, bond_breaks=bond_breaks(patches, broken0, m.broken))


def open_close_iteration(system: BlockSystem, state: State, contacts: ContactSet,
                         patches: ContactPatches, start: StartModes, dt: float) -> StepResult:
    """The converged step of `dt` s from the start modes `start` (StepFailure if it does
    not converge within `max_open_close_iterations` open/closed changes, or breaks a rescue
    rule)."""
    clock = _time.perf_counter()
    kb, fb, mass = block_terms(system, state, dt)
    f_block = asm.scatter_vector(system.dof_map, np.arange(system.n), fb, system.n_unknowns)
    t = _terms(system, state, contacts, patches, start.shear)
    broken0 = start.broken.copy()
    m = _start(system, start, t)
    lin = _LinearSystem(system, kb, t, dt, bolt_links(system, state), state.workspace)
    max_changes = system.controls.max_open_close_iterations
    for it in range(1, FRICTION_ITERATIONS_PER_CHANGE * (max_changes + 1) + 1):
        was_sliding = m.mode == SLIDING
        cyc, clock = _cycle(system, state, t, m, lin, f_block, dt, clock)
        m.mode_changes += int(cyc.closed_changed)
        if m.mode_changes > max_changes:
            break
        m.fric_prev = cyc.fric
        m.mode, m.tangent, m.nstar = cyc.mode, cyc.tangent, cyc.nstar
        m.steady = 0 if cyc.changed else m.steady + 1
        if slide_dragged_anchors(t, m, cyc):
            continue
        if not _settled(m, cyc, was_sliding):
            continue
        if release_held_contacts(system, t, m, cyc):
            continue
        if lock_reversed_sliders(system, t, m, cyc, was_sliding):
            continue
        return _converged(system, state, contacts, t, m, cyc, mass, it, dt, patches, broken0)
    raise StepFailure(f"open-close iteration did not converge ({m.mode_changes} mode "
                      f"changes, {it} cycles)", "open_close")
