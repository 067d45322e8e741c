"""Stability map v2 (issue 12): the scenes users build, started the way real models start.

A block that must stay put (the 1 m cube on the 30° incline at φ 35°, a stack of ten 1 m
cubes) over penalty × Δt × start state {exact, 0.3 µm overlap, 1 µm gap, 1 mm drop}; the
paper's toppling and block-system examples at Δt and penalty ×0.1…×10 of their own; the
user-style jointed slope. Verdicts: **pass** = completed, stayed put (< 0.1 mm; the drop: no
more than twice its free-flight slide) and created no more than 0.5 % of gravity's work as
energy; **failed (clear status)** = `failed` with its reason; anything else is a silent
failure (**wrong**, **blew up**).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from benchmarks.cases import DOWN_DIP, UP_NORMAL, W, incline_model
from engine.geometry.shapes import box
from engine.model import AnalysisControls, Block, JointMaterial, Model
from engine.step.frame import STORED_ENERGIES, WORKS
from engine.step.frame import energy_created as energy_balance
from engine.step.simulation import STATUS_COMPLETED

#: a run may create at most this fraction of gravity's work as energy (issue 12)
CREATED_TOL = 5e-3
#: a block that must stay put moves less than this (m)
STAY_TOL = 1e-4
#: start states: offset (m) of each resting block from its support, along the contact normal
STARTS: dict[str, float] = {"exact": 0.0, "overlap 0.3 µm": -3e-7, "gap 1 µm": 1e-6,
                            "drop 1 mm": 1e-3}
#: the grid (full mode) and its quick subset
PENALTIES = (1e9, 1e10, 1e11, 1e12, 1e13, 1e14)
DTS = (3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)
QUICK_PENALTIES = (1e9, 1e11, 1e14)
QUICK_DTS = (1e-4, 1e-3, 1e-2)
#: factors of the examples' own Δt and penalty
FACTORS = (0.1, 0.3, 1.0, 3.0, 10.0)
QUICK_FACTORS = (0.1, 1.0, 10.0)
#: wall-time cap of one run (s): past it the run is cancelled and reported as stopped
WALL_CAP = {False: 120.0, True: 300.0}
#: a drop of 1 mm normal to the 30° slab carries the cube tan 30° mm down-dip in free flight
FREE_FLIGHT_SLIDE = 1e-3 * np.tan(np.radians(30.0))

PASS, WRONG, FAILED, BLEW_UP, STOPPED = ("pass", "wrong", "failed (clear status)", "blew up",
                                         "stopped at wall cap")


def duration_for(dt: float) -> float:
    """Simulated time of a map run (s): 3,000 steps, between 0.1 and 0.5 s."""
    return float(np.clip(3000 * dt, 0.1, 0.5))


def _ctl(dt: float, k: float | None, duration: float) -> AnalysisControls:
    return AnalysisControls(duration=duration, time_step=dt, penalty=k, record_interval=1,
                            record_contacts=False)


# --------------------------------------------------------------------------- scenes


def incline35(dt: float, k: float, offset: float) -> Model:
    """The 1 m cube on the 30° slab at φ 35° (it must stay), `offset` m off the slab along
    its normal (negative: overlapping)."""
    m = incline_model(dt=dt, penalty=k, phi_deg=35.0, duration=duration_for(dt),
                      record_interval=1, record_contacts=False)
    cube = m.blocks[1]
    cube.polyhedron = cube.polyhedron.moved(cube.polyhedron.vertices + offset * UP_NORMAL)
    return m


def stack10(dt: float, k: float, offset: float) -> Model:
    """Ten 1 m cubes on a fixed base (φ 30°), every interface `offset` m open (negative:
    overlapping)."""
    blocks = [Block(box([-1, -1, -1], [2, 2, 0]), "base", fixed=True)]
    z = 0.0
    for j in range(10):
        z += offset
        blocks.append(Block(box([0, 0, z], [1, 1, z + 1]), f"c{j}"))
        z += 1.0
    return Model(blocks=blocks, joint_materials=[JointMaterial(np.radians(30))],
                 controls=_ctl(dt, k, duration_for(dt)))


# --------------------------------------------------------------------------- checks


def check_incline(res: Any, model: Model, offset: float) -> tuple[bool, float, str]:
    """Down-dip slide of the cube: < 0.1 mm, or for the drop 0 … 2 × its free-flight slide."""
    c0 = model.blocks[1].polyhedron.centroid
    d = float((res.state.centroid[1] - c0) @ DOWN_DIP)
    limit = 2 * FREE_FLIGHT_SLIDE if offset >= 1e-4 else STAY_TOL
    return abs(d) <= limit, d, f"slid {d * 1e3:.4g} mm down-dip (limit {limit * 1e3:.3g} mm)"


def check_stack(res: Any, model: Model, offset: float) -> tuple[bool, float, str]:
    """Every cube: lateral drift and rotation < 0.1 mm (rad·m), and settled within 0.1 mm of
    its exact resting height plus twice the static spring compression."""
    k = model.controls.penalty
    exact = np.array([[0.5, 0.5, j + 0.5] for j in range(10)])
    c = res.state.centroid[1:11]
    drift = float(np.max(np.linalg.norm(c[:, :2] - exact[:, :2], axis=1)))
    rot = max(float(np.linalg.norm(b["rotation"])) for b in res.summary["blocks"][1:])
    static = np.array([W * sum(range(10 - j, 11)) / (4 * k) for j in range(10)])  # cumulative
    dz = c[:, 2] - exact[:, 2]
    settle = float(np.max(np.abs(dz + static) - static))
    worst = max(drift, rot, settle)
    ok = drift < STAY_TOL and rot < STAY_TOL and settle < STAY_TOL
    return ok, worst, (f"drift {drift * 1e3:.3g} mm, rotation {rot:.2g} rad, "
                       f"settled {settle * 1e3:.3g} mm off static")


@dataclass(frozen=True)
class MapScene:
    """A scene that must stay put, built for (Δt, penalty, start offset), and its check."""

    name: str
    title: str
    build: Callable[[float, float, float], Model]
    check: Callable[[Any, Model, float], tuple[bool, float, str]]


MAP_SCENES = {s.name: s for s in [
    MapScene("incline35", "1 m cube on the 30° incline, φ 35° (stays)", incline35,
             check_incline),
    MapScene("stack10_starts", "ten 1 m cubes stacked on a fixed base", stack10,
             check_stack),
]}


# --------------------------------------------------------------------------- energy


def energy_created(log: h.FrameLog) -> tuple[float, float]:
    """(energy created J, gravity's work J) of a recorded run: the largest rise of the
    mechanical energy (stored − work of gravity and loads) above its start — it may only
    fall — and the largest |work of gravity| reached (at least the stored energy at the
    start, so a start that overlaps has a scale)."""
    if not log.frames:
        return float("nan"), float("nan")
    stored = sum(log.energy(n) for n in STORED_ENERGIES)
    work = sum(log.energy(n) for n in WORKS)
    mech = stored - work
    if not np.all(np.isfinite(mech)):
        return float("inf"), float("nan")
    created = float(np.max(mech - mech[0]))
    scale = max(float(np.max(np.abs(log.energy("gravity_work")))), float(stored[0]))
    return created, scale


def verdict_of(out: h.Outcome, within: bool, created_ok: bool) -> str:
    """The map's verdict of a run (see the module docstring)."""
    finite = bool(np.all(np.isfinite(out.result.state.centroid)))
    if out.status == STATUS_COMPLETED:
        return PASS if within and created_ok and finite else WRONG
    if out.status == "cancelled":
        return STOPPED if created_ok else WRONG
    return FAILED if out.message and finite else BLEW_UP


def _exception_row(base: dict[str, Any], exc: Exception) -> dict[str, Any]:
    return {**base, "status": "exception", "message": f"{type(exc).__name__}: {exc}",
            "within": False, "metric": float("nan"), "detail": "run() raised",
            "created": float("nan"), "gravity_work": float("nan"), "created_ratio": float("nan"),
            "verdict": BLEW_UP, "steps": 0, "simulated": 0.0, "mean_dt": float("nan"),
            "wall_s": float("nan")}


def run_map_one(scene: MapScene, dt: float, k: float, start: str,
                max_wall: float | None = None, solver: str = "open_close") -> dict[str, Any]:
    """One run of the map under the contact `solver`: status, stay-put check, energy
    created, verdict."""
    offset = STARTS[start]
    base = {"group": "map", "case": scene.name, "start": start, "dt": dt, "penalty": k,
            "solver": solver}
    model = scene.build(dt, k, offset)
    model.controls = dataclasses.replace(model.controls, contact_solver=solver)
    try:
        out = h.run_model(model, record=True, max_wall=max_wall)
    except Exception as exc:  # noqa: BLE001 - an engine exception is a finding, not a crash
        return _exception_row(base, exc)
    within, metric, detail = scene.check(out.result, model, offset)
    return _finish(base, out, within, metric, detail)


def _finish(base: dict[str, Any], out: h.Outcome, within: bool, metric: float,
            detail: str) -> dict[str, Any]:
    created, scale = energy_created(out.log)
    ratio = created / scale if scale and np.isfinite(scale) and scale > 0 else float("nan")
    created_ok = bool(np.isfinite(created) and created <= CREATED_TOL * scale + 1e-9)
    verdict = verdict_of(out, within, created_ok)
    row = {**base, "status": out.status, "message": out.message, "within": bool(within),
           "metric": metric, "detail": detail, "created": created, "gravity_work": scale,
           "created_ratio": ratio, "verdict": verdict, "steps": out.steps,
           "simulated": out.simulated, "mean_dt": out.simulated / max(out.steps, 1),
           "wall_s": out.compute_wall}
    print(f"  {base['case']:12s} {base.get('start', base.get('sweep', '')):15s} "
          f"dt={base['dt']:<7g} k={base['penalty']:<7g} {verdict:22s} {detail}; "
          f"created {ratio:.2e} of gravity's work; steps={out.steps} "
          f"wall={out.compute_wall:.1f}s {out.message[:120]}", flush=True)
    return row


# --------------------------------------------------------------------------- examples


def _example(name: str) -> Model:
    from schemas.convert import build_model

    return build_model(h.ROOT / "examples" / f"{name}.json").model


@dataclass(frozen=True)
class ExampleSweep:
    """One of the paper's examples swept in Δt and penalty around its own values, with the
    quantity whose convergence is reported."""

    name: str
    title: str
    duration: float
    quantity: str
    measure: Callable[[Any], float]
    #: (Δt factors, penalty factors) of the quick mode
    quick: tuple[tuple[float, ...], tuple[float, ...]] = (QUICK_FACTORS, QUICK_FACTORS)


def _t1_rotation(res: Any) -> float:
    return float(np.linalg.norm(res.summary["blocks"][0]["rotation"]))


EXAMPLE_SWEEPS = {s.name: s for s in [
    ExampleSweep("toppling", "paper 6.2: six columns toppling on a 30° slab", 0.3,
                 "T1 rotation at 0.3 s (rad)", _t1_rotation),
    ExampleSweep("block_system", "paper 6.3: 10 m cube cut by three sets", 0.2,
                 "gravity's work at 0.2 s (J)", lambda res: float("nan"),
                 quick=((1.0, 10.0), (0.1, 1.0, 10.0))),
]}


def run_example_one(sweep: ExampleSweep, dt_factor: float, k_factor: float,
                    max_wall: float | None = None, solver: str = "open_close"
                    ) -> dict[str, Any]:
    """One run of an example at factors of its own Δt and penalty, under `solver`."""
    model = _example(sweep.name)
    c = model.controls
    dt, k = c.time_step * dt_factor, c.penalty * k_factor
    model.controls = dataclasses.replace(c, time_step=dt, penalty=k, duration=sweep.duration,
                                         record_interval=1, record_contacts=False,
                                         contact_solver=solver)
    base = {"group": "example", "case": sweep.name, "sweep": f"Δt×{dt_factor:g} k×{k_factor:g}",
            "dt_factor": dt_factor, "k_factor": k_factor, "dt": dt, "penalty": k,
            "solver": solver}
    try:
        out = h.run_model(model, record=True, max_wall=max_wall)
    except Exception as exc:  # noqa: BLE001
        return _exception_row(base, exc)
    value = sweep.measure(out.result)
    if not np.isfinite(value) and out.log and out.log.frames:
        value = float(out.log.frames[-1].energies.get("gravity_work", np.nan))
    return _finish(base, out, True, value, f"{sweep.quantity} = {value:.5g}")


def slope_checks(frames: list[Any]) -> tuple[float, float, float]:
    """The jointed slope's two checks over its recorded frames: the fastest block's speed
    over twice the free-fall speed of the deepest drop in the slope at that frame (what an
    impact of a heavy block on a light one can give; ≤ 1), and the energy balance and
    gravity's work at the end (J)."""
    c0 = frames[0].centroids
    worst = 0.0
    for f in frames:
        drop = max(float(np.max(c0[:, 2] - f.centroids[:, 2])), 0.0)
        speed = float(np.linalg.norm(f.velocity[:, :3], axis=1).max())
        worst = max(worst, speed / max(2 * np.sqrt(2 * 9.81 * drop), 1e-9))
    e = frames[-1].energies
    return worst, float(energy_balance(e)), float(e["gravity_work"])


def run_jointed_slope(full: bool, max_wall: float | None = None) -> dict[str, Any]:
    """The user-style jointed slope (examples/jointed_slope.json) as written: energy created,
    balance, and the fastest block against twice the free-fall speed of the deepest drop."""
    model = _example("jointed_slope")
    if not full:
        model.controls = dataclasses.replace(model.controls, duration=0.5)
    c = model.controls
    base = {"group": "slope", "case": "jointed_slope", "sweep": "as written", "dt": c.time_step,
            "penalty": c.penalty}
    try:
        out = h.run_model(model, record=True, max_wall=max_wall)
    except Exception as exc:  # noqa: BLE001
        return _exception_row(base, exc)
    worst, balance, work = slope_checks(out.log.frames)
    within = worst <= 1.0 + 1e-6 and abs(balance) <= 0.01 * work
    reseat = out.result.summary.get("reseat_dissipation", 0.0)
    return _finish(base, out, within, worst,
                   f"fastest block {worst:.2f} × twice free fall, balance "
                   f"{balance / work:+.2%} of gravity's work over {out.simulated:g} s "
                   f"(springs' re-seat loss {reseat / work:.2%}, booked as dissipation)")


# --------------------------------------------------------------------------- section


def run_trust(out: Path, full: bool, names: list[str] | None = None) -> dict[str, Any]:
    """Stability map v2: every scene × penalty × Δt × start, the example sweeps, the slope."""
    names = names or [*MAP_SCENES, *EXAMPLE_SWEEPS, "jointed_slope"]
    old = h.load_json(out, "trust") or {"rows": []}
    rows = [r for r in old["rows"] if r["case"] not in names]
    cap = WALL_CAP[full]
    ks, dts = (PENALTIES, DTS) if full else (QUICK_PENALTIES, QUICK_DTS)
    for name in names:
        print(f"[trust] {name}", flush=True)
        if name in MAP_SCENES:
            for start in STARTS:
                for k in ks:
                    for dt in dts:
                        rows.append(run_map_one(MAP_SCENES[name], dt, k, start, cap))
        elif name in EXAMPLE_SWEEPS:
            sweep = EXAMPLE_SWEEPS[name]
            fdts, fks = (FACTORS, FACTORS) if full else sweep.quick
            pairs = [(f, 1.0) for f in fdts] + [(1.0, f) for f in fks if f != 1.0]
            for fdt, fk in pairs:
                rows.append(run_example_one(sweep, fdt, fk, cap))
        elif name == "jointed_slope":
            rows.append(run_jointed_slope(full, 2 * cap))
    data = {"rows": rows, "created_tol": CREATED_TOL, "stay_tol": STAY_TOL,
            "wall_cap": cap, "starts": STARTS,
            "scenes": {n: s.title for n, s in MAP_SCENES.items()}
            | {n: s.title for n, s in EXAMPLE_SWEEPS.items()}
            | {"jointed_slope": "user-style 30 m jointed slope (examples/jointed_slope.json)"}}
    h.save_json(out, "trust", data)
    return data


def silent(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs that failed without saying so."""
    return [r for r in rows if r["verdict"] in (WRONG, BLEW_UP)]


COLOURS = {PASS: "tab:green", WRONG: "tab:orange", FAILED: "tab:blue", BLEW_UP: "tab:red",
           STOPPED: "tab:gray"}


def _verdict_panel(ax: Any, rows: list[dict[str, Any]], x: str, y: str, title: str,
                   xlabel: str, ylabel: str) -> None:
    """One log-log panel of runs, a square per run coloured by its verdict."""
    for r in rows:
        ax.scatter(r[x], r[y], s=110, marker="s", color=COLOURS[r["verdict"]])
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)


def plot_trust(out: Path, data: dict[str, Any]) -> str:
    """One panel per map scene × start (penalty against Δt, coloured by verdict) and one per
    example sweep. Also writes trust.csv."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h.write_csv(out / "trust.csv", data["rows"])
    scenes = [n for n in MAP_SCENES if any(r["case"] == n for r in data["rows"])]
    starts = list(data["starts"])
    fig, axes = plt.subplots(len(scenes) + 1, len(starts),
                             figsize=(3.2 * len(starts), 3.0 * (len(scenes) + 1)),
                             squeeze=False)
    for i, n in enumerate(scenes):
        for j, s in enumerate(starts):
            _verdict_panel(axes[i, j], [r for r in data["rows"]
                                        if r["case"] == n and r["start"] == s],
                           "dt", "penalty", f"{n}: {s}", "Δt (s)", "penalty (N/m)")
    ex = [n for n in EXAMPLE_SWEEPS if any(r["case"] == n for r in data["rows"])]
    for j in range(len(starts)):
        if j < len(ex):
            _verdict_panel(axes[-1, j], [r for r in data["rows"] if r["case"] == ex[j]],
                           "dt_factor", "k_factor", f"{ex[j]}: factors of its own",
                           "Δt factor", "penalty factor")
        else:
            axes[-1, j].axis("off")
    for v, c in COLOURS.items():
        axes[-1, -1].scatter([], [], color=c, marker="s", label=v)
    axes[-1, -1].legend(fontsize=8, loc="center")
    fig.tight_layout()
    name = "trust.png"
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name

