"""Every contact solver on the same cases, in one run: speed against accuracy (issues 29
and 38).

Accuracy: the analytic cases (docs/validation.md) at Δt 1 ms, their error and wall time.
Speed: the cut rock masses of `benchmarks.pile.rock_mass_model` (10 m cube, three sets,
φ 30°, asked Δt 1 ms; STEPS steps) and the shared piles (their whole second), each in a
process of its own: the wall per step and per phase, iterations per step (open-close
cycles, Newton iterations with the conjugate-gradient iterations per Newton iteration and
the rounds whose caps stayed lagged, or Gauss–Seidel sweeps), the complementarity
residual, the Δt actually held, the
blocks asleep, peak RSS and the (extrapolated) wall per simulated second; MuJoCo on the
same piles in the same run when it is installed.
Run: `python -m benchmarks.bench_contact_solvers [STEPS]` (default 10); writes
`benchmarks/results/contact_solvers.json` and prints the table.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

SOLVERS = ("open_close", "newton", "complementarity")
PHASES = ("detection", "assembly", "solve", "open_close", "update")
#: (name, builder expression, simulated seconds or None: STEPS steps): the speed cases
CASES = (
    ("rock mass 5 m", "rock_mass_model(5.0)", None),
    ("rock mass 2.5 m", "rock_mass_model(2.5)", None),
    ("rock mass 1.2 m", "rock_mass_model(1.2)", None),
    ("pile 100", "pile_model(100)", 1.0),
    ("pile 1000", "pile_model(1000)", 1.0),
)
#: a run stops here (wall seconds) and says so
WALL_CAP = 1800.0
OUT = Path(__file__).parent / "results" / "contact_solvers.json"


def one(builder: str, solver: str, steps: int, seconds: float | None = None,
        probe: Callable[[Any], dict] | None = None) -> dict:
    """Step the case `builder` under `solver` (in this process) `steps` times, or through
    `seconds` of simulated time; WALL_CAP stops it. `probe(sim)`, called after the timed
    loop, adds its keys to the row (benchmarks.bench_lmgc90: where the blocks went)."""
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
    its, krylov, contacts, resid, status, message = [], [], [], [], "completed", ""
    sim.state.diagnostics.timings.clear()
    t1, cpu1 = time.perf_counter(), time.process_time()
    while (sim.state.time < seconds - 1e-9 if seconds else sim.state.step < steps):
        if time.perf_counter() - t1 > WALL_CAP:
            status, message = "stopped", f"wall cap {WALL_CAP:.0f} s"
            break
        try:
            res = sim.step()
        except StepFailure as exc:
            status, message = "failed", str(exc)
            break
        its.append(res.iterations)
        krylov.append(res.linear_iterations)
        if res.residual is not None:
            resid.append(res.residual)
        contacts.append(len(res.contacts))
    wall, cpu = time.perf_counter() - t1, time.process_time() - cpu1
    n = max(sim.state.step, 1)
    tm = sim.state.diagnostics.timings
    asleep = 0 if sim.state.asleep is None else int(sim.state.asleep.sum())
    return {"blocks": int((~sim.system.fixed).sum()), "solver": solver, "setup_s": setup,
            "steps": sim.state.step, "simulated_s": sim.state.time, "wall_s": wall, "cpu_s": cpu,
            "per_step_s": wall / n, "per_sim_second_s": wall / max(sim.state.time, 1e-12),
            "mean_dt": sim.state.time / n, "iterations_mean": float(np.mean(its or [0])),
            "iterations_max": int(np.max(its or [0])),
            "iterations_median": float(np.median(its or [0])),
            "krylov_per_iteration": float(np.sum(krylov) / max(np.sum(its), 1)),
            "lagged_caps": int(sim.state.diagnostics.lagged_caps),
            "residual_max": float(np.max(resid)) if resid else None, "contacts_mean": float(
                np.mean(contacts or [0])), "asleep_end": asleep, "status": status,
            "message": message[:200], "rss_peak_mb": peak_rss_mb(),
            **{f"t_{p}": tm.get(p, 0.0) / n for p in PHASES}, **(probe(sim) if probe else {})}


def accuracy() -> list[dict]:
    """The incline (φ 20°, 1 s) and the ten-cube stack (50 steps) under every solver
    (awake: a sleeping stack's contacts are not in the step's result)."""
    from engine.geometry.shapes import box
    from engine.model import AnalysisControls, Block, JointMaterial, Model
    from engine.step.simulation import Simulation, run
    from tests.test_simulation import DOWN_DIP, W, incline_model

    rows = []
    a = 9.81 * (np.sin(np.radians(30)) - np.cos(np.radians(30)) * np.tan(np.radians(20)))
    for solver in SOLVERS:
        m = incline_model(20.0)
        m.controls = dataclasses.replace(m.controls, contact_solver=solver, sleep_velocity=0.0)
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
                                            contact_solver=solver, sleep_velocity=0.0))
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

        r = mujoco_pile(n, dt=1e-3, duration=steps * 1e-3)
    except ImportError:
        return None
    return {"blocks": n, "solver": "MuJoCo", "steps": steps, "wall_s": r["wall_s"],
            "per_sim_second_s": r["wall_s"] / (steps * 1e-3), "mean_dt": 1e-3}


def plot(data: dict, out: Path) -> str:
    """Speed against accuracy (analytic cases) and wall per simulated second against
    blocks (rock masses; MuJoCo on the piles), both solvers: the chart's file name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    marks = {"open_close": "o", "newton": "D", "complementarity": "s", "MuJoCo": "^"}
    for row in data["accuracy"]:
        ax1.loglog(row["wall_s"], max(row["error"], 1e-16), marks[row["solver"]],
                   label=f"{row['case']}, {row['solver']}")
    ax1.set_xlabel("wall (s)")
    ax1.set_ylabel("relative error")
    ax1.set_title("analytic cases at Δt 1 ms")
    ax1.legend(fontsize=7)
    for solver in (*SOLVERS, "MuJoCo"):
        for kind in ("rock mass", "pile"):
            rows = [r for r in data["speed"] if r.get("solver") == solver
                    and r.get("case", "").startswith(kind) and "per_sim_second_s" in r]
            if rows:
                ax2.loglog([r["blocks"] for r in rows], [r["per_sim_second_s"] for r in rows],
                           marks[solver] + ("-" if kind == "rock mass" else ":"),
                           label=f"{kind}, {solver}")
    ax2.axhline(60.0, color="grey", lw=0.8)
    ax2.text(40, 70, "issues 29/38's target at ~1,000 blocks: 1 s in 60 s", fontsize=7)
    ax2.set_xlabel("free blocks")
    ax2.set_ylabel("wall per simulated second (s)")
    ax2.set_title("cut rock masses (10 steps) and piles (their second)")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    name = "contact_solvers.png"
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name


def _maybe(value: float | None) -> str:
    """A number for the table, or nothing."""
    return "" if value is None else f"{value:.1e}"


def report_part(data: dict, chart: str, trust: dict[str, dict] | None = None) -> str:
    """REPORT.md's section on the contact solvers, with the stability map v2 under each
    solver other than the default that has been run (`trust`: solver → its map)."""
    lines = ["## 7. Contact solvers side by side (issues 29, 38)", "",
             "`python -m benchmarks.bench_contact_solvers 10`: every solver on the same "
             "cases in one run (asked Δt 1 ms, each case in its own process: the rock masses "
             "10 steps from rest, the piles their whole second, MuJoCo too). Iterations are "
             "open-close cycles, Newton iterations (with the conjugate-gradient iterations "
             "per Newton iteration, and the rounds whose friction caps stayed lagged) or "
             "Gauss–Seidel sweeps; for the complementarity solve the `solve` phase is its "
             "position stage and `open_close` its velocity (impact) stage; for Newton's "
             "`solve` is all of it.", "",
             "| case | solver | relative error | wall (s) |", "|---|---|---|---|"]
    lines += [f"| {r['case']} | {r['solver']} | {r['error']:.1e} | {r['wall_s']:.2f} |"
              for r in data["accuracy"]]
    lines += ["", "| case | solver | blocks | s/step | " + " | ".join(PHASES) +
              " | iterations median/mean/max | CG per Newton it. | lagged rounds | "
              "residual (m) | Δt held (s) | s per simulated s | peak RSS (MB) | status |",
              "|---" * (12 + len(PHASES)) + "|"]
    for r in data["speed"]:
        if r.get("status") == "error":
            lines.append(f"| {r['case']} | {r['solver']} | error: {r['message'][:80]} |")
        elif r["solver"] == "MuJoCo":
            lines.append(f"| {r['case']} | MuJoCo | {r['blocks']} | "
                         f"{r['wall_s'] / r['steps']:.4f} |" + " |" * len(PHASES) +
                         f" | | | | 1e-3 | {r['per_sim_second_s']:.3g} | | |")
        else:
            newton = r["solver"] == "newton"
            lines.append(
                f"| {r['case']} | {r['solver']} | {r['blocks']} | {r['per_step_s']:.3f} | " +
                " | ".join(f"{r[f't_{p}']:.3f}" for p in PHASES) +
                f" | {r.get('iterations_median', 0):.0f}/{r['iterations_mean']:.0f}/"
                f"{r['iterations_max']} | "
                + (f"{r['krylov_per_iteration']:.0f} | {r['lagged_caps']} | " if newton
                   else " | | ")
                + f"{_maybe(r.get('residual_max'))} | {r['mean_dt']:.2g} | "
                f"{r['per_sim_second_s']:.3g} | {r['rss_peak_mb']:.0f} | {r['status']} |")
    if data.get("note"):
        lines += ["", f"Note: {data['note']}."]
    lines += ["", f"![contact solvers](results/{chart})", ""]
    from collections import Counter

    from benchmarks import trust as map_v2
    from benchmarks.bench_trust_complementarity import SPRINGS

    dts = " / ".join(f"{dt * 1e3:g}" for dt in map_v2.QUICK_DTS)
    factors = " / ".join(f"×{f:g}" for f in map_v2.QUICK_FACTORS)
    penalties = " / ".join(f"{k:.0e}".replace("e+0", "e").replace("e+", "e")
                           for k in map_v2.QUICK_PENALTIES)
    for solver, runs in (trust or {}).items():
        counts = Counter((r["case"], r["verdict"]) for r in runs["rows"])
        springs = solver in SPRINGS
        lines += [f"Stability map v2 under `{solver}` (`python -m "
                  f"benchmarks.bench_trust_complementarity {solver}`: the stay-put scenes "
                  f"over Δt {dts} ms × {len(map_v2.STARTS)} starts"
                  + (f" × penalty {penalties} N/m" if springs else "")
                  + f", the examples at {factors} their Δt"
                  + (" and penalty" if springs else "") + "):", "",
                  "| scene | verdict | runs |", "|---|---|---|"]
        lines += [f"| {case} | {verdict} | {n} |" for (case, verdict), n in
                  sorted(counts.items())]
        lines.append("")
    return "\n".join(lines)


def _save(out: dict) -> None:
    """Write what has been measured so far (a later case that crashes loses only itself)."""
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1))


def main() -> None:
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    only = sys.argv[2:]  # case names to run (default all)
    out = {"accuracy": accuracy(), "speed": []}
    for row in out["accuracy"]:
        print(f"{row['case']:30s} {row['solver']:16s} error {row['error']:.2e} "
              f"({row['measure']}) in {row['wall_s']:.2f} s", flush=True)
    for name, builder, seconds in CASES:
        if only and name not in only:
            continue
        for solver in SOLVERS:
            try:
                proc = subprocess.run([sys.executable, "-c", (
                    "import json; from benchmarks.bench_contact_solvers import one; "
                    f"print(json.dumps(one({builder!r}, {solver!r}, {steps}, {seconds})))")],
                    capture_output=True, text=True, check=True, timeout=2 * WALL_CAP)
                r = json.loads(proc.stdout.strip().splitlines()[-1])
            except (subprocess.SubprocessError, ValueError) as exc:
                r = {"solver": solver, "status": "error", "message": str(exc)[-300:]}
            r["case"] = name
            out["speed"].append(r)
            _save(out)
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
            mj = mujoco(int(name.split()[1]), 1000)  # its whole second
            if mj is not None:
                mj["case"] = name
                out["speed"].append(mj)
                print(f"{name:16s} MuJoCo           {mj['per_sim_second_s']:.4g} s per "
                      "simulated s", flush=True)
    _save(out)
    plot(out, OUT.parent)


if __name__ == "__main__":
    main()
