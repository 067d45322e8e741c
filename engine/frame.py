"""What the simulation hands to a recorder at each recorded step, and the recorder protocol."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from engine.contacts import ContactSet
from engine.model import Model


@dataclass
class Frame:
    """The state of every block (and optionally the contacts) at one recorded step.

    Block `k`'s vertices at this step are `centroids[k] + affine[k] @ (X0 - c0)` where
    `X0`, `c0` are its initial vertices and centroid: a rigid transform for rigid
    blocks, rotation times accumulated strain for elastic ones.

    - `centroids (n, 3)` m; `affine (n, 3, 3)`; `rotation (n, 3)` rotation vector (rad)
    - `velocity (n, 12)`: translation, spin, strain rates (zeros for rigid blocks)
    - `stress (n, 6)` Pa, Voigt order σx σy σz τyz τzx τxy (zeros for rigid blocks)
    - `energies`: J, keys `kinetic`, `elastic`, `contact`, `gravity_work`,
      `friction_dissipation`, `external_work`
    - `contacts` with `normal_force (c,)` N (compression positive) and
      `shear_force (c, 3)` N on block i
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


class Recorder(Protocol):
    """Receives the run as it goes (the HDF5 writer is one)."""

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        """Called once before the first step with the model (initial geometry)."""

    def record(self, frame: Frame) -> None:
        """Called at every recorded step; the step must become durable (kept by a run that
        is killed) by the recorder's flush policy, at the latest at `end`."""

    def end(self, status: str, message: str = "", summary: dict[str, Any] | None = None) -> None:
        """Called once when the run ends, whatever the status."""
