"""Stability map: where the method fails. For each hard case, a Δt sweep (at the case's
penalty) and a penalty sweep (at the case's Δt): is the result within tolerance, does the
mechanical energy stay below its start, and does a failing run stop with a clear status?"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from benchmarks.cases import DOWN_DIP, INCLINE_D1, RHO, W, fall_model, incline_model
from benchmarks.pile import pile_model
from engine.geometry.cutting.cut import convex_decomposition
from engine.geometry.polyhedron import rotation_matrix
from engine.geometry.shapes import box, prism
from engine.model import AnalysisControls, Block, JointMaterial, Model
from engine.step.simulation import STATUS_COMPLETED

#: energy may not rise above its start by more than this fraction of the reference energy
ENERGY_TOL = 0.01
#: wall-time cap of one run (s), quick and full mode: a run past it is cancelled
WALL_CAP = {False: 30.0, True: 600.0}
STOPPED = "stopped at wall cap"
#: completed outside tolerance, but the run's summary warned about it (soft penalty)
WARNED = "wrong, warned"


def _ctl(dt: float, k: float, duration: float) -> AnalysisControls:
    return AnalysisControls(duration=duration, time_step=dt, penalty=k, record_interval=1,
                            record_contacts=False)


def _cube_at(center: np.ndarray, rot: np.ndarray | None = None, size: float = 1.0):
    """A cube of edge `size` centred at `center`, rotated by the matrix `rot`."""
    c = box([-size / 2] * 3, [size / 2] * 3)
    v = c.vertices @ (rot.T if rot is not None else np.eye(3)) + np.asarray(center, float)
    return c.moved(v)


def _rot(axis: list[float], angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    return rotation_matrix(np.radians(angle_deg) * a / np.linalg.norm(a)).reshape(3, 3)


def _corner_up() -> np.ndarray:
    """Rotation taking the body diagonal (1, 1, 1)/√3 to +z (a cube standing on a vertex)."""
    d = np.ones(3) / np.sqrt(3.0)
    axis = np.cross(d, [0, 0, 1.0])
    ang = np.degrees(np.arccos(d[2]))
    return _rot(axis, ang)


# --------------------------------------------------------------------------- scenes


def thin_plate(dt: float, k: float) -> Model:
    """A cube at 40 m/s onto a 5 cm fixed plate (tunnelling test), 0.2 s."""
    plate = box([-2, -2, -0.05], [3, 3, 0.0])
    cube = box([0, 0, 0.5], [1, 1, 1.5])
    return Model(blocks=[Block(plate, "plate", fixed=True),
                         Block(cube, "cube", velocity=np.array([0, 0, -40.0, 0, 0, 0]))],
                 controls=_ctl(dt, k, 0.2))


def vertex_vertex(dt: float, k: float) -> Model:
    """A cube standing on a vertex (diagonal vertical) dropped 0.1 m onto the upward vertex
    of a fixed cube, 2 cm off axis: the contact plane jumps as it slides off, 1 s."""
    r = _corner_up()
    h3 = np.sqrt(3.0) / 2.0
    fixed = _cube_at([0, 0, 0], r)
    free = _cube_at([0.02, 0.0, 2 * h3 + 0.1], r)
    floor = box([-4, -4, -h3 - 0.5], [4, 4, -h3 + 0.3])
    return Model(blocks=[Block(floor, "floor", fixed=True), Block(fixed, "post", fixed=True),
                         Block(free, "cube")],
                 joint_materials=[JointMaterial(np.radians(30))], controls=_ctl(dt, k, 1.0))


def edge_edge(dt: float, k: float) -> Model:
    """A cube resting edge-down (45° about y) dropped 0.1 m across the upward edge of a
    fixed cube (45° about x), 2 cm off centre: crossing edges, then tipping, 1 s."""
    s2 = np.sqrt(2.0) / 2.0
    fixed = _cube_at([0, 0, 0], _rot([1, 0, 0], 45))
    free = _cube_at([0.0, 0.02, 2 * s2 + 0.1], _rot([0, 1, 0], 45))
    floor = box([-4, -4, -s2 - 0.5], [4, 4, -s2 + 0.2])
    return Model(blocks=[Block(floor, "floor", fixed=True), Block(fixed, "ridge", fixed=True),
                         Block(free, "cube")],
                 joint_materials=[JointMaterial(np.radians(30))], controls=_ctl(dt, k, 1.0))


def slide_off_edge(dt: float, k: float) -> Model:
    """A cube sliding at 3 m/s (φ = 10°) off the end of a fixed platform onto a floor 2 m
    below, 1.5 s."""
    platform = box([-3, -1, -1], [1.5, 2, 0])
    floor = box([-3, -3, -3], [8, 4, -2])
    cube = box([0, 0, 0], [1, 1, 1])
    return Model(blocks=[Block(platform, "platform", fixed=True),
                         Block(floor, "floor", fixed=True),
                         Block(cube, "cube", velocity=np.array([3.0, 0, 0, 0, 0, 0]))],
                 joint_materials=[JointMaterial(np.radians(10))], controls=_ctl(dt, k, 1.5))


def concave_corner(dt: float, k: float) -> Model:
    """A cube in the re-entrant corner of a fixed L-shaped (concave) block, pushed into the
    corner by gravity tilted 20° toward the wall; φ = 30°: it must stay put, 0.5 s."""
    ell = np.array([[-1, 0], [3, 0], [3, 1], [0, 1], [0, 3], [-1, 3]], float)  # in x–z
    p = prism(ell, 3.0)  # extruded along z: map (x, y, z) -> (x, -z, y) (rotation about x)
    verts = p.vertices[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0]) + np.array([0, 1.0, 0])
    lblock = convex_decomposition(p.moved(verts))
    cube = box([0, -1, 1], [1, 0, 2])
    g = 9.81 * np.array([-np.sin(np.radians(20)), 0.0, -np.cos(np.radians(20))])
    return Model(blocks=[Block(lblock, "L", fixed=True), Block(cube, "cube")], gravity=g,
                 joint_materials=[JointMaterial(np.radians(30))], controls=_ctl(dt, k, 0.5))


def stack10(dt: float, k: float) -> Model:
    """Ten 1 m cubes stacked on a fixed base, released from rest (dynamic), 0.5 s."""
    blocks = [Block(box([-1, -1, -1], [2, 2, 0]), "base", fixed=True)]
    blocks += [Block(box([0, 0, j], [1, 1, j + 1]), f"c{j}") for j in range(10)]
    return Model(blocks=blocks, joint_materials=[JointMaterial(np.radians(30))],
                 controls=_ctl(dt, k, 0.5))


def pile100(dt: float, k: float) -> Model:
    """The shared 100-block pile falling into its box, 1 s."""
    return pile_model(100, dt=dt, penalty=k, duration=1.0, record_interval=10,
                      record_contacts=False)


def incline(dt: float, k: float) -> Model:
    """Case 1a (large steps, extreme penalties), 1 s."""
    return incline_model(dt=dt, penalty=k, record_interval=1, record_contacts=False)


def fall(dt: float, k: float) -> Model:
    """Case 4 impact from 1 m, 1 s (to the first rebounds)."""
    return fall_model(dt=dt, penalty=k, duration=1.0, record_interval=1, record_contacts=False)


# --------------------------------------------------------------------------- checks


def _mass(model: Model) -> float:
    return sum(RHO * b.polyhedron.volume for b in model.blocks if not b.fixed)


def _reference_energy(model: Model, height: float) -> float:
    """Initial kinetic energy + weight × a characteristic height (J)."""
    ke = 0.0
    for b in model.blocks:
        if not b.fixed:
            ke += 0.5 * RHO * b.polyhedron.volume * float(np.sum(np.asarray(b.velocity)[:3] ** 2))
    return ke + _mass(model) * float(np.linalg.norm(model.gravity)) * height


def check_incline(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    d = float(np.asarray(out.result.summary["blocks"][1]["displacement"]) @ DOWN_DIP)
    err = abs(d / (INCLINE_D1 * out.simulated**2) - 1)
    return err < 0.01, err, f"d(1 s) = {d:.6g} m"


def check_fall(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    k4 = 4 * model.controls.penalty
    bound = (W + np.sqrt(W**2 + 2 * k4 * W * 1.0)) / k4
    log = out.log
    z = log.series(1)[:, 2] if log else np.array([np.nan])
    t = log.times() if log else np.array([np.nan])
    apex = float(np.max(z[t > 0.5]) - 0.5) if np.any(t > 0.5) else 0.0
    ok = out.result.max_penetration <= bound and apex <= 1.0 + 1e-9
    return ok, out.result.max_penetration / bound, (
        f"max penetration {out.result.max_penetration:.3g} m (bound {bound:.3g}), "
        f"rebound apex {apex:.3g} m")


def check_plate(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    zmin = float(np.min(out.log.series(1)[:, 2])) if out.log else np.nan
    # the cube's bottom (centroid − 0.5) must stay above the plate bottom (z = −0.05)
    ok = zmin - 0.5 > -0.05
    return ok, max(0.0, -(zmin - 0.5)) / 0.05, f"lowest bottom face z = {zmin - 0.5:.3g} m"


def check_settles_somewhere(limit: float) -> Callable[[h.Outcome, Model], tuple[bool, float, str]]:
    """Within tolerance when the deepest penetration stays below `limit` × block size."""

    def check(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
        pen = out.result.max_penetration
        return pen < limit, pen / limit, f"max penetration {pen:.3g} m"

    return check


def check_slide_off(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    zf = float(out.result.state.centroid[2, 2])
    # it must have left the platform (top z = 0) and landed near the floor (top z = −2)
    ok = zf < -1.0 and out.result.max_penetration < 0.05
    return ok, abs(zf + 1.5), f"final centroid z = {zf:.3g} m (on floor: −1.5)"


def check_corner(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    """Stays put: displacement below 1e-4 m plus ten spring displacements W / k."""
    d = float(np.linalg.norm(out.result.state.centroid[1] - np.array([0.5, -0.5, 1.5])))
    rot = float(np.linalg.norm(out.result.summary["blocks"][1]["rotation"]))
    tol = 1e-4 + 10 * W / model.controls.penalty
    return d < tol and rot < tol, d / tol, f"displacement {d:.3g} m, rotation {rot:.2g} rad"


def check_stack(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    k = model.controls.penalty
    static = W * 55.0 / (4 * k)  # Σ (cubes above + 1) W / 4k over the ten interfaces
    top = out.result.state.centroid[10] - np.array([0.5, 0.5, 9.5])
    lateral = float(np.linalg.norm(top[:2]))
    rot = max(float(np.linalg.norm(b["rotation"])) for b in out.result.summary["blocks"])
    ok = abs(top[2]) <= 2.0 * static + 1e-6 and lateral < 1e-4 and rot < 1e-4
    return ok, abs(top[2]) / (2 * static), (f"top settles {top[2]:.3g} m (static {-static:.3g}),"
                                            f" drift {lateral:.2g} m, rotation {rot:.2g} rad")


def check_pile(out: h.Outcome, model: Model) -> tuple[bool, float, str]:
    pen = out.result.max_penetration
    return pen < 0.05, pen / 0.05, f"max penetration {pen:.3g} m"


@dataclass(frozen=True)
class StabilityCase:
    """A hard scene, its tolerance check, its reference Δt and penalty, the sweeps."""

    name: str
    title: str
    build: Callable[[float, float], Model]
    check: Callable[[h.Outcome, Model], tuple[bool, float, str]]
    criterion: str
    dt: float
    penalty: float
    height: float  #: m, characteristic drop for the reference energy
    dts: tuple[float, ...] = (1e-3, 1e-2, 5e-2)
    penalties: tuple[float, ...] = (1e6, 1e8, 1e12, 1e14)
    full_dts: tuple[float, ...] = (3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1)
    full_penalties: tuple[float, ...] = (1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14)


STAB_CASES: dict[str, StabilityCase] = {c.name: c for c in [
    StabilityCase("incline", "incline φ = 20° (case 1a)", incline, check_incline,
                  "|d(1 s)| within 1 %", 1e-2, 1e10, 1.0, dts=(1e-2, 5e-2, 2e-1)),
    StabilityCase("impact", "free fall 1 m onto a base (case 4)", fall, check_fall,
                  "max penetration ≤ energy bound, rebound apex ≤ drop", 1e-3, 1e9, 1.0),
    StabilityCase("thin_plate", "cube at 40 m/s onto a 5 cm plate", thin_plate, check_plate,
                  "never passes through the plate", 1e-2, 1e10, 0.1,
                  dts=(1e-3, 1e-2, 5e-2), penalties=(1e6, 1e8, 1e12)),
    StabilityCase("vertex_vertex", "vertex onto vertex, sliding off", vertex_vertex,
                  check_settles_somewhere(0.05), "max penetration < 5 cm", 1e-3, 1e10, 1.0),
    StabilityCase("edge_edge", "crossing edges, tipping", edge_edge,
                  check_settles_somewhere(0.05), "max penetration < 5 cm", 1e-3, 1e10, 1.0),
    StabilityCase("slide_off", "cube sliding off a platform edge", slide_off_edge,
                  check_slide_off, "lands on the floor 2 m below, penetration < 5 cm",
                  1e-3, 1e10, 2.0),
    StabilityCase("concave_corner", "cube in the corner of a concave L block",
                  concave_corner, check_corner, "stays put (< 1e-4 m + 10 W/k, same in rad)",
                  1e-2, 1e10, 1.0),
    StabilityCase("stack10", "stack of 10 cubes", stack10, check_stack,
                  "top settles ≤ 2× static, no drift or rotation > 1e-4", 1e-2, 1e10, 1.0),
    StabilityCase("pile100", "pile_100 settling (1 s)", pile100, check_pile,
                  "completes, max penetration < 5 cm", 1e-3, 1e10, 1.0,
                  dts=(1e-3,), penalties=(1e9,), full_dts=(1e-3, 3e-3, 1e-2),
                  full_penalties=(1e8, 1e9, 1e11)),
]}


def run_one(case: StabilityCase, dt: float, k: float, sweep: str,
            max_wall: float | None = None) -> dict[str, Any]:
    """One run of a stability case: status, check, energy growth and balance."""
    model = case.build(dt, k)
    try:
        out = h.run_model(model, record=True, max_wall=max_wall)
    except Exception as exc:  # noqa: BLE001 - an engine exception is a finding, not a crash
        print(f"  {case.name:14s} {sweep} dt={dt:<6g} k={k:<6g} EXCEPTION {exc!r}", flush=True)
        return {"case": case.name, "sweep": sweep, "dt": dt, "penalty": k,
                "status": "exception", "message": f"{type(exc).__name__}: {exc}",
                "within_tolerance": False, "metric": float("nan"),
                "detail": "run() raised instead of returning a status",
                "energy_growth": float("nan"), "energy_residual": float("nan"),
                "energy_ok": False, "verdict": "blew up", "steps": 0, "simulated": 0.0,
                "mean_dt": float("nan"), "wall_s": float("nan")}
    ref = _reference_energy(model, case.height)
    en = h.energy_check(out.log, ref) if out.log else {"growth": np.nan, "residual": np.nan}
    completed = out.status == STATUS_COMPLETED
    try:
        within, metric, detail = case.check(out, model)
    except (IndexError, ValueError) as exc:
        within, metric, detail = False, float("nan"), f"check failed: {exc}"
    energy_ok = bool(en["growth"] <= ENERGY_TOL)
    finite = bool(np.all(np.isfinite(out.result.state.centroid)))
    if completed:
        verdict = "pass" if within and energy_ok else (
            WARNED if out.result.summary.get("warnings") else "wrong")
    elif out.status == "cancelled":
        verdict = STOPPED if energy_ok else "wrong"
    else:
        verdict = "failed (clear status)" if out.message and finite else "blew up"
    row = {"case": case.name, "sweep": sweep, "dt": dt, "penalty": k, "status": out.status,
           "message": out.message, "within_tolerance": bool(within), "metric": metric,
           "detail": detail, "energy_growth": en["growth"], "energy_residual": en["residual"],
           "energy_ok": energy_ok, "verdict": verdict, "steps": out.steps,
           "simulated": out.simulated, "mean_dt": out.simulated / max(out.steps, 1),
           "wall_s": out.compute_wall}
    print(f"  {case.name:14s} {sweep} dt={dt:<6g} k={k:<6g} {verdict:22s} {detail}; "
          f"dE={en['growth']:.2e} steps={out.steps} wall={out.compute_wall:.1f}s", flush=True)
    return row


def run_stability(out: Path, full: bool, names: list[str] | None = None) -> dict[str, Any]:
    """Section 3: for each case a Δt sweep at its penalty and a penalty sweep at its Δt."""
    rows = []
    old = h.load_json(out, "stability") or {"rows": []}
    names = names or list(STAB_CASES)
    rows = [r for r in old["rows"] if r["case"] not in names]
    for name in names:
        c = STAB_CASES[name]
        print(f"[stability] {name}", flush=True)
        dts = c.full_dts if full else c.dts
        ks = c.full_penalties if full else c.penalties
        cap = WALL_CAP[full] * (5 if name == "pile100" else 1)
        for dt in sorted(set(dts) | {c.dt}):
            rows.append(run_one(c, dt, c.penalty, "dt", cap))
        for k in sorted(set(ks) - {c.penalty}):
            rows.append(run_one(c, c.dt, k, "penalty", cap))
    data = {"rows": rows, "energy_tol": ENERGY_TOL, "wall_cap": WALL_CAP[full],
            "cases": {n: {"title": c.title, "criterion": c.criterion, "dt": c.dt,
                          "penalty": c.penalty} for n, c in STAB_CASES.items()}}
    h.save_json(out, "stability", data)
    return data


def summarize(data: dict[str, Any]) -> list[dict[str, Any]]:
    """Per case: largest passing Δt, passing penalty range, and whether failures were clean."""
    table = []
    for name, meta in data["cases"].items():
        rows = [r for r in data["rows"] if r["case"] == name]
        if not rows:
            continue
        dt_pass = [r["dt"] for r in rows if r["sweep"] == "dt" and r["verdict"] == "pass"]
        k_pass = [r["penalty"] for r in rows if r["verdict"] == "pass"
                  and (r["sweep"] == "penalty" or r["dt"] == meta["dt"])]
        bad = [r for r in rows if r["verdict"] != "pass"]
        table.append({
            "case": name, "title": meta["title"], "criterion": meta["criterion"],
            "dt_tested": sorted({r["dt"] for r in rows if r["sweep"] == "dt"}),
            "largest_dt_pass": max(dt_pass) if dt_pass else None,
            "k_tested": sorted({r["penalty"] for r in rows}),
            "k_pass": (min(k_pass), max(k_pass)) if k_pass else None,
            "blew_up": sum(r["verdict"] == "blew up" for r in rows),
            "failed_clean": sum(r["verdict"] == "failed (clear status)" for r in rows),
            "wrong": sum(r["verdict"] == "wrong" for r in rows),
            "warned": sum(r["verdict"] == WARNED for r in rows),
            "stopped": sum(r["verdict"] == STOPPED for r in rows),
            "runs": len(rows), "bad": bad,
        })
    return table


def plot_stability(out: Path, data: dict[str, Any]) -> str:
    """Two panels (Δt sweep, penalty sweep): one row per case, one cell per run, coloured
    by verdict. Also writes stability.csv."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h.write_csv(out / "stability.csv", data["rows"])
    colours = {"pass": "tab:green", "wrong": "tab:orange", "failed (clear status)": "tab:blue",
               "blew up": "tab:red", STOPPED: "tab:gray", WARNED: "tab:olive"}
    names = [n for n in data["cases"] if any(r["case"] == n for r in data["rows"])]
    fig, axes = plt.subplots(1, 2, figsize=(12, 0.5 * len(names) + 2))
    for ax, sweep, key, label in ((axes[0], "dt", "dt", "requested Δt (s)"),
                                  (axes[1], "penalty", "penalty", "penalty k (N/m)")):
        for y, n in enumerate(names):
            rs = [r for r in data["rows"] if r["case"] == n and
                  (r["sweep"] == sweep or (sweep == "penalty" and r["dt"] == data["cases"][n]["dt"]
                                           and r["sweep"] == "dt"))]
            for r in rs:
                ax.scatter(r[key], y, s=140, color=colours[r["verdict"]], marker="s",
                           edgecolors="k" if not r["energy_ok"] else "none", linewidths=1.5)
        ax.set_xscale("log")
        ax.set_yticks(range(len(names)))
        ax.set_yticklabels(names)
        ax.set_xlabel(label)
        ax.grid(True, which="major", alpha=0.3)
        ax.set_ylim(-0.5, len(names) - 0.5)
    for v, c in colours.items():
        axes[1].scatter([], [], color=c, marker="s", label=v)
    axes[1].scatter([], [], color="white", edgecolors="k", marker="s", label="energy grew")
    axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[0].set_title("Δt sweep at the case's penalty")
    axes[1].set_title("penalty sweep at the case's Δt")
    fig.tight_layout()
    name = "stability.png"
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name
