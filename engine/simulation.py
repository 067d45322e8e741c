"""DDA time stepping: the orchestrator of detect -> assemble -> open-close iterate -> update.

One step (THEORY.md "One step"): detect contacts at the start of the step, assemble the
block terms once, iterate contact modes (paper Tables 1 and 2) until they stop changing,
check the displacement limit, then move blocks with the exact rotation. When a step
cannot converge the time step is cut and the step redone; below the smallest allowed
time step the run stops with a clear status and keeps what was recorded.
"""

from __future__ import annotations

import dataclasses
import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from engine import assembly as asm
from engine._assembly_kernels import relative_displacement
from engine._motion_kernels import block_vertices, move_blocks
from engine._open_close_kernels import contact_loads, step_results, update_modes
from engine._open_close_kernels import initial_modes as _initial_modes
from engine.contacts import LOCKED, OPEN, SLIDING, ContactSet, assign_joint_materials
from engine.detection import detect_contacts
from engine.frame import Frame, Recorder
from engine.geometry import Polyhedron
from engine.model import Model
from engine.solver import BlockJacobi, SolveError, make_solver
from engine.tolerances import DEFAULT_TOLERANCES

STATUS_COMPLETED = "completed"
STATUS_FAILED = "failed"
STATUS_CANCELLED = "cancelled"

#: time-step cut factor when a step fails, and growth factor after easy steps
#: a step's displacement limit: this × the displacement its start velocities predict ...
SEARCH_SAFETY = 2.0
#: ... and at least this fraction of the model's step limit (blocks at rest)
SEARCH_FLOOR = 0.02
DT_CUT = 0.3
DT_GROW = 1.5
#: relative change of friction forces below which the open-close iteration has converged
FRICTION_RTOL = 1e-4
#: cycles allowed per mode change for the explicit friction forces to settle (no refactor)
FRICTION_ITERATIONS_PER_CHANGE = 6
#: after that many cycles without a mode change, a friction change below this is accepted:
#: the explicit friction fixed point of a large contact system can creep instead of converge
FRICTION_RTOL_STALLED = 1e-2
#: locked <-> sliding switches a contact may make in one step before its mode is kept
MAX_SHEAR_SWITCHES = 2
#: times a contact may open in one step before it is kept closed for the rest of the step
MAX_REOPENINGS = 2
#: a run whose contacts penetrated deeper than this fraction of the thinner block's
#: thickness says so in its summary: the penalty is soft for the loads, and the motion
#: carries an error of that order
SOFT_PENALTY_WARNING_RATIO = 0.01
#: a step whose capped sliding contact slips back against its friction by more than this
#: fraction of the step displacement limit is redone with a smaller time step (the
#: friction would push the blocks and create energy; measured on the stability map's pile)
FRICTION_REVERSAL_RATIO = 0.01
#: a converged step whose penalty springs release more than this fraction of the blocks'
#: kinetic energy (plus the round-off floor) that they never stored is redone with a
#: smaller time step
SPRING_ENERGY_RTOL = 1e-2


@dataclass
class Progress:
    """Progress of a run, for callbacks: step, simulated time (s), duration (s), Δt (s)."""

    step: int
    time: float
    duration: float
    dt: float

    @property
    def fraction(self) -> float:
        return min(1.0, self.time / self.duration) if self.duration > 0 else 1.0


def _row_keys(key: np.ndarray) -> np.ndarray:
    """Contact keys `(c, 4) int64` as one sortable scalar per row `(c,)` (bytes)."""
    k = np.ascontiguousarray(key, dtype=np.int64)
    return k.view(np.dtype((np.void, k.dtype.itemsize * k.shape[1]))).ravel()


@dataclass
class ContactMemory:
    """What the closed contacts carry to the next step (inherited modes, paper 2.4 (2)).

    One row per closed contact, sorted by key: `key (m, 4)`, `mode (m,)`, accumulated
    tangential displacement `shear (m, 3)` m, sliding direction `tangent (m, 3)`, and
    `broken (m,)` (cohesion and tensile strength lost).
    """

    key: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    mode: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    shear: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tangent: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    broken: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    gap: np.ndarray = field(default_factory=lambda: np.zeros(0))  # end-of-step gap (m)

    def __post_init__(self) -> None:
        order = np.argsort(_row_keys(self.key), kind="stable")
        for name in ("key", "mode", "shear", "tangent", "broken", "gap"):
            setattr(self, name, getattr(self, name)[order])
        self._sorted = _row_keys(self.key)

    def find(self, key: np.ndarray) -> np.ndarray:
        """Row of each key `(c, 4)` in the memory `(c,) int`, -1 where it is not there."""
        if len(self._sorted) == 0:
            return np.full(len(key), -1, dtype=np.int64)
        q = _row_keys(key)
        pos = np.minimum(np.searchsorted(self._sorted, q), len(self._sorted) - 1)
        return np.where(self._sorted[pos] == q, pos, -1)


@dataclass
class State:
    """Everything that changes from step to step."""

    centroid: np.ndarray  # (n, 3)
    affine: np.ndarray  # (n, 3, 3) x = c + A (X0 - c0)
    rotation: np.ndarray  # (n, 3, 3) accumulated rotation
    velocity: np.ndarray  # (n, 12)
    stress: np.ndarray  # (n, 6)
    time: float = 0.0
    step: int = 0
    memory: ContactMemory = field(default_factory=ContactMemory)
    energies: dict[str, float] = field(default_factory=lambda: {
        "gravity_work": 0.0, "external_work": 0.0, "friction_dissipation": 0.0,
        "numerical_dissipation": 0.0})


@dataclass
class StepResult:
    """The converged solution of one step."""

    d: np.ndarray  # (n, 12) block displacement increments
    contacts: ContactSet
    gap1: np.ndarray  # (c,) normal distance at the end of the step
    shear: np.ndarray  # (c, 3) shear spring stretch (locked) at the end
    slip: np.ndarray  # (c, 3) relative tangential displacement in the step
    normal_force: np.ndarray  # (c,) N, compression positive
    shear_force: np.ndarray  # (c, 3) N on block i
    friction_work: float
    iterations: int
    mode_changes: int = 0
    numerical_dissipation: float = 0.0  # J, of the implicit springs in this step
    broken: np.ndarray | None = None  # (c,) cohesion / tensile strength lost


@dataclass
class RunResult:
    """How a run ended and the final state."""

    status: str
    message: str
    state: State
    steps: int
    wall_time: float
    max_penetration: float
    summary: dict[str, Any]


class StepFailure(RuntimeError):
    """A step did not converge at this time step (the caller cuts Δt)."""


# --------------------------------------------------------------------------- helpers


def _rows_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _kinetic_energy(velocity: np.ndarray, mass: np.ndarray) -> float:
    """½ Σ vᵀ M v (J) of block velocities `(n, 12)` and masses `(n, 12, 12)`."""
    return 0.5 * float(np.sum(velocity * (mass @ velocity[:, :, None])[:, :, 0]))


class Simulation:
    """A DDA run of one model: holds constants and state, advances step by step."""

    def __init__(self, model: Model) -> None:
        self.model = model
        c = model.controls
        blocks = model.blocks
        n = len(blocks)
        self.n = n
        self.polys0 = [b.polyhedron for b in blocks]
        self.points0 = [p.vertices.copy() for p in self.polys0]
        self.c0 = np.array([p.centroid for p in self.polys0]).reshape(n, 3)
        #: all vertices stacked `(V, 3)` relative to their block centroid, and their block
        counts = [len(p) for p in self.points0]
        self._vertex_block = np.repeat(np.arange(n, dtype=np.int64), counts)
        self._vertex_start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self._vertex_rel0 = (np.concatenate(self.points0) - self.c0[self._vertex_block]
                             if n else np.zeros((0, 3)))
        self.volume0 = np.array([p.volume for p in self.polys0])
        self.second0 = np.array([p.second_moments for p in self.polys0]).reshape(n, 3, 3)
        self.density = np.array([model.materials[b.material].density for b in blocks])
        self.fixed = np.array([b.fixed for b in blocks], dtype=bool)
        self.elastic = c.block_model == "elastic"
        ndof = 12 if self.elastic else 6
        dof_map = np.full((n, 12), -1, dtype=np.int64)
        k = 0
        for b in range(n):
            if not self.fixed[b]:
                dof_map[b, :ndof] = np.arange(k, k + ndof)
                k += ndof
        self.dof_map = dof_map
        self.n_unknowns = k
        #: unknowns per free block, and each block's block row in K (-1 when fixed)
        self.ndof = ndof
        self.block_row = np.where(self.fixed, -1, dof_map[:, 0] // ndof)
        self.emat = np.array([
            asm.elastic_matrix(model.materials[b.material].young_modulus,
                               model.materials[b.material].poisson_ratio) for b in blocks
        ]).reshape(n, 6, 6)
        self.kn = float(c.penalty)
        self.ks = float(c.penalty * c.shear_penalty_ratio)
        self.kf = float(c.fixed_point_penalty or 10.0 * c.penalty)
        self.scale = model.scale
        thickness = np.array([2.0 * p.volume / max(p.face_areas.sum(), 1e-300)
                              for p in self.polys0])
        # thin blocks, fixed or not, bound the step so nothing tunnels through them: no
        # point moves more than half the width of the thinnest block in a step
        thin = min(p.width for p in self.polys0) if n else self.scale
        #: largest displacement of any point in one step (paper eq. 50 in spirit)
        self.max_step_displacement = min(c.max_displacement_ratio * self.scale, 0.5 * thin)
        self.search_distance = 2.0 * self.max_step_displacement
        #: search each step within its own predicted limit (:meth:`step_search`)
        self.adaptive_search = True
        #: blocks closer than this (m) touch: their contacts start closed (and bonded)
        self.touch_gap = DEFAULT_TOLERANCES.length("touching", self.scale)
        #: open-close hysteresis (m): the depth an open contact must penetrate to close
        #: (any tension opens a closed one: a threshold there would act as a bond)
        self.open_close_gap = c.open_close_tolerance * self.max_step_displacement
        #: block thickness 2 V / A (m); a contact may penetrate a fraction of the thinner one
        self.thickness = thickness
        self.radius = np.array([
            np.linalg.norm(p.vertices[p.surface_vertex_ids] - p.centroid, axis=1).max()
            for p in self.polys0
        ])
        self.tan_phi = np.array([np.tan(j.friction_angle_rad) for j in model.joint_materials])
        self.cohesion = np.array([j.cohesion for j in model.joint_materials])
        self.tension = np.array([j.tensile_strength for j in model.joint_materials])
        #: contact patch areas matter only where joints have cohesion or tensile strength
        self.needs_areas = bool(np.any(self.cohesion > 0) or np.any(self.tension > 0))
        self.loads_ref = [(ld.block, np.asarray(ld.point, float), np.asarray(ld.force, float))
                          for ld in model.point_loads]
        self.fixed_ref = [(fp.block, np.asarray(fp.point, float)) for fp in model.fixed_points]
        v0 = np.zeros((n, 12))
        for b, blk in enumerate(blocks):
            if not self.fixed[b]:
                v0[b, :6] = np.asarray(blk.velocity, float)[:6]
        self.state = State(
            centroid=self.c0.copy(),
            affine=np.repeat(np.eye(3)[None], n, axis=0),
            rotation=np.repeat(np.eye(3)[None], n, axis=0),
            velocity=v0,
            stress=np.zeros((n, 6)),
        )
        self.dt = float(c.time_step)
        #: the last accepted step and its time step
        self.last: StepResult | None = None
        self.last_dt = self.dt
        self.max_penetration = 0.0
        #: deepest penetration seen / thickness of the thinner block of that contact
        self.max_penetration_ratio = 0.0
        #: contacts found already deeply penetrating and relaxed (see plausible_gaps)
        self.relaxed_contacts = 0
        #: J: energy differences below this are round-off (1e-6 of the model's potential
        #: energy scale or of a spring pressed by a whole step limit)
        vol0 = np.array([p.volume for p in self.polys0])
        self.energy_floor = 1e-6 * max(
            float(np.sum((self.density * vol0)[~self.fixed]))
            * float(np.linalg.norm(model.gravity))
            * self.scale, 0.5 * self.kn * self.max_step_displacement**2)
        #: wall time (s) per phase: detection, assembly, solve, open_close, update, output
        self.timings: dict[str, float] = {}
        self._mass_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ geometry
    def map_point(self, b: int, point0: np.ndarray) -> np.ndarray:
        """Current position of a material point given at its initial position."""
        s = self.state
        return s.centroid[b] + s.affine[b] @ (point0 - self.c0[b])

    def current_vertices(self) -> np.ndarray:
        """Current positions `(V, 3)` of all blocks' vertices, stacked in block order."""
        s = self.state
        return block_vertices(s.centroid, s.affine, self._vertex_block, self._vertex_rel0)

    def current_polyhedra(self) -> list[Polyhedron]:
        """The blocks as polyhedra at the current state."""
        pts = np.split(self.current_vertices(), self._vertex_start[1:])
        return [p.moved(x) for p, x in zip(self.polys0, pts, strict=True)]

    def mass_properties(self) -> tuple[np.ndarray, np.ndarray]:
        """Current volume `(n,)` and second moments `(n, 3, 3)` (affine images of the initial;
        computed once per state: the step replaces the affine array)."""
        a = self.state.affine
        hit = self._mass_cache
        if hit is not None and hit[0] is a:
            return hit[1], hit[2]
        det = np.linalg.det(a)
        vol = self.volume0 * det
        second = det[:, None, None] * (a @ self.second0 @ np.transpose(a, (0, 2, 1)))
        self._mass_cache = (a, vol, second)
        return vol, second

    # ------------------------------------------------------------------ contacts
    def detect(self, search: float | np.ndarray | None = None) -> ContactSet:
        """Contacts within `search` m (default :attr:`search_distance`; or each block's
        reach, see :func:`detect_contacts`) at the start of the step, with their joint
        materials."""
        contacts = detect_contacts(self.polys0, self.search_distance if search is None
                                   else search, active=~self.fixed,
                                   vertices=self.current_vertices())
        m = self.model
        assign_joint_materials(contacts, m.default_joint_material, m.joint_material_of_tag,
                               m.pair_joint_material)
        return contacts

    @staticmethod
    def contact_areas(contacts: ContactSet) -> np.ndarray:
        """Each constraint's share `(c,)` m² of its contact patch.

        Constraints of one block pair with a common plane form a patch; its area is the
        area of the convex hull of their points in that plane, shared equally. Fewer than
        three points (edge or vertex contacts) carry no area.
        """
        out = np.zeros(len(contacts))
        if not len(contacts):
            return out
        key = np.column_stack([contacts.block_i, contacts.block_j,
                               np.round(contacts.normal * 1e6)]).astype(np.int64)
        _, group = np.unique(key, axis=0, return_inverse=True)
        group = group.ravel()
        for g in np.unique(group):
            idx = np.flatnonzero(group == g)
            if len(idx) < 3:
                continue
            nrm = contacts.normal[idx[0]]
            u = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
            u /= np.linalg.norm(u)
            v = np.cross(nrm, u)
            p = contacts.point_j[idx]
            pts = np.column_stack([p @ u, p @ v])
            try:
                area = ConvexHull(pts).volume
            except QhullError:
                area = 0.0
            out[idx] = area / len(idx)
        return out

    # ------------------------------------------------------------------ one step
    def block_terms(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Block stiffness `(n, d, d)` and block forces `(n, 12)` on the d = 6 (rigid) or
        12 (elastic) unknowns of each block, and the mass `(n, 12, 12)`."""
        s = self.state
        nd = self.ndof
        vol, second = self.mass_properties()
        mass = asm.mass_matrices(self.density, vol, second)
        kb = mass[:, :nd, :nd] * (2.0 / dt**2)
        fb = (mass @ s.velocity[:, :, None])[:, :, 0]
        fb *= 2.0 / dt
        fb[:, :3] += (self.density * vol)[:, None] * self.model.gravity[None]
        if self.elastic:
            kb[:, 6:, 6:] += vol[:, None, None] * self.emat
            fb[:, 6:] -= vol[:, None] * s.stress
        for b, p0, f in self.loads_ref:
            t = asm.displacement_matrices(self.map_point(b, p0)[None], s.centroid[b][None])[0]
            fb[b] += t.T @ f
        for b, p0 in self.fixed_ref:
            p = self.map_point(b, p0)
            t = asm.displacement_matrices(p[None], s.centroid[b][None])[0]
            kb[b] += self.kf * (t.T @ t)[:nd, :nd]
            fb[b] -= self.kf * t.T @ (p - p0)
        return kb, fb, mass

    def plausible_gaps(self, contacts: ContactSet) -> int:
        """Start no spring with energy it never stored; returns how many contacts were
        found implausibly deep (detection artefacts).

        Blocks end a step with the penetrations of its converged contacts, and the next
        step starts from those positions: a contact of a block pair cannot start deeper
        than that pair's deepest penetration at the end of the last step (twice it, plus
        a slack of 1e-6 × the model size). A deeper one is a detection artefact (features
        passing each other at a convex edge). A contact found again starts no deeper than
        it ended (plus the exact rotation's second-order shift of its points), where
        re-detection picks a different plane (vertex-vertex, vertex-edge); one that ended
        open (pressed in within the open-close hysteresis) stored nothing and starts
        unstretched. A penalty spring started deeper would push the blocks apart with
        energy from nowhere; its initial gap is limited to the plausible depth.
        """
        s = self.state
        if s.step == 0 or not len(contacts):
            return 0
        if not np.any(contacts.gap < 0):
            return 0
        mem = s.memory
        n = self.n
        slack = 1e-6 * self.scale
        plausible = np.full(len(contacts), slack)  # beyond it: an artefact (counted)
        if len(mem.key):
            pair_keys = mem.key[:, 0] * n + mem.key[:, 2]
            uniq, inv = np.unique(pair_keys, return_inverse=True)
            pair_prev = np.zeros(len(uniq))
            np.maximum.at(pair_prev, inv.ravel(), np.maximum(-mem.gap, 0.0))
            q = contacts.block_i * n + contacts.block_j
            pos = np.minimum(np.searchsorted(uniq, q), len(uniq) - 1)
            found = uniq[pos] == q
            plausible[found] += 2.0 * pair_prev[pos[found]]
        allowed = plausible.copy()  # the depth a spring may start at
        row = mem.find(contacts.key)
        again = row >= 0
        if np.any(again) and self.last is not None:
            turn = np.linalg.norm(self.last.d[:, 3:6], axis=1) ** 2 * self.radius
            second = 0.5 * (turn[contacts.block_i] + turn[contacts.block_j])
            r = row[again]
            stored = np.where(mem.mode[r] != OPEN, np.maximum(-mem.gap[r], 0.0), 0.0)
            own = second[again] + stored
            plausible[again] = np.minimum(plausible[again], slack + own)
            allowed[again] = np.minimum(allowed[again], self.touch_gap + own)
        artefacts = int(np.sum(contacts.gap < -plausible))
        deep = contacts.gap < -allowed
        contacts.gap[deep] = -allowed[deep]
        return artefacts

    def initial_modes(self, contacts: ContactSet, dt: float) -> tuple[np.ndarray, ...]:
        """Modes, accumulated shear, tangents and broken bonds at the start of the step.

        Inherited from the previous step for the same closed contact, else the paper's
        Table 1 from the penetration and the relative tangential velocity, where blocks
        that already touch (cut blocks, stacked blocks) start closed so a resting mass
        carries its weight from the first cycle instead of closing one layer of contacts
        per open-close iteration. Joints are bonded (cohesion, tensile strength) where
        blocks touch at the start; a contact that forms later has only friction.
        """
        s = self.state
        mem = s.memory
        jm = contacts.joint_material
        return _initial_modes(
            contacts.block_i, contacts.block_j, contacts.point_i, contacts.point_j,
            contacts.normal, contacts.gap, s.centroid, s.velocity, mem.find(contacts.key),
            mem.mode, mem.shear, mem.tangent, mem.broken, self.tan_phi[jm],
            (self.cohesion[jm] > 0) | (self.tension[jm] > 0), s.step == 0, self.touch_gap,
            dt, self.kn, self.ks)

    def solve_step(self, contacts: ContactSet, dt: float, areas: np.ndarray) -> StepResult:
        """Open-close iteration for one step at time step `dt` (raises StepFailure)."""
        s = self.state
        clock = _time.perf_counter()
        kb, fb, mass = self.block_terms(dt)
        nu = self.n_unknowns
        nd = self.ndof
        f_block = asm.scatter_vector(self.dof_map, np.arange(self.n), fb, nu)
        c = len(contacts)
        mode, shear0, tangent, broken = self.initial_modes(contacts, dt)
        # locked <-> sliding switches per contact in this step; a contact that switched
        # twice keeps its shear mode for the rest of the step (no flip-flop)
        switches = np.zeros(len(contacts), dtype=np.int64)
        reopenings = np.zeros(len(contacts), dtype=np.int64)
        forced = np.zeros(len(contacts), dtype=bool)  # capped sliding contacts locked
        released = np.zeros(len(contacts), dtype=bool)  # capped closed contacts opened
        bi, bj = contacts.block_i, contacts.block_j
        n = contacts.normal
        d0 = contacts.gap
        # T at the contact points, only the columns that are unknowns (6 for rigid blocks)
        ti = np.ascontiguousarray(
            asm.displacement_matrices(contacts.point_i, s.centroid[bi])[:, :, :nd])
        tj = np.ascontiguousarray(
            asm.displacement_matrices(contacts.point_j, s.centroid[bj])[:, :, :nd])
        dmap = np.ascontiguousarray(self.dof_map[:, :nd])
        tan_phi = self.tan_phi[contacts.joint_material]
        cohesion_force = self.cohesion[contacts.joint_material] * areas
        tension_force = self.tension[contacts.joint_material] * areas
        # friction normal distance d_n* (paper eq. 30): start of step, then last cycle
        dstar = np.minimum(d0, 0.0)
        offset = np.zeros((c, 3))  # revised contact point shift for contacts closing (eq. 47)
        solver = None
        jacobi = BlockJacobi()
        plan: asm.SystemPlan | None = None
        solver_key: tuple[bytes, bytes] | None = None
        x = None
        fric_prev = np.zeros((c, 3))
        max_changes = self.model.controls.max_open_close_iterations
        mode_changes = 0
        steady = 0  # consecutive cycles without a mode change
        for it in range(1, FRICTION_ITERATIONS_PER_CHANGE * (max_changes + 1) + 1):
            closed = mode != OPEN
            locked = mode == LOCKED
            sliding = mode == SLIDING
            key = (closed.tobytes(), locked.tobytes())
            if solver is None or key != solver_key:
                if plan is None:
                    plan = asm.plan_system(self.block_row, kb, bi, bj, ti, tj, n)
                k, kdiag = plan.matrix(self.kn * closed, self.ks * locked)
                clock = self._tick("assembly", clock)
                try:
                    solver = make_solver(k, nd, kdiag, jacobi, plan.coupled)
                except SolveError as exc:
                    raise StepFailure(str(exc)) from exc
                solver_key = key
            # contact forces on block i (on j the opposite), as generalized loads
            f = f_block.copy()
            fric_mag, fric = contact_loads(f, dmap, bi, bj, ti, tj, n, d0, mode, shear0,
                                           offset, tangent, dstar, tan_phi, self.kn, self.ks)
            clock = self._tick("assembly", clock)
            try:
                x = solver(f, x)
            except SolveError as exc:
                raise StepFailure(str(exc)) from exc
            clock = self._tick("solve", clock)
            dr = relative_displacement(x, dmap, bi, bj, ti, tj)
            # ---- update modes (paper Table 2)
            (new_mode, new_tangent, new_dstar, d1, dr_t, along, changed, closed_changed,
             fric_change) = update_modes(
                d0, n, dr, shear0, offset, mode, tangent, broken, reopenings, switches,
                tan_phi, tension_force, cohesion_force, fric_mag, fric_prev, self.kn,
                self.ks, self.open_close_gap, MAX_REOPENINGS, MAX_SHEAR_SWITCHES)
            # the iteration converges on open / closed (paper 4.3); locked <-> sliding
            # changes iterate too but are bounded per contact (MAX_SHEAR_SWITCHES)
            mode_changes += int(closed_changed)
            clock = self._tick("open_close", clock)
            if mode_changes > max_changes:
                break
            fric_prev = fric
            mode, tangent, dstar = new_mode, new_tangent, new_dstar
            steady = 0 if changed else steady + 1
            settled = fric_change <= FRICTION_RTOL or (
                steady >= FRICTION_ITERATIONS_PER_CHANGE and fric_change <= FRICTION_RTOL_STALLED)
            if not changed and (settled or not np.any(sliding)):
                # contacts kept closed by the reopening cap must not end pulling the blocks
                # together: that would be a bond the joint does not have
                allow_tension = np.where(broken, 0.0, tension_force)
                held = (mode != OPEN) & (reopenings >= MAX_REOPENINGS) & (
                    -self.kn * d1 < -allow_tension - self.kn * self.open_close_gap)
                if np.any(held & ~released):
                    # open them once more (the cap had kept them closed) and iterate on;
                    # a contact held again after that stops the step
                    free_now = held & ~released
                    mode = mode.copy()
                    mode[free_now] = OPEN
                    dstar = np.where(free_now, 0.0, dstar)
                    reopenings[free_now] = 0
                    released |= free_now
                    continue
                if np.any(held):
                    raise StepFailure(
                        f"open-close iteration did not settle: {int(held.sum())} contact(s) "
                        "kept closing and opening")
                # nor may a sliding contact kept by the switch cap slip against its friction
                # force: the friction would then push the blocks and create energy
                driven = sliding & (switches >= MAX_SHEAR_SWITCHES) & (
                    along < -FRICTION_REVERSAL_RATIO * self.max_step_displacement)
                if np.any(driven & ~forced):
                    # Table 2: a slip that reverses locks the contact; the switch cap
                    # had kept it sliding. Lock it (for the rest of the step, continuing
                    # from its friction force) and iterate on, instead of cutting Δt
                    lock = driven & ~forced
                    mode = mode.copy()
                    mode[lock] = LOCKED
                    offset[lock] = (fric_mag[lock, None] / self.ks * tangent[lock]
                                    - dr_t[lock] - shear0[lock])
                    forced |= lock
                    continue
                if np.any(driven):
                    raise StepFailure(
                        f"open-close iteration did not settle: {int(driven.sum())} sliding "
                        "contact(s) reversed against their friction")
                nf, sf, shear1, fw, num = step_results(
                    d0, d1, n, shear0, offset, dr, dr_t, mode, tangent, fric, fric_mag,
                    self.kn, self.ks)
                d = np.zeros((self.n, 12))
                m = self.dof_map >= 0
                d[m] = x[self.dof_map[m]]
                num += self._block_dissipation(d)
                # the implicit springs only take energy out; one that gives some back (a
                # spring re-locked with an offset from an earlier cycle of a fast step) would
                # accelerate the blocks: redo the step smaller
                kinetic = _kinetic_energy(s.velocity, mass)
                if -num > SPRING_ENERGY_RTOL * kinetic + self.energy_floor:
                    raise StepFailure(
                        f"open-close iteration settled with springs that release {-num:.3g} J "
                        "they never stored")
                return StepResult(
                    d=d, contacts=_with_modes(contacts, mode, tangent),
                    gap1=d1, shear=shear1, slip=dr_t,
                    normal_force=nf, shear_force=sf, friction_work=fw, iterations=it,
                    mode_changes=mode_changes, numerical_dissipation=num, broken=broken,
                )
        raise StepFailure(
            f"open-close iteration did not converge ({mode_changes} mode changes, "
            f"{it} cycles)"
        )

    def _block_dissipation(self, d: np.ndarray) -> float:
        """½ dᵀ K d of the implicit elastic and fixed-point springs in a step (J)."""
        out = 0.0
        if self.elastic:
            vol, _ = self.mass_properties()
            out += 0.5 * float(np.einsum("ni,nij,nj->", d[:, 6:],
                                         vol[:, None, None] * self.emat, d[:, 6:]))
        for b, p0 in self.fixed_ref:
            t = asm.displacement_matrices(self.map_point(b, p0)[None],
                                          self.state.centroid[b][None])[0]
            r = t @ d[b]
            out += 0.5 * self.kf * float(r @ r)
        return out

    def check_penetration(self, res: StepResult) -> None:
        """StepFailure if a closed contact penetrates deeper than its allowed share
        (`max_penetration_ratio`) of the thinner of its two blocks: nothing tunnels."""
        cs = res.contacts
        if not len(cs):
            return
        limit = self.model.controls.max_penetration_ratio * np.minimum(
            self.thickness[cs.block_i], self.thickness[cs.block_j])
        excess = np.where(cs.mode != OPEN, -res.gap1 - limit, -np.inf)
        k = int(np.argmax(excess))
        if excess[k] > 0:
            raise StepFailure(
                f"penetration {-res.gap1[k]:.3g} m between blocks {cs.block_i[k]} and "
                f"{cs.block_j[k]} exceeds the limit {limit[k]:.3g} m")

    def _tick(self, phase: str, since: float) -> float:
        """Add the wall time since `since` to `phase` of :attr:`timings`; return now."""
        now = _time.perf_counter()
        self.timings[phase] = self.timings.get(phase, 0.0) + now - since
        return now

    def step_limit(self, dt: float) -> np.ndarray:
        """Each block's displacement limit `(n,)` m for the next step: SEARCH_SAFETY × what
        its velocity, gravity and loads predict for a step of `dt`, within [SEARCH_FLOOR,
        1] × :attr:`max_step_displacement` (0 for fixed blocks). A block that moves further
        is detected again with a larger limit, at the same Δt (:meth:`step`)."""
        if not self.adaptive_search:
            return np.where(self.fixed, 0.0, self.max_step_displacement)
        accel = np.full(self.n, float(np.linalg.norm(self.model.gravity)))
        if self.loads_ref:
            mass = self.density * self.mass_properties()[0]
            for b, _, f in self.loads_ref:
                accel[b] += float(np.linalg.norm(f)) / mass[b]
        pred = self.point_displacements(self.state.velocity * dt) + accel * dt**2
        limit = np.clip(SEARCH_SAFETY * pred, SEARCH_FLOOR * self.max_step_displacement,
                        self.max_step_displacement)
        return np.where(self.fixed, 0.0, limit)

    def step_search(self, limit: np.ndarray) -> np.ndarray:
        """Each block's contact search reach `(n,)` m for a step whose points move at most
        `limit (n,)`: a block pair is searched within the sum of its two reaches. A
        block's reach is its limit, and at least the deepest penetration its contacts
        ended the last step with (detection keeps penetrations down to about -2 × the
        pair's search, so no contact is lost); half the model's full
        :attr:`search_distance` on the first step, whose overlaps are the user's. A
        falling pile then looks for millimetres around each block, not for 1 % of the
        model's size, and a fast block does not widen the search of the others."""
        half = 0.5 * self.search_distance
        if not self.adaptive_search or self.last is None:
            return np.full(self.n, half)
        deepest = np.zeros(self.n)
        gap = self.last.gap1
        if len(gap):
            depth = np.maximum(-gap, 0.0)
            np.maximum.at(deepest, self.last.contacts.block_i, depth)
            np.maximum.at(deepest, self.last.contacts.block_j, depth)
        return np.minimum(np.maximum(limit, deepest), half)

    def point_displacements(self, d: np.ndarray) -> np.ndarray:
        """Bound `(n,)` on the largest displacement of any point of each block in the
        step (m) for block displacements `d (n, 12)`."""
        trans = np.linalg.norm(d[:, :3], axis=1)
        rot = np.linalg.norm(d[:, 3:6], axis=1) * self.radius
        strain = np.abs(d[:, 6:]).max(axis=1) * 2.0 * self.radius
        return trans + rot + strain

    def advance(self, res: StepResult, dt: float) -> None:
        """Move the blocks (exact rotation), update velocities, stresses and contact memory."""
        s = self.state
        d = res.d
        vol, _ = self.mass_properties()
        weight = (self.density * vol)[:, None] * self.model.gravity[None]
        s.energies["gravity_work"] += float(np.sum(weight * d[:, :3]))
        for b, p0, f in self.loads_ref:
            t = asm.displacement_matrices(self.map_point(b, p0)[None], s.centroid[b][None])[0]
            s.energies["external_work"] += float(f @ (t @ d[b]))
        s.energies["friction_dissipation"] += res.friction_work
        s.energies["numerical_dissipation"] += res.numerical_dissipation
        s.centroid, s.affine, s.rotation = (s.centroid.copy(), s.affine.copy(),
                                            s.rotation.copy())
        move_blocks(d, s.centroid, s.affine, s.rotation)
        v1 = 2.0 * d / dt - s.velocity
        v1[self.fixed] = 0.0
        s.velocity = self.model.controls.dynamic_ratio * v1
        if self.elastic:
            s.stress = s.stress + np.einsum("nij,nj->ni", self.emat, d[:, 6:])
        # contact memory for the next step: closed contacts, broken ones (stay broken) and
        # open ones pressed in within the open-close hysteresis (their springs start the
        # next step unstretched, see plausible_gaps)
        cs = res.contacts
        broken = res.broken if res.broken is not None else np.zeros(len(cs), dtype=bool)
        keep = (cs.mode != OPEN) | broken | (res.gap1 < 0)
        slip = res.slip[keep]
        slip_norm = np.linalg.norm(slip, axis=1)
        # sliding direction for the next step: this step's slip (paper eq. 7)
        big = slip_norm > 1e-14 * self.scale
        tangent = np.where(big[:, None], slip / np.maximum(slip_norm, 1e-300)[:, None],
                           cs.tangent[keep])
        # a contact that slid or ended open has lost its bond (cohesion, tensile strength)
        memory = ContactMemory(key=cs.key[keep], mode=cs.mode[keep], shear=res.shear[keep],
                               tangent=tangent, broken=broken[keep] | (cs.mode[keep] != LOCKED),
                               gap=res.gap1[keep])
        s.memory = memory
        s.time += dt
        s.step += 1
        closed = cs.mode != OPEN
        pen = float(np.max(-res.gap1[closed], initial=0.0))
        self.max_penetration = max(self.max_penetration, pen)
        if np.any(closed):
            thin = np.minimum(self.thickness[cs.block_i], self.thickness[cs.block_j])
            ratio = float(np.max(-res.gap1[closed] / thin[closed], initial=0.0))
            self.max_penetration_ratio = max(self.max_penetration_ratio, ratio)

    def step(self) -> StepResult:
        """Advance one step, cutting Δt as needed (raises StepFailure below the minimum)."""
        c = self.model.controls
        remaining = c.duration - self.state.time
        dt = min(self.dt, remaining) if remaining > 0 else self.dt
        limit = self.step_limit(dt)
        contacts, areas = self._contacts_within(self.step_search(limit))
        reason = ""
        while dt >= c.min_time_step:
            try:
                res = self.solve_step(contacts, dt, areas)
                disp = self.point_displacements(res.d)
                over = disp > limit
                wider = over & (limit < self.max_step_displacement)
                if np.any(wider):
                    # blocks moved further than predicted: search again, wider, same Δt
                    limit = np.where(wider, np.minimum(np.maximum(SEARCH_SAFETY * disp,
                                                                  2.0 * limit),
                                                       self.max_step_displacement), limit)
                    contacts, areas = self._contacts_within(self.step_search(limit))
                    continue
                if np.any(over):
                    b = int(np.argmax(disp - limit))
                    raise StepFailure(
                        f"largest displacement {disp[b]:.3g} m (block {b}) exceeds the step "
                        f"limit {limit[b]:.3g} m")
                self.check_penetration(res)
            except StepFailure as exc:
                reason = str(exc)
                dt *= DT_CUT
                continue
            clock = _time.perf_counter()
            self.advance(res, dt)
            self._tick("update", clock)
            if dt < self.dt and dt < remaining:
                self.dt = dt  # remember the cut; grow back after easy steps
            elif res.mode_changes <= c.max_open_close_iterations // 2:
                self.dt = min(c.time_step, self.dt * DT_GROW)
            self.last = res
            self.last_dt = dt
            return res
        raise StepFailure(
            f"step {self.state.step + 1} at t = {self.state.time:.6g} s did not converge even "
            f"at the smallest time step {c.min_time_step:g} s: {reason}")

    def _contacts_within(self, reach: np.ndarray) -> tuple[ContactSet, np.ndarray]:
        """Contacts of the step within the blocks' `reach (n,)` m (:meth:`step_search`;
        depths made plausible) and their areas."""
        clock = _time.perf_counter()
        contacts = self.detect(reach)
        self.relaxed_contacts += self.plausible_gaps(contacts)
        self._tick("detection", clock)
        areas = (self.contact_areas(contacts) if self.needs_areas
                 else np.zeros(len(contacts)))
        return contacts, areas

    # ------------------------------------------------------------------ output
    def energies(self, res: StepResult | None) -> dict[str, float]:
        s = self.state
        vol, second = self.mass_properties()
        mass = asm.mass_matrices(self.density, vol, second)
        kinetic = _kinetic_energy(s.velocity, mass)
        contact = 0.0
        if res is not None and len(res.contacts):
            closed = res.contacts.mode != OPEN
            contact = 0.5 * self.kn * float(np.sum(res.gap1[closed] ** 2))
            contact += 0.5 * self.ks * float(np.sum(res.shear**2))
        elastic = 0.0
        if self.elastic:
            comp = np.linalg.solve(self.emat, s.stress[:, :, None])[:, :, 0]
            elastic = 0.5 * float(np.sum(vol * _rows_dot(s.stress, comp)))
        return {"kinetic": kinetic, "elastic": elastic, "contact": contact, **s.energies}

    def frame(self, res: StepResult | None, dt: float) -> Frame:
        s = self.state
        rv = Rotation.from_matrix(s.rotation).as_rotvec().reshape(self.n, 3)
        f = Frame(
            step=s.step, time=s.time, dt=dt,
            open_close_iterations=res.iterations if res else 0,
            max_penetration=float(np.max(-res.gap1[res.contacts.mode != OPEN], initial=0.0))
            if res is not None and len(res.contacts) else 0.0,
            centroids=s.centroid.copy(), affine=s.affine.copy(), rotation=rv,
            velocity=s.velocity.copy(), stress=s.stress.copy(), energies=self.energies(res),
        )
        if res is not None and self.model.controls.record_contacts:
            f.contacts = res.contacts
            f.normal_force = res.normal_force
            f.shear_force = res.shear_force
        return f

    def summary(self, status: str, message: str, wall: float) -> dict[str, Any]:
        s = self.state
        rv = Rotation.from_matrix(s.rotation).as_rotvec().reshape(self.n, 3)
        blocks = []
        for b, blk in enumerate(self.model.blocks):
            blocks.append({
                "name": blk.name or f"block{b}",
                "centroid": s.centroid[b].tolist(),
                "rotation": rv[b].tolist(),
                "displacement": (s.centroid[b] - self.c0[b]).tolist(),
                "velocity": s.velocity[b, :6].tolist(),
            })
        return {
            "status": status, "message": message, "steps": s.step,
            "simulated_time": s.time, "wall_time": wall,
            "max_penetration": self.max_penetration, "warnings": self.warnings(),
            "blocks": blocks,
        }

    def warnings(self) -> list[str]:
        """What the user should know about a run that did complete (soft penalty...)."""
        out = []
        if self.max_penetration_ratio > SOFT_PENALTY_WARNING_RATIO:
            out.append(
                f"contacts penetrated up to {self.max_penetration:.3g} m "
                f"({self.max_penetration_ratio:.1%} of the thinner block): the penalty "
                f"{self.kn:.3g} N/m is soft for these loads and displacements carry an "
                "error of that order; raise analysis.penalty")
        return out


def _with_modes(contacts: ContactSet, mode: np.ndarray, tangent: np.ndarray) -> ContactSet:
    """`contacts` with the converged modes and tangents (the other arrays shared: nothing
    writes to a step's contacts after detection)."""
    return dataclasses.replace(contacts, mode=mode.astype(np.int8), tangent=tangent)


def run(
    model: Model,
    recorder: Recorder | None = None,
    progress: Callable[[Progress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    scene_json: str | None = None,
) -> RunResult:
    """Run `model` to its duration; record frames; never return NaN or silently wrong results.

    Status is `completed`, `cancelled` (should_stop returned True) or `failed` (a step
    could not converge at the smallest time step, or the state became non-finite).
    """
    start = _time.perf_counter()
    sim = Simulation(model)
    c = model.controls
    if recorder is not None:
        recorder.begin(model, scene_json)
        recorder.record(sim.frame(None, sim.dt))
    status, message = STATUS_COMPLETED, ""
    res = None
    eps = 1e-12 * max(c.duration, 1.0)
    try:
        while sim.state.time < c.duration - eps:
            if should_stop is not None and should_stop():
                status, message = STATUS_CANCELLED, "cancelled by request"
                break
            try:
                res = sim.step()
            except StepFailure as exc:
                status, message = STATUS_FAILED, str(exc)
                break
            s = sim.state
            if not (np.all(np.isfinite(s.centroid)) and np.all(np.isfinite(s.velocity))):
                status = STATUS_FAILED
                message = f"non-finite state at step {s.step}; stopped"
                break
            last = sim.state.time >= c.duration - eps
            if recorder is not None and (s.step % c.record_interval == 0 or last):
                clock = _time.perf_counter()
                recorder.record(sim.frame(res, sim.last_dt))
                sim._tick("output", clock)
            if progress is not None:
                progress(Progress(s.step, s.time, c.duration, sim.last_dt))
    finally:
        wall = _time.perf_counter() - start
        summary = sim.summary(status, message, wall)
        summary["timings"] = dict(sim.timings)
        summary["relaxed_contacts"] = sim.relaxed_contacts
        if recorder is not None:
            recorder.end(status, message, summary)
    return RunResult(status, message, sim.state, sim.state.step, wall, sim.max_penetration,
                     summary)
