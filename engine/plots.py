"""PNG plots of a result file: block histories, energy balance, rock bolt forces, water
forces, 3-D snapshots.

Figures are built with the object API on the Agg canvas (no pyplot, no global state), so
plotting is safe in servers and threads and never opens a window.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from engine.frame import energy_created
from engine.results import Result, open_result

PathLike = str | os.PathLike[str]
#: energy terms drawn by plot_energy, with their labels
ENERGY_LABELS = {
    "kinetic": "kinetic", "elastic": "elastic strain", "contact": "contact springs",
    "gravity_work": "work of gravity", "external_work": "work of loads",
    "friction_dissipation": "friction dissipation",
    "numerical_dissipation": "dissipated by the DDA integrator",
    "damping_dissipation": "dissipated by contact damping",
}
MAX_HISTORY_BLOCKS = 8


def _save(fig: Figure, path: PathLike, dpi: int = 120) -> Path:
    """Render a figure to PNG with Agg and return the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(out, dpi=dpi, format="png")
    return out


def _title(result: Result, text: str) -> str:
    status = result.status
    return text if status == "completed" else f"{text}  [run {status}]"


def default_blocks(result: Result, limit: int = MAX_HISTORY_BLOCKS) -> list[int]:
    """Free blocks with the largest final displacement (at most `limit`), in index order."""
    free = np.flatnonzero(~result.fixed)
    if result.n_steps == 0 or len(free) <= limit:
        return free.tolist()
    disp = np.linalg.norm(result.centroids(-1)[free] - result.initial_centroids[free], axis=1)
    return sorted(free[np.argsort(-disp, kind="stable")[:limit]].tolist())


def plot_histories(result: Result | PathLike, path: PathLike,
                   blocks: list[str | int] | None = None) -> Path:
    """Centroid displacement and velocity magnitudes vs time of some blocks.

    `blocks`: names or indices (default: the free blocks that moved most, at most 8).
    """
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_histories(r, path, blocks)
    idx = default_blocks(result) if blocks is None else [result.block_index(b) for b in blocks]
    fig = Figure(figsize=(8, 6), layout="constrained")
    ax_u, ax_v = fig.subplots(2, 1, sharex=True)
    for i in idx:
        h = result.block_history(i)
        label = result.block_names[i] or f"block {i}"
        ax_u.plot(h["time"], np.linalg.norm(h["displacement"], axis=1), label=label)
        ax_v.plot(h["time"], np.linalg.norm(h["velocity"][:, :3], axis=1), label=label)
    ax_u.set_ylabel("displacement |u| (m)")
    ax_v.set_ylabel("velocity |v| (m/s)")
    ax_v.set_xlabel("time (s)")
    ax_u.set_title(_title(result, "Block centroid histories"))
    for ax in (ax_u, ax_v):
        ax.grid(True, alpha=0.3)
    if idx:
        ax_u.legend(fontsize="small", loc="best")
    else:
        ax_u.text(0.5, 0.5, "no free blocks", ha="center", transform=ax_u.transAxes)
    return _save(fig, path)


def energy_residual(energies: dict[str, np.ndarray]) -> np.ndarray:
    """Energy balance residual `(K,)` J since step 0: the energy the run created
    (:func:`engine.frame.energy_created`: stored + dissipated − work); terms that are
    missing or NaN count as zero."""
    created = np.asarray(energy_created(energies), float)
    if created.ndim == 0:
        return np.zeros(len(next(iter(energies.values()), [])))
    return created - created[0]


def plot_energy(result: Result | PathLike, path: PathLike) -> Path:
    """Energy terms vs time and the balance residual (what the work does not account for)."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_energy(r, path)
    t = result.times
    e = result.energies()
    fig = Figure(figsize=(8, 6), layout="constrained")
    ax, ax_r = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    for name, label in ENERGY_LABELS.items():
        values = e.get(name)
        if values is not None and len(values) and not np.all(np.isnan(values)):
            ax.plot(t, values, label=label)
    res = energy_residual(e) if e else np.zeros(len(t))
    ax_r.plot(t, res, color="black", label="residual")
    ax_r.axhline(0.0, color="grey", lw=0.5)
    ax.set_ylabel("energy / work (J)")
    ax_r.set_ylabel("balance residual (J)")
    ax_r.set_xlabel("time (s)")
    ax.set_title(_title(result, "Energy balance"))
    ax.grid(True, alpha=0.3)
    ax_r.grid(True, alpha=0.3)
    if ax.lines:
        ax.legend(fontsize="small", loc="best")
    return _save(fig, path)


def plot_bolts(result: Result | PathLike, path: PathLike) -> Path:
    """Axial and shear force of every rock bolt vs time, broken bolts marked."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_bolts(r, path)
    b = result.bolts()
    if b is None:
        raise ValueError(f"{result.path} has no rock bolts")
    t = result.times
    fig = Figure(figsize=(8, 6), layout="constrained")
    ax_n, ax_s = fig.subplots(2, 1, sharex=True)
    for k, name in enumerate(b["names"]):
        (line,) = ax_n.plot(t, b["axial_force"][:, k] / 1e3, label=name)
        ax_s.plot(t, b["shear_force"][:, k] / 1e3, color=line.get_color(), label=name)
        broke = np.flatnonzero(b["status"][:, k] == 2)
        if len(broke):
            ax_n.axvline(t[broke[0]], color=line.get_color(), ls=":", lw=1)
            ax_n.annotate(f"{name} breaks", (t[broke[0]], 0.0), fontsize="small")
    ax_n.set_ylabel("axial force (kN, tension +)")
    ax_s.set_ylabel("shear force (kN)")
    ax_s.set_xlabel("time (s)")
    ax_n.set_title(_title(result, "Rock bolts"))
    for ax in (ax_n, ax_s):
        ax.grid(True, alpha=0.3)
    if len(b["names"]) <= 12:
        ax_n.legend(fontsize="small", loc="best")
    return _save(fig, path)


def plot_water(result: Result | PathLike, path: PathLike) -> Path:
    """Magnitude of the resultant water force on each wetted block vs time."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_water(r, path)
    w = result.water_resultants()
    if w is None:
        raise ValueError(f"{result.path} has no water")
    t = result.times
    mag = np.linalg.norm(w, axis=2)
    fig = Figure(figsize=(8, 4), layout="constrained")
    ax = fig.subplots()
    for b in np.flatnonzero(np.nanmax(mag, axis=0, initial=0.0) > 0)[:MAX_HISTORY_BLOCKS]:
        ax.plot(t, mag[:, b] / 1e3, label=result.block_names[b] or f"block {b}")
    ax.set_ylabel("water force |U| (kN)")
    ax.set_xlabel("time (s)")
    ax.set_title(_title(result, "Resultant water force per block"))
    ax.grid(True, alpha=0.3)
    if ax.lines:
        ax.legend(fontsize="small", loc="best")
    return _save(fig, path)


def plot_snapshot(result: Result | PathLike, step: int | None, path: PathLike) -> Path:
    """3-D view of all blocks at recorded step `step` (None or no steps: initial geometry),
    faces coloured by the mean displacement magnitude of their vertices."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_snapshot(r, step, path)
    x0 = result.initial_vertices()
    if step is None or result.n_steps == 0:
        xs, label = x0, "initial geometry"
    else:
        k = result.resolve_step(step)
        xs, label = result.vertices(k), f"t = {result.times[k]:.4g} s (step {result.steps[k]})"
    polys, values = [], []
    for b, (x, x_0) in enumerate(zip(xs, x0, strict=True)):
        d = np.linalg.norm(x - x_0, axis=1)
        for face in result.faces(b):
            polys.append(x[face])
            values.append(float(d[face].mean()))
    vals = np.asarray(values)
    vmax = float(vals.max()) if len(vals) and vals.max() > 0 else 1.0
    norm = Normalize(vmin=0.0, vmax=vmax)
    mappable = ScalarMappable(norm=norm, cmap="viridis")
    fig = Figure(figsize=(8, 7), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    coll = Poly3DCollection(polys, facecolors=mappable.to_rgba(vals), edgecolors="k",
                            linewidths=0.3)
    ax.add_collection3d(coll)
    pts = np.concatenate(xs) if xs else np.zeros((1, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.maximum(hi - lo, 1e-9 * max(1.0, float(np.ptp(pts))))
    ax.set_xlim(lo[0], lo[0] + span[0])
    ax.set_ylim(lo[1], lo[1] + span[1])
    ax.set_zlim(lo[2], lo[2] + span[2])
    ax.set_box_aspect(tuple(span / span.max()))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(_title(result, label))
    fig.colorbar(mappable, ax=ax, shrink=0.6, label="displacement (m)")
    return _save(fig, path)


def snapshot_steps(result: Result, times: list[float] | None = None,
                   steps: list[int] | None = None) -> list[int]:
    """Step indices of the 3-D snapshots: the recorded step nearest each time in `times` (s)
    and the recorded solver steps `steps`, in that order without repeats.

    ValueError for a time outside the recorded times or a step that was not recorded.
    """
    t, recorded = result.times, result.steps
    out: list[int] = []
    for x in times or []:
        if not len(t) or not (t[0] - 1e-9 * max(1.0, abs(t[-1])) <= x
                              <= t[-1] + 1e-9 * max(1.0, abs(t[-1]))):
            span = f"{t[0]:g} to {t[-1]:g} s" if len(t) else "no steps"
            raise ValueError(f"time {x:g} s is outside the recorded times ({span})")
        out.append(int(np.argmin(np.abs(t - x))))
    for n in steps or []:
        hits = np.flatnonzero(recorded == n)
        if not len(hits):
            span = (f"{recorded[0]} to {recorded[-1]}, {len(recorded)} records"
                    if len(recorded) else "no steps")
            raise ValueError(f"step {n} was not recorded (recorded steps: {span})")
        out.append(int(hits[0]))
    return list(dict.fromkeys(out))


def plot_all(result: Result | PathLike, out_dir: PathLike | None = None, *,
             blocks: list[str | int] | None = None, times: list[float] | None = None,
             steps: list[int] | None = None) -> list[Path]:
    """Every plot of a result file as PNGs in `out_dir` (default `<result stem>_plots/`).

    `blocks`: names or indices of the blocks in the histories (default: the free blocks that
    moved most, at most 8). `times` (s) and `steps` (solver steps): 3-D snapshots at the
    recorded steps nearest those times and at those recorded steps, `snapshot_step<N>.png`
    (default: `snapshot_initial.png` and `snapshot_final.png`).
    """
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_all(r, out_dir, blocks=blocks, times=times, steps=steps)
    src = result.path
    out = Path(out_dir) if out_dir is not None else src.with_name(f"{src.stem}_plots")
    out.mkdir(parents=True, exist_ok=True)
    r = result
    for b in blocks or []:
        r.block_index(b)  # an unknown block fails before any plot is made
    chosen = times is not None or steps is not None
    picks = snapshot_steps(r, times, steps) if chosen else []
    if r.n_steps == 0:
        return [plot_snapshot(r, None, out / "snapshot_initial.png")]
    paths = [plot_histories(r, out / "histories.png", blocks), plot_energy(r, out / "energy.png")]
    if r.bolts() is not None:
        paths.append(plot_bolts(r, out / "bolts.png"))
    if r.water_resultants() is not None:
        paths.append(plot_water(r, out / "water.png"))
    if not chosen:
        return paths + [plot_snapshot(r, None, out / "snapshot_initial.png"),
                        plot_snapshot(r, -1, out / "snapshot_final.png")]
    return paths + [plot_snapshot(r, k, out / f"snapshot_step{int(r.steps[k])}.png")
                    for k in picks]
