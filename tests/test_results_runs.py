"""Result files of real engine runs: vertices and energies through the file, a replaced file,
and a `polydda run` killed with SIGKILL."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from engine.dynamics.motion import current_vertices
from engine.results.plots import energy_residual
from engine.results.reader import open_result, recover_result
from engine.results.writer import ResultWriter
from engine.step.frame import energy_created
from engine.step.simulation import STATUS_COMPLETED, Simulation, run
from schemas.convert import build_model
from tests.test_results import write_run

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def _model(name: str, **controls: object):
    built = build_model(EXAMPLES / f"{name}.json")
    if controls:
        built.model.controls = dataclasses.replace(built.model.controls, **controls)
    return built.model


def _surface_vertices(model, stacked: np.ndarray) -> list[np.ndarray]:
    """Split `engine.dynamics.motion.current_vertices` per block, surface vertices only."""
    counts = [len(b.polyhedron.vertices) for b in model.blocks]
    parts = np.split(stacked, np.cumsum(counts)[:-1])
    return [p[b.polyhedron.surface_vertex_ids] for p, b in zip(parts, model.blocks, strict=True)]


@pytest.mark.parametrize(("scene", "block_model", "n_steps"), [
    ("incline", "rigid", 40),
    ("toppling", "elastic", 150),
    ("toppling", "rigid", 150),
])
def test_vertices_from_transforms_equal_engine_vertices(
        tmp_path: Path, scene: str, block_model: str, n_steps: int) -> None:
    """At every recorded step, `centroid + affine (X0 - c0)` read back from the file is the
    engine's own `engine.dynamics.motion.current_vertices` captured during the run (to 1e-9 m)."""
    model = _model(scene, block_model=block_model)
    sim = Simulation(model)
    path = tmp_path / "run.h5"
    w = ResultWriter(path)
    w.begin(model)
    w.record(sim.frame())
    engine = [current_vertices(sim.system, sim.state)]
    for _ in range(n_steps):
        res = sim.step()
        w.record(sim.frame(res))
        engine.append(current_vertices(sim.system, sim.state))
    w.end("completed")
    with open_result(path) as r:
        assert r.n_steps == n_steps + 1
        moved = 0.0
        for k, stacked in enumerate(engine):
            want = _surface_vertices(model, stacked)
            got = r.vertices(k)
            assert len(got) == len(want)
            for g, x in zip(got, want, strict=True):
                assert np.abs(g - x).max() < 1e-9, (k, np.abs(g - x).max())
            moved = max(moved, max(np.abs(g - x0).max()
                                   for g, x0 in zip(got, r.initial_vertices(), strict=True)))
        assert moved > 1e-4  # the blocks did move
        aff = r.block_history(0)["affine"]
        strain = np.abs(np.einsum("kji,kjl->kil", aff, aff) - np.eye(3)).max()
        rotation = np.abs(r.block_history(0)["rotation"]).max()
        if block_model == "elastic":
            assert strain > 1e-12  # affine = rotation x stretch, not a rotation
        else:
            assert strain < 1e-12
        if scene == "toppling":
            assert rotation > 1e-3  # the columns tip: rotations are exercised


@pytest.mark.slow
@pytest.mark.ci
@pytest.mark.parametrize(("scene", "settled"), [("free_fall", 1.2), ("incline", 0.05)])
def test_energy_balance_read_from_result_file(tmp_path: Path, scene: str,
                                              settled: float) -> None:
    """Work of gravity = kinetic + contact + dissipated (friction + numerical) + elastic
    within 1 %, with the energies read back from the file, and the residual the energy plot
    shows is that difference."""
    path = tmp_path / f"{scene}.h5"
    res = run(_model(scene), recorder=ResultWriter(path))
    assert res.status == STATUS_COMPLETED, res.message
    with open_result(path) as r:
        assert r.status == "completed" and r.n_steps > 10
        e = {k: np.nan_to_num(v) for k, v in r.energies().items()}
        t = r.times
        work = e["gravity_work"] + e["external_work"]
        accounted = work + energy_created(e)
        late = t >= settled
        assert late.sum() >= 5
        assert np.all(work[late] > 0)
        assert np.abs(accounted - work)[late].max() <= 0.01 * work[late].min()
        residual = energy_residual(r.energies())
        np.testing.assert_allclose(residual, accounted - work, rtol=0,
                                   atol=1e-9 * np.abs(work).max())
        if scene == "free_fall":  # settled: the work of gravity went into the contact
            assert e["kinetic"][-1] < 1e-6 * work[-1]
            lost = e["numerical_dissipation"][-1] + e["damping_dissipation"][-1]
            assert lost > 0.99 * work[-1]
        else:  # sliding: the friction took most of it
            assert e["friction_dissipation"][-1] > 0.5 * work[-1]


def test_replacing_a_finished_file_leaves_its_readers_a_valid_file(tmp_path: Path) -> None:
    """`overwrite` puts a new file at the path (a rename): a reader that holds the old file
    keeps reading it whole; the old file is not truncated or rewritten in place."""
    path = tmp_path / "run.h5"
    write_run(path, n_steps=12)
    old_inode = os.stat(path).st_ino
    with open_result(path) as old:
        before = old.vertices(11)
        model = _model("incline", duration=0.01)
        res = run(model, recorder=ResultWriter(path, overwrite=True))
        assert res.status == STATUS_COMPLETED
        assert os.stat(path).st_ino != old_inode
        old.refresh()
        assert (old.status, old.n_steps, old.block_names) == ("completed", 12, ["base", "cube"])
        for a, b in zip(old.vertices(11), before, strict=True):
            np.testing.assert_array_equal(a, b)
        assert len(old.contacts(11)["gap"]) == 11 % 4
    with open_result(path) as new:
        assert new.status == "completed" and new.block_names == ["cube", "slab"]
        assert new.n_steps == 2  # step 0 and the last (10 steps, record interval 10)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]  # no temporary left
    with pytest.raises(FileExistsError):
        ResultWriter(path).begin(model)


def _polydda(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from service.cli.main import main; "
            "sys.exit(main(sys.argv[1:]))", *args]


@pytest.mark.slow
@pytest.mark.ci
def test_sigkill_of_a_real_run_keeps_every_flushed_step(tmp_path: Path) -> None:
    """`polydda run --out` over an earlier finished file, SIGKILLed once the file holds a
    few flushed batches: the reader opens the file with every step it had seen (status
    still running), the data are consistent, and the earlier file's reader is unharmed."""
    scene = json.loads((EXAMPLES / "wedge.json").read_text())
    scene["joint_materials"]["joint"]["friction_angle"] = 0  # the wedge slides
    scene["analysis"].update(duration=60.0, record_interval=2)
    scene_path = tmp_path / "wedge.json"
    scene_path.write_text(json.dumps(scene))
    out = tmp_path / "wedge.h5"
    write_run(out, n_steps=5)  # an earlier result at the same path
    old = open_result(out)
    old_inode = os.stat(out).st_ino  # not reused while `old` holds the file
    proc = subprocess.Popen(_polydda("run", str(scene_path), "--out", str(out), "--quiet"),
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    seen, deadline = 0, time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            if os.stat(out).st_ino != old_inode:  # the run's file is in place
                with open_result(out) as r:
                    assert r.status == "running" and r.block_names == ["B1", "B2"]
                    seen = max(seen, r.n_steps)
                    if seen > 1:  # past the first step: at least one time-batched flush
                        break
            time.sleep(0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    assert seen > 1, "the run did not flush a batch of steps in time"

    assert (old.status, old.n_steps, old.block_names) == ("completed", 5, ["base", "cube"])
    old.close()
    assert not list(tmp_path.glob(".*.tmp"))  # the new file was in place before step 0
    with open_result(out) as r:
        assert r.status == "running" and r.summary is None
        n = r.n_steps
        assert n >= seen
        steps = r.steps
        np.testing.assert_array_equal(steps, 2 * np.arange(n))  # every 2nd step, none lost
        assert np.all(np.diff(r.times) > 0)
        for name, v in r.energies().items():
            assert len(v) == n and np.all(np.isfinite(v)), name
        xs = r.vertices(n - 1)
        assert all(np.all(np.isfinite(x)) for x in xs)
        assert np.linalg.norm(xs[1] - r.initial_vertices()[1], axis=1).min() > 0  # it slid
        assert len(r.contacts(n - 1)["gap"]) > 0
        nv = len(r.all_vertices(0))
    with h5py.File(out, "r", swmr=True) as f:
        assert f["VTKHDF/Steps"].attrs["NSteps"] >= n
        assert f["VTKHDF/Points"].shape[0] >= n * nv
        assert f["contacts/step_offsets"].shape[0] >= n + 1
    copy = recover_result(out, tmp_path / "copy.h5")
    with h5py.File(copy, "r") as f:  # closed copy: a plain open works
        assert f["VTKHDF/Steps"].attrs["NSteps"] == n
