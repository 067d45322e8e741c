"""Analytic cases (docs/validation.md) and the speed–accuracy sweep over Δt, penalty
and open-close iterations: error against wall time, with the Pareto front per case."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from engine.geometry.shapes import box, oriented_box
from engine.model import AnalysisControls, Block, JointMaterial, Model, PointLoad
from engine.step.simulation import STATUS_COMPLETED

G = 9.81
RHO = 2600.0
W = RHO * G  #: weight of a 1 m cube, N
ALPHA = np.radians(30.0)
DOWN_DIP = np.array([np.cos(ALPHA), 0.0, -np.sin(ALPHA)])
STRIKE = np.array([0.0, 1.0, 0.0])
UP_NORMAL = np.array([np.sin(ALPHA), 0.0, np.cos(ALPHA)])
INCLINE_AXES = np.array([DOWN_DIP, STRIKE, UP_NORMAL])
#: docs/validation.md: d(1 s) for φ = 20° on 30°
INCLINE_D1 = 0.906407
#: case 2: line of intersection (downward) and accelerations along it
WEDGE_LINE = np.array([0.113060, -0.869407, -0.480987])
WEDGE_A = {0.0: 4.718485, 10.0: 2.538901}
#: case 6: d(1 s) at P = 1.5 W tan 30°
PUSHED_D1 = 1.415952


def controls(dt: float, penalty: float, duration: float, **kw: Any) -> AnalysisControls:
    """Analysis controls of a benchmark run (dynamic, rigid unless told)."""
    return AnalysisControls(duration=duration, time_step=dt, penalty=penalty, **kw)


def incline_model(dt: float = 1e-3, penalty: float = 1e10, phi_deg: float = 20.0,
                  duration: float = 1.0, **kw: Any) -> Model:
    """Case 1: a 1 m cube on a fixed slab dipping 30°; block 1 is the cube."""
    slab = oriented_box(-DOWN_DIP - STRIKE - UP_NORMAL, INCLINE_AXES, [22.0, 3.0, 1.0])
    cube = oriented_box(np.zeros(3), INCLINE_AXES, [1.0, 1.0, 1.0])
    return Model(blocks=[Block(slab, "slab", fixed=True), Block(cube, "block")],
                 joint_materials=[JointMaterial(np.radians(phi_deg))],
                 controls=controls(dt, penalty, duration, **kw))


def wedge_model(dt: float = 1e-3, penalty: float = 1e10, phi_deg: float = 0.0,
                duration: float = 1.0, **kw: Any) -> Model:
    """Case 2: the wedge in the fixed V-trough (examples/wedge_trough.json); block 0 is it."""
    from schemas.convert import build_model

    model = build_model(h.ROOT / "examples" / "wedge_trough.json").model
    model.joint_materials = [JointMaterial(np.radians(phi_deg))]
    model.controls = dataclasses.replace(model.controls, duration=duration, time_step=dt,
                                         penalty=penalty, **kw)
    return model


def fall_model(dt: float = 1e-3, penalty: float = 1e9, duration: float = 2.0,
               drop: float = 1.0, **kw: Any) -> Model:
    """Case 4: a 1 m cube `drop` m above a fixed base (top z = 0); block 1 is the cube."""
    base = box([-2, -2, -1], [3, 3, 0])
    cube = box([0, 0, drop], [1, 1, drop + 1])
    return Model(blocks=[Block(base, "base", fixed=True), Block(cube, "cube")],
                 joint_materials=[JointMaterial(np.radians(30))],
                 controls=controls(dt, penalty, duration, **kw))


def pushed_model(dt: float = 1e-3, penalty: float = 1e10, factor: float = 1.5,
                 duration: float = 1.0, **kw: Any) -> Model:
    """Case 6: a cube on a φ = 30° floor pushed through its centroid by factor × W tan φ."""
    p = factor * W * np.tan(np.radians(30))
    return Model(blocks=[Block(box([-2, -2, -1], [6, 3, 0]), "floor", fixed=True),
                         Block(box([0, 0, 0], [1, 1, 1]), "cube")],
                 joint_materials=[JointMaterial(np.radians(30))],
                 point_loads=[PointLoad(1, np.array([0.0, 0.5, 0.5]), np.array([p, 0.0, 0.0]))],
                 controls=controls(dt, penalty, duration, **kw))


# --------------------------------------------------------------------------- error measures


def incline_error(out: h.Outcome) -> tuple[float, float]:
    """(relative error of d(1 s), measured d)."""
    d = float(np.asarray(out.result.summary["blocks"][1]["displacement"]) @ DOWN_DIP)
    t = out.simulated
    expected = INCLINE_D1 * t**2
    return abs(d / expected - 1.0), d


def wedge_error(phi: float) -> Callable[[h.Outcome], tuple[float, float]]:
    """Error of the acceleration along the line of intersection (slope of v over 0.5–1 s)."""

    def err(out: h.Outcome) -> tuple[float, float]:
        log = out.log
        assert log is not None
        t = log.times()
        v = log.series(0, "velocity")[:, :3] @ WEDGE_LINE
        sel = t >= 0.5 - 1e-9
        if sel.sum() < 2:
            return float("nan"), float("nan")
        a = float(np.polyfit(t[sel], v[sel], 1)[0])
        return abs(a / WEDGE_A[phi] - 1.0), a

    return err


def fall_error(penalty: float) -> Callable[[h.Outcome], tuple[float, float]]:
    """Error of the static penetration W / (4 k) after settling (k per vertex)."""

    def err(out: h.Outcome) -> tuple[float, float]:
        z = out.result.state.centroid[1, 2]
        pen = 0.5 - z
        return abs(pen / (W / (4.0 * penalty)) - 1.0), float(pen)

    return err


def pushed_error(out: h.Outcome) -> tuple[float, float]:
    """(relative error of d(1 s), measured d)."""
    d = float(out.result.state.centroid[1, 0] - 0.5)
    return abs(d / (PUSHED_D1 * out.simulated**2) - 1.0), d


@dataclass(frozen=True)
class Case:
    """An analytic case: its builder, error measure, what is measured and the exact value."""

    name: str
    title: str
    build: Callable[..., Model]
    error: Callable[[float], Callable[[h.Outcome], tuple[float, float]]]
    quantity: str
    exact: float
    record: bool = False


CASES: dict[str, Case] = {
    "incline": Case("incline", "block on a 30° incline, φ = 20°", incline_model,
                    lambda k: incline_error, "d(1 s) m", INCLINE_D1),
    "wedge0": Case("wedge0", "wedge in the trough, φ = 0°",
                   lambda **kw: wedge_model(phi_deg=0.0, **kw),
                   lambda k: wedge_error(0.0), "a along I m/s²", WEDGE_A[0.0], record=True),
    "wedge10": Case("wedge10", "wedge in the trough, φ = 10°",
                    lambda **kw: wedge_model(phi_deg=10.0, **kw),
                    lambda k: wedge_error(10.0), "a along I m/s²", WEDGE_A[10.0], record=True),
    "fall": Case("fall", "free fall 1 m + settling (2 s), static penetration W/(4k)",
                 fall_model, fall_error, "penetration m", float("nan")),
    "pushed": Case("pushed", "pushed block, P = 1.5 W tan 30°", pushed_model,
                   lambda k: pushed_error, "d(1 s) m", PUSHED_D1),
}

#: the default largest displacement in a step, / model size (AnalysisControls)
RATIO = 0.01
#: `big_dts` run at the stiffest penalty with a displacement limit of `ratio` × the model
#: size: the DDA integrator is exact for constant acceleration, so where nothing else
#: limits the step a user may allow larger steps (analysis.max_displacement_ratio)
QUICK_GRID = {"dts": [1e-1, 3e-2, 1e-2, 3e-3, 1e-3], "penalties": [1e8, 1e10], "oc": [20],
              "oc_extra": [2], "big_dts": [0.25], "ratio": [0.05]}
FULL_GRID = {"dts": [1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 3e-4],
             "penalties": [1e7, 1e8, 1e9, 1e10, 1e11, 1e12], "oc": [20], "oc_extra": [1, 2, 4],
             "big_dts": [0.1, 0.25, 0.35, 0.5], "ratio": [0.05]}


def sweep_case(case: Case, dts: list[float], penalties: list[float], oc: list[int],
               oc_extra: list[int], big_dts: list[float] = (),
               ratios: list[float] = ()) -> list[dict[str, Any]]:
    """Run one case over the grid (plus open-close limits at the stiffest penalty, largest
    Δt, and larger steps with a larger displacement limit); one row per run."""
    combos = [(dt, k, it, RATIO) for dt in dts for k in penalties for it in oc]
    if oc_extra:
        combos += [(dt, max(penalties), it, RATIO) for dt in dts[:2] for it in oc_extra]
    combos += [(dt, max(penalties), oc[0], r) for dt in big_dts for r in ratios]
    rows = []
    for dt, k, it, ratio in combos:
        duration = 2.0 if case.name == "fall" else 1.0
        rec_every = max(1, int(round(0.01 / dt)))
        model = case.build(dt=dt, penalty=k, duration=duration, max_open_close_iterations=it,
                           record_interval=rec_every, record_contacts=False,
                           max_displacement_ratio=ratio)
        out = h.run_model(model, record=case.record)
        err, value = case.error(k)(out) if out.status == STATUS_COMPLETED else (np.nan, np.nan)
        exact = W / (4 * k) if case.name == "fall" else case.exact
        rows.append({"engine": "PolyDDA", "case": case.name, "dt": dt, "penalty": k,
                     "oc_iterations": it, "max_displacement_ratio": ratio,
                     "status": out.status, "message": out.message,
                     "steps": out.steps, "wall_s": out.compute_wall, "value": value,
                     "exact": exact, "rel_error": err, **{f"t_{p}": v
                                                          for p, v in out.timings.items()}})
        print(f"  {case.name:8s} dt={dt:<7g} k={k:<7g} oc={it} ratio={ratio:g} {out.status:9s} "
              f"err={err:.2e} wall={out.compute_wall:.2f}s steps={out.steps}", flush=True)
    return rows


def run_accuracy(out: Path, full: bool, names: list[str] | None = None,
                 grid: dict[str, list[float]] | None = None) -> dict[str, Any]:
    """Section 1: sweep every (or the named) case; store rows and charts."""
    g = dict(FULL_GRID if full else QUICK_GRID)
    if grid:
        g.update({k: v for k, v in grid.items() if v is not None})
    names = names or list(CASES)
    h.run_model(incline_model(dt=0.05, duration=0.2))  # warm-up: imports, caches, kernels
    old = h.load_json(out, "accuracy") or {"rows": [], "grid": g}
    rows = [r for r in old["rows"] if r["case"] not in names]
    for name in names:
        print(f"[accuracy] {name}", flush=True)
        rows += sweep_case(CASES[name], [float(x) for x in g["dts"]],
                           [float(x) for x in g["penalties"]],
                           [int(x) for x in g["oc"]], [int(x) for x in g["oc_extra"]],
                           [float(x) for x in g.get("big_dts", [])],
                           [float(x) for x in g.get("ratio", [])])
    data = {"rows": rows, "grid": g}
    h.save_json(out, "accuracy", data)
    return data


def plot_accuracy(out: Path, accuracy: dict[str, Any], peers: dict[str, Any] | None) -> list[str]:
    """One log–log error-vs-wall-time PNG per case with its Pareto front (peers on the
    incline chart); also writes the CSV of every point. Returns the PNG names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = accuracy["rows"]
    full_oc = max(accuracy["grid"]["oc"])  # the default limit: filled markers
    peer_rows = (peers or {}).get("rows", [])
    h.write_csv(out / "accuracy.csv", rows + peer_rows)
    names = []
    for case in dict.fromkeys(r["case"] for r in rows):
        pts = [r for r in rows if r["case"] == case]
        fig, ax = plt.subplots(figsize=(9, 5))
        floor = 1e-9
        ok = [r for r in pts if r["status"] == STATUS_COMPLETED and np.isfinite(r["rel_error"])]
        bad = [r for r in pts if r not in ok]
        cmap = plt.get_cmap("viridis")
        dts = sorted({r["dt"] for r in pts})
        markers = dict(zip(sorted({r["penalty"] for r in pts}), "osD^vP*X", strict=False))
        for r in ok:
            c = cmap(dts.index(r["dt"]) / max(len(dts) - 1, 1))
            ax.loglog(r["wall_s"], max(r["rel_error"], floor), markers[r["penalty"]],
                      color=c, mfc="none" if r["oc_iterations"] < full_oc else c, ms=7)
        for r in bad:
            ax.loglog(r["wall_s"], 1.0, "x", color="red", ms=8)
        if ok:
            front = h.pareto_front([r["wall_s"] for r in ok], [r["rel_error"] for r in ok])
            ax.loglog([ok[i]["wall_s"] for i in front],
                      [max(ok[i]["rel_error"], floor) for i in front], "k--", lw=1,
                      drawstyle="steps-post", label="PolyDDA Pareto front")
        for dt in dts:
            ax.plot([], [], "s", color=cmap(dts.index(dt) / max(len(dts) - 1, 1)),
                    label=f"Δt = {dt:g} s")
        for k, m in markers.items():
            ax.plot([], [], m, color="gray", label=f"k = {k:g} N/m")
        if bad:
            ax.plot([], [], "x", color="red", label="failed / no result (drawn at 1)")
        if case == "incline":
            styles = {"MuJoCo": ("^", "tab:orange"), "LMGC90": ("v", "tab:green"),
                      "YADE": ("<", "tab:purple")}
            for eng, (m, col) in styles.items():
                pr = [r for r in peer_rows if r["engine"] == eng and r["case"] == "incline"
                      and np.isfinite(r["rel_error"])]
                if pr:
                    ax.loglog([r["wall_s"] for r in pr],
                              [max(r["rel_error"], floor) for r in pr], m, color=col, ms=9,
                              mec="k", label=f"{eng} (re-run here)")
        title = CASES[case].title if case in CASES else case
        ax.set_title(f"{title}\nerror vs wall time (hollow: fewer open-close iterations)",
                     fontsize=10)
        ax.set_xlabel("wall time of the run (s)")
        ax.set_ylabel("relative error")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))  # off the points
        fig.tight_layout()
        name = f"accuracy_{case}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        names.append(name)
    return names
