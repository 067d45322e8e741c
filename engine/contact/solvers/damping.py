"""Damping the ring and the rebound, not the motion: dashpots after the step at closed
contacts whose relative velocity reversed in it, or that part while their spring presses.

DDA's integrator (velocities `2 d / Δt − v0`, β = ½, γ = 1) leaves an oscillation faster
than the step resolves — a stiff penalty spring's — undamped: it rings at the step's own
frequency, velocities flipping sign every step, and a block resting on its contacts rocks
and walks down a slope its friction should hold. The normal dashpots inside the solve
(`open_close.contact_damping`) cannot stop it: they act on the step's mean velocity, which
a ring keeps near zero. And a penalty spring that gives back as motion the energy it
stored makes a block rebound by an amount that depends on the penalty, a numerical
choice: a stiff spring rebounds in one step (restitution ~1), a soft one over many, damped
by the dashpots (~0.4 at ζ 0.5). Here, after the converged step, closed contacts get
their dashpots again, implicitly on the end velocities — `(M + Δt Jᵀ C J) v = M v1`, J
their relative velocity — normally where the relative velocity reversed or the blocks part
while the spring still presses (an impact is plastic, whatever the penalty), and
tangentially where a locked contact's slip reversed, toward the step's mean slip rate (a
ring about a drift keeps the drift). That kills a ring at any stiffness (c Δt ≫ m) and
moves no block. A contact moving one way through the step (a column starting to topple, a
block sliding) keeps its tangential motion: a dashpot on it would act as viscous static
friction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from engine.contact.constraints import LOCKED, OPEN, ContactSet
from engine.contact.solution import StepResult
from engine.contact.solvers.open_close import contact_damping
from engine.dynamics import assembly as asm
from engine.dynamics.block_terms import kinetic_energy
from engine.dynamics.motion import mass_matrices
from engine.dynamics.solver import BlockJacobi, SolveError, make_solver
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem
from engine.geometry._transform_kernels import point_motions
from engine.status import StepFailure

#: passes that scale down the dashpots that would pull or beat friction
MAX_DAMPING_PASSES = 4


@dataclass
class _Points:
    """The closed contacts a step's dashpots act on: blocks, points, normals, modes and
    joint materials `(r, ...)` (rows of the step's ContactSet)."""

    block_i: np.ndarray
    block_j: np.ndarray
    point_i: np.ndarray
    point_j: np.ndarray
    normal: np.ndarray
    mode: np.ndarray
    joint_material: np.ndarray

    def __len__(self) -> int:
        return len(self.block_i)

    @classmethod
    def of(cls, cs: ContactSet | _Points, rows: np.ndarray) -> _Points:
        """The contacts `rows` of `cs`."""
        return cls(cs.block_i[rows], cs.block_j[rows], cs.point_i[rows], cs.point_j[rows],
                   cs.normal[rows], cs.mode[rows], cs.joint_material[rows])


def _relative_velocity(before: State, sub: ContactSet | _Points, v: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Relative velocity of block i's contact point to block j's for block velocities
    `v (n, 12)` at the step's start geometry: normal `(c,)` m/s (positive: parting) and
    tangential `(c, 3)` m/s."""
    bi, bj = sub.block_i, sub.block_j
    rel = (point_motions(sub.point_i, before.centroid[bi], v[bi])
           - point_motions(sub.point_j, before.centroid[bj], v[bj]))
    vn = np.einsum("ij,ij->i", rel, sub.normal)
    return vn, rel - vn[:, None] * sub.normal


def ringing(before: State, sub: ContactSet | _Points, v1: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Which closed contacts get their dashpots after the step `(c,) bool`, normally and
    tangentially: normally where the relative velocity at the step's end, `v1 (n, 12)`,
    points against the one at its start (a ring, a landing) or the blocks part (the spring
    giving back what it stored: a rebound); tangentially where the slip reversed (a ring of
    the shear spring). A contact sliding or rolling one way through the step is not."""
    vn0, vt0 = _relative_velocity(before, sub, before.velocity)
    vn1, vt1 = _relative_velocity(before, sub, v1)
    return (vn0 * vn1 < 0.0) | (vn1 > 0.0), np.einsum("ij,ij->i", vt0, vt1) < 0.0


@dataclass
class _Dashpots:
    """The ringing contacts' dashpots after a step: `sub` the contacts, `plan` M + Δt Jᵀ C J,
    `ti`, `tj (r, 3, d)` T at their points, `rhs` M v0 on the unknowns, their dashpots `cn`,
    `cshear (r,)` N·s/m and force limits `pressed`, `headroom (r,)` N."""

    system: BlockSystem
    before: State
    sub: _Points
    plan: asm.SystemPlan
    ti: np.ndarray
    tj: np.ndarray
    rhs: np.ndarray
    v0: np.ndarray
    cn: np.ndarray
    cshear: np.ndarray
    pressed: np.ndarray
    headroom: np.ndarray
    dt: float
    #: the block-Jacobi inverses, kept across the passes: only the rows whose dashpots
    #: changed are inverted again (the others are M's blocks)
    jacobi: BlockJacobi = field(default_factory=BlockJacobi)

    def velocities(self, v_target: np.ndarray) -> np.ndarray:
        """End velocities `(n, 12)` with the dashpots pulling the shear rings' slip rates
        toward `v_target (r, 3)` m/s, each dashpot scaled down to its force limit."""
        system, sub, dt, nd = self.system, self.sub, self.dt, self.system.ndof
        free = system.dof_map >= 0
        c_n, c_s, v = self.cn, self.cshear, self.v0
        for _ in range(MAX_DAMPING_PASSES):
            if not (np.any(c_n > 0) or np.any(c_s > 0)):
                break
            a, adiag = self.plan.matrix(dt * c_n, dt * c_s)
            impulse = (dt * c_s)[:, None] * v_target  # the dashpots' pull toward the target
            gi, gj = np.zeros((len(sub), 12)), np.zeros((len(sub), 12))
            gi[:, :nd] = np.einsum("cki,ck->ci", self.ti, impulse)
            gj[:, :nd] = np.einsum("cki,ck->ci", self.tj, impulse)
            b = (self.rhs + asm.scatter_vector(system.dof_map, sub.block_i, gi, system.n_unknowns)
                 - asm.scatter_vector(system.dof_map, sub.block_j, gj, system.n_unknowns))
            try:
                x = make_solver(a, nd, adiag, self.jacobi, self.plan.components)(b, None)
            except SolveError as exc:
                raise StepFailure(str(exc), "solve") from exc
            v = self.v0.copy()
            v[free] = x[system.dof_map[free]]
            vn, vt_vec = _relative_velocity(self.before, sub, v)
            vt = np.linalg.norm(vt_vec - v_target, axis=1)
            pulling = c_n * vn > self.pressed * (1.0 + 1e-9)
            over = c_s * vt > self.headroom * (1.0 + 1e-9)
            if not (np.any(pulling) or np.any(over)):
                break
            # (pulling and over imply vn, vt > 0: c v exceeds a force ≥ 0)
            c_n, c_s = c_n.copy(), c_s.copy()
            c_n[pulling] = self.pressed[pulling] / vn[pulling]
            c_s[over] = self.headroom[over] / vt[over]
        return v


def damp_contacts(system: BlockSystem, before: State, res: StepResult, after: State,
                  dt: float) -> State:
    """`after` with its velocities damped at the contacts the step `res` (from `before`)
    ended closed and ringing (`ringing`), the kinetic energy removed counted as damping
    dissipation (in place; StepFailure "solve" if the system cannot be solved). A normal
    dashpot pulls no harder than its spring presses and a shear dashpot of a locked contact
    holds no more than the friction its spring leaves (each scaled down to that, a few
    passes), so damping neither glues blocks together nor stops a slip."""
    cs = res.contacts
    closed = np.flatnonzero(cs.mode != OPEN)
    if system.controls.contact_damping <= 0 or len(closed) == 0:
        return after
    nd = system.ndof
    sub = _Points.of(cs, closed)
    # what the normal spring presses with, and the friction a locked contact's shear spring
    # leaves, for the dashpots (N)
    pressed = np.maximum(res.normal_force[closed], 0.0)
    headroom = np.where(sub.mode == LOCKED, np.maximum(
        system.tan_phi[sub.joint_material] * pressed
        - np.linalg.norm(res.shear_force[closed], axis=1), 0.0), 0.0)
    ring_n, ring_t = ringing(before, sub, after.velocity)
    ring_t &= headroom > 0.0
    rings = np.flatnonzero(ring_n | ring_t)
    if len(rings) == 0:
        return after
    # the dashpots of the closed contacts (a pair's mass shared by those that carry it)
    cn, cshear = (c[rings] for c in contact_damping(system, before, sub.block_i, sub.block_j))
    sub, pressed, headroom = _Points.of(sub, rings), pressed[rings], headroom[rings]
    cn = np.where(ring_n[rings], cn, 0.0)
    cshear = np.where(ring_t[rings], cshear, 0.0)
    bi, bj = sub.block_i, sub.block_j
    ti = asm.point_matrices(sub.point_i, before.centroid, bi, nd)
    tj = asm.point_matrices(sub.point_j, before.centroid, bj, nd)
    mass = mass_matrices(system, after)
    plan = asm.plan_system(system.block_row, np.ascontiguousarray(mass[:, :nd, :nd]), bi, bj,
                           ti, tj, sub.normal)
    v0 = after.velocity
    momentum = np.einsum("nij,nj->ni", mass, v0)
    rhs = asm.scatter_vector(system.dof_map, np.arange(system.n), momentum,
                             system.n_unknowns)
    dash = _Dashpots(system, before, sub, plan, ti, tj, rhs, v0, cn, cshear, pressed,
                     headroom, dt)
    # a shear ring is damped toward the step's mean slip rate, not to rest: a contact whose
    # slip rings about a drift (a column starting to topple, a toe starting to slip) keeps
    # it; where that would add kinetic energy, the rings are damped to rest instead
    kinetic0 = kinetic_energy(v0, mass)
    v = dash.velocities(np.where(ring_t[rings, None], res.slip[closed][rings] / dt, 0.0))
    if kinetic_energy(v, mass) > kinetic0:
        v = dash.velocities(np.zeros((len(rings), 3)))
    removed = kinetic0 - kinetic_energy(v, mass)
    after.velocity = v
    after.energies["damping_dissipation"] += float(removed)
    return after
