"""The linear systems of a Newton step (:mod:`.newton`) on the step's block-sparse pattern:
the step potential's Hessian (symmetric: the engine's Cholesky or block-Jacobi conjugate
gradients) and the semi-smooth Jacobian with Coulomb's cap following the normal force (not
symmetric: LU when small, block-Jacobi BiCGSTAB when large)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from engine.contact.solvers import _newton_kernels as kern
from engine.dynamics.assembly import SystemPlan
from engine.dynamics.solver import (
    DIRECT_SOLVE_MAX_UNKNOWNS,
    BlockJacobi,
    SolveError,
    make_solver,
)
from engine.status import StepFailure


class NewtonSystems:
    """The Newton systems of one step on its pattern: the energy's Hessian by the engine's
    Cholesky (small) or block-Jacobi conjugate gradients (large; the preconditioner kept
    across iterations), the coupled Jacobian (not symmetric) by LU (small) or block-Jacobi
    BiCGSTAB (large); the Krylov iterations counted."""

    def __init__(self, plan: SystemPlan, links: np.ndarray | None) -> None:
        self.plan = plan
        #: the bolts' spring matrices `(k, 3, 3)`, after the contacts on the plan (None: none)
        self.links = links
        self.jacobi = BlockJacobi()
        self.krylov_iterations = 0
        #: rounds whose caps stayed lagged (the polish did not converge)
        self.lagged = 0

    def solve(self, jac: np.ndarray, rhs: np.ndarray, rtol: float, x0: np.ndarray | None,
              symmetric: bool = True) -> np.ndarray:
        """The Newton direction `(m, d)`: J p = rhs."""
        plan = self.plan
        if self.links is not None:
            jac = np.concatenate([jac, self.links])
        data = kern.fill_jacobian(plan.base, plan.ti, plan.tj, jac, plan.slot_ii,
                                  plan.slot_jj, plan.slot_ij, plan.slot_ji)
        k, kdiag = plan.wrap(data, np.ascontiguousarray(np.einsum("cii->c", jac)))
        try:
            if symmetric:
                solver = make_solver(k, plan.d, kdiag, self.jacobi, plan.components,
                                     rtol=rtol)
                p = solver(rhs.ravel(), None if x0 is None else x0.ravel())
                self.krylov_iterations += getattr(solver, "iterations", 0)
            else:
                p = self._unsymmetric(k, data, kdiag, rhs.ravel(), rtol, x0)
        except (SolveError, np.linalg.LinAlgError, RuntimeError) as exc:
            raise StepFailure(f"the Newton system could not be solved: {exc}", "solve") from exc
        if not np.all(np.isfinite(p)):
            raise StepFailure("the Newton system's solution is not finite", "solve")
        return p.reshape(rhs.shape)

    def _unsymmetric(self, k: object, data: np.ndarray, kdiag: np.ndarray, f: np.ndarray,
                     rtol: float, x0: np.ndarray | None) -> np.ndarray:
        plan = self.plan
        if isinstance(k, np.ndarray):
            return np.linalg.solve(k, f)
        if k.shape[0] <= DIRECT_SOLVE_MAX_UNKNOWNS:
            return spla.splu(sp.csc_matrix(k)).solve(f)
        x, its = kern.bicgstab_bsr(plan.indptr, plan.indices, data, np.linalg.inv(kdiag), f,
                                   np.zeros_like(f) if x0 is None else x0.ravel(), rtol,
                                   10 * len(f))
        if its < 0:
            raise SolveError("BiCGSTAB did not converge")
        self.krylov_iterations += its
        return x
