"""Contact damping: dashpots on the relative velocity of the blocks at their closed contacts.

DDA's integrator (velocities `2 d / Δt − v0`, β = ½, γ = 1) leaves an oscillation faster
than the step resolves — every stiff penalty spring's — undamped: it rings at the step's own
frequency, velocities flipping sign every step, and a block resting on its contacts rocks
and walks down a slope its friction should hold. A dashpot inside the step's solve cannot
stop it: it acts on the step's mean velocity, which such a ring keeps near zero. Here the
dashpots act after the converged step, implicitly on the end velocities — `(M + Δt Jᵀ C J)
v = M v1`, J the closed contacts' relative velocity (normal, and tangential where locked),
C the dashpots — which for a slow contact is the physical dashpot to first order, kills a
ring at any stiffness (c Δt ≫ m), moves no block, and only ever removes kinetic energy.
"""

from __future__ import annotations

import numpy as np

from engine import assembly as asm
from engine._motion_kernels import point_motions
from engine.block_terms import kinetic_energy
from engine.contacts import LOCKED, OPEN, ContactSet
from engine.motion import mass_matrices, mass_properties
from engine.solver import BlockJacobi, SolveError, make_solver
from engine.state import State, StepResult
from engine.status import StepFailure
from engine.system import BlockSystem

#: passes that scale down the dashpots that would pull or beat friction
MAX_DAMPING_PASSES = 4


def contact_dashpots(system: BlockSystem, state: State, contacts: ContactSet
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Normal and shear dashpots `(cn, cs)` `(c,)` N·s/m: the fraction `contact_damping` of
    critical damping, 2 ζ √(k m), of each contact's spring carrying its share of the block
    pair's reduced mass (a fixed block's mass is infinite; a pair's contacts share its mass
    equally)."""
    zeta = system.controls.contact_damping
    c = len(contacts)
    if zeta <= 0 or c == 0:
        return np.zeros(c), np.zeros(c)
    mass = np.where(system.fixed, np.inf, system.density * mass_properties(system, state)[0])
    mi, mj = mass[contacts.block_i], mass[contacts.block_j]
    reduced = 1.0 / (1.0 / mi + 1.0 / mj)
    pair = contacts.block_i * system.n + contacts.block_j
    _, inverse, count = np.unique(pair, return_inverse=True, return_counts=True)
    share = reduced / count[inverse.ravel()]
    return 2.0 * zeta * np.sqrt(system.kn * share), 2.0 * zeta * np.sqrt(system.ks * share)


def _normal_velocity(before: State, sub: ContactSet, v: np.ndarray) -> np.ndarray:
    """Relative normal velocity `(c,)` m/s of block i's contact point to block j's (positive:
    parting) for block velocities `v (n, 12)`, at the step's start geometry."""
    bi, bj = sub.block_i, sub.block_j
    rel = (point_motions(sub.point_i, before.centroid[bi], v[bi])
           - point_motions(sub.point_j, before.centroid[bj], v[bj]))
    return np.einsum("ij,ij->i", rel, sub.normal)


def _relative_velocity(before: State, sub: ContactSet, v: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Relative velocity of block i's contact point to block j's for block velocities
    `v (n, 12)` at the step's start geometry: normal `(c,)` m/s (positive: parting) and the
    tangential speed `(c,)` m/s."""
    bi, bj = sub.block_i, sub.block_j
    rel = (point_motions(sub.point_i, before.centroid[bi], v[bi])
           - point_motions(sub.point_j, before.centroid[bj], v[bj]))
    vn = np.einsum("ij,ij->i", rel, sub.normal)
    return vn, np.linalg.norm(rel - vn[:, None] * sub.normal, axis=1)


def damp_contacts(system: BlockSystem, before: State, res: StepResult, after: State,
                  dt: float) -> State:
    """`after` with its velocities damped at the contacts the step `res` (from `before`)
    ended closed, and the kinetic energy that removed counted as damping dissipation
    (in place; StepFailure "solve" if the system cannot be solved). A normal dashpot pulls
    no harder than its spring presses and a shear dashpot of a locked contact holds no more
    than the friction its spring leaves (each scaled down to that, a few passes), so
    damping neither glues blocks together nor stops a slip."""
    cs = res.contacts
    closed = np.flatnonzero(cs.mode != OPEN)
    if system.controls.contact_damping <= 0 or len(closed) == 0:
        return after
    nd = system.ndof
    sub = cs.subset(closed)
    cn, cshear = contact_dashpots(system, before, sub)
    # what the normal spring presses with, and the friction a locked contact's shear spring
    # leaves, for the dashpots (N)
    pressed = np.maximum(res.normal_force[closed], 0.0)
    headroom = np.where(sub.mode == LOCKED, np.maximum(
        system.tan_phi[sub.joint_material] * np.maximum(res.normal_force[closed], 0.0)
        - np.linalg.norm(res.shear_force[closed], axis=1), 0.0), 0.0)
    cshear = np.where(headroom > 0.0, cshear, 0.0)
    bi, bj = sub.block_i, sub.block_j
    ti = np.ascontiguousarray(
        asm.displacement_matrices(sub.point_i, before.centroid[bi])[:, :, :nd])
    tj = np.ascontiguousarray(
        asm.displacement_matrices(sub.point_j, before.centroid[bj])[:, :, :nd])
    mass = mass_matrices(system, after)
    plan = asm.plan_system(system.block_row, np.ascontiguousarray(mass[:, :nd, :nd]), bi, bj,
                           ti, tj, sub.normal)
    v0 = after.velocity
    momentum = np.einsum("nij,nj->ni", mass, v0)
    rhs = asm.scatter_vector(system.dof_map, np.arange(system.n), momentum,
                             system.n_unknowns)
    free = system.dof_map >= 0
    v = v0
    for _ in range(MAX_DAMPING_PASSES):
        if not (np.any(cn > 0) or np.any(cshear > 0)):
            break
        a, adiag = plan.matrix(dt * cn, dt * cshear)
        try:
            x = make_solver(a, nd, adiag, BlockJacobi(), plan.coupled)(rhs, None)
        except SolveError as exc:
            raise StepFailure(str(exc), "solve") from exc
        v = v0.copy()
        v[free] = x[system.dof_map[free]]
        vn, vt = _relative_velocity(before, sub, v)
        pulling = cn * vn > pressed * (1.0 + 1e-9)
        over = cshear * vt > headroom * (1.0 + 1e-9)
        if not (np.any(pulling) or np.any(over)):
            break
        cn = np.where(pulling, pressed / np.maximum(vn, 1e-300), cn)
        cshear = np.where(over, headroom / np.maximum(vt, 1e-300), cshear)
    removed = kinetic_energy(v0, mass) - kinetic_energy(v, mass)
    after.velocity = v
    after.energies["damping_dissipation"] += float(removed)
    return after
