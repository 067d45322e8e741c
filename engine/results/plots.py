"""PNG plots of a result file: block histories, energy balance, rock bolt forces, water
forces, 3-D snapshots.

Figures are built with the object API on the Agg canvas (no pyplot, no global state), so
plotting is safe in servers and threads and never opens a window.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from engine.results.reader import Result, open_result
from engine.step.frame import energy_created

PathLike = str | os.PathLike[str]
#: energy terms drawn by plot_energy, with their labels
ENERGY_LABELS = {
    "kinetic": "kinetic", "elastic": "elastic strain", "contact": "contact springs",
    "gravity_work": "work of gravity", "external_work": "work of loads",
    "friction_dissipation": "friction dissipation",
    "numerical_dissipation": "dissipated by the DDA integrator",
    "damping_dissipation": "dissipated by contact damping",
    "removed_energy": "removed with excavated blocks",
}
MAX_HISTORY_BLOCKS = 8
#: the half-span a nearly constant curve is drawn in at least: 1 nm (and nm/s), 1 nJ, 1 N
LENGTH_FLOOR, ENERGY_FLOOR, FORCE_FLOOR_KN = 1e-9, 1e-9, 1e-3
#: snapshots name the free blocks when there are at most this many
MAX_LABELS = 30
#: (elevation, azimuth) degrees of the snapshots' camera: the browser viewer's first view
#: (from the south-west, above: camera direction (-0.45, -0.8, 0.45))
VIEWER_VIEW = (26.1, -119.4)


def _save(fig: Figure, path: PathLike, dpi: int = 120) -> Path:
    """Render a figure to PNG with Agg and return the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(out, dpi=dpi, format="png")
    return out


def _readable_y(ax: Any, floor: float, relative: float = 1e-3) -> None:
    """Keep a y axis readable when its curves hardly vary: limits at least ± max(`floor`,
    `relative` × |level|) about their middle (round-off of 1e-15 J draws as a flat line at
    0, a constant 40 kN as 40.00), and no offset text such as '1e-11+4.000001478e1'."""
    ax.ticklabel_format(axis="y", useOffset=False)
    ys = [np.asarray(line.get_ydata(), float) for line in ax.get_lines()]
    v = np.concatenate([y[np.isfinite(y)] for y in ys]) if ys else np.zeros(0)
    if not len(v):
        return
    lo, hi = float(v.min()), float(v.max())
    mid = 0.5 * (lo + hi)
    half = max(floor, relative * abs(mid))
    if hi - lo < 2.0 * half:
        ax.set_ylim(mid - half, mid + half)


def _title(result: Result, text: str) -> str:
    status = result.status
    return text if status == "completed" else f"{text}  [run {status}]"


def mark_stages(result: Result, *axes: Any) -> None:
    """A staged run's stage starts on time axes: a dashed line and the stage's name at
    each start after the first (nothing for a run without stages)."""
    for st in result.stages()[1:]:
        for k, ax in enumerate(axes):
            ax.axvline(st["start_time"], color="grey", ls="--", lw=0.8)
            if k == 0:
                ax.annotate(st["name"], (st["start_time"], 1.0), xycoords=("data", "axes fraction"),
                            xytext=(2, -10), textcoords="offset points", fontsize="small",
                            color="dimgrey")


def _removed(result: Result) -> set[int]:
    """Blocks a staged run removed (excavated)."""
    names = list(result.block_names)
    return {names.index(n) for st in result.stages() for n in st["removed_blocks"]
            if n in names}


def default_blocks(result: Result, limit: int = MAX_HISTORY_BLOCKS) -> list[int]:
    """Free blocks with the largest final displacement (at most `limit`), in index order;
    blocks a stage removed are left out."""
    gone = np.zeros(len(result.fixed), bool)
    gone[list(_removed(result))] = True
    free = np.flatnonzero(~result.fixed & ~gone)
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
    mark_stages(result, ax_u, ax_v)
    for ax in (ax_u, ax_v):
        ax.grid(True, alpha=0.3)
        _readable_y(ax, LENGTH_FLOOR)
    if idx:
        ax_u.legend(fontsize="small", loc="best")
    else:
        ax_u.text(0.5, 0.5, "no free blocks", ha="center", transform=ax_u.transAxes)
    return _save(fig, path)


def energy_residual(energies: dict[str, np.ndarray]) -> np.ndarray:
    """Energy balance residual `(K,)` J since step 0: the energy the run created
    (:func:`engine.step.frame.energy_created`: stored + dissipated − work); terms that are
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
    _readable_y(ax, ENERGY_FLOOR)
    scale = max((float(np.nanmax(np.abs(v))) for v in e.values()
                 if len(v) and not np.all(np.isnan(v))), default=0.0)
    _readable_y(ax_r, max(ENERGY_FLOOR, 1e-3 * scale))  # round-off is 0 on this scale
    ax_r.axhline(0.0, color="grey", lw=0.5)
    ax.set_ylabel("energy / work (J)")
    ax_r.set_ylabel("balance residual (J)")
    ax_r.set_xlabel("time (s)")
    ax.set_title(_title(result, "Energy balance"))
    mark_stages(result, ax, ax_r)
    ax.grid(True, alpha=0.3)
    ax_r.grid(True, alpha=0.3)
    if ax.lines:  # beside the axes: it hides no curve
        ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  borderaxespad=0.0)
    return _save(fig, path)


def trend_plunge(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Trend (° clockwise from North = +y) and plunge (° below horizontal) of vectors
    `(..., 3)` (x East, y North, z up); NaN for zero vectors."""
    d = np.asarray(d, float)
    h = np.hypot(d[..., 0], d[..., 1])
    zero = (h == 0) & (d[..., 2] == 0)
    trend = np.where(zero, np.nan, np.degrees(np.arctan2(d[..., 0], d[..., 1])) % 360.0)
    plunge = np.where(zero, np.nan, np.degrees(np.arctan2(-d[..., 2], h)))
    return trend, plunge


def plot_displacements(result: Result | PathLike, path: PathLike,
                       blocks: list[str | int] | None = None) -> Path:
    """Centroid displacement components u_x (East), u_y (North), u_z (up) vs time of some
    blocks, and the direction of their final displacement (trend, plunge) on a polar plot
    (lower hemisphere: centre = straight down)."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_displacements(r, path, blocks)
    idx = default_blocks(result) if blocks is None else [result.block_index(b) for b in blocks]
    fig = Figure(figsize=(11, 6.5), layout="constrained")
    axes = fig.subplot_mosaic([["x", "dir"], ["y", "dir"], ["z", "dir"]],
                              width_ratios=(1.6, 1.0), sharex=False,
                              per_subplot_kw={"dir": {"projection": "polar"}})
    polar = axes["dir"]
    colours = [f"C{k % 10}" for k in range(len(idx))]
    for c, i in zip(colours, idx, strict=True):
        h = result.block_history(i)
        label = result.block_names[i] or f"block {i}"
        for j, key in enumerate("xyz"):
            axes[key].plot(h["time"], h["displacement"][:, j], color=c, label=label)
        d = h["displacement"][-1] if len(h["time"]) else np.zeros(3)
        trend, plunge = trend_plunge(d)
        if np.isfinite(trend):
            polar.plot(np.radians(trend), 90.0 - plunge, "o", color=c,
                       label=f"{label}: {np.linalg.norm(d):.3g} m, {trend:03.0f}/{plunge:.0f}")
    for key, name in zip("xyz", ("u_x East", "u_y North", "u_z up"), strict=True):
        axes[key].set_ylabel(f"{name} (m)")
        axes[key].grid(True, alpha=0.3)
        axes[key].axhline(0.0, color="grey", lw=0.5)
        _readable_y(axes[key], LENGTH_FLOOR)
    axes["z"].set_xlabel("time (s)")
    mark_stages(result, axes["x"], axes["y"], axes["z"])
    axes["x"].set_title(_title(result, "Centroid displacement components"))
    if polar.lines:  # below the polar plot: |u| and trend/plunge of each block
        polar.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.08),
                     ncols=2, title="final |u|, trend/plunge (°)")
    polar.set_theta_zero_location("N")
    polar.set_theta_direction(-1)
    polar.set_rlim(0.0, 180.0)
    polar.set_rticks([30, 60, 90, 120, 150])
    polar.set_yticklabels(["60° down", "30° down", "horizontal", "30° up", "60° up"],
                          fontsize="x-small")
    polar.set_title("final displacement: trend (° from N) / plunge", fontsize="medium")
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
    mark_stages(result, ax_n, ax_s)
    for ax in (ax_n, ax_s):
        ax.grid(True, alpha=0.3)
        _readable_y(ax, FORCE_FLOOR_KN)
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
    mark_stages(result, ax)
    ax.grid(True, alpha=0.3)
    _readable_y(ax, FORCE_FLOOR_KN)
    if ax.lines:
        ax.legend(fontsize="small", loc="best")
    return _save(fig, path)


def plot_snapshot(result: Result | PathLike, step: int | None, path: PathLike, *,
                  view: tuple[float, float] = VIEWER_VIEW) -> Path:
    """3-D view of all blocks at recorded step `step` (None or no steps: initial geometry),
    faces coloured by the mean displacement magnitude of their vertices, fixed blocks grey;
    seen from `view` (elevation, azimuth in degrees: by default as the viewer first shows
    the blocks)."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return plot_snapshot(r, step, path, view=view)
    x0 = result.initial_vertices()
    gone: set[int] = set()
    if step is None or result.n_steps == 0:
        xs, label = x0, "initial geometry"
    else:
        k = result.resolve_step(step)
        xs, label = result.vertices(k), f"t = {result.times[k]:.4g} s (step {result.steps[k]})"
        gone = result.removed_at(float(result.times[k]))  # excavated by then: not drawn
    polys, values, colours = [], [], []
    initial = xs is x0
    for b, (x, x_0) in enumerate(zip(xs, x0, strict=True)):
        if b in gone:
            continue
        d = np.linalg.norm(x - x_0, axis=1)
        for face in result.faces(b):
            polys.append(x[face])
            values.append(float(d[face].mean()))
            colours.append(b)
    vals = np.asarray(values)
    fig = Figure(figsize=(8, 7), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    fixed = np.asarray(result.fixed, bool)
    if initial:  # nothing moved yet: colour by block, fixed blocks grey
        palette = [f"C{b % 10}" for b in range(result.n_blocks)]
        faces = [("0.7" if fixed[b] else palette[b]) for b in colours]
        mappable = None
    else:  # the colour bar spans the displacements shown (max of the free blocks' faces)
        top = float(vals.max()) if len(vals) and vals.max() > 0 else 1.0
        # the colour bar in the unit of its largest value (m, mm or µm: no 1e-6 offset)
        unit, scale = next((u, f) for u, f in (("m", 1.0), ("mm", 1e3), ("µm", 1e6))
                           if top * f >= 1.0 or u == "µm")
        vals = vals * scale
        mappable = ScalarMappable(norm=Normalize(vmin=0.0, vmax=top * scale), cmap="viridis")
        faces = [("0.7" if fixed[b] else mappable.to_rgba(v))
                 for b, v in zip(colours, vals, strict=True)]
    coll = Poly3DCollection(polys, facecolors=faces, edgecolors="k", linewidths=0.3)
    # the limits are set from the vertices below: matplotlib's own autoscale reads the
    # collection's padded face array (faces of unequal vertex counts), whose padding is
    # uninitialised memory, and overflowed now and then on a staged run's snapshots
    ax.add_collection3d(coll, autolim=False)
    shown = [x for b, x in enumerate(xs) if b not in gone]
    pts = np.concatenate(shown) if shown else np.zeros((1, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.maximum(hi - lo, 1e-9 * max(1.0, float(np.ptp(pts))))
    ax.set_xlim(lo[0], lo[0] + span[0])
    ax.set_ylim(lo[1], lo[1] + span[1])
    ax.set_zlim(lo[2], lo[2] + span[2])
    ax.set_box_aspect(tuple(span / span.max()))
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_xlabel("x East (m)")
    ax.set_ylabel("y North (m)")
    ax.set_zlabel("z up (m)")
    ax.set_title(_title(result, label))
    free = np.array([b for b in np.flatnonzero(~fixed) if b not in gone], dtype=np.int64)
    labels = []
    if len(free) <= MAX_LABELS:  # block names at their highest vertex, the largest first
        for b in sorted(free, key=lambda b: -float(np.ptp(xs[b], axis=0).prod())):
            top = xs[b][np.argmax(xs[b][:, 2])]
            labels.append(ax.text(*top, f" {result.block_names[b] or b}", fontsize="small",
                                  zorder=10))
    if mappable is not None:
        fig.colorbar(mappable, ax=ax, shrink=0.6,
                     label=f"displacement ({unit}), 0 to {mappable.norm.vmax:.3g} {unit} "
                           "(fixed: grey)")
    declutter(fig, ax, labels)
    return _save(fig, path)


def _tick_boxes(axis: Any, renderer: Any) -> list[Any]:
    """The display boxes of an axis's tick labels as last drawn (the ticks in its view;
    get_ticklabels would move a 3-D axis's labels back to their 2-D places first)."""
    lo, hi = sorted(axis.get_view_interval())
    return [t.label1.get_window_extent(renderer) for t in axis.get_major_ticks()
            if lo <= t.get_loc() <= hi and t.label1.get_visible() and t.label1.get_text()]


def _overlapping(boxes: list[Any]) -> bool:
    """Whether any two of the display boxes overlap."""
    return any(a.overlaps(b) for k, a in enumerate(boxes) for b in boxes[k + 1:])


def declutter(fig: Figure, ax: Any, labels: list[Any]) -> None:
    """No text over another on a 3-D snapshot: each axis with fewer ticks until its tick
    labels stand apart (a short axis of a flat scene crowded them), then the block names
    kept in their order (the largest blocks first), each left out that would cover one
    already kept."""
    from matplotlib.ticker import MaxNLocator

    FigureCanvasAgg(fig)
    renderer = fig.canvas.get_renderer()
    crowded = [ax.xaxis, ax.yaxis, ax.zaxis]
    for bins in (6, 4, 3, 2, 1):  # a draw per round (a large scene draws slowly)
        for axis in crowded:
            axis.set_major_locator(MaxNLocator(nbins=bins))
        fig.canvas.draw()
        crowded = [a for a in crowded if _overlapping(_tick_boxes(a, renderer))]
        if not crowded:
            break
    kept: list[Any] = []
    for text in labels:
        box = text.get_window_extent(renderer)
        if any(box.overlaps(k) for k in kept):
            text.remove()
        else:
            kept.append(box)


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

    `blocks`: names or indices of the blocks in the histories and displacement components
    (default: the free blocks that moved most, at most 8). `times` (s) and `steps` (solver
    steps): 3-D snapshots at the recorded steps nearest those times and at those recorded
    steps, `snapshot_step<N>.png` (default: `snapshot_initial.png` and `snapshot_final.png`).
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
    paths = [plot_histories(r, out / "histories.png", blocks), plot_energy(r, out / "energy.png"),
             plot_displacements(r, out / "displacements.png", blocks)]
    if r.bolts() is not None:
        paths.append(plot_bolts(r, out / "bolts.png"))
    if r.water_resultants() is not None:
        paths.append(plot_water(r, out / "water.png"))
    if not chosen:
        return paths + [plot_snapshot(r, None, out / "snapshot_initial.png"),
                        plot_snapshot(r, -1, out / "snapshot_final.png")]
    return paths + [plot_snapshot(r, k, out / f"snapshot_step{int(r.steps[k])}.png")
                    for k in picks]


def plot_fos_trials(runs: list[dict], path: PathLike,
                    factor_of_safety: float | None = None) -> Path:
    """The strength-reduction bisection: each trial's reduction factor (held: circle,
    failed: cross) and the factor of safety found."""
    fig = Figure(figsize=(7, 3.6), layout="constrained")
    ax = fig.add_subplot()
    k = np.arange(1, len(runs) + 1)
    f = np.array([float(r["factor"]) for r in runs]) if runs else np.zeros(0)
    failed = np.array([bool(r["failed"]) for r in runs], bool)
    ax.plot(k, f, color="0.6", lw=1)
    ax.plot(k[~failed], f[~failed], "o", color="C2", label="holds")
    ax.plot(k[failed], f[failed], "x", color="C3", ms=8, mew=2, label="fails")
    if factor_of_safety is not None and np.isfinite(factor_of_safety):
        ax.axhline(factor_of_safety, color="C0", ls="--", label=f"FS = {factor_of_safety:.4g}")
    ax.set_xlabel("trial")
    ax.set_ylabel("strength reduction factor")
    ax.set_title("Factor of safety: bisection of the reduction factor")
    ax.grid(True, alpha=0.3)
    if len(k):
        ax.set_xticks(k)
        ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _save(fig, path)


def plot_fs_distribution(aggregates: dict[str, dict], path: PathLike,
                         title: str = "Factor of safety over the realisations") -> Path:
    """Histogram and empirical CDF of the factor of safety of a sweep: `aggregates` maps a
    label (e.g. "dda", "analytic") to engine.analyses.reliability.aggregate's document (its
    `histogram`, `cdf`, `probability_of_failure`); FS = 1 marked on both."""
    fig = Figure(figsize=(10, 3.8), layout="constrained")
    hist, cdf = fig.subplots(1, 2)
    for k, (label, a) in enumerate(aggregates.items()):
        pof = a.get("probability_of_failure")
        name = f"{label} (n = {a.get('n', 0)}" + (f", PoF {pof:.3g})" if pof is not None
                                                 else ")")
        h = a.get("histogram")
        if h and h.get("counts"):
            edges = np.asarray(h["edges"], float)
            hist.stairs(np.asarray(h["counts"], float), edges, fill=k == 0, alpha=0.5 if k == 0
                        else 1.0, color=f"C{k}", label=name)
        c = a.get("cdf")
        if c and c.get("fs"):
            fs = np.asarray(c["fs"], float)
            cdf.step(fs, np.asarray(c["p"], float), where="post", color=f"C{k}", label=name)
    for ax in (hist, cdf):
        ax.axvline(1.0, color="C3", ls="--", lw=1, label="FS = 1")
        ax.set_xlabel("factor of safety")
        ax.grid(True, alpha=0.3)
    hist.set_ylabel("realisations")
    hist.set_title("histogram")
    cdf.set_ylabel("P(FS ≤ x)")
    cdf.set_ylim(0, 1.02)
    cdf.set_title("empirical CDF")
    cdf.legend(fontsize="small", loc="lower right")
    fig.suptitle(title)
    return _save(fig, path)
