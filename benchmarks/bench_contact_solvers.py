"""Both contact solvers on the same cases, in one run: speed against accuracy (issue 29).

Accuracy: the analytic cases (VALIDATION.md 1 and 5) at Δt 1 ms, their error and wall time.
Speed: the cut rock masses of `benchmarks.pile.rock_mass_model` (10 m cube, three sets,
φ 30°, asked Δt 1 ms) and the shared piles, STEPS steps each in a process of its own: the
wall per step and per phase, iterations per step (open-close cycles, or Gauss–Seidel
sweeps), the Δt actually held, the blocks asleep, peak RSS and the extrapolated wall per
simulated second; MuJoCo on the same piles in the same run when it is installed.
Run: `python -m benchmarks.bench_contact_solvers [STEPS]` (default 10); writes
`benchmarks/results/contact_solvers.json` and prints the table.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SOLVERS = ("open_close", "complementarity")
PHASES = ("detection", "assembly", "solve", "open_close", "update")
#: (name, builder expression): the speed cases
CASES = (
    ("rock mass 5 m", "rock_mass_model(5.0)"),
    ("rock mass 2.5 m", "rock_mass_model(2.5)"),
    ("rock mass 1.2 m", "rock_mass_model(1.2)"),
    ("pile 100", "pile_model(100)"),
    ("pile 1000", "pile_model(1000)"),
)
OUT = Path(__file__).parent / "results" / "contact_solvers.json"


def one(builder: str, solver: str, steps: int) -> dict:
    """Step the case `builder` under `solver` (in this process)."""
    import warnings

    warnings.simplefilter("ignore")
    from benchmarks.harness import peak_rss_mb
    from benchmarks.pile import pile_model, rock_mass_model  # noqa: F401 (the builders)
    from engine.status import StepFailure
    from engine.step.simulation import Simulation

    model = eval(builder)  # one of CASES' expressions
    model.controls = dataclasses.replace(model.controls, contact_solver=solver)
    t0 = time.perf_counter()
    sim = Simulation(model)
    setup = time.perf_counter() - t0
    its, contacts, status, message = [], [], "completed", ""
    sim.state.diagnostics.timings.clear()
    t1 = time.perf_counter()
    for _ in range(steps):
        try:
            res = sim.step()
        except StepFailure as exc:
            status, message = "failed", str(exc)
            break
        its.append(res.iterations)
        contacts.append(len(res.contacts))
    wall = time.perf_counter() - t1
    n = max(sim.state.step, 1)
    tm = sim.state.diagnostics.timings
    asleep = 0 if sim.state.asleep is None else int(sim.state.asleep.sum())
    return {"blocks": int((~sim.system.fixed).sum()), "solver": solver, "setup_s": setup,
            "steps": sim.state.step, "simulated_s": sim.state.time, "wall_s": wall,
            "per_step_s": wall / n, "per_sim_second_s": wall / max(sim.state.time, 1e-12),
            "mean_dt": sim.state.time / n, "iterations_mean": float(np.mean(its or [0])),
            "iterations_max": int(np.max(its or [0])), "contacts_mean": float(
                np.mean(contacts or [0])), "asleep_end": asleep, "status": status,
            "message": message[:200], "rss_peak_mb": peak_rss_mb(),
            **{f"t_{p}": tm.get(p, 0.0) / n for p in PHASES}}


def accuracy() -> list[dict]:
    """The incline (φ 20°, 1 s) and the ten-cube stack (50 steps) under both solvers."""
    from engine.geometry.shapes import box
    from engine.model import AnalysisControls, Block, JointMaterial, Model
    from engine.step.simulation import Simulation, run
    from tests.test_simulation import DOWN_DIP, W, incline_model

    rows = []
    a = 9.81 * (np.sin(np.radians(30)) - np.cos(np.radians(30)) * np.tan(np.radians(20)))
    for solver in SOLVERS:
        m = incline_model(20.0)
        m.controls = dataclasses.replace(m.controls, contact_solver=solver)
        t0 = time.perf_counter()
        r = run(m)
        s = np.array(r.summary["blocks"][1]["displacement"]) @ DOWN_DIP
        rows.append({"case": "incline φ20 (1 s)", "solver": solver,
                     "wall_s": time.perf_counter() - t0,
                     "error": abs(s / (0.5 * a) - 1.0), "measure": "slide distance"})
        blocks = [Block(box([-1, -1, -1], [2, 2, 0]), "base", fixed=True)]
        blocks += [Block(box([0, 0, k], [1, 1, k + 1]), f"c{k}") for k in range(10)]
        m = Model(blocks=blocks, joint_materials=[JointMaterial(np.radians(30))],
                  controls=AnalysisControls(duration=1, time_step=1e-3, penalty=1e10,
                                            contact_solver=solver))
        sim = Simulation(m)
        t0 = time.perf_counter()
        for _ in range(50):
            res = sim.step()
        cs = res.contacts
        err = 0.0
        for upper in range(1, 11):
            sel = ((cs.block_i == upper) & (cs.block_j == upper - 1)) | (
                (cs.block_j == upper) & (cs.block_i == upper - 1))
            err = max(err, abs(res.normal_force[sel].sum() / ((11 - upper) * W) - 1.0))
        rows.append({"case": "stack of 10 cubes (50 steps)", "solver": solver,
                     "wall_s": time.perf_counter() - t0, "error": err,
                     "measure": "interface forces kW"})
    return rows


def mujoco(n: int, steps: int) -> dict | None:
    """MuJoCo on the pile of `n` for `steps` steps of 1 ms, or None when not installed."""
    try:
        from benchmarks.peers import mujoco_pile
        from benchmarks.pile import pile_path

        r = mujoco_pile(pile_path(n), dt=1e-3, duration=steps * 1e-3)
    except ImportError:
        return None
    return {"blocks": n, "solver": "MuJoCo", "steps": steps, "wall_s": r["wall_s"],
            "per_sim_second_s": r["wall_s"] / (steps * 1e-3), "mean_dt": 1e-3}


def main() -> None:
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    only = sys.argv[2:]  # case names to run (default all)
    out = {"accuracy": accuracy(), "speed": []}
    for row in out["accuracy"]:
        print(f"{row['case']:30s} {row['solver']:16s} error {row['error']:.2e} "
              f"({row['measure']}) in {row['wall_s']:.2f} s", flush=True)
    for name, builder in CASES:
        if only and name not in only:
            continue
        for solver in SOLVERS:
            try:
                proc = subprocess.run([sys.executable, "-c", (
                    "import json; from benchmarks.bench_contact_solvers import one; "
                    f"print(json.dumps(one({builder!r}, {solver!r}, {steps})))")],
                    capture_output=True, text=True, check=True, timeout=3600)
                r = json.loads(proc.stdout.strip().splitlines()[-1])
            except (subprocess.SubprocessError, ValueError) as exc:
                r = {"solver": solver, "status": "error", "message": str(exc)[-300:]}
            r["case"] = name
            out["speed"].append(r)
            if r.get("status") == "error":
                print(f"{name:16s} {solver:16s} error {r['message']}", flush=True)
                continue
            print(f"{name:16s} {solver:16s} {r['blocks']:5d} blocks {r['steps']:3d} steps "
                  f"{r['per_step_s']:.3f} s/step (" + ", ".join(
                      f"{p} {r[f't_{p}']:.3f}" for p in PHASES) +
                  f") its {r['iterations_mean']:.0f}/{r['iterations_max']} "
                  f"mean dt {r['mean_dt']:.2g} s -> {r['per_sim_second_s']:.4g} s per "
                  f"simulated s; asleep {r['asleep_end']}; {r['rss_peak_mb']:.0f} MB; "
                  f"{r['status']} {r['message'][:80]}", flush=True)
        if name.startswith("pile"):
            mj = mujoco(int(name.split()[1]), 1000)
            if mj is not None:
                mj["case"] = name
                out["speed"].append(mj)
                print(f"{name:16s} MuJoCo           {mj['per_sim_second_s']:.4g} s per "
                      "simulated s", flush=True)
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
