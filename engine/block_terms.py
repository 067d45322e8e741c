"""Shi's block terms of a step (THEORY.md): inertia of the constant-acceleration scheme,
elasticity, initial stress, gravity, point loads and fixed points, on the blocks' own
unknowns; and the energy the implicit block springs dissipate in a step."""

from __future__ import annotations

import numpy as np

from engine import assembly as asm
from engine.motion import map_point, mass_properties
from engine.state import State
from engine.system import BlockSystem


def kinetic_energy(velocity: np.ndarray, mass: np.ndarray) -> float:
    """½ Σ vᵀ M v (J) of block velocities `(n, 12)` and masses `(n, 12, 12)`."""
    return 0.5 * float(np.sum(velocity * (mass @ velocity[:, :, None])[:, :, 0]))


def block_terms(system: BlockSystem, state: State, dt: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block stiffness `(n, d, d)` and block forces `(n, 12)` on the d = 6 (rigid) or 12
    (elastic) unknowns of each block for a step of `dt` s, and the mass `(n, 12, 12)`."""
    nd = system.ndof
    vol, second = mass_properties(system, state)
    mass = asm.mass_matrices(system.density, vol, second)
    kb = mass[:, :nd, :nd] * (2.0 / dt**2)
    fb = (mass @ state.velocity[:, :, None])[:, :, 0]
    fb *= 2.0 / dt
    fb[:, :3] += (system.density * vol)[:, None] * system.gravity[None]
    if system.elastic:
        kb[:, 6:, 6:] += vol[:, None, None] * system.emat
        fb[:, 6:] -= vol[:, None] * state.stress
    for b, p0, f in system.loads:
        t = asm.displacement_matrices(map_point(system, state, b, p0)[None],
                                      state.centroid[b][None])[0]
        fb[b] += t.T @ f
    for b, p0 in system.fixed_points:
        p = map_point(system, state, b, p0)
        t = asm.displacement_matrices(p[None], state.centroid[b][None])[0]
        kb[b] += system.kf * (t.T @ t)[:nd, :nd]
        fb[b] -= system.kf * t.T @ (p - p0)
    return kb, fb, mass


def block_dissipation(system: BlockSystem, state: State, d: np.ndarray) -> float:
    """½ dᵀ K d (J) of the implicit elastic and fixed-point springs in a step of block
    displacements `d (n, 12)`."""
    out = 0.0
    if system.elastic:
        vol, _ = mass_properties(system, state)
        out += 0.5 * float(np.einsum("ni,nij,nj->", d[:, 6:],
                                     vol[:, None, None] * system.emat, d[:, 6:]))
    for b, p0 in system.fixed_points:
        t = asm.displacement_matrices(map_point(system, state, b, p0)[None],
                                      state.centroid[b][None])[0]
        r = t @ d[b]
        out += 0.5 * system.kf * float(r @ r)
    return out
