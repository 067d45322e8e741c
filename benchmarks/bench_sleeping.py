"""Sleeping islands on a slope where a tenth of the blocks move (issue 38): the same scene
with sleeping on and off under the Newton solve, in one run.

The scene: the 10 m cube cut by three joint sets at 2.5 m (134 blocks, `benchmarks.pile.
rock_mass_model`) with joints at φ 80° (the cut mass stands), and beside it a fixed 30°
ramp down which 13 free cubes (a tenth of the blocks) slide at φ 10°. Each run goes
`DURATION` s at the asked 1 ms; the wall time of its last `MEASURED` s (once the standing
mass has had time to fall asleep) is compared.

Run: `python -m benchmarks.bench_sleeping [DURATION]` (default 0.3 s); writes
`benchmarks/results/sleeping.json` and prints the ratio.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

OUT = Path(__file__).parent / "results" / "sleeping.json"
#: the wall time of this last part of each run is compared (s of simulated time)
MEASURED = 0.15
SLIDERS = 13


def scene(duration: float, sleep_velocity: float):  # noqa: ANN201 (an engine Model)
    """The standing cut mass and the sliding cubes on their ramp, under the Newton solve."""
    from benchmarks.pile import rock_mass_model
    from engine.geometry.shapes import oriented_box
    from engine.model import Block, JointMaterial

    model = rock_mass_model(2.5, dt=1e-3, penalty=1e10, duration=duration)
    a = np.radians(30.0)
    down = np.array([np.cos(a), 0.0, -np.sin(a)])
    up = np.array([np.sin(a), 0.0, np.cos(a)])
    axes = np.array([down, [0.0, 1.0, 0.0], up])
    ramp_origin = np.array([14.0, 0.0, 12.0])
    blocks = list(model.blocks)
    blocks.append(Block(oriented_box(ramp_origin - up * 1.0 - down * 1.0, axes,
                                     [40.0, 2.0 * SLIDERS + 2.0, 1.0]), "ramp", fixed=True))
    for k in range(SLIDERS):
        blocks.append(Block(oriented_box(ramp_origin + np.array([0.0, 1.0 + 2.0 * k, 0.0]),
                                         axes, [1.0, 1.0, 1.0]), f"slider{k}", material=0))
    ramp = len(model.blocks)
    joints = [JointMaterial(np.radians(80.0)), JointMaterial(np.radians(10.0))]
    pairs = {(ramp, ramp + 1 + k): 1 for k in range(SLIDERS)}
    controls = dataclasses.replace(model.controls, contact_solver="newton",
                                   sleep_velocity=sleep_velocity, record_contacts=False)
    return dataclasses.replace(model, blocks=blocks, joint_materials=joints,
                               pair_joint_material=pairs, controls=controls)


def one(duration: float, sleep_velocity: float) -> dict:
    """Run the scene; the wall time of its last MEASURED s, the blocks asleep at the end."""
    from engine.step.simulation import Simulation

    sim = Simulation(scene(duration, sleep_velocity))
    start, clock = duration - MEASURED, None
    while sim.state.time < duration - 1e-9:
        if clock is None and sim.state.time >= start - 1e-9:
            clock, steps0 = time.perf_counter(), sim.state.step
        res = sim.step()
    wall = time.perf_counter() - clock
    weak_blocks, weak_contacts = _not_holding(sim, res)
    asleep = 0 if sim.state.asleep is None else int(sim.state.asleep.sum())
    moved = np.linalg.norm(sim.state.centroid - sim.system.c0, axis=1)
    return {"sleep_velocity": sleep_velocity, "wall_s": wall,
            "steps": sim.state.step - steps0, "asleep_end": asleep,
            "free_blocks": int((~sim.system.fixed).sum()),
            "sliders_moved_m": float(moved[-SLIDERS:].min()),
            "wakes": sim.state.diagnostics.wakes,
            "contacts_end": int(np.sum(np.maximum(res.contacts.block_i, res.contacts.block_j)
                                       < sim.system.n - SLIDERS - 1)),
            "blocks_not_holding_end": weak_blocks, "contacts_not_holding_end": weak_contacts}


def _not_holding(sim, res) -> tuple[int, int]:  # noqa: ANN001 (a Simulation, a StepResult)
    """At the end: the standing mass's free blocks that fail sleeping's holding test, and
    its contacts that make them fail it (carrying a force, not stuck below the rim by the
    sleep margin)."""
    from engine.step import sleep

    system, cs = sim.system, res.contacts
    holding = sleep._holding(system, sim.state, res)
    mass = np.arange(system.n) < system.n - SLIDERS - 1  # not the ramp and its cubes
    weak = (sleep.weak_contacts(system, sim.state, res) & mass[cs.block_i]
            & mass[cs.block_j])
    return int((~holding & ~system.fixed & mass).sum()), int(weak.sum())


def main() -> None:
    warnings.simplefilter("ignore")
    duration = float(sys.argv[1]) if len(sys.argv) > 1 else 0.3
    rows = [one(duration, 1e-3), one(duration, 0.0)]
    ratio = rows[0]["wall_s"] / rows[1]["wall_s"]
    out = {"duration_s": duration, "measured_s": MEASURED, "rows": rows,
           "ratio_sleeping_to_awake": ratio}
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1))
    for r in rows:
        print(f"sleep_velocity {r['sleep_velocity']:g}: last {MEASURED:g} s in "
              f"{r['wall_s']:.2f} s wall ({r['steps']} steps), {r['asleep_end']} of "
              f"{r['free_blocks']} asleep, sliders moved ≥ {r['sliders_moved_m']:.3f} m",
              flush=True)
    print(f"sleeping / awake: {ratio:.2f}")


if __name__ == "__main__":
    main()
