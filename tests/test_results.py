"""HDF5 result files: round trip of exact rigid motions, contacts, VTKHDF, crash safety."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from engine.contact.constraints import ContactSet
from engine.geometry.polyhedron import Polyhedron
from engine.model import Block, Model
from engine.results.layout import point_velocities
from engine.results.reader import open_result, recover_result
from engine.results.writer import ResultWriter
from engine.step.frame import Frame

CUBE_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def box(lo: tuple[float, float, float], size: tuple[float, float, float]) -> Polyhedron:
    """Axis-aligned box as a Polyhedron (faces counter-clockwise from outside)."""
    x, y, z = lo
    a, b, c = size
    v = np.array([[x, y, z], [x + a, y, z], [x + a, y + b, z], [x, y + b, z],
                  [x, y, z + c], [x + a, y, z + c], [x + a, y + b, z + c], [x, y + b, z + c]])
    return Polyhedron.from_faces(v, CUBE_FACES, face_tags=[0, 1, 2, 3, 4, 5])


def two_block_model() -> Model:
    """A fixed base slab and a unit cube resting on it."""
    return Model(blocks=[
        Block(box((-1.0, -1.0, -1.0), (3.0, 3.0, 1.0)), name="base", fixed=True),
        Block(box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), name="cube", material=1),
    ])


def exact_motion(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cube centroid `(3,)`, rotation vector `(3,)`, velocity `(12,)` at time t (exact)."""
    c = np.array([0.5 + 2.0 * t, 0.5 - 0.3 * t, 0.5 + 0.1 * t - 0.5 * t * t])
    w = np.array([0.4, -1.1, 2.3])
    vel = np.zeros(12)
    vel[:3] = [2.0, -0.3, 0.1 - t]
    vel[3:6] = w
    return c, w * t, vel


def make_frame(model: Model, k: int, t: float, n_contacts: int) -> Frame:
    """Frame k: base at rest, cube translating and spinning; `n_contacts` synthetic contacts."""
    n = len(model.blocks)
    cents = np.array([b.polyhedron.centroid for b in model.blocks])
    rot = np.zeros((n, 3))
    aff = np.tile(np.eye(3), (n, 1, 1))
    vel = np.zeros((n, 12))
    cents[1], rot[1], vel[1] = exact_motion(t)
    aff[1] = Rotation.from_rotvec(rot[1]).as_matrix()
    rng = np.random.default_rng(k)
    c = n_contacts
    cs = ContactSet(
        block_i=np.ones(c, np.int64), block_j=np.zeros(c, np.int64),
        kind=(np.arange(c) % 4).astype(np.int8), point_i=rng.normal(size=(c, 3)),
        point_j=rng.normal(size=(c, 3)), normal=np.tile([0.0, 0.0, 1.0], (c, 1)),
        tangent=np.tile([1.0, 0.0, 0.0], (c, 1)), mode=(np.arange(c) % 3).astype(np.int8),
        gap=-1e-4 * (k + np.arange(c)), key=np.zeros((c, 4), np.int64),
        face_tag=np.zeros(c, np.int64), joint_material=np.zeros(c, np.int64),
        cand_indptr=np.zeros(c + 1, np.int64),
    )
    return Frame(
        step=10 * k, time=t, dt=0.01, open_close_iterations=k % 3 + 1,
        max_penetration=1e-5 * k, centroids=cents, affine=aff, rotation=rot, velocity=vel,
        stress=np.full((n, 6), float(k)),
        energies={"kinetic": 0.5 * t, "elastic": 0.0, "contact": 0.1 * t,
                  "gravity_work": t, "friction_dissipation": 0.25 * t, "external_work": 0.0},
        contacts=cs, normal_force=np.arange(c, dtype=float) + k,
        shear_force=np.full((c, 3), float(k)),
    )


def write_run(path: Path, n_steps: int = 12, status: str | None = "completed",
              **kw: object) -> Model:
    """Write a synthetic run of `n_steps` steps (contacts count varies per step)."""
    model = two_block_model()
    w = ResultWriter(path, **kw)  # type: ignore[arg-type]
    w.begin(model, json.dumps({"schema_version": "1.0", "blocks": []}))
    for k in range(n_steps):
        w.record(make_frame(model, k, 0.1 * k, n_contacts=k % 4))
    if status is not None:
        w.end(status, "done", {"steps": n_steps, "max_disp": np.float64(1.5)})
    return model


def exact_vertices(model: Model, t: float) -> list[np.ndarray]:
    """Exact surface vertices of each block at time t."""
    out = []
    for b, block in enumerate(model.blocks):
        poly = block.polyhedron
        x0 = poly.vertices[poly.surface_vertex_ids]
        if b == 0:
            out.append(x0)
            continue
        c, rv, _ = exact_motion(t)
        out.append(c + Rotation.from_rotvec(rv).apply(x0 - poly.centroid))
    return out


def test_round_trip_vertices_and_histories(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    model = write_run(path)
    with open_result(path) as r:
        assert r.status == "completed"
        assert r.message == "done"
        assert r.summary == {"steps": 12, "max_disp": 1.5}
        assert r.n_steps == 12
        assert r.block_names == ["base", "cube"]
        assert r.schema_version == "1.0"
        assert json.loads(r.scene_json or "") == {"schema_version": "1.0", "blocks": []}
        np.testing.assert_allclose(r.times, 0.1 * np.arange(12))
        np.testing.assert_array_equal(r.steps, 10 * np.arange(12))
        for k in range(12):
            got = r.vertices(k)
            want = exact_vertices(model, 0.1 * k)
            assert len(got) == 2
            for g, w in zip(got, want, strict=True):
                assert np.abs(g - w).max() < 1e-9
        h = r.block_history("cube")
        c, rv, _ = exact_motion(1.1)
        np.testing.assert_allclose(h["centroid"][-1], c, atol=1e-12)
        np.testing.assert_allclose(h["rotation"][-1], rv, atol=1e-12)
        np.testing.assert_allclose(h["displacement"][-1], c - model.blocks[1].polyhedron.centroid)
        assert h["velocity"].shape == (12, 12) and h["stress"].shape == (12, 6)
        np.testing.assert_array_equal(r.block_history(0)["displacement"], 0.0)
        e = r.energies()
        assert set(e) >= {"kinetic", "gravity_work", "friction_dissipation"}
        np.testing.assert_allclose(e["gravity_work"], 0.1 * np.arange(12))
        faces = r.faces("cube")
        assert len(faces) == 6 and all(len(f) == 4 for f in faces)
        with pytest.raises(KeyError):
            r.block_history("nope")
        with pytest.raises(IndexError):
            r.vertices(12)


def test_contacts_sliced_per_step(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    model = write_run(path)
    with open_result(path) as r:
        for k in range(r.n_steps):
            frame = make_frame(model, k, 0.1 * k, n_contacts=k % 4)
            cs = r.contacts(k)
            assert len(cs["block_i"]) == k % 4
            np.testing.assert_array_equal(cs["point_i"], frame.contacts.point_i)
            np.testing.assert_array_equal(cs["gap"], frame.contacts.gap)
            np.testing.assert_array_equal(cs["mode"], frame.contacts.mode)
            np.testing.assert_array_equal(cs["normal_force"], frame.normal_force)
            np.testing.assert_array_equal(cs["shear_force"], frame.shear_force)


def test_no_contacts_recorded(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    write_run(path, n_steps=3, record_contacts=False, compression=None)
    with open_result(path) as r:
        assert r.n_steps == 3 and not r.contacts_recorded
        with pytest.raises(ValueError, match="not recorded"):
            r.contacts(0)
    model = two_block_model()
    model.controls = replace(model.controls, record_contacts=False)
    w = ResultWriter(tmp_path / "b.h5")
    w.begin(model)
    w.record(make_frame(model, 0, 0.0, 3))
    w.end("completed")
    with open_result(tmp_path / "b.h5") as r:
        assert r.n_steps == 1 and not r.contacts_recorded


def test_layout_and_compression(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    write_run(path, n_steps=5)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "polydda-result"
        assert f["history/affine"].shape == (5, 2, 3, 3)
        assert "vertices" not in f["history"]
        assert f["blocks/vertices"].shape == (16, 3)
        assert f["blocks/face_offsets"].shape == (13,)
        assert f["contacts/step_offsets"].shape == (6,)
        assert len(f["scene"].attrs["sha256"]) == 64
        for ds in _datasets(f):
            assert ds.compression in (None, "gzip"), ds.name


def test_large_model_compressed_without_leaks(tmp_path: Path) -> None:
    """Big steps get gzip+shuffle chunks written once: the file holds no dead chunk copies."""
    model = Model(blocks=[Block(box((2.0 * k, 0.0, 0.0), (1.0, 1.0, 1.0)), name=f"b{k}")
                          for k in range(200)])
    n = len(model.blocks)
    path = tmp_path / "big.h5"
    w = ResultWriter(path)
    w.begin(model)
    rng = np.random.default_rng(1)
    for k in range(6):
        fr = make_frame(two_block_model(), k, 0.1 * k, n_contacts=3 * n + 17 * k)
        fr.centroids = np.array([b.polyhedron.centroid for b in model.blocks]) + 0.01 * k
        fr.affine = np.tile(np.eye(3), (n, 1, 1))
        fr.rotation = rng.normal(size=(n, 3))
        fr.velocity = rng.normal(size=(n, 12))
        fr.stress = np.zeros((n, 6))
        w.record(fr)
    w.end("completed")
    with h5py.File(path, "r") as f:
        for name in ("history/centroid", "history/velocity", "VTKHDF/Points",
                     "contacts/point_i"):
            assert f[name].compression == "gzip" and f[name].shuffle, name
        assert f["history/velocity"].chunks == (1, n, 12)
        stored = sum(ds.id.get_storage_size() for ds in _datasets(f))
    assert path.stat().st_size < 1.1 * stored + 200_000


def _datasets(group: h5py.Group) -> list[h5py.Dataset]:
    out: list[h5py.Dataset] = []
    group.visititems(lambda _, obj: out.append(obj) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_refuses_to_overwrite_and_bad_status(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    write_run(path, n_steps=1)
    with pytest.raises(FileExistsError):
        ResultWriter(path).begin(two_block_model())
    w = ResultWriter(tmp_path / "b.h5")
    w.begin(two_block_model())
    with pytest.raises(ValueError, match="status"):
        w.end("finished")
    w.end("cancelled", "user")
    with pytest.raises(RuntimeError):
        w.end("completed")
    with open_result(tmp_path / "b.h5") as r:
        assert (r.status, r.message, r.n_steps) == ("cancelled", "user", 0)
    with pytest.raises(ValueError, match="gzip"):
        ResultWriter(tmp_path / "c.h5", compression="lzf")


def test_writer_context_manager_marks_failure(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    model = two_block_model()
    with pytest.raises(ZeroDivisionError), ResultWriter(path) as w:
        w.begin(model)
        w.record(make_frame(model, 0, 0.0, 2))
        _ = 1 / 0
    with open_result(path) as r:
        assert r.status == "failed" and "ZeroDivisionError" in r.message
        assert r.n_steps == 1


def test_point_velocity_rigid_and_strain() -> None:
    x = np.array([[1.0, 2.0, 3.0]])
    c = np.zeros((1, 3))
    v = np.zeros((1, 12))
    v[0, :3] = [1, 0, 0]
    v[0, 3:6] = [0, 0, 1]
    v[0, 6:12] = [0.1, 0, 0, 0, 0, 0.2]  # εx, γxy
    got = point_velocities(x, c, v)[0]
    want = np.array([1, 0, 0]) + np.cross([0, 0, 1], x[0]) + [0.1 * 1 + 0.1 * 2, 0.1 * 1, 0]
    np.testing.assert_allclose(got, want)


def test_live_reader_sees_new_steps(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    model = two_block_model()
    w = ResultWriter(path, flush_every=1)  # every step visible when record() returns
    w.begin(model)
    w.record(make_frame(model, 0, 0.0, 1))
    with open_result(path) as r:
        assert r.status == "running" and r.n_steps == 1 and r.summary is None
        w.record(make_frame(model, 1, 0.1, 2))
        assert r.refresh() == 2
        assert len(r.contacts(1)["gap"]) == 2
        assert np.abs(r.vertices(1)[1] - exact_vertices(model, 0.1)[1]).max() < 1e-9
    w.end("completed")


def vtk_step(path: Path, step: int):  # noqa: ANN201 (vtk types: optional import)
    """`(reader, output)` of ParaView's VTKHDF reader at recorded `step` of the file
    (skips the test without the vtk wheel)."""
    vtk = pytest.importorskip("vtk")
    reader = vtk.vtkHDFReader()
    reader.SetFileName(str(path))
    reader.Update()
    reader.SetStep(step)
    reader.Update()
    return reader, reader.GetOutput()


def test_vtkhdf_opens_in_vtk(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    model = write_run(path, n_steps=7)
    reader, out = vtk_step(path, 6)
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    assert reader.GetNumberOfSteps() == 7
    assert out.GetNumberOfCells() == 12
    pts = vtk_to_numpy(out.GetPoints().GetData())
    want = np.concatenate(exact_vertices(model, 0.6))
    assert np.abs(pts - want).max() < 1e-9
    disp = vtk_to_numpy(out.GetPointData().GetArray("displacement"))
    x0 = np.concatenate(exact_vertices(model, 0.0))
    assert np.abs(disp - (want - x0)).max() < 1e-9
    bid = vtk_to_numpy(out.GetPointData().GetArray("block_id"))
    np.testing.assert_array_equal(bid, np.repeat([0, 1], 8))
    assert out.GetCellData().GetArray("face_tag") is not None
    # the time values drive ParaView's animation
    times = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    np.testing.assert_allclose(times, 0.1 * np.arange(7))
    reader.UpdateTimeStep(times[3])
    pts3 = vtk_to_numpy(reader.GetOutput().GetPoints().GetData())
    assert np.abs(pts3 - np.concatenate(exact_vertices(model, times[3]))).max() < 1e-9


KILL_SCRIPT = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {tests!r})
    from test_results import two_block_model, make_frame
    from engine.results.writer import ResultWriter
    model = two_block_model()
    w = ResultWriter({path!r}, flush_every=1)
    w.begin(model, "{{}}")
    k = 0
    while True:
        w.record(make_frame(model, k, 0.1 * k, n_contacts=k % 5))
        k += 1
        print(k, flush=True)
""")


@pytest.fixture(scope="module")
def killed_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A file whose writer was SIGKILLed after reporting at least 25 flushed steps."""
    path = tmp_path_factory.mktemp("killed") / "killed.h5"
    script = KILL_SCRIPT.format(tests=str(Path(__file__).parent), path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).parent.parent)
    flushed = 0
    deadline = time.monotonic() + 60
    assert proc.stdout is not None
    live: tuple[str, int, int] | None = None
    while flushed < 25 and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        flushed = int(line)
        if flushed == 10:  # another process reads while the writer runs
            with open_result(path) as r:
                live = (r.status, r.n_steps, r.refresh())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    assert flushed >= 25, "writer did not get going"
    assert live is not None and live[0] == "running" and live[2] >= live[1] >= 10
    return path, flushed


def test_sigkill_leaves_readable_file(killed_run: tuple[Path, int]) -> None:
    path, flushed = killed_run
    model = two_block_model()
    with open_result(path) as r:
        assert r.status == "running"
        assert r.summary is None
        assert r.n_steps >= flushed
        k = r.n_steps - 1
        assert np.abs(r.vertices(k)[1] - exact_vertices(model, 0.1 * k)[1]).max() < 1e-9
        assert len(r.contacts(k)["gap"]) == k % 5
        assert len(r.energies()["kinetic"]) == r.n_steps


def test_recover_killed_run(killed_run: tuple[Path, int], tmp_path: Path) -> None:
    path, _ = killed_run
    with open_result(path) as r:
        n = r.n_steps
        last = r.vertices(n - 1)
    out = recover_result(path, tmp_path / "copy.h5")
    with h5py.File(out, "r") as f:  # a plain (non-SWMR) open works on the copy
        assert f["VTKHDF/Steps"].attrs["NSteps"] == n
        assert f["VTKHDF/Points"].shape == (16 * n, 3)
    with open_result(out) as r:
        assert r.status == "running" and r.n_steps == n
        assert "recovered" in r.message
        for a, b in zip(r.vertices(-1), last, strict=True):
            np.testing.assert_array_equal(a, b)
        assert len(r.contacts(n - 1)["gap"]) == (n - 1) % 5
    vtk = pytest.importorskip("vtk")
    reader = vtk.vtkHDFReader()
    reader.SetFileName(str(out))
    reader.Update()
    assert reader.GetNumberOfSteps() == n
    with pytest.raises(FileExistsError):
        recover_result(path, out)


def test_flush_policy_batches_steps(tmp_path: Path) -> None:
    """Steps are written in batches: the first at once, then every `flush_every` records or
    `flush_seconds`; `flush()` and `end()` write the rest. A reader sees the flushed ones."""
    model = two_block_model()
    path = tmp_path / "count.h5"
    w = ResultWriter(path, flush_every=3, flush_seconds=None)
    w.begin(model)
    seen = []
    with open_result(path) as r:
        for k in range(8):
            w.record(make_frame(model, k, 0.1 * k, k % 4))
            seen.append((w.n_recorded, w.n_flushed, r.refresh()))
        assert seen == [(1, 1, 1), (2, 1, 1), (3, 1, 1), (4, 4, 4), (5, 4, 4), (6, 4, 4),
                        (7, 7, 7), (8, 7, 7)]
        w.flush()
        assert w.n_flushed == r.refresh() == 8
        w.record(make_frame(model, 8, 0.8, 1))
        w.end("completed")
    with open_result(path) as r:
        assert r.n_steps == 9 and r.status == "completed"
        assert len(r.contacts(8)["gap"]) == 1
        assert np.abs(r.vertices(7)[1] - exact_vertices(model, 0.7)[1]).max() < 1e-9

    w = ResultWriter(tmp_path / "time.h5", flush_seconds=0.5)
    w.begin(model)
    w.record(make_frame(model, 0, 0.0, 1))
    w.record(make_frame(model, 1, 0.1, 1))
    assert (w.n_recorded, w.n_flushed) == (2, 1)
    time.sleep(0.55)
    w.record(make_frame(model, 2, 0.2, 1))
    assert w.n_flushed == 3
    w.end("completed")
    with pytest.raises(ValueError, match="flush_seconds"):
        ResultWriter(tmp_path / "x.h5", flush_seconds=-1.0)


@pytest.mark.parametrize("background", [True, False])
def test_large_steps_compressed_by_the_writer_read_back_exactly(tmp_path: Path,
                                                                background: bool) -> None:
    """Whole-step chunks compressed by the writer (shuffle + deflate, in its thread or not)
    and written as chunks read back bit for bit through HDF5's filters, by h5py and VTK."""
    n = 200  # a centroid step of 4.8 kB: compressed
    model = Model(blocks=[Block(box((2.0 * k, 0.0, 0.0), (1.0, 1.0, 1.0)), name=f"b{k}")
                          for k in range(n)])
    c0 = np.array([b.polyhedron.centroid for b in model.blocks])
    rng = np.random.default_rng(3)
    frames = []
    for k in range(7):
        fr = make_frame(two_block_model(), k, 0.1 * k, n_contacts=2 * n + k)
        fr.centroids = c0 + rng.normal(scale=0.01, size=(n, 3))
        fr.rotation = rng.normal(scale=0.1, size=(n, 3))
        fr.affine = Rotation.from_rotvec(fr.rotation).as_matrix()
        fr.velocity = rng.normal(size=(n, 12))
        fr.stress = rng.normal(size=(n, 6))
        frames.append(fr)
    path = tmp_path / "big.h5"
    w = ResultWriter(path, flush_every=3, flush_seconds=None, background=background)
    w.begin(model)
    for fr in frames:
        w.record(fr)
    assert {"history/centroid", "VTKHDF/Points"} <= set(w._batcher._direct)  # as chunks
    assert (w._batcher._pool is not None) == background
    w.end("completed")
    with h5py.File(path, "r") as f:
        for name in ("history/centroid", "history/affine", "VTKHDF/Points"):
            assert f[name].compression == "gzip" and f[name].shuffle, name
        np.testing.assert_array_equal(f["history/velocity"][()],
                                      np.stack([fr.velocity for fr in frames]))
        np.testing.assert_array_equal(f["history/stress"][()],
                                      np.stack([fr.stress for fr in frames]))
    with open_result(path) as r:
        assert r.n_steps == 7
        for k, fr in enumerate(frames):
            np.testing.assert_array_equal(r.centroids(k), fr.centroids)
            np.testing.assert_array_equal(r.contacts(k)["gap"], fr.contacts.gap)
        last = np.concatenate(r.vertices(6))
    reader, out = vtk_step(path, 6)
    from vtk.util.numpy_support import vtk_to_numpy

    assert reader.GetNumberOfSteps() == 7
    pts = vtk_to_numpy(out.GetPoints().GetData())
    assert np.abs(pts - last).max() < 1e-12


def test_surface_history_and_scene_hash(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    write_run(path, n_steps=12)
    with open_result(path) as r:
        mesh = r.surface()
        assert mesh["vertices"].shape == (16, 3) and mesh["vertex_offsets"].tolist() == [0, 8, 16]
        assert mesh["face_block_offsets"].tolist() == [0, 6, 12]
        np.testing.assert_array_equal(r.history("centroid", slice(2, 9, 3)),
                                      [r.centroids(k) for k in (2, 5, 8)])
        assert r.history("affine").shape == (12, 2, 3, 3)
        assert r.history("velocity", slice(20, 30)).shape == (0, 2, 12)
        with pytest.raises(KeyError):
            r.history("nope")
        text = json.dumps({"schema_version": "1.0", "blocks": []})
        assert r.scene_sha256 == hashlib.sha256(text.encode()).hexdigest()
