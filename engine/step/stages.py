"""Staged analyses: settle, excavate, support, raise the water, shake — one run through an
ordered list of stages, each changing the model when it starts.

A :class:`BlockSystem` never changes, so a stage builds the system of its own
:class:`Model` (:func:`stage_model`: the full model less the blocks removed so far, with the
stage's bolts, water, joint materials, seismic load, ground motion and fixed blocks) and
carries the :class:`State` over (:func:`carry_state`): the kept blocks' rows, the contacts
between kept blocks, the kept bolts' states. Blocks are referred to by their index in the
full model throughout; the recorder sees every frame at full size
(:class:`engine.step.staged_run.FullFrames`), removed blocks frozen where they were removed.

Energy: what leaves with a removed block (its kinetic and strain energy, its contacts'
springs, its fixed points') and with a removed bolt (its spring) is booked as
`removed_energy`, which the balance counts like a dissipation: removing never creates
energy, and the watchdog sees none. The contact penalty is the full model's throughout.

A run through its stages equals, bit for bit, the same run stopped at a stage's end and
resumed from its checkpoint (:mod:`engine.step.staged_run`: `run_stages`,
`save_checkpoint`, `load_checkpoint`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.dynamics.block_terms import kinetic_energy
from engine.dynamics.motion import mass_matrices, mass_properties
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem, default_penalty
from engine.loads import bolts as bolt_loads
from engine.loads.seismic import GroundMotion, SeismicLoad
from engine.loads.water import Water
from engine.model import JointMaterial, Model
from engine.step import sleep


@dataclass(frozen=True)
class Stage:
    """What holds during one stage (complete, not a difference from the stage before).

    `removed`: full-model blocks gone by this stage (those not gone before are removed as
    it starts); `bolts`: names of the full model's bolts acting in it (a bolt not acting
    before is installed as it starts); `fixed`: full-model blocks held fixed (None: those
    the full model fixes). `end_time` (s) is where the stage ends on the run's clock.
    """

    name: str
    end_time: float
    removed: frozenset[int] = frozenset()
    bolts: tuple[str, ...] = ()
    fixed: frozenset[int] | None = None
    water: Water | None = None
    joint_materials: tuple[JointMaterial, ...] | None = None
    seismic: SeismicLoad | None = None
    ground_motion: GroundMotion | None = None


@dataclass
class Ledger:
    """What a staged run carries besides the State: the stage it is in, where each bolt was
    installed (name -> installed length m, span (3,) m), the blocks of the current system
    (full-model indices) and the bolts in it (names)."""

    stage: int = -1
    installed: dict[str, tuple[float, tuple[float, float, float]]] = field(default_factory=dict)
    blocks: list[int] = field(default_factory=list)
    bolts: list[str] = field(default_factory=list)


def fixed_blocks(full: Model, stage: Stage) -> frozenset[int]:
    """The full-model blocks held fixed in `stage`."""
    if stage.fixed is not None:
        return stage.fixed
    return frozenset(b for b, blk in enumerate(full.blocks) if blk.fixed)


def _bolt_name(model: Model, k: int) -> str:
    return model.bolts[k].name or f"bolt{k + 1}"


def stage_model(full: Model, stage: Stage, ledger: Ledger) -> tuple[Model, np.ndarray]:
    """The model of `stage` and its blocks' full-model indices `(n,)`: the full model less
    the removed blocks; bolts on a removed block go with it. The penalty stays the full
    model's, so the contact springs keep their stiffness across stages."""
    keep = np.array([b for b in range(len(full.blocks)) if b not in stage.removed], np.int64)
    new = {int(b): k for k, b in enumerate(keep)}
    fixed = fixed_blocks(full, stage)
    blocks = [dataclasses.replace(full.blocks[b], fixed=b in fixed) for b in keep]
    bolts = []
    for k, bolt in enumerate(full.bolts):
        name = _bolt_name(full, k)
        if name not in stage.bolts or bolt.block not in new or (
                bolt.anchor_block >= 0 and bolt.anchor_block not in new):
            continue
        length, span = ledger.installed.get(name, (None, None))
        bolts.append(dataclasses.replace(
            bolt, name=name, block=new[bolt.block],
            anchor_block=new[bolt.anchor_block] if bolt.anchor_block >= 0 else -1,
            installed_length=length, installed_span=span))
    controls = dataclasses.replace(
        full.controls, duration=stage.end_time,
        penalty=full.controls.penalty if full.controls.penalty is not None
        else default_penalty(full))
    model = dataclasses.replace(
        full, blocks=blocks, bolts=bolts, controls=controls, water=stage.water,
        seismic=stage.seismic, ground_motion=stage.ground_motion,
        joint_materials=list(stage.joint_materials or full.joint_materials),
        pair_joint_material={(new[a], new[b]): m for (a, b), m in
                             full.pair_joint_material.items() if a in new and b in new},
        point_loads=[dataclasses.replace(p, block=new[p.block]) for p in full.point_loads
                     if p.block in new],
        fixed_points=[dataclasses.replace(p, block=new[p.block]) for p in full.fixed_points
                      if p.block in new])
    return model, keep


def _leaving_energy(system: BlockSystem, state: State, gone: np.ndarray,
                    stopped: np.ndarray, lost_rows: np.ndarray) -> float:
    """Energy (J) that leaves the model with the blocks `gone` (bool over the old system's
    blocks: kinetic, strain, fixed points), the blocks `stopped` (newly fixed: kinetic) and
    the contacts `lost_rows` of the memory (their springs)."""
    mass = mass_matrices(system, state)
    take = gone | stopped
    out = kinetic_energy(state.velocity[take], mass[take]) if take.any() else 0.0
    if system.elastic and gone.any():
        vol, _ = mass_properties(system, state)
        comp = np.linalg.solve(system.emat[gone], state.stress[gone][:, :, None])[:, :, 0]
        out += 0.5 * float(np.sum(vol[gone] * np.einsum("ij,ij->i", state.stress[gone], comp)))
    for b, p0 in system.fixed_points:
        if gone[b]:
            r = (state.centroid[b] + state.affine[b] @ (p0 - system.c0[b])) - p0
            out += 0.5 * system.kf * float(r @ r)
    return out + state.memory.spring_energy(system.kn, system.ks, lost_rows)


def _bolt_rows(system: BlockSystem, state: State, names: list[str]
               ) -> tuple[np.ndarray, float]:
    """Rows of the old system's bolts that stay (in the order of `names`, -1: new) and the
    energy (J) the bolts that go held."""
    if system.bolts is None:
        return np.full(len(names), -1, np.int64), 0.0
    old = [b.name for b in system.bolts.bolts]
    rows = np.array([old.index(n) if n in old else -1 for n in names], np.int64)
    going = np.setdiff1d(np.arange(len(old)), rows[rows >= 0])
    if not len(going):
        return rows, 0.0
    bs = bolt_loads.bolt_set([system.bolts.bolts[k] for k in going])
    head, anchor = bolt_loads.bolt_ends(bs, system.c0, state.centroid, state.affine)
    gone = bolt_loads.stored_energy(bs, head, anchor, state.bolt_plastic[going],
                                    state.bolt_shear[going], state.bolt_status[going])
    return rows, gone


def _install(full: Model, system: BlockSystem, state: State, old_keep: np.ndarray,
             stage: Stage, ledger: Ledger) -> None:
    """Record in the ledger the bolts `stage` installs: their length and span now (their
    ends are material points of the blocks given at t = 0; a ground anchor stays put)."""
    pos = {int(b): k for k, b in enumerate(old_keep)}
    for k, bolt in enumerate(full.bolts):
        name = _bolt_name(full, k)
        if name not in stage.bolts or name in ledger.installed or name in ledger.bolts:
            continue
        if bolt.block not in pos or (bolt.anchor_block >= 0 and bolt.anchor_block not in pos):
            continue
        b = pos[bolt.block]
        head = state.centroid[b] + state.affine[b] @ (np.asarray(bolt.head) - system.c0[b])
        anchor = np.asarray(bolt.anchor, float)
        if bolt.anchor_block >= 0:
            a = pos[bolt.anchor_block]
            anchor = state.centroid[a] + state.affine[a] @ (anchor - system.c0[a])
        span = anchor - head
        ledger.installed[name] = (float(np.linalg.norm(span)), tuple(float(x) for x in span))


def carry_state(full: Model, old: BlockSystem, state: State, old_keep: np.ndarray,
                stage: Stage, ledger: Ledger) -> tuple[Model, State]:
    """The model of `stage` and the state it starts from: `state` (of the system `old`,
    whose blocks are `old_keep` in the full model) less what the stage removes, with
    `removed_energy` booked. Updates the ledger."""
    _install(full, old, state, old_keep, stage, ledger)
    model, keep = stage_model(full, stage, ledger)
    stay = np.isin(old_keep, keep)
    rows = np.flatnonzero(stay)
    fixed = fixed_blocks(full, stage)
    now_fixed = np.array([b in fixed for b in old_keep], bool) & ~old.fixed
    mem = state.memory
    kept_contact = stay[mem.key[:, 0]] & stay[mem.key[:, 2]]
    names = [b.name for b in model.bolts]
    bolt_rows, bolt_gone = _bolt_rows(old, state, names)
    leaving = _leaving_energy(old, state, ~stay, now_fixed & stay,
                              np.flatnonzero(~kept_contact)) + bolt_gone
    new_index = np.full(len(old_keep), -1, np.int64)
    new_index[rows] = np.arange(len(rows))
    memory = mem.rows(kept_contact).renumbered(new_index)
    arrays = state.take_blocks(rows)
    arrays["velocity"][now_fixed[rows]] = 0.0
    if arrays["last_d"] is not None:
        arrays["last_d"][now_fixed[rows]] = 0.0
    # a removed neighbour or a newly fixed one changes what a sleeping block rests on
    sleep.forget_basis(arrays, sleep.touched_blocks(mem, ~stay | now_fixed)[rows])
    energies = dict(state.energies)
    energies["removed_energy"] = energies.get("removed_energy", 0.0) + leaving
    new = dataclasses.replace(
        state, **arrays, memory=memory, energies=energies, cache={}, workspace={},
        contact_energy=state.contact_energy - mem.spring_energy(
            old.kn, old.ks, np.flatnonzero(~kept_contact)),
        **_bolt_arrays(state, bolt_rows))
    ledger.blocks, ledger.bolts = keep.tolist(), names
    for name in [n for n in ledger.installed if n not in names]:
        del ledger.installed[name]  # a bolt that left is installed afresh if it comes back
    return model, new


def _bolt_arrays(state: State, rows: np.ndarray) -> dict[str, Any]:
    """The bolt state arrays of the new system: old rows where kept, fresh for new bolts."""
    if not len(rows):
        return {"bolt_plastic": None, "bolt_shear": None, "bolt_status": None}
    plastic, shear = np.zeros(len(rows)), np.zeros((len(rows), 3))
    status = np.zeros(len(rows), np.int8)
    old = rows >= 0
    if old.any():
        plastic[old] = state.bolt_plastic[rows[old]]
        shear[old] = state.bolt_shear[rows[old]]
        status[old] = state.bolt_status[rows[old]]
    return {"bolt_plastic": plastic, "bolt_shear": shear, "bolt_status": status}
