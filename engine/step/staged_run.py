"""Running a staged analysis (:mod:`engine.step.stages`): the stages in order, each from the
state the one before ended with; a checkpoint at each stage's end; the recorder fed frames
of the full model; the result's summary with a table of the stages."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from engine.dynamics.state import State, load_state, save_state
from engine.dynamics.system import build_system
from engine.model import Model
from engine.status import STATUS_COMPLETED
from engine.step.frame import Frame, Recorder
from engine.step.simulation import Progress, RunResult, run
from engine.step.stages import Ledger, Stage, carry_state, stage_model


class FullFrames:
    """A recorder in front of another: `begin` and `end` once for the whole run, and every
    frame of a stage's smaller model expanded to the full model's blocks and bolts (a
    removed block frozen where it was removed, at rest; a bolt not acting: no force)."""

    def __init__(self, inner: Recorder, full: Model) -> None:
        self.inner, self.full = inner, full
        n = len(full.blocks)
        self.centroid = np.array([b.polyhedron.centroid for b in full.blocks]).reshape(n, 3)
        self.affine = np.repeat(np.eye(3)[None], n, axis=0)
        self.rotation = np.zeros((n, 3))
        self.keep = np.arange(n)
        self.bolt_rows = np.zeros(0, np.int64)  # full bolt index of each acting bolt
        self.started = False

    def hold(self, state: State, blocks: list[int]) -> None:
        """Where the blocks `blocks` (full-model indices) are in `state`: a block removed
        next stays there in the frames that follow (a resumed run knows it from its
        checkpoint, as the whole run does)."""
        from scipy.spatial.transform import Rotation

        k = np.asarray(blocks, np.int64)
        self.centroid[k], self.affine[k] = state.centroid, state.affine
        self.rotation[k] = Rotation.from_matrix(state.rotation).as_rotvec().reshape(-1, 3)

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        if not self.started:
            self.inner.begin(self.full, scene_json)
            self.started = True

    def record(self, frame: Frame) -> None:
        k, n = self.keep, len(self.full.blocks)
        self.centroid[k], self.affine[k], self.rotation[k] = (
            frame.centroids, frame.affine, frame.rotation)
        velocity, stress = np.zeros((n, 12)), np.zeros((n, 6))
        velocity[k], stress[k] = frame.velocity, frame.stress
        out = dataclasses.replace(frame, centroids=self.centroid.copy(),
                                  affine=self.affine.copy(), rotation=self.rotation.copy(),
                                  velocity=velocity, stress=stress)
        if frame.contacts is not None:
            out.contacts = dataclasses.replace(frame.contacts, block_i=k[frame.contacts.block_i],
                                               block_j=k[frame.contacts.block_j])
        if frame.water_force is not None:
            out.water_force = np.zeros((n, 3))
            out.water_force[k] = frame.water_force
        if self.full.bolts:
            nb = len(self.full.bolts)
            out.bolt_axial_force, out.bolt_shear_force = np.zeros(nb), np.zeros(nb)
            out.bolt_status = np.zeros(nb, np.int8)
            if frame.bolt_axial_force is not None:
                r = self.bolt_rows
                out.bolt_axial_force[r] = frame.bolt_axial_force
                out.bolt_shear_force[r] = frame.bolt_shear_force
                out.bolt_status[r] = frame.bolt_status
        self.inner.record(out)

    def end(self, status: str, message: str = "", summary: dict[str, Any] | None = None) -> None:
        self.last = (status, message, summary)

    def close(self, status: str, message: str, summary: dict[str, Any]) -> None:
        """End the inner recorder once, with the whole run's summary."""
        if self.started:
            self.inner.end(status, message, summary)


@dataclass
class StageRecord:
    """How one stage went: its name, clock (s) and steps, what it removed and installed."""

    name: str
    start_time: float
    end_time: float
    start_step: int
    end_step: int = 0
    status: str = ""
    removed_blocks: list[int] = field(default_factory=list)
    bolts: list[str] = field(default_factory=list)
    removed_energy: float = 0.0
    checkpoint: str | None = None


def save_checkpoint(path: str | os.PathLike[str], state: State, ledger: Ledger) -> None:
    """Save the state at a stage's end (`path`, .npz) with the ledger beside it
    (`path` + `.stage.json`)."""
    save_state(state, path)
    Path(f"{os.fspath(path)}.stage.json").write_text(json.dumps({
        "stage": ledger.stage, "blocks": ledger.blocks, "bolts": ledger.bolts,
        "installed": {k: [v[0], list(v[1])] for k, v in ledger.installed.items()}}))


def load_checkpoint(path: str | os.PathLike[str]) -> tuple[State, Ledger]:
    """The state and ledger saved by :func:`save_checkpoint`."""
    meta = json.loads(Path(f"{os.fspath(path)}.stage.json").read_text())
    ledger = Ledger(stage=int(meta["stage"]), blocks=[int(b) for b in meta["blocks"]],
                    bolts=list(meta["bolts"]),
                    installed={k: (float(v[0]), tuple(float(x) for x in v[1]))
                               for k, v in meta["installed"].items()})
    return load_state(path), ledger


def checkpoint_fits(full: Model, stages: Sequence[Stage], ledger: Ledger) -> str:
    """Why a checkpoint cannot continue this staged run ('' when it can): its stage must be
    one of the run's, and the blocks in play at its end the same."""
    if not 0 <= ledger.stage < len(stages):
        return f"the checkpoint ends stage {ledger.stage + 1}; the scene has {len(stages)}"
    model, keep = stage_model(full, stages[ledger.stage], ledger)
    name = stages[ledger.stage].name
    if keep.tolist() != ledger.blocks:
        return (f"the blocks in play at the end of stage '{name}' differ from the "
                "checkpoint's (another domain, joints or excavation?)")
    bolts = [b.name for b in model.bolts]
    if bolts != ledger.bolts:
        return (f"the bolts acting at the end of stage '{name}' differ from the checkpoint's "
                f"({', '.join(bolts) or 'none'} against {', '.join(ledger.bolts) or 'none'}): "
                "change only the stages after it (a bolt no stage adds acts from the start)")
    return ""


def _transition(full: Model, stages: Sequence[Stage], k: int, state: State | None,
                ledger: Ledger) -> tuple[Model, State | None]:
    """The model of stage `k` and the state it starts from (None: the run's start)."""
    if state is None:
        model, keep = stage_model(full, stages[k], ledger)
        ledger.blocks = keep.tolist()
        ledger.bolts = [b.name for b in model.bolts]
        return model, None
    old_model, old_keep = stage_model(full, stages[ledger.stage], ledger)
    old_system = build_system(old_model)
    return carry_state(full, old_system, state, old_keep, stages[k], ledger)


def run_stages(full: Model, stages: Sequence[Stage], recorder: Recorder | None = None,
               progress: Callable[[Progress], None] | None = None,
               should_stop: Callable[[], bool] | None = None, scene_json: str | None = None,
               checkpoints: str | os.PathLike[str] | None = None,
               resume: tuple[State, Ledger] | None = None) -> RunResult:
    """Run `full` through `stages` (from the start, or from a checkpoint `resume` at a
    stage's end). With `checkpoints` (a folder) the state at each stage's end is saved
    there as `stage-<k>.npz` (k from 1). The summary carries `stages`, one
    :class:`StageRecord` each (as dicts)."""
    started = time.perf_counter()  # the summary's wall time is the whole run's
    state, ledger = (None, Ledger()) if resume is None else resume
    first = 0 if resume is None else ledger.stage + 1
    front = None if recorder is None else FullFrames(recorder, full)
    records: list[StageRecord] = []
    result: RunResult | None = None
    gone: dict[int, dict[str, Any]] = {}  # removed block -> where and when it went
    for k in range(first, len(stages)):
        before = set(ledger.blocks) if ledger.stage >= 0 else set(range(len(full.blocks)))
        if state is not None and front is not None:
            front.hold(state, ledger.blocks)
        if state is not None:
            for pos, b in enumerate(ledger.blocks):
                if b in stages[k].removed:
                    gone[b] = {"centroid": state.centroid[pos].tolist(),
                               "removed_in_stage": stages[k].name, "removed_at": state.time}
        energy0 = 0.0 if state is None else state.energies.get("removed_energy", 0.0)
        model, state = _transition(full, stages, k, state, ledger)
        ledger.stage = k
        rec = StageRecord(stages[k].name, 0.0 if state is None else state.time,
                          stages[k].end_time, 0 if state is None else state.step,
                          removed_blocks=sorted(before - set(ledger.blocks)),
                          bolts=list(ledger.bolts))
        rec.removed_energy = (0.0 if state is None else
                              state.energies.get("removed_energy", 0.0) - energy0)
        if front is not None:
            front.keep = np.array(ledger.blocks, np.int64)
            names = [b.name or f"bolt{i + 1}" for i, b in enumerate(full.bolts)]
            front.bolt_rows = np.array([names.index(b) for b in ledger.bolts], np.int64)
        result = run(model, recorder=front, progress=_whole(progress, stages[-1].end_time),
                     should_stop=should_stop,
                     scene_json=scene_json, resume_from=state)
        state = result.state
        rec.end_step, rec.status = state.step, result.status
        if checkpoints is not None and result.status == STATUS_COMPLETED:
            path = Path(checkpoints) / f"stage-{k + 1}.npz"
            path.parent.mkdir(parents=True, exist_ok=True)
            save_checkpoint(path, state, ledger)
            rec.checkpoint = str(path)
        records.append(rec)
        if result.status != STATUS_COMPLETED:
            break
    if result is None:
        raise ValueError("no stage left to run after the checkpoint")
    names = [b.name or f"block{i}" for i, b in enumerate(full.blocks)]
    result.summary["stages"] = [
        {**dataclasses.asdict(r), "removed_blocks": [names[b] for b in r.removed_blocks]}
        for r in records]
    result.summary["removed_energy"] = state.energies.get("removed_energy", 0.0)
    result.summary["blocks"] = _full_blocks(full, ledger, result.summary["blocks"], gone)
    wall = time.perf_counter() - started
    result.summary["wall_time"] = wall  # every stage's, not the last one's
    result = dataclasses.replace(result, wall_time=wall)
    if front is not None:
        front.close(result.status, result.message, result.summary)
    return result


def _whole(progress: Callable[[Progress], None] | None, end: float
           ) -> Callable[[Progress], None] | None:
    """A stage's progress as progress through the whole run (its duration the stages')."""
    if progress is None:
        return None
    return lambda p: progress(Progress(p.step, p.time, end, p.dt))


def _full_blocks(full: Model, ledger: Ledger, last: list[dict[str, Any]],
                 gone: dict[int, dict[str, Any]]) -> list[dict[str, Any]]:
    """The summary's blocks at full size: the last stage's, and each removed block where it
    was when it went (at rest: its motion left the model with it)."""
    out: list[dict[str, Any]] = []
    pos = {b: k for k, b in enumerate(ledger.blocks)}
    for b, blk in enumerate(full.blocks):
        if b in pos:
            out.append(last[pos[b]])
            continue
        c0 = blk.polyhedron.centroid
        c = gone.get(b, {}).get("centroid", c0.tolist())
        out.append({"name": blk.name or f"block{b}", "centroid": c, "rotation": [0.0] * 3,
                    "displacement": (np.asarray(c) - c0).tolist(), "velocity": [0.0] * 6,
                    "removed": True, **{k: v for k, v in gone.get(b, {}).items()
                                        if k != "centroid"}})
    return out


def run_scene(model: Model, stages: Sequence[Stage], **kwargs: Any) -> RunResult:
    """A staged run when there are stages, else one :func:`run` of the model (the keyword
    arguments of :func:`run_stages`; `checkpoints` and `resume` only with stages)."""
    if stages:
        return run_stages(model, stages, **kwargs)
    kwargs.pop("checkpoints", None)
    if kwargs.pop("resume", None) is not None:
        raise ValueError("only a staged run resumes from a stage's checkpoint")
    return run(model, **kwargs)
