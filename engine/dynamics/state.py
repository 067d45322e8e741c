"""Everything that changes during a run (as MuJoCo's data): block positions and velocities,
stresses, the contacts' memory, time and Δt, energies and diagnostics.

A run can be saved and resumed from its :class:`State` alone (:func:`save_state`,
:func:`load_state`); the constants live in :class:`engine.dynamics.system.BlockSystem`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time as _time
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from engine.dynamics._state_kernels import key_order, key_rows, sortable_keys

#: the arrays of a :class:`ContactMemory`, in its field order
MEMORY_FIELDS = ("key", "mode", "shear", "tangent", "broken", "gap", "force", "joint_material")


@dataclass
class ContactMemory:
    """What the closed contacts carry to the next step (inherited modes, paper 2.4 (2)).

    One row per closed contact, sorted by key: `key (m, 4)`, `mode (m,)`, accumulated
    tangential displacement `shear (m, 3)` m, sliding direction `tangent (m, 3)`,
    `broken (m,)` (cohesion and tensile strength lost), the end-of-step `gap (m,)` m and
    the contact `force (m, 3)` N on block i (the complementarity solve's warm start; zero
    from the open-close iteration) and each contact's `joint_material (m,)` (-1: not known;
    what a change of a joint's strength wakes, :func:`engine.step.sleep.reconcile`).
    """

    key: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    mode: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    shear: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tangent: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    broken: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    gap: np.ndarray = field(default_factory=lambda: np.zeros(0))
    force: np.ndarray | None = None
    joint_material: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.force is None:
            self.force = np.zeros((len(self.key), 3))
        if self.joint_material is None:
            self.joint_material = np.full(len(self.key), -1, dtype=np.int64)
        sortable = sortable_keys(self.key)
        order = key_order(sortable)
        if not np.array_equal(order, np.arange(len(order))):
            for name in MEMORY_FIELDS:
                setattr(self, name, getattr(self, name)[order])
            sortable = sortable[order]
        self._sorted = sortable

    def find(self, key: np.ndarray) -> np.ndarray:
        """Row of each key `(c, 4)` in the memory `(c,) int`, -1 where it is not there."""
        if len(self._sorted) == 0:
            return np.full(len(key), -1, dtype=np.int64)
        return key_rows(self._sorted, sortable_keys(key))

    def rows(self, index: np.ndarray) -> ContactMemory:
        """The memory of the contacts `index` (boolean mask or rows), every field kept."""
        return ContactMemory(**{name: getattr(self, name)[index] for name in MEMORY_FIELDS})

    def spring_energy(self, kn: float, ks: float, rows: np.ndarray) -> float:
        """Energy (J) the springs of the contacts `rows` held at the last step's end: the
        normal spring `kn` of the closed ones (the memory also keeps open contacts pressed
        in, whose springs hold nothing) and the shear springs `ks`."""
        closed = self.mode[rows] != 0  # (engine.contact.constraints.OPEN)
        return (0.5 * kn * float(np.sum(self.gap[rows][closed] ** 2))
                + 0.5 * ks * float(np.sum(self.shear[rows] ** 2)))

    def renumbered(self, new_index: np.ndarray) -> ContactMemory:
        """The memory with its blocks renumbered by `new_index (n_old,)` (a stage's kept
        blocks; every contact's blocks must be kept)."""
        key = self.key.copy()
        key[:, 0], key[:, 2] = new_index[key[:, 0]], new_index[key[:, 2]]
        return ContactMemory(**{name: key if name == "key" else getattr(self, name)
                                for name in MEMORY_FIELDS})


def _zero_energies() -> dict[str, float]:
    return {"gravity_work": 0.0, "external_work": 0.0, "friction_dissipation": 0.0,
            "numerical_dissipation": 0.0, "damping_dissipation": 0.0}


@dataclass
class Diagnostics:
    """What a run observed about itself: deepest penetration (m) and its ratio to the
    thinner block's thickness, contacts found implausibly deep and relaxed, the Δt cuts by
    reason, what limited each step's Δt, the linear solves and K factorizations of the
    open-close iterations (failed attempts included), wall time (s) per phase (detection,
    assembly, solve, open_close, update, damping: the dashpots after an open-close step,
    output), the blocks' initial overlaps and the energy balance."""

    max_penetration: float = 0.0
    max_penetration_ratio: float = 0.0
    relaxed_contacts: int = 0
    #: energy (J) the contact springs lost between steps, re-detected shallower, on another
    #: plane or not at all (booked as numerical dissipation)
    reseat_dissipation: float = 0.0
    cuts: dict[str, int] = field(default_factory=dict)
    #: steps by what limited their Δt (:data:`engine.step.stepping.LIMITS`): the asked Δt, the
    #: run's end, a cut in the step (by the cut's reason), a cut kept from the step before,
    #: regrowth after a cut, or held because the step before changed many contacts
    limited_by: dict[str, int] = field(default_factory=dict)
    #: why the state's Δt (the next step's) is what it is, decided by the step before
    dt_reason: str = "asked"
    #: linear solves and K factorizations of the open-close iterations, failed attempts
    #: included (what a step costs beyond detection)
    solves: int = 0
    factorizations: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    #: deepest overlap of the blocks as given (m; their springs start unstretched) and how
    #: many contacts had one
    initial_overlap: float = 0.0
    initial_overlaps: int = 0
    #: energy the run has created (J; stored + dissipated − work), its largest value so far,
    #: and the run's energy scale (J; the largest of the work done and the energy stored)
    energy_created: float = 0.0
    max_energy_created: float = 0.0
    energy_scale: float = 0.0
    #: face-to-face bonds (cohesion, tensile strength over a contact patch) broken whole,
    #: and broken in part, progressively, where the stress over the patch is uneven
    bonds_broken: int = 0
    bonds_broken_progressively: int = 0

    #: blocks woken from sleep, and steps redone to wake them (engine.step.sleep)
    wakes: int = 0
    #: Newton solves whose friction caps kept the normal forces of the step's own first
    #: solve (a lag of one round: the semi-smooth polish did not converge)
    lagged_caps: int = 0

    def tick(self, phase: str, since: float) -> float:
        """Add the wall time since `since` (perf_counter) to `phase`; return now."""
        now = _time.perf_counter()
        self.timings[phase] = self.timings.get(phase, 0.0) + now - since
        return now


#: field metadata of the State's arrays with one row per block, and with one row per bolt:
#: a stage that removes blocks keeps their rows (:func:`State.take_blocks`), a checkpoint
#: saves them and a resume loads them (:func:`save_state`, :func:`load_state`), by this mark
PER_BLOCK = {"rows": "block"}
PER_BOLT = {"rows": "bolt"}


@dataclass
class State:
    """Everything that changes from step to step. Shapes: `n` blocks.

    Block `b`'s points are at `centroid[b] + affine[b] (X0 − c0[b])`; `rotation (n, 3, 3)`
    is the accumulated rotation, `velocity (n, 12)` the block velocities, `stress (n, 6)`
    Pa. `dt` is the time step the next step tries, `last_dt` the last step's;
    `last_d (n, 12)` the last step's block displacements and `deepest (n,)` m each block's
    deepest contact penetration at its end (None before the first step). `energies` are
    the accumulated works and dissipations (J).
    """

    centroid: np.ndarray = field(metadata=PER_BLOCK)
    affine: np.ndarray = field(metadata=PER_BLOCK)
    rotation: np.ndarray = field(metadata=PER_BLOCK)
    velocity: np.ndarray = field(metadata=PER_BLOCK)
    stress: np.ndarray = field(metadata=PER_BLOCK)
    time: float = 0.0
    step: int = 0
    dt: float = 0.0
    last_dt: float = 0.0
    memory: ContactMemory = field(default_factory=ContactMemory)
    last_d: np.ndarray | None = field(default=None, metadata=PER_BLOCK)
    deepest: np.ndarray | None = field(default=None, metadata=PER_BLOCK)
    energies: dict[str, float] = field(default_factory=_zero_energies)
    #: J held by the contact springs at the end of the last step
    contact_energy: float = 0.0
    #: rock bolts (None without): plastic elongation `(b,)` m, shear force on the head
    #: block `(b, 3)` N, state `(b,)` (:data:`engine.loads.bolts.ELASTIC`, YIELDED, BROKEN)
    bolt_plastic: np.ndarray | None = field(default=None, metadata=PER_BOLT)
    bolt_shear: np.ndarray | None = field(default=None, metadata=PER_BOLT)
    bolt_status: np.ndarray | None = field(default=None, metadata=PER_BOLT)
    #: blocks asleep `(n,)` (out of the solve, at rest with their contact forces kept;
    #: None: all awake) and how long each has been quiet `(n,)` s (engine.step.sleep)
    asleep: np.ndarray | None = field(default=None, metadata=PER_BLOCK)
    quiet: np.ndarray | None = field(default=None, metadata=PER_BLOCK)
    #: each sleeping block's change of contact resultant since it fell asleep `(n, 6)` N
    drift: np.ndarray | None = field(default=None, metadata=PER_BLOCK)
    #: what each block's sleep rests on `(n, 7)`: fixed (1) or not (0), and the resultant of
    #: its point loads and fixed points (force N, moment N·m); NaN where a stage changed its
    #: neighbours (engine.step.sleep.basis; None: nothing has slept)
    sleep_loads: np.ndarray | None = field(default=None, metadata=PER_BLOCK)
    #: the joint strengths `(j, 3)` (tan φ, c Pa, σt Pa) and the body acceleration `(3,)`
    #: m/s² the sleeping islands fell asleep under (None: nothing has slept)
    sleep_joints: np.ndarray | None = field(default=None, metadata={"rows": "joint"})
    sleep_body: np.ndarray | None = field(default=None, metadata={"rows": "whole"})
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
    #: values derived from this state, computed once (not saved)
    cache: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    #: what a run keeps from step to step to save work, each entry checked against the
    #: state it serves before use (the contact detection's skin, the last K pattern): shared
    #: by a state and the one its step makes, never saved (a resumed run rebuilds it)
    workspace: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def awake(self, fixed: np.ndarray) -> np.ndarray:
        """The blocks that move in the next step `(n,)`: free and not asleep."""
        return ~fixed if self.asleep is None else ~fixed & ~self.asleep

    def resting_contacts(self, fixed: np.ndarray) -> np.ndarray:
        """The memory's contacts between blocks that do not move in the next step (asleep
        or fixed) `(m,) bool`: they keep what they held."""
        mem = self.memory
        if self.asleep is None or not np.any(self.asleep):
            return np.zeros(len(mem.key), dtype=bool)
        awake = self.awake(fixed)
        return ~awake[mem.key[:, 0]] & ~awake[mem.key[:, 2]]

    def take_blocks(self, rows: np.ndarray) -> dict[str, np.ndarray | None]:
        """Every per-block array cut to the blocks `rows` (copies; None stays None): what a
        stage that removes blocks carries over (:data:`PER_BLOCK`)."""
        return {name: None if getattr(self, name) is None else getattr(self, name)[rows].copy()
                for name in state_arrays("block")}


def state_arrays(rows: str | None = None) -> tuple[str, ...]:
    """The State's array fields with one row per `rows` ("block", "bolt", "joint",
    "whole"; None: all of them), in field order."""
    return tuple(f.name for f in fields(State) if "rows" in f.metadata
                 and (rows is None or f.metadata["rows"] == rows))


def initial_state(centroid: np.ndarray, velocity: np.ndarray, dt: float) -> State:
    """The state at t = 0 of blocks at `centroid (n, 3)` moving with `velocity (n, 12)`."""
    n = len(centroid)
    return State(centroid=centroid.copy(), affine=np.repeat(np.eye(3)[None], n, axis=0),
                 rotation=np.repeat(np.eye(3)[None], n, axis=0), velocity=velocity,
                 stress=np.zeros((n, 6)), dt=dt, last_dt=dt)


_SCALARS = ("time", "step", "dt", "last_dt", "contact_energy")


def save_state(state: State, path: str | os.PathLike[str]) -> None:
    """Write `state` to `path` (a `.npz` file of plain arrays; floats kept bit for bit)."""
    arrays = {name: getattr(state, name) for name in state_arrays()
              if getattr(state, name) is not None}
    arrays.update({f"memory_{name}": getattr(state.memory, name) for name in MEMORY_FIELDS})
    meta = {name: getattr(state, name) for name in _SCALARS}
    meta.update(energies=state.energies, diagnostics=dataclasses.asdict(state.diagnostics))
    with open(path, "wb") as fh:  # np.savez would add ".npz" to a name without it
        np.savez(fh, meta=np.array(json.dumps(meta)), **arrays)


def load_state(path: str | os.PathLike[str]) -> State:
    """The :class:`State` written by :func:`save_state`."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {name: z[name] if name in z.files else None for name in state_arrays()}
        memory = ContactMemory(**{name: z[f"memory_{name}"] for name in MEMORY_FIELDS
                                  if f"memory_{name}" in z.files})
    diagnostics = Diagnostics(**meta["diagnostics"])
    return State(**arrays, **{name: meta[name] for name in _SCALARS}, memory=memory,
                 energies=meta["energies"], diagnostics=diagnostics)
