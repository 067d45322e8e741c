"""What the simulation hands to a recorder at each recorded step, and the recorder protocol."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from engine.contact.constraints import ContactSet
from engine.model import Model

#: energies of a frame (J): what is stored, the work done on the blocks, what was dissipated
STORED_ENERGIES = ("kinetic", "elastic", "contact")
WORKS = ("gravity_work", "external_work")
DISSIPATIONS = ("friction_dissipation", "numerical_dissipation", "damping_dissipation")
#: energy that left the model with what a stage removed (excavated blocks' kinetic, strain
#: and spring energy, removed bolts'): like a dissipation, never created energy; only a
#: staged run (:mod:`engine.step.stages`) has it, 0 for any other
REMOVED = ("removed_energy",)
#: every energy a frame carries, in the order of the result file
ENERGY_NAMES = ("kinetic", "elastic", "contact", "gravity_work", "friction_dissipation",
                "external_work", "numerical_dissipation", "damping_dissipation",
                "removed_energy")


def energy_created(energies: dict) -> float | np.ndarray:
    """Energy the run created (J; scalars or series): stored + dissipated − work done.
    Zero for an exact run; the balance is taken from the start (subtract its value at step
    0 for a run that did not start at rest and unloaded). Missing terms count as zero."""
    def total(names: tuple[str, ...]) -> float | np.ndarray:
        return sum(_finite(energies[n]) for n in names if n in energies)

    return total(STORED_ENERGIES) + total(DISSIPATIONS) + total(REMOVED) - total(WORKS)


def _finite(x: object) -> float | np.ndarray:
    """`x` with NaN as 0 and infinities as the largest floats (numpy's nan_to_num), without
    its cost for a finite Python or numpy scalar (a step checks its energies every time)."""
    if isinstance(x, float) and math.isfinite(x):
        return np.float64(x)
    return np.nan_to_num(np.asarray(x, float))


@dataclass
class Frame:
    """The state of every block (and optionally the contacts) at one recorded step.

    Block `k`'s vertices at this step are `centroids[k] + affine[k] @ (X0 - c0)` where
    `X0`, `c0` are its initial vertices and centroid: a rigid transform for rigid
    blocks, rotation times accumulated strain for elastic ones.

    - `centroids (n, 3)` m; `affine (n, 3, 3)`; `rotation (n, 3)` rotation vector (rad)
    - `velocity (n, 12)`: translation, spin, strain rates (zeros for rigid blocks)
    - `stress (n, 6)` Pa, Voigt order σx σy σz τyz τzx τxy (zeros for rigid blocks)
    - `energies`: J, keys :data:`ENERGY_NAMES` (`kinetic`, `elastic` and `contact` stored;
      `gravity_work`, `external_work` done on the blocks; `friction_dissipation`,
      `numerical_dissipation` by the integrator's implicit springs and velocity reduction,
      `damping_dissipation` by the contact dashpots)
    - `contacts` with `normal_force (c,)` N (compression positive) and
      `shear_force (c, 3)` N on block i
    - rock bolts (None without): `bolt_axial_force (b,)` N (tension positive),
      `bolt_shear_force (b,)` N, `bolt_status (b,)` (0 elastic, 1 yielded, 2 broken)
    - `water_force (n, 3)` N: resultant water force on each block (None: a dry model)
    """

    step: int
    time: float
    dt: float
    open_close_iterations: int
    max_penetration: float
    centroids: np.ndarray
    affine: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    stress: np.ndarray
    energies: dict[str, float] = field(default_factory=dict)
    contacts: ContactSet | None = None
    normal_force: np.ndarray | None = None
    shear_force: np.ndarray | None = None
    bolt_axial_force: np.ndarray | None = None
    bolt_shear_force: np.ndarray | None = None
    bolt_status: np.ndarray | None = None
    water_force: np.ndarray | None = None


class Recorder(Protocol):
    """Receives the run as it goes (the HDF5 writer is one)."""

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        """Called once before the first step with the model (initial geometry)."""

    def record(self, frame: Frame) -> None:
        """Called at every recorded step; the step must become durable (kept by a run that
        is killed) by the recorder's flush policy, at the latest at `end`."""

    def end(self, status: str, message: str = "", summary: dict[str, Any] | None = None) -> None:
        """Called once when the run ends, whatever the status."""
