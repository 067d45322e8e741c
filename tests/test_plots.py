"""PNG plots and text summaries of result files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from engine.results.plots import (  # noqa: E402
    energy_residual,
    plot_all,
    plot_displacements,
    plot_energy,
    plot_fos_trials,
    plot_histories,
    plot_snapshot,
    trend_plunge,
)
from engine.results.reader import open_result  # noqa: E402
from engine.results.summary import format_summary, summarize  # noqa: E402
from engine.results.writer import ResultWriter  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from test_results import make_frame, two_block_model, write_run  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def assert_png(path: Path, min_bytes: int = 5_000) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    assert len(data) > min_bytes, (path, len(data))


@pytest.fixture(scope="module")
def result_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("plots") / "run.h5"
    write_run(path, n_steps=12)
    return path


def test_plot_all_makes_pngs(result_file: Path, tmp_path: Path) -> None:
    paths = plot_all(result_file, tmp_path / "out")
    assert [p.name for p in paths] == ["histories.png", "energy.png", "displacements.png",
                                       "snapshot_initial.png", "snapshot_final.png"]
    for p in paths:
        assert_png(p)
    # the snapshot moves with the block: first and last images differ
    assert paths[3].read_bytes() != paths[4].read_bytes()


def test_plot_all_default_dir(tmp_path: Path) -> None:
    path = tmp_path / "r.h5"
    write_run(path, n_steps=3)
    paths = plot_all(path)
    assert all(p.parent == tmp_path / "r_plots" for p in paths)


def test_individual_plots(result_file: Path, tmp_path: Path) -> None:
    with open_result(result_file) as r:
        assert_png(plot_histories(r, tmp_path / "h.png", blocks=["cube", 0]))
        assert_png(plot_energy(r, tmp_path / "e.png"))
        assert_png(plot_snapshot(r, 5, tmp_path / "s.png"))
        with pytest.raises(IndexError):
            plot_snapshot(r, 99, tmp_path / "bad.png")
    assert_png(plot_energy(result_file, tmp_path / "e2.png"))


def test_displacement_and_fos_plots(result_file: Path, tmp_path: Path) -> None:
    with open_result(result_file) as r:
        assert_png(plot_displacements(r, tmp_path / "d.png", blocks=["cube", "base"]))
    runs = [{"factor": 1.0, "failed": False}, {"factor": 2.0, "failed": True},
            {"factor": 1.5, "failed": False}]
    assert_png(plot_fos_trials(runs, tmp_path / "fos.png", 1.5))
    assert_png(plot_fos_trials([], tmp_path / "none.png", None), min_bytes=2_000)


def test_trend_and_plunge_of_displacements() -> None:
    trend, plunge = trend_plunge(np.array([[1.0, 0, 0], [0, -1, -1], [0, 0, 0], [0, 0, 2]]))
    np.testing.assert_allclose(trend[:2], [90.0, 180.0])
    np.testing.assert_allclose(plunge[[0, 1, 3]], [0.0, 45.0, -90.0])
    assert np.isnan(trend[2]) and np.isnan(plunge[2])


def test_energy_residual_matches_balance() -> None:
    t = np.linspace(0.0, 2.0, 9)
    e = {"kinetic": 0.5 * t + 3.0, "contact": 0.1 * t, "gravity_work": t,
         "friction_dissipation": 0.25 * t, "elastic": np.full_like(t, np.nan)}
    np.testing.assert_allclose(energy_residual(e), (0.6 - 0.75) * t)


def test_plots_of_run_without_steps_and_of_running_file(tmp_path: Path) -> None:
    model = two_block_model()
    w = ResultWriter(tmp_path / "empty.h5")
    w.begin(model)
    w.end("cancelled", "before the first step")
    paths = plot_all(tmp_path / "empty.h5", tmp_path / "e")
    assert [p.name for p in paths] == ["snapshot_initial.png"]
    assert_png(paths[0])

    w = ResultWriter(tmp_path / "live.h5")
    w.begin(model)
    for k in range(3):
        w.record(make_frame(model, k, 0.1 * k, 2))
    for p in plot_all(tmp_path / "live.h5", tmp_path / "l"):
        assert_png(p)
    w.end("completed")


def test_summary(result_file: Path) -> None:
    s = summarize(result_file)
    assert s["status"] == "completed" and s["n_steps"] == 12
    assert s["max_displacement"]["block"] == "cube"
    assert s["final_contacts"] == 11 % 4
    text = format_summary(result_file)
    assert "recorded steps: 12" in text and "cube" in text


def test_no_pyplot_state(result_file: Path, tmp_path: Path) -> None:
    code = ("import sys; from engine.results.plots import plot_all; "
            f"plot_all({str(result_file)!r}, {str(tmp_path)!r}); "
            "assert 'matplotlib.pyplot' not in sys.modules")
    subprocess.run([sys.executable, "-W", "error", "-c", code], check=True,
                   cwd=Path(__file__).parent.parent)


def test_nearly_constant_curves_get_readable_axes() -> None:
    """A bolt's constant 40 kN with 1e-11 kN of round-off drew as '1e-11+4.000001478e1' and a
    residual of 1e-20 J on an axis scaled at 1e-20: now no offset, and limits at least
    ± max(floor, 0.1 % of the level) about the curve (40 ± 0.04 kN; ± the floor at 0)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from engine.results.plots import FORCE_FLOOR_KN, LENGTH_FLOOR, _readable_y

    fig = Figure()
    force, noise, moving = fig.subplots(3)
    t = np.linspace(0.0, 1.0, 50)
    force.plot(t, 40.000001478 + 1e-11 * np.sin(7 * t))
    noise.plot(t, 1e-20 * np.sin(7 * t))
    moving.plot(t, 3e-6 * t)  # a real 3 µm displacement: its own limits stay
    _readable_y(force, FORCE_FLOOR_KN)
    _readable_y(noise, FORCE_FLOOR_KN)
    _readable_y(moving, LENGTH_FLOOR)
    FigureCanvasAgg(fig).draw()
    for ax in (force, noise):
        assert ax.yaxis.get_major_formatter().get_offset() == ""
    assert moving.yaxis.get_major_formatter().get_offset() == "1e−6"  # a scale, no offset
    level = 40.000001478  # ± 0.1 % of it
    assert force.get_ylim() == pytest.approx((0.999 * level, 1.001 * level), rel=1e-12)
    assert noise.get_ylim() == pytest.approx((-1e-3, 1e-3), abs=1e-12)
    lo, hi = moving.get_ylim()
    assert hi - lo < 1e-5  # autoscaled to the data, not widened


def test_plots_raise_no_warning(result_file: Path, tmp_path: Path) -> None:
    """`polydda plot` makes every figure without a RuntimeWarning (pytest turns warnings into
    errors: filterwarnings = error)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(plot_all(result_file, tmp_path / "w")) == 5
