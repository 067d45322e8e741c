"""Equal-area lower-hemisphere stereonet of a kinematic analysis (mplstereonet projection).

:func:`stereonet_data` computes every plotted curve as (longitude, latitude) arrays in
radians, mplstereonet's native coordinates, from the orientations it stands for; the figure
draws exactly these arrays, so a test can pin the figure's content without pixels.
Elements: poles and great circles of the sets, the slope face, the pole friction cone
(poles of planes dipping at φ), the planar daylight envelope (poles of planes dipping at the
face's apparent dip), the planar lateral limits, the flexural toppling zone (poles at plunge
slope dip − φ within its lateral limits), the line friction circle (lines plunging at φ,
for wedge intersections), the direct toppling zone and the sets' intersections.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from engine.analyses.kinematics import KinematicResult, apparent_dip

with warnings.catch_warnings():  # mplstereonet 0.6 overrides Axes.cla (matplotlib >= 3.6)
    warnings.filterwarnings("ignore", message="Overriding `Axes.cla`",
                            category=PendingDeprecationWarning)
    from mplstereonet import stereonet_math as sm

__all__ = ["plot_stereonet", "stereonet_data"]

#: points along each curve
SEGMENTS = 181


def _lines(plunge: np.ndarray, trend: np.ndarray) -> np.ndarray:
    """(2, n) lon/lat (rad) of lines given by plunge and trend (degrees)."""
    lon, lat = sm.line(np.asarray(plunge, float), np.asarray(trend, float))
    return np.vstack([np.ravel(lon), np.ravel(lat)])


def _plane(dip: float, dip_direction: float) -> np.ndarray:
    """(2, n) lon/lat (rad) of a plane's great circle (strike by the right-hand rule)."""
    lon, lat = sm.plane(dip_direction - 90.0, dip, SEGMENTS)
    return np.vstack([np.ravel(lon), np.ravel(lat)])


def _arc(plunge: float, centre: float, half: float) -> np.ndarray:
    """Lines of constant `plunge` with trends centre ± half (a small circle on the net)."""
    trends = centre + np.linspace(-half, half, SEGMENTS)
    return _lines(np.full(SEGMENTS, plunge), trends)


def _sector(plunge: float, centre: float, half: float, outer: bool) -> np.ndarray:
    """Closed outline of the trends centre ± half between plunge `plunge` and the
    primitive (`outer`) or the centre of the net."""
    edge = _arc(plunge, centre, half)
    end = _arc(0.0 if outer else 90.0, centre, half)[:, ::-1]
    return np.hstack([edge, end, edge[:, :1]])


def stereonet_data(result: KinematicResult) -> dict[str, Any]:
    """Every curve and point of the figure as (2, n) lon/lat arrays in radians.

    Keys: `poles`, `great_circles`, `intersections` (dicts by set / pair name), `slope_face`,
    `friction_cone`, `daylight_envelope`, `planar_lateral_limits` (two lines),
    `toppling_zone`, `line_friction_circle`, `direct_toppling_zone`.
    """
    s = result.slope
    dd, phi = s.dip_direction, s.friction_angle
    poles = {j.name: np.vstack(sm.pole(j.dip_direction - 90.0, j.dip)) for j in result.sets}
    inter = {f"{w.sets[0]}/{w.sets[1]}": _lines(np.array([w.plunge]), np.array([w.trend]))
             for w in result.wedge if w.trend is not None}
    # daylight envelope: the pole of every plane dipping out of the face at its apparent dip
    ddirs = dd + np.linspace(-90.0, 90.0, SEGMENTS)
    app = np.array([max(0.0, apparent_dip(s.dip, dd, a)) for a in ddirs])
    daylight = _lines(90.0 - app, ddirs + 180.0)
    lim = result.limits
    return {
        "poles": poles,
        "great_circles": {j.name: _plane(j.dip, j.dip_direction) for j in result.sets},
        "intersections": inter,
        "slope_face": _plane(s.dip, dd),
        "friction_cone": _arc(90.0 - phi, 0.0, 180.0),
        "daylight_envelope": np.hstack([daylight, daylight[:, :1]]),
        "planar_lateral_limits": [
            _lines(np.linspace(0.0, 90.0, SEGMENTS), np.full(SEGMENTS, dd + 180.0 + side))
            for side in (-lim.planar, lim.planar)],
        "toppling_zone": _sector(max(0.0, s.dip - phi), dd, lim.flexural_toppling,
                                 outer=True),
        "line_friction_circle": _arc(phi, 0.0, 180.0),
        "direct_toppling_zone": _sector(90.0 - s.dip, dd + 180.0, lim.direct_toppling,
                                        outer=False),
    }


def plot_stereonet(result: KinematicResult, path: str | Path | None = None,
                   title: str | None = None) -> tuple[Any, dict[str, Any]]:
    """Draw :func:`stereonet_data` on an equal-area lower-hemisphere net (a matplotlib
    Figure on the Agg canvas); save to `path` (PNG) if given. Returns it and the data."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Overriding `Axes.cla`",
                                category=PendingDeprecationWarning)
        import mplstereonet  # noqa: F401  (registers the projection)

    data = stereonet_data(result)
    fig = Figure(figsize=(8, 9.4))  # object API on Agg, as engine.results.plots: no pyplot state
    FigureCanvasAgg(fig)
    # a square axes box: mplstereonet places the azimuth labels on the box's ellipse
    ax = fig.add_axes((0.125, 0.2, 0.75, 6 / 9.4), projection="equal_area_stereonet")
    ax.fill(*data["toppling_zone"], color="tab:purple", alpha=0.18,
            label=f"flexural toppling zone (poles, ±{result.limits.flexural_toppling:g}°)")
    ax.fill(*data["direct_toppling_zone"], color="tab:orange", alpha=0.18,
            label=f"direct toppling zone (intersections, ±{result.limits.direct_toppling:g}°)")
    ax.plot(*data["daylight_envelope"], color="tab:blue", lw=1.5,
            label="daylight envelope (poles)")
    for k, line in enumerate(data["planar_lateral_limits"]):
        ax.plot(*line, color="tab:blue", lw=0.8, ls=":",
                label=f"planar lateral limits (±{result.limits.planar:g}°)" if k == 0 else None)
    ax.plot(*data["friction_cone"], color="tab:red", lw=1.5,
            label=f"friction cone φ = {result.slope.friction_angle:g}° (poles)")
    ax.plot(*data["line_friction_circle"], color="tab:red", lw=1.0, ls="--",
            label="plunge = φ (intersections)")
    ax.plot(*data["slope_face"], color="k", lw=2.0,
            label=f"slope face {result.slope.dip:g}/{result.slope.dip_direction:03g}")
    colors = matplotlib.colormaps["tab10"]
    for k, (name, circle) in enumerate(data["great_circles"].items()):
        c = colors((k + 2) % 10)
        ax.plot(*circle, color=c, lw=1.0)
        ax.plot(*data["poles"][name], "o", color=c, ms=7, label=f"{name} pole / plane")
        lon, lat = data["poles"][name][:, 0]
        ax.annotate(name, (lon, lat), xytext=(5, 5), textcoords="offset points")
    admissible = {f"{a}/{b}" for a, b in result.admissible()["wedge"]}
    labelled: set[bool] = set()
    for name, pt in data["intersections"].items():
        ok = name in admissible
        label = None if ok in labelled else ("intersection, wedge admissible" if ok
                                             else "intersection")
        labelled.add(ok)
        ax.plot(*pt, "^", color="tab:red" if ok else "0.3", ms=8, label=label)
        ax.annotate(name, (pt[0, 0], pt[1, 0]), xytext=(5, -12), textcoords="offset points",
                    fontsize=8)
    ax.grid(True, alpha=0.3)
    ax.set_azimuth_ticks(np.arange(0, 360, 30))
    ax.set_title(title or "Kinematic analysis (equal area, lower hemisphere)", y=1.06)
    fig.legend(loc="lower center", ncol=2, fontsize=8, frameon=False)
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig, data
