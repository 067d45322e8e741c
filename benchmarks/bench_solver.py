"""Direct factorization (SuperLU) against block-Jacobi conjugate gradients on real DDA systems.

Grids of 1 m cubes stacked on a fixed base, all contacts closed: the system K of the first
open-close cycle is assembled exactly as the simulation does, then solved both ways.
Run: `python benchmarks/bench_solver.py [--quick]`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.sparse.linalg as spla

from engine.contact.search import detect
from engine.dynamics import assembly as asm
from engine.dynamics.block_terms import block_terms
from engine.dynamics.solver import CG_RTOL, block_jacobi, pcg
from engine.geometry.shapes import box
from engine.model import AnalysisControls, Block, JointMaterial, Model
from engine.step.simulation import Simulation


def grid_model(n: int) -> Model:
    """n × n × n unit cubes in contact, on a fixed base."""
    blocks = [Block(box([-1, -1, -1], [n + 1, n + 1, 0]), "base", fixed=True)]
    for i in range(n):
        for j in range(n):
            for k in range(n):
                blocks.append(Block(box([i, j, k], [i + 1, j + 1, k + 1]), f"c{i}{j}{k}"))
    return Model(blocks=blocks, joint_materials=[JointMaterial(np.radians(30))],
                 controls=AnalysisControls(time_step=1e-3, penalty=1e10))


def system(n: int):
    """K `(N, N)` and F `(N,)` of the first cycle with every contact locked."""
    sim = Simulation(grid_model(n))
    sys_, s = sim.system, sim.state
    cs = detect(sys_, s)
    kb, fb, _ = block_terms(sys_, s, 1e-3)
    ti = asm.displacement_matrices(cs.point_i, s.centroid[cs.block_i])
    tj = asm.displacement_matrices(cs.point_j, s.centroid[cs.block_j])
    kn = np.full(len(cs), sys_.kn)
    ks = np.full(len(cs), sys_.ks)
    plan = asm.plan_system(sys_.block_row, kb, cs.block_i, cs.block_j,
                           ti[..., :6], tj[..., :6], cs.normal)
    k, kdiag = plan.matrix(kn, ks)
    f = asm.scatter_vector(sys_.dof_map, np.arange(sys_.n), fb, sys_.n_unknowns)
    return k, kdiag, f, len(cs)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    sizes = [4, 6, 8] if p.parse_args().quick else [4, 6, 8, 10, 13]
    print(f"{'blocks':>7} {'unknowns':>9} {'contacts':>9} {'splu (s)':>9} {'cg (s)':>9} "
          f"{'cg iters':>8} {'rel diff':>9}")
    for n in sizes:
        k, kdiag, f, nc = system(n)
        t0 = time.perf_counter()
        x_direct = spla.splu(k.tocsc()).solve(f)
        t_direct = time.perf_counter() - t0
        t0 = time.perf_counter()
        pre = block_jacobi(kdiag)
        x_cg, iters = pcg(k, f, pre, None, CG_RTOL, 10 * len(f))
        t_cg = time.perf_counter() - t0
        diff = np.linalg.norm(x_cg - x_direct) / np.linalg.norm(x_direct)
        print(f"{n**3:>7} {k.shape[0]:>9} {nc:>9} {t_direct:>9.4f} {t_cg:>9.4f} "
              f"{iters:>8} {diff:>9.1e}")


if __name__ == "__main__":
    main()
