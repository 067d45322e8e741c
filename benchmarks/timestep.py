"""Why Δt is what it is on a cut rock mass (issue 14): time per simulated second, the
steps' Δt histogram by what limited each one (`Diagnostics.limited_by`), cuts by reason,
linear solves and K factorizations per step, open-close cycles and open/closed changes.

`python -m benchmarks.timestep [spacing] [simulated_s]` prints it for the jointed cube
(examples/jointed_cube.json, 12 m, three persistent sets; default spacing 3 m, 0.01 s);
`python -m benchmarks --only timestep` puts it in REPORT.md.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from benchmarks.bench_jointed_cube import scene
from engine.model import Model
from engine.step.simulation import Simulation, StepFailure
from schemas.convert import build_model

#: Δt histogram bins (s): the asked 1 ms down to 1 µs, logarithmic
DT_BINS = np.array([1e-6, 1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3 * (1 + 1e-9)])


def jointed_cube(spacing: float = 3.0, **controls: Any) -> Model:
    """The jointed cube example with its three sets at `spacing` m (1.5: the example)."""
    s = scene(12.0)
    for j in s["joints"]:
        j["spacing"] = spacing
    model = build_model(s).model
    model.controls = dataclasses.replace(model.controls, **controls)
    return model


def time_step_budget(model: Model, simulated_s: float, max_wall: float = 240.0
                     ) -> dict[str, Any]:
    """Step `model` through `simulated_s` s (or `max_wall` s of wall time): per simulated
    second of wall time, mean Δt, the Δt histogram (`DT_BINS`) split by what limited each
    step, cuts by reason, and solves, factorizations, open-close cycles and open/closed
    changes per step (solves and factorizations include the failed attempts)."""
    sim = Simulation(model)
    status, message = "completed", ""
    dts: list[float] = []
    reasons: list[str] = []
    cycles: list[int] = []
    changes: list[int] = []
    t0 = time.perf_counter()
    while sim.state.time < simulated_s - 1e-12 and time.perf_counter() - t0 < max_wall:
        before = dict(sim.state.diagnostics.limited_by)
        try:
            res = sim.step()
        except StepFailure as exc:
            status, message = "failed", str(exc)
            break
        after = sim.state.diagnostics.limited_by
        reasons.append(next(k for k, v in after.items() if v != before.get(k, 0)))
        dts.append(sim.state.last_dt)
        cycles.append(res.iterations)
        changes.append(res.mode_changes)
    wall = time.perf_counter() - t0
    d = sim.state.diagnostics
    n = max(len(dts), 1)
    dt = np.asarray(dts)
    bins = np.digitize(dt, DT_BINS)
    hist = {r: np.bincount(bins[[x == r for x in reasons]], minlength=len(DT_BINS) + 1)
            .tolist() for r in sorted(set(reasons))}
    return {"blocks": int((~sim.system.fixed).sum()), "unknowns": sim.system.n_unknowns,
            "steps": len(dts), "simulated": sim.state.time, "wall_s": wall,
            "per_sim_second_s": wall / sim.state.time if sim.state.time > 0 else float("nan"),
            "mean_dt": float(dt.mean()) if len(dt) else float("nan"),
            "asked_dt": model.controls.time_step,
            "limited_by": dict(d.limited_by), "cuts": dict(d.cuts), "dt_bins": DT_BINS.tolist(),
            "dt_hist": hist, "solves_per_step": d.solves / n,
            "factorizations_per_step": d.factorizations / n,
            "cycles_per_step": float(np.mean(cycles)) if cycles else 0.0,
            "mode_changes_per_step": float(np.mean(changes)) if changes else 0.0,
            "timings_per_step": {k: v / n for k, v in d.timings.items()},
            "status": status, "message": message}


def describe(r: dict[str, Any]) -> str:
    """Lines of text for one :func:`time_step_budget` result."""
    edges = [f"{x:.0e}" for x in r["dt_bins"]]
    labels = [f"<{edges[0]}"] + [f"{a}–{b}" for a, b in zip(edges, edges[1:], strict=False)] + [
        f"≥{edges[-1]}"]
    lines = [f"{r['blocks']} blocks, {r['steps']} steps to t = {r['simulated']:.4g} s in "
             f"{r['wall_s']:.1f} s: {r['per_sim_second_s']:.4g} s per simulated s, mean Δt "
             f"{r['mean_dt']:.3g} s (asked {r['asked_dt']:g}); solves/step "
             f"{r['solves_per_step']:.1f}, factorizations/step "
             f"{r['factorizations_per_step']:.1f}, cycles/step {r['cycles_per_step']:.1f}, "
             f"open/closed changes/step {r['mode_changes_per_step']:.1f}; {r['status']}",
             f"  limited by {r['limited_by']}; cuts {r['cuts']}",
             "  ms/step " + ", ".join(f"{k} {v * 1e3:.1f}"
                                      for k, v in r["timings_per_step"].items()),
             "  Δt histogram (steps per bin, by limit): " + " ".join(labels)]
    lines += [f"    {k:22s} {v}" for k, v in r["dt_hist"].items()]
    return "\n".join(lines)


def run_timestep(out: Path, full: bool) -> dict[str, Any]:
    """Section 4b: the jointed cube at 3 m spacing (quick, 0.01 s) and the example itself
    (1.5 m, ~750 blocks; full, 0.005 s)."""
    rows = []
    for spacing, simulated in ((3.0, 0.01), *(((1.5, 0.005),) if full else ())):
        r = time_step_budget(jointed_cube(spacing, duration=simulated), simulated)
        rows.append({"scene": f"jointed cube, sets at {spacing:g} m", "spacing": spacing, **r})
        print(describe(r), flush=True)
    data = {"rows": rows}
    h.save_json(out, "timestep", data)
    return data


def timestep_part(data: dict[str, Any]) -> str:
    """Section 4b of REPORT.md: one block of :func:`describe` per scene."""
    lines = ["## 4b. Why Δt is what it is on a cut rock mass", "",
             "The jointed cube (`examples/jointed_cube.json`: 12 m, three persistent sets, "
             "fixed base, penalty 1e11, asked Δt 1 ms) stepped through a short simulated "
             "time: what limited each step's Δt (`Diagnostics.limited_by`: a cut in the step "
             "by its reason, a cut kept from the step before, regrowth by ×1.5, held by the "
             "step before's open/closed changes, the asked Δt), and the linear solves and K "
             "factorizations per step (failed attempts included). Reproduce one scene with "
             "`python -m benchmarks.timestep SPACING SIMULATED_S`.", ""]
    for r in data["rows"]:
        lines += [f"**{r['scene']}**", "", "```", describe(r), "```", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    args = [float(a) for a in sys.argv[1:3]]
    simulated = args[1] if len(args) > 1 else 0.01
    print(describe(time_step_budget(jointed_cube(args[0] if args else 3.0,
                                                 duration=simulated), simulated)))
