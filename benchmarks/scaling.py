"""Scaling of the step cost with block count (shared piles, cut rock mass) split by phase,
and "no more than a scene needs": what rigid blocks, fixed blocks, a small contact search
distance and the adaptive time step save on the same scenes."""

from __future__ import annotations

import dataclasses
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from benchmarks.cases import fall_model, incline_error, incline_model
from benchmarks.pile import pile_model, pile_path, rock_mass_model
from benchmarks.stability import stack10, thin_plate
from engine.model import FixedPoint, Model
from engine.step.simulation import Simulation, StepFailure

PHASES = ("detection", "assembly", "solve", "open_close", "update")


def time_steps(model: Model, steps: int | None, memory: bool = False,
               adaptive_search: bool = True, warmup: int = 2,
               simulated_s: float | None = None) -> dict[str, Any]:
    """Step `model` `steps` times (None: no count limit), or until `simulated_s` of
    simulated time have passed, or until it fails, after `warmup` untimed steps;
    per-step wall and phase times of the timed steps. With `memory`, the peak of Python
    allocations is measured in a separate short run (tracemalloc slows Python code
    several-fold, so it must not run under the timed steps)."""
    peak = _traced_peak_mb(model, warmup + min(steps or 3, 3), adaptive_search) if memory else (
        float("nan"))
    t0 = time.perf_counter()
    sim = Simulation(model, adaptive_search=adaptive_search)
    setup = time.perf_counter() - t0
    contacts = []
    status, message = "completed", ""
    for _ in range(warmup):
        try:
            sim.step()
        except StepFailure as exc:
            status, message = "failed", str(exc)
            steps = 0
            break
    timings = sim.state.diagnostics.timings
    timings.clear()
    step0, time0 = sim.state.step, sim.state.time
    t1 = time.perf_counter()
    while (steps is None or sim.state.step - step0 < steps) and (
            simulated_s is None or sim.state.time - time0 < simulated_s - 1e-12):
        try:
            res = sim.step()
        except StepFailure as exc:
            status, message = "failed", str(exc)
            break
        contacts.append(len(res.contacts))
    wall = time.perf_counter() - t1
    n = sim.state.step - step0
    simulated = sim.state.time - time0
    return {"blocks": len(model.blocks), "free_blocks": int((~sim.system.fixed).sum()),
            "unknowns": sim.system.n_unknowns, "steps": n, "setup_s": setup, "wall_s": wall,
            "per_step_s": wall / max(n, 1), "simulated": simulated, "warmup": warmup,
            "per_sim_second_s": wall / simulated if simulated > 0 else float("nan"),
            "contacts_mean": float(np.mean(contacts)) if contacts else 0.0,
            "contacts_last": contacts[-1] if contacts else 0, "status": status,
            "message": message, "tracemalloc_peak_mb": peak, "rss_peak_mb": h.peak_rss_mb(),
            **{f"t_{p}": timings.get(p, 0.0) / max(n, 1) for p in (*PHASES, "damping")}}


def _traced_peak_mb(model: Model, steps: int, adaptive_search: bool) -> float:
    """Peak MB of Python allocations while setting up and stepping `model` `steps` times."""
    tracemalloc.start()
    try:
        sim = Simulation(model, adaptive_search=adaptive_search)
        for _ in range(steps):
            try:
                sim.step()
            except StepFailure:
                break
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def run_scaling(out: Path, full: bool) -> dict[str, Any]:
    """Section 4: piles of 100/400/1000 and rock masses of ~40–320 blocks."""
    rows = []
    # full: every pile's whole second after the warm-up (the model runs 2 s so the
    # warm-up steps do not eat into it); quick: the first steps of the fall
    pile_steps: dict[int, int | None] = ({100: None, 400: None, 1000: None} if full
                                         else {100: 20, 400: 20, 1000: 20})
    for n, steps in pile_steps.items():
        if not pile_path(n).exists():
            continue
        r = time_steps(pile_model(n, dt=1e-3, penalty=1e10, duration=2.0), steps,
                       memory=True, simulated_s=1.0)
        rows.append({"scene": "pile", "N": n, **r})
        print(f"  pile_{n}: {r['steps']} steps, {r['per_step_s'] * 1e3:.1f} ms/step, "
              f"{r['contacts_mean']:.0f} contacts, {r['status']}", flush=True)
    spacings = [5.0, 3.4, 2.5, 1.8] if not full else [5.0, 3.4, 2.5, 1.8, 1.4]
    for s in spacings:
        steps = 10 if not full else 50
        r = time_steps(rock_mass_model(s, dt=1e-3, penalty=1e10), steps, memory=True)
        rows.append({"scene": "rock_mass", "N": r["blocks"] - 1, "spacing": s, **r})
        mean_dt = r["simulated"] / max(r["steps"], 1)
        print(f"  rock mass s={s}: {r['blocks'] - 1} blocks, {r['per_step_s'] * 1e3:.1f} "
              f"ms/step, {r['contacts_mean']:.0f} contacts, mean dt {mean_dt:.2g} s", flush=True)
    exps: dict[str, dict[str, float]] = {}
    for scene in ("pile", "rock_mass"):
        rs = [r for r in rows if r["scene"] == scene and r["steps"] > 0]
        x = [r["N"] for r in rs]
        exps[scene] = {p: h.growth_exponent(x, [r[f"t_{p}"] for r in rs]) for p in PHASES}
        exps[scene]["total per step"] = h.growth_exponent(x, [r["per_step_s"] for r in rs])
        exps[scene]["per simulated second"] = h.growth_exponent(
            x, [r["per_sim_second_s"] for r in rs])
        exps[scene]["contacts"] = h.growth_exponent(x, [r["contacts_mean"] for r in rs])
    data = {"rows": rows, "exponents": exps, "pile_steps": pile_steps}
    h.save_json(out, "scaling", data)
    return data


def plot_scaling(out: Path, data: dict[str, Any], peers: dict[str, Any] | None) -> str:
    """Per-phase time per step against block count, log–log; also writes scaling.csv."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h.write_csv(out / "scaling.csv", data["rows"])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, scene in zip(axes, ("pile", "rock_mass"), strict=True):
        rs = sorted([r for r in data["rows"] if r["scene"] == scene], key=lambda r: r["N"])
        x = [r["N"] for r in rs]
        for p in PHASES:
            e = data["exponents"][scene][p]
            ax.loglog(x, [max(r[f"t_{p}"], 1e-7) for r in rs], "o-", label=f"{p} (N^{e:.2f})")
        e = data["exponents"][scene]["total per step"]
        ax.loglog(x, [r["per_step_s"] for r in rs], "ks-", lw=2, label=f"total (N^{e:.2f})")
        if scene == "pile" and peers and peers.get("piles"):
            pp = sorted(peers["piles"], key=lambda r: r["N"])
            ax.loglog([r["N"] for r in pp], [r["wall_s"] / r["steps"] for r in pp], "^--",
                      color="tab:orange", label="MuJoCo, whole 1 s run (re-run here)")
        ax.set_xlabel("blocks")
        ax.set_ylabel("wall time per step (s)")
        ax.set_title("shared piles (first steps: falling, few contacts)" if scene == "pile"
                     else "cut rock mass on a base (every block in contact)", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    name = "scaling.png"
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name


# --------------------------------------------------------------------------- savings


def _held_incline(dt: float) -> Model:
    """The incline with the slab free but held by three stiff fixed points."""
    m = incline_model(dt=dt)
    slab = m.blocks[0]
    v = slab.polyhedron.vertices
    pts = [v[0], v[1], v[3]]
    m.blocks[0] = dataclasses.replace(slab, fixed=False)
    m.fixed_points = [FixedPoint(0, np.asarray(p, float)) for p in pts]
    return m


def run_savings(out: Path, full: bool) -> dict[str, Any]:
    """Section 5: each option against its heavier alternative on the same scene."""
    rows: list[dict[str, Any]] = []
    steps = 200 if full else 60

    def add(group: str, variant: str, r: dict[str, Any], **extra: Any) -> None:
        rows.append({"group": group, "variant": variant, **r, **extra})
        print(f"  {group:16s} {variant:34s} {r['per_step_s'] * 1e3:7.2f} ms/step "
              f"unknowns={r['unknowns']} contacts={r['contacts_mean']:.0f} {r['status']}",
              flush=True)

    # rigid vs elastic, same stack of ten cubes
    for bm in ("rigid", "elastic"):
        m = stack10(1e-3, 1e10)
        m.controls = dataclasses.replace(m.controls, block_model=bm)
        add("block model", f"{bm} blocks (stack of 10)", time_steps(m, steps))
    # fixed slab (no unknowns) vs free slab held by three fixed points
    for variant, m in (("slab fixed (no unknowns)", incline_model(dt=1e-3)),
                       ("slab free, held by 3 fixed points", _held_incline(1e-3))):
        m.controls = dataclasses.replace(m.controls, duration=1.0)
        o = h.run_model(m)
        err, d = incline_error(o) if o.status == "completed" else (np.nan, np.nan)
        r = {"unknowns": Simulation(m).system.n_unknowns, "steps": o.steps,
             "wall_s": o.compute_wall,
             "per_step_s": o.compute_wall / max(o.steps, 1), "contacts_mean": float("nan"),
             "status": o.status, "message": o.message, "simulated": o.simulated,
             **{f"t_{p}": o.timings.get(p, 0.0) / max(o.steps, 1) for p in PHASES}}
        add("fixed blocks", variant, r, incline_rel_error=err)
    # contact search: each step's own predicted limit (default) vs the model's step limit
    variants = (("adaptive search (each step's predicted displacement)", True),
                ("fixed search (2 × the model's step limit)", False))
    mass = rock_mass_model(3.4)
    for name, adaptive in variants:
        add("search distance", f"rock mass, {name}",
            time_steps(mass, 10 if not full else 40, adaptive_search=adaptive))
    if pile_path(100).exists():
        for name, adaptive in variants:
            add("search distance", f"pile_100, {name}",
                time_steps(pile_model(100), 20 if not full else 100, adaptive_search=adaptive))
    # adaptive Δt (start large, cut where needed) vs a fixed small Δt
    for variant, m, fixed_dt in (
            ("impact, adaptive from Δt = 1e-2", fall_model(dt=1e-2, duration=1.0), False),
            ("impact, fixed Δt = 1e-3", fall_model(dt=1e-3, duration=1.0), True),
            ("thin plate, adaptive from Δt = 1e-2", thin_plate(1e-2, 1e10), False),
            ("thin plate, fixed Δt = 1e-4", thin_plate(1e-4, 1e10), True)):
        m.controls = dataclasses.replace(m.controls, record_interval=10 ** 6,
                                         record_contacts=False)
        o = h.run_model(m)
        pen = o.result.max_penetration
        r = {"unknowns": 6, "steps": o.steps, "wall_s": o.compute_wall,
             "per_step_s": o.compute_wall / max(o.steps, 1), "contacts_mean": float("nan"),
             "status": o.status, "message": o.message, "simulated": o.simulated,
             **{f"t_{p}": o.timings.get(p, 0.0) / max(o.steps, 1) for p in PHASES}}
        add("time step", variant, r, max_penetration=pen, fixed=fixed_dt)
    data = {"rows": rows}
    h.save_json(out, "savings", data)
    h.write_csv(out / "savings.csv", rows)
    return data
