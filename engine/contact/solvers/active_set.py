"""The active-set step of the complementarity solve: the linear problem that the status the
Gauss–Seidel sweeps found implies, solved globally.

Gauss–Seidel propagates a contact force one contact per visit: on a stack it converges in
about the square of the stack's depth sweeps from cold, and blocks wedged on sliding joints
(a cut rock mass on 45° joints) converge slower still. From the sweeps' status of each
contact — open (no force), stuck (its relative motion is `b`: three rows) or sliding (its
normal motion is `b_n`, its shear force `C + μ r_n` along its current direction) — this
step solves the status's linear problem with an augmented Lagrangian in the blocks'
unknowns: `(K + ρ Hᵀ H) x = F + Hᵀ (r + ρ b)`, `r ← r − ρ (H x − b)`, on the engine's
block-sparse assembly and linear solver (the penalty ρ only speeds the iteration: at its
fixed point `H x = b` exactly). A global solve carries a load through the whole mass at
once; the result is projected onto the contact law and handed back to the sweeps, which
confirm or correct the status (one semi-smooth Newton step with its Jacobian frozen at the
sweeps' status; Alart & Curnier 1991; Bao et al. 2014 for the augmented Lagrangian in DDA).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import engine.contact.solvers._complementarity_kernels as kern
from engine.dynamics import assembly as asm
from engine.dynamics.solver import BlockJacobi, SolveError, make_solver
from engine.status import StepFailure

#: the augmented Lagrangian's penalty, per contact, in units of the lighter block's inertia
#: term 2 m / Δt² (its translational diagonal in K)
PENALTY_RATIO = 10.0
#: augmented Lagrangian iterations in one active-set step
ITERATIONS = 4


@dataclass
class Primal:
    """The step's problem in the free blocks' unknowns: the block terms `kb (n, d, d)` and
    forces `f (m·d,)` (global order), each block's block row `row (n,)` (-1: fixed), the
    contacts' blocks `block_i`, `block_j (c,)`, rows `bi`, `bj`, world T at their points
    `ti`, `tj (c, 3, d)`, frames `(c, 3, 3)`, and the bolts between free blocks as springs
    (`links`: the blocks, T at their ends, axes and stiffnesses, or None)."""

    kb: np.ndarray
    f: np.ndarray
    row: np.ndarray
    block_i: np.ndarray
    block_j: np.ndarray
    bi: np.ndarray
    bj: np.ndarray
    ti: np.ndarray
    tj: np.ndarray
    frames: np.ndarray
    links: tuple[np.ndarray, ...] | None
    plan: asm.SystemPlan | None = None

    def _plan(self) -> asm.SystemPlan:
        if self.plan is None:
            normal = np.ascontiguousarray(self.frames[:, 0, :])
            if self.links is None:
                self.plan = asm.plan_system(self.row, self.kb, self.block_i, self.block_j,
                                            self.ti, self.tj, normal)
            else:
                lb_i, lb_j, lti, ltj, axis = self.links[:5]
                self.plan = asm.plan_system(
                    self.row, self.kb, np.concatenate([self.block_i, lb_i]),
                    np.concatenate([self.block_j, lb_j]), np.concatenate([self.ti, lti]),
                    np.concatenate([self.tj, ltj]), np.concatenate([normal, axis]))
        return self.plan

    def solver(self, kn: np.ndarray, ks: np.ndarray):  # noqa: ANN201 (the engine's solver)
        """The linear solver of K with contact springs `kn`, `ks (c,)` (and the bolts)."""
        if self.links is not None:
            kn = np.concatenate([kn, self.links[5]])
            ks = np.concatenate([ks, self.links[6]])
        plan = self._plan()
        k, kdiag = plan.matrix(kn, ks)
        try:
            return make_solver(k, self.kb.shape[1], kdiag, BlockJacobi(), plan.components)
        except SolveError as exc:
            raise StepFailure(str(exc), "solve") from exc


def _status(r: np.ndarray, mu: np.ndarray, tension: np.ndarray, cohesion: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Stuck and sliding contacts `(c,)` of the forces `r (c, 3)` (the rest are open)."""
    rim = cohesion + mu * np.maximum(r[:, 0], 0.0)
    shear = np.hypot(r[:, 1], r[:, 2])
    carrying = (r[:, 0] > 0.0) | ((tension > 0) & (r[:, 0] > -tension)) | (shear > 0)
    sliding = carrying & (rim > 0) & (shear >= rim * (1.0 - 1e-9))
    return carrying & ~sliding, sliding


def active_set_step(pr: Primal, hi: np.ndarray, hj: np.ndarray, bn: np.ndarray,
                    mu: np.ndarray, tension: np.ndarray, cohesion: np.ndarray,
                    r: np.ndarray) -> np.ndarray | None:
    """Forces `(c, 3)` in the contacts' frames after ITERATIONS augmented Lagrangian
    iterations on the status of `r`, projected onto the law (None when no contact carries
    force)."""
    stuck, sliding = _status(r, mu, tension, cohesion)
    if not (np.any(stuck) or np.any(sliding)):
        return None
    lighter = np.full(len(r), np.inf)
    diag = pr.kb[:, 0, 0]
    free_i, free_j = pr.bi >= 0, pr.bj >= 0
    lighter[free_i] = diag[pr.block_i[free_i]]
    lighter[free_j] = np.minimum(lighter[free_j], diag[pr.block_j[free_j]])
    rho = PENALTY_RATIO * lighter
    kn = np.where(stuck | sliding, rho, 0.0)
    ks = np.where(stuck, rho, 0.0)
    solve = pr.solver(kn, ks)
    m, d = int(pr.row.max(initial=-1)) + 1, pr.kb.shape[1]
    shear = np.hypot(r[:, 1], r[:, 2])
    direction = np.zeros((len(r), 2))
    direction[sliding] = r[sliding, 1:] / np.maximum(shear[sliding], 1e-300)[:, None]
    r = r.copy()
    r[~(stuck | sliding)] = 0.0
    x = None
    for _ in range(ITERATIONS):
        target = r.copy()  # r + ρ b on the constrained rows (b = (bn, 0, 0))
        target[:, 0] += kn * bn
        rhs = pr.f + kern.generalized_forces(pr.bi, pr.bj, hi, hj, target, m).ravel()
        try:
            x = solve(rhs, x)
        except SolveError as exc:
            raise StepFailure(str(exc), "solve") from exc
        u = kern.relative_motion(pr.bi, pr.bj, hi, hj, x.reshape(m, d))
        r[stuck] -= rho[stuck, None] * (u[stuck] - np.column_stack(
            [bn[stuck], np.zeros((int(stuck.sum()), 2))]))
        r[sliding, 0] -= rho[sliding] * (u[sliding, 0] - bn[sliding])
        rim = cohesion[sliding] + mu[sliding] * np.maximum(r[sliding, 0], 0.0)
        r[sliding, 1:] = rim[:, None] * direction[sliding]
    return project(r, mu, tension, cohesion)


def project(r: np.ndarray, mu: np.ndarray, tension: np.ndarray,
            cohesion: np.ndarray) -> np.ndarray:
    """Forces `r (c, 3)` made admissible: normal forces no lower than −T, shear within the
    rim C + μ max(r_n, 0)."""
    out = r.copy()
    low = out[:, 0] < -tension
    out[low, 0] = -tension[low]
    rim = cohesion + mu * np.maximum(out[:, 0], 0.0)
    shear = np.hypot(out[:, 1], out[:, 2])
    over = shear > rim
    out[over, 1:] *= (rim[over] / np.maximum(shear[over], 1e-300))[:, None]
    return out
