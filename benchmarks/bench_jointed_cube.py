"""Benchmark: issue 12's jointed cube (examples/jointed_cube.json) starts clean.

Run as `python benchmarks/bench_jointed_cube.py [size_m] [steps]` (default 12 m, 50 steps):
cuts the cube with and without the small-block and sliver merges, prints block counts,
thinnest blocks, cutting time, the deepest contact at step 0 (detected within the first
step's search) and the Δt of each of the first `steps` steps with the reasons of its cuts.
"""

from __future__ import annotations

import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

from engine.contact.search import detect
from engine.step.simulation import Simulation
from schemas.convert import build_model

SCENE = Path(__file__).resolve().parents[1] / "examples" / "jointed_cube.json"


def scene(size: float = 12.0, **domain: float) -> dict:
    """The example scene with the cube's edge `size` m (base scaled along) and domain options."""
    s = json.loads(SCENE.read_text())
    s = copy.deepcopy(s)
    s["domain"]["box"]["max"] = [size] * 3
    s["domain"].update(domain)
    c = size / 2
    for j in s["joints"]:
        j["point"] = [c, c, c]
    base = s["blocks"][0]
    lo, hi = -3.0, size + 3.0
    base["vertices"] = [[x, y, z] for z in (-2.0, 0.0) for (x, y) in
                        ((lo, lo), (hi, lo), (hi, hi), (lo, hi))]
    return s


def cut_stats(s: dict) -> tuple[object, float]:
    t0 = time.perf_counter()
    built = build_model(s)
    elapsed = time.perf_counter() - t0
    free = [b.polyhedron for b in built.model.blocks if not b.fixed]
    width = min(p.width for p in free)
    vol = sum(p.volume for p in free)
    small = min(p.volume for p in free)
    print(f"  {len(free)} blocks, thinnest {width:.4g} m, smallest {small:.3g} m³, "
          f"volume {vol:.12g} m³, build {elapsed:.2f} s")
    for w in built.warnings:
        print("  warning:", w)
    return built, width


def run_steps(built: object, steps: int) -> None:
    """Detect at step 0 within the first step's search, then run `steps` steps."""
    sim = Simulation(built.model)
    contacts = detect(sim.system, sim.state, 0.5 * sim.system.search_distance)
    print(f"  step 0: {len(contacts)} contacts within {sim.system.search_distance:.3g} m, "
          f"deepest {-min(contacts.gap.min(), 0.0):.3g} m; step limit "
          f"{sim.system.max_step_displacement:.3g} m")
    t0 = time.perf_counter()
    dts = []
    for _ in range(steps):
        sim.step()
        dts.append(sim.state.last_dt)
    d = sim.state.diagnostics
    print(f"  {steps} steps in {time.perf_counter() - t0:.1f} s to t = {sim.state.time:.3g} s: "
          f"dt min {min(dts):.3g} s, median {np.median(dts):.3g} s, last {dts[-1]:.3g} s; "
          f"cuts by reason {d.cuts}; deepest penetration {d.max_penetration:.3g} m")


def main(size: float = 12.0, steps: int = 50) -> None:
    print(f"jointed cube {size:g} m, sets 40/120 70/250 80/010 at 1.5 m")
    print("every cell kept (min_block_volume 0, min_block_width 0):")
    built, _ = cut_stats(scene(size, min_block_volume=0, min_block_width=0))
    run_steps(built, steps)
    print("default merges (small blocks and slivers):")
    built, _ = cut_stats(scene(size))
    run_steps(built, steps)


if __name__ == "__main__":
    main(*(float(a) for a in sys.argv[1:2]), *(int(a) for a in sys.argv[2:3]))
