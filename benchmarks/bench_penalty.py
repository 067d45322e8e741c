"""Speed against accuracy on a cut rock mass: the contact penalty (issue 14).

The 10 m cube of `benchmarks.pile.rock_mass_model` (three joint sets at SPACING m, φ 30°,
fixed base, asked Δt 1 ms) stepped through SIMULATED s at penalties from 1e8 N/m to the
scene's default (:func:`engine.dynamics.system.default_penalty`). Per penalty: wall time per
simulated second, mean Δt, solves per step, cuts, the deepest penetration, and how far
the blocks' displacements at the end differ from the stiffest run's (RMS over the blocks,
relative to that run's RMS displacement). Run:
`python -m benchmarks.bench_penalty [SPACING] [SIMULATED] [PENALTY ...]` (defaults 2.5 m,
0.1 s, 1e8 – 1e11 and the default; ~3 min on 2 cores).
"""

from __future__ import annotations

import sys
import time
import warnings

import numpy as np

from benchmarks.pile import rock_mass_model
from engine.dynamics.system import default_penalty
from engine.step.simulation import Simulation, StepFailure


def run_one(spacing: float, simulated_s: float, penalty: float) -> dict:
    """Step the rock mass at `penalty` N/m through `simulated_s` s (or until it fails)."""
    sim = Simulation(rock_mass_model(spacing, dt=1e-3, penalty=penalty))
    free = ~sim.system.fixed
    start = sim.state.centroid[free].copy()
    status = "completed"
    t0 = time.perf_counter()
    while sim.state.time < simulated_s - 1e-12:
        try:
            sim.step()
        except StepFailure as exc:
            status = f"failed: {exc}"
            break
    wall = time.perf_counter() - t0
    d = sim.state.diagnostics
    steps = max(sim.state.step, 1)
    return {"penalty": penalty, "blocks": int(free.sum()), "status": status, "wall_s": wall,
            "simulated_s": sim.state.time, "per_sim_second_s": wall / max(sim.state.time, 1e-300),
            "mean_dt": sim.state.time / steps, "solves_per_step": d.solves / steps,
            "cuts": sum(d.cuts.values()), "max_penetration_m": d.max_penetration,
            "max_penetration_ratio": d.max_penetration_ratio,
            "displacement": sim.state.centroid[free] - start}


def _rms(u: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(u ** 2, axis=1))))


def compare(rows: list[dict]) -> None:
    """Each run's RMS displacement, vertical and horizontal (a soft penalty lets the mass
    sink into its springs; sliding is horizontal), and its RMS difference from the
    stiffest run's, relative to that run's RMS (in place)."""
    ref = max(rows, key=lambda r: r["penalty"])["displacement"]
    for r in rows:
        u = r["displacement"]
        r["rms_vertical_m"] = _rms(u[:, 2:])
        r["rms_horizontal_m"] = _rms(u[:, :2])
        r["vertical_difference"] = _rms(u[:, 2:] - ref[:, 2:]) / max(_rms(ref[:, 2:]), 1e-300)
        r["horizontal_difference"] = _rms(u[:, :2] - ref[:, :2]) / max(_rms(ref[:, :2]),
                                                                       1e-300)


def main() -> None:
    warnings.simplefilter("ignore")
    args = sys.argv[1:]
    spacing = float(args[0]) if args else 2.5
    simulated = float(args[1]) if len(args) > 1 else 0.1
    default = default_penalty(rock_mass_model(spacing, dt=1e-3, penalty=None))
    penalties = [float(a) for a in args[2:]] or sorted({1e8, 1e9, 1e10, 1e11, default})
    rows = [run_one(spacing, simulated, p) for p in penalties]
    compare(rows)
    print(f"rock mass at {spacing} m spacing ({rows[0]['blocks']} blocks), {simulated} s "
          f"simulated, asked dt 1 ms; the scene's default penalty is {default:.0e} N/m")
    print("| penalty (N/m) | s per simulated s | mean Δt (s) | solves / step | cuts | "
          "deepest penetration (m, share of thickness) | RMS displacement vertical / "
          "horizontal (m) | differs from the stiffest's, vertical / horizontal | status |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['penalty']:.0e}{' (default)' if r['penalty'] == default else ''} | "
              f"{r['per_sim_second_s']:.0f} | {r['mean_dt']:.2g} | {r['solves_per_step']:.1f} | "
              f"{r['cuts']} | {r['max_penetration_m']:.2g} ({r['max_penetration_ratio']:.1e}) | "
              f"{r['rms_vertical_m']:.3g} / {r['rms_horizontal_m']:.3g} | "
              f"{r['vertical_difference']:.1%} / {r['horizontal_difference']:.1%} | "
              f"{r['status']} |",
              flush=True)


if __name__ == "__main__":
    main()
