"""Issue 41: a staged run's wall time is the whole run's; a snapshot's tick labels and block
names stand apart; `polydda warm-up` compiles the kernels in groups, each in a process that
runs the other groups' kernels as Python, and leaves a cache the run needs nothing more of."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from benchmarks.bench_startup import cubes
from service.cli.main import main
from tests.excavation_scenes import roof_wedge_scene

ROOT = Path(__file__).resolve().parent.parent


def test_a_staged_runs_wall_time_is_the_whole_runs() -> None:
    """A long first stage (150 steps) and a short last one (10 steps): the summary's wall
    time is the whole run's (it was the last stage's, a sixteenth of it)."""
    from engine.step.staged_run import run_stages
    from schemas.convert import build_model

    built = build_model(roof_wedge_scene(settle=0.3, fall=0.02))
    t0 = time.perf_counter()
    res = run_stages(built.model, built.stages)
    whole = time.perf_counter() - t0
    assert res.status == "completed"
    assert 0.9 * whole <= res.summary["wall_time"] <= whole
    assert res.wall_time == res.summary["wall_time"]


# --------------------------------------------------------------------------- snapshots


def _snapshot_figure(tmp_path: Path, scene: dict[str, Any],
                     monkeypatch: pytest.MonkeyPatch) -> Any:
    """The figure of the last snapshot of a run of `scene`."""
    from engine.results import plots
    from engine.results.reader import open_result

    tmp_path.mkdir()
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    assert main(["run", str(path), "--out", str(tmp_path / "r.h5"), "--quiet"]) == 0
    saved = []
    monkeypatch.setattr(plots, "_save", lambda fig, p, dpi=120: saved.append(fig) or Path(p))
    with open_result(tmp_path / "r.h5") as r:
        plots.plot_snapshot(r, -1, tmp_path / "s.png")
    return saved[0]


def _overlaps(fig: Any) -> tuple[list[str], int]:
    """The texts of the snapshot that cover one another, and how many names are shown."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    bad = []
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        lo, hi = sorted(axis.get_view_interval())
        labels = [t.label1 for t in axis.get_major_ticks()
                  if lo <= t.get_loc() <= hi and t.label1.get_visible() and t.label1.get_text()]
        boxes = [t.get_window_extent(renderer) for t in labels]
        bad += [f"{a.get_text()}/{b.get_text()}" for i, a in enumerate(labels)
                for j, b in enumerate(labels) if i < j and boxes[i].overlaps(boxes[j])]
    names = [t for t in ax.texts if t.get_visible()]
    boxes = [t.get_window_extent(renderer) for t in names]
    bad += [f"{a.get_text()}/{b.get_text()}" for i, a in enumerate(names)
            for j, b in enumerate(names) if i < j and boxes[i].overlaps(boxes[j])]
    return bad, len(names)


@pytest.mark.parametrize("case", ["flat", "tunnel"])
def test_snapshot_labels_do_not_overlap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                        case: str) -> None:
    """A flat scene (30 unit cubes 0.5 m apart on a 6 x 5 grid: a short z axis crowded its
    tick labels) and the staged tunnel after its excavation (26 free blocks: names over
    names): no text covers another, and most names stay; without the thinning both have
    texts over texts (the test can fail)."""
    from engine.results import plots

    if case == "flat":
        scene = cubes(30, gap=0.5) | {"analysis": {"duration": 0.002, "time_step": 0.001}}
    else:
        scene = json.loads((ROOT / "examples" / "tunnel_staged.json").read_text())
        for stage in scene["stages"]:
            stage["duration"] = 0.004
    bad, shown = _overlaps(_snapshot_figure(tmp_path / "a", scene, monkeypatch))
    assert not bad, bad
    monkeypatch.setattr(plots, "declutter", lambda fig, ax, labels: None)
    bad_before, shown_before = _overlaps(_snapshot_figure(tmp_path / "b", scene, monkeypatch))
    assert bad_before
    assert shown >= 0.8 * shown_before and shown_before >= 19


# --------------------------------------------------------------------------- warm-up


def test_warm_up_groups_kernel_modules_that_call_each_other() -> None:
    from service.cli.warmup import groups, kernel_modules

    modules = kernel_modules()
    assert "engine.contact._detection_kernels" in modules and len(modules) >= 5
    found = groups()
    assert sorted(m for g in found for m in g) == modules
    # the open-close kernels call the transform kernels: one group
    together = next(g for g in found if "engine.contact.solvers._open_close_kernels" in g)
    assert "engine.geometry._transform_kernels" in together


def test_a_warm_up_worker_runs_the_other_groups_as_python() -> None:
    """A worker that compiles the detection kernels runs every other kernel module as
    Python (its py_func); one that compiles the rest runs the detection as Python (its
    fused multiply-add by a stand-in); both complete the warm-up scene."""
    from service.cli.warmup import kernel_modules

    detection = "engine.contact._detection_kernels"
    for compiled in ([detection], [m for m in kernel_modules() if m != detection]):
        proc = subprocess.run([sys.executable, "-m", "service.cli.warmup", "--worker",
                               ",".join(compiled)], cwd=ROOT, capture_output=True, text=True,
                              timeout=900, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert proc.returncode == 0, proc.stderr
        report = json.loads(proc.stdout)
        assert sorted(report["python"] + report["compiled"]) == kernel_modules()


@pytest.mark.slow
def test_warm_up_fills_an_empty_cache(tmp_path: Path) -> None:
    """From an empty cache: `polydda warm-up` compiles in parallel processes, and the wedge
    then runs without compiling anything (numba's compile events counted)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "service.cli.main", "warm-up", "--json"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=3000)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert not report["already_cached"] and len(report["workers"]) >= 2
    assert all("failed" not in w for w in report["workers"])
    count = ("import sys; from numba.core import event as ev; n = []\n"
             "class L(ev.Listener):\n"
             "    def on_start(self, e): n.append(1)\n"
             "    def on_end(self, e): pass\n"
             "ev.register('numba:compile', L())\n"
             "from service.cli.main import main\n"
             f"rc = main(['run', 'examples/wedge.json', '--out', r'{tmp_path / 'w.h5'}', "
             "'--quiet']); print(len(n)); sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", count], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "0"  # compilations after the warm-up
