"""Measured joint orientations, as Dips reads them: the poles of dip / dip direction
measurements, the sets picked among them by k-means on the sphere, each set's Fisher mean,
concentration κ and 95 % confidence cone, and the stereonet of the pole density.

Poles are axes, not vectors: a plane's normal and its opposite are one pole (a vertical set
has poles on both sides of the net). The k-means therefore measures the angle between axes
(1 − |n·c|) and takes each set's centre as the principal axis of its poles' orientation
tensor Σ n nᵀ (Fisher, Lewis & Embleton 1987, §3.2); the set's normals are then turned to
the centre's side and the Fisher statistics follow: R̄ = |Σ n| / N, κ by maximum likelihood
from coth κ − 1/κ = R̄ (:func:`engine.analyses.jointstats.fisher_stats`), and the cone
α95 = arccos(1 − (N − R)/R (20^{1/(N−1)} − 1)) (Fisher 1953).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.analyses.jointstats import fisher_stats

__all__ = ["JointSetFit", "fit_sets", "pick_sets", "plot_pole_density", "poles"]

#: k-means runs from different starts; the tightest grouping wins
RESTARTS = 10
MAX_ITERATIONS = 100


@dataclass(frozen=True)
class JointSetFit:
    """One set of measured planes: its mean plane (degrees), Fisher's κ, the number of
    poles, the mean resultant length R̄ and the 95 % confidence cone of the mean (degrees)."""

    name: str
    dip: float
    dip_direction: float
    kappa: float
    count: int
    mean_resultant_length: float
    cone_95: float

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def poles(dips: Any, dip_directions: Any) -> np.ndarray:
    """Unit normals `(n, 3)` of planes (x East, y North, z up; upward: a pole is an axis)."""
    d, a = np.radians(np.ravel(dips)), np.radians(np.ravel(dip_directions))
    return np.column_stack([np.sin(d) * np.sin(a), np.sin(d) * np.cos(a), np.cos(d)])


def _principal(v: np.ndarray) -> np.ndarray:
    """The principal axis of the orientation tensor of unit vectors `v (m, 3)`."""
    _, vecs = np.linalg.eigh(v.T @ v)
    return vecs[:, -1]


def _kmeans(v: np.ndarray, k: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Axial k-means from a k-means++ start: (labels, total 1 − |n·c|)."""
    centres = [v[rng.integers(len(v))]]
    for _ in range(1, k):  # k-means++: far from the centres chosen, more likely
        d = np.clip(1.0 - np.abs(v @ np.array(centres).T).max(axis=1), 0.0, None)
        p = d / d.sum() if d.sum() > 0 else None
        centres.append(v[rng.choice(len(v), p=p)])
    c = np.array(centres)
    labels = np.full(len(v), -1)
    for _ in range(MAX_ITERATIONS):
        new = np.argmax(np.abs(v @ c.T), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            members = v[labels == j]
            if len(members):
                c[j] = _principal(members)
            else:  # an empty set takes the pole farthest from its own centre
                far = np.argmin(np.abs(np.sum(v * c[labels], axis=1)))
                c[j] = v[far]
    cost = float(np.sum(1.0 - np.abs(np.sum(v * c[labels], axis=1))))
    return labels, cost


def pick_sets(dips: Any, dip_directions: Any, k: int, seed: int = 0) -> np.ndarray:
    """Which of `k` sets each measured plane belongs to `(n,) int`: axial k-means on the
    poles, the tightest of RESTARTS starts from `seed`; sets numbered by size, largest
    first."""
    v = poles(dips, dip_directions)
    if not 1 <= k <= len(v):
        raise ValueError(f"cannot pick {k} sets from {len(v)} measurements")
    rng = np.random.default_rng(seed)
    labels, _ = min((_kmeans(v, k, rng) for _ in range(RESTARTS)), key=lambda r: r[1])
    order = np.argsort(-np.bincount(labels, minlength=k), kind="stable")
    rank = np.empty(k, dtype=int)
    rank[order] = np.arange(k)
    return rank[labels]


def _fit(name: str, v: np.ndarray) -> JointSetFit:
    """The Fisher statistics of one set's poles `v (m, 3)`."""
    axis = _principal(v)
    v = np.where((v @ axis)[:, None] < 0, -v, v)  # every normal on the axis' side
    s = fisher_stats(v)
    n, r = len(v), s["mean_resultant_length"] * len(v)
    if n > 1 and r > 0:
        c = 1.0 - (n - r) / r * (20.0 ** (1.0 / (n - 1)) - 1.0)
        cone = math.degrees(math.acos(max(-1.0, min(1.0, c))))
    else:
        cone = 180.0
    return JointSetFit(name, s["dip"], s["dip_direction"], s["kappa"], n,
                       s["mean_resultant_length"], cone)


def fit_sets(dips: Any, dip_directions: Any, k: int, seed: int = 0,
             names: list[str] | None = None) -> tuple[list[JointSetFit], np.ndarray]:
    """The `k` sets of measured planes (J1, J2, ... by size, or `names`) with their Fisher
    statistics, and each measurement's set `(n,) int`."""
    labels = pick_sets(dips, dip_directions, k, seed)
    v = poles(dips, dip_directions)
    names = names or [f"J{j + 1}" for j in range(k)]
    return [_fit(names[j], v[labels == j]) for j in range(k)], labels


def plot_pole_density(dips: Any, dip_directions: Any, sets: list[JointSetFit],
                      labels: np.ndarray, path: str | Path, title: str = "") -> Path:
    """Equal-area lower-hemisphere net of the poles (coloured by set), their density
    contoured (mplstereonet, exponential Kamb), each set's mean pole and plane."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with warnings.catch_warnings():  # mplstereonet 0.6 overrides Axes.cla
        warnings.filterwarnings("ignore", message="Overriding `Axes.cla`",
                                category=PendingDeprecationWarning)
        import mplstereonet  # noqa: F401  (registers the projection)

    strikes = (np.ravel(dip_directions) - 90.0) % 360.0  # right-hand rule
    dips = np.ravel(dips)
    fig = Figure(figsize=(8, 8.6))
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.1, 0.14, 0.72, 0.72 * 8 / 8.6), projection="equal_area_stereonet")
    filled = ax.density_contourf(strikes, dips, measurement="poles", cmap="Greys", alpha=0.7)
    cax = fig.add_axes((0.86, 0.25, 0.025, 0.5))
    fig.colorbar(filled, cax=cax, label="pole density (exponential Kamb, σ)")
    ax.density_contour(strikes, dips, measurement="poles", colors="k", linewidths=0.5)
    colours = matplotlib.colormaps["tab10"]
    for j, s in enumerate(sets):
        c = colours(j % 10)
        members = labels == j
        ax.pole(strikes[members], dips[members], ".", color=c, ms=3)
        strike = (s.dip_direction - 90.0) % 360.0
        ax.pole(strike, s.dip, "s", color=c, mec="k", ms=9,
                label=f"{s.name}: {s.dip:.0f}/{s.dip_direction:03.0f}, κ {s.kappa:.0f}, "
                      f"n {s.count}, α95 {s.cone_95:.1f}°")
        ax.plane(strike, s.dip, color=c, lw=1.5)
    ax.grid(True, alpha=0.4)
    ax.set_azimuth_ticks(np.arange(0, 360, 30))
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.06), fontsize="small", ncols=2)
    ax.set_title(title or f"{len(dips)} poles, {len(sets)} sets", y=1.08)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, format="png")
    return out
