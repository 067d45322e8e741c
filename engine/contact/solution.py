"""What a contact solver returns for one step: the block displacements and the contacts'
converged modes, gaps, forces and works (the same document whichever solver ran)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.contact.constraints import ContactSet


@dataclass
class StepResult:
    """The converged solution of one step. Shapes: `n` blocks, `c` contacts.

    `d (n, 12)` block displacement increments; the step's `contacts` with their converged
    modes; `gap1 (c,)` m normal distance at the end of the step; `shear (c, 3)` m the shear
    springs' stretch (locked); `slip (c, 3)` m relative tangential displacement;
    `normal_force (c,)` N (compression positive); `shear_force (c, 3)` N on block i; the
    friction work and the implicit springs' dissipation (J); `broken (c,)` bonds lost.
    """

    d: np.ndarray
    contacts: ContactSet
    gap1: np.ndarray
    shear: np.ndarray
    slip: np.ndarray
    normal_force: np.ndarray
    shear_force: np.ndarray
    friction_work: float
    iterations: int
    mode_changes: int = 0
    numerical_dissipation: float = 0.0
    damping_dissipation: float = 0.0
    broken: np.ndarray | None = None
    #: of `numerical_dissipation`, what the springs lost between the steps (J; re-detected
    #: shallower, on another plane or not at all: `open_close.reseat_loss`)
    reseat_dissipation: float = 0.0
    #: face-to-face bonds (patches, engine.contact.patches) the step broke whole, and those
    #: it broke in part (progressively: tension where the stress over the patch is uneven)
    bond_breaks: tuple[int, int] = (0, 0)
    #: the blocks' velocities at the step's end `(n, 12)` when the solver applied an impact
    #: law (None: DDA's `2 d / Δt − v0`)
    velocity: np.ndarray | None = None
    #: contact forces `(c, 3)` N on block i (world axes), carried to the next step
    force: np.ndarray | None = None
    #: energy (J) the contacts store at the step's end (None: the penalty springs')
    contact_energy: float | None = None
    #: whether the contacts are springs that store energy (False: hard contacts); the
    #: springs of sleeping blocks keep theirs (engine.step.advance)
    springs: bool = True
    #: the complementarity solve's residual: the contact law's largest violation at the end
    #: of its position stage (m; None: the open-close iteration)
    residual: float | None = None
    #: conjugate-gradient iterations of the step's linear solves (the Newton solve's; 0 where
    #: they were direct or not counted)
    linear_iterations: int = 0
