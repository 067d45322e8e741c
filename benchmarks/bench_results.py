"""Benchmark: the cost of writing the HDF5 result file, on made-up frames and on real runs.

Run as `python -m benchmarks.bench_results [--only synthetic pile small] [--quick]
[--repeat R] [--pile-steps N] [--blocks N] [--steps K] [--variants]`:

- `synthetic`: 1,000 blocks x 1,000 recorded steps, ~6 contacts per block, made-up frames
  written back to back (quick: 100 steps): file size, write time, cost per step. With
  `--variants` also without compression, gzip-1, without contacts, flush every 10.
- `pile`: the shared 1,000-block pile (`benchmarks.pile.pile_model`), `--pile-steps` steps
  (default 100) recording every step, then 3x as many steps recording every 10th: the
  run's time per step without a recorder and with the writer, the engine's `output` phase
  per record (frame + writer) against a step, and the writer's share of the run's wall
  time (with the end of the file) and CPU time.
- `small`: the wedge example at its default record interval (10): the share of `output`
  in the run's wall time, per record.

Each measurement is repeated (`--repeat`, default 3) and the minimum kept: the machine may
be shared. The writer compresses large steps on a second thread while the run goes on, so
the pile also reports the process CPU time the writing adds.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from engine.contact.constraints import ContactSet
from engine.geometry.polyhedron import Polyhedron
from engine.model import Block, Model
from engine.results.reader import open_result
from engine.results.writer import ResultWriter
from engine.step.frame import Frame
from engine.step.simulation import run as run_model

CUBE_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
UNIT = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                 [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def grid_model(n_blocks: int) -> Model:
    """`n_blocks` unit cubes on a cubic grid with 1 m spacing (a stacked block pile)."""
    side = int(np.ceil(n_blocks ** (1 / 3)))
    idx = np.array(np.unravel_index(np.arange(n_blocks), (side, side, side))).T
    return Model(blocks=[Block(Polyhedron.from_faces(UNIT + p, CUBE_FACES), name=f"b{k}")
                         for k, p in enumerate(idx.astype(float))])


class FrameSource:
    """Synthetic, smoothly varying frames: blocks settle and rock, ~6 contacts per block."""

    def __init__(self, model: Model, contacts_per_block: int = 6, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        n = len(model.blocks)
        self.n = n
        self.c0 = np.array([b.polyhedron.centroid for b in model.blocks])
        self.drift = rng.normal(scale=0.05, size=(n, 3))
        self.spin = rng.normal(scale=0.1, size=(n, 3))
        c = contacts_per_block * n
        self.block_i = np.repeat(np.arange(n), contacts_per_block)
        self.block_j = (self.block_i + rng.integers(1, 30, size=c)) % n
        self.offset = rng.uniform(-0.5, 0.5, size=(c, 3))
        axes = np.eye(3)[rng.integers(0, 3, size=c)]
        self.normal = axes
        self.tangent = np.roll(axes, 1, axis=1)
        self.kind = rng.integers(0, 4, size=c).astype(np.int8)
        self.mode = rng.integers(0, 3, size=c).astype(np.int8)
        self.force = rng.uniform(1e3, 1e5, size=c)

    def frame(self, k: int, t: float) -> Frame:
        """Frame at recorded step k, time t."""
        n = self.n
        rotvec = self.spin * np.sin(t)
        aff = Rotation.from_rotvec(rotvec).as_matrix()
        cent = self.c0 + self.drift * t
        vel = np.zeros((n, 12))
        vel[:, :3] = self.drift
        vel[:, 3:6] = self.spin * np.cos(t)
        p = cent[self.block_i] + self.offset
        c = len(self.block_i)
        gap = -1e-4 * (1 + np.sin(t + self.force * 1e-3))
        cs = ContactSet(
            block_i=self.block_i, block_j=self.block_j, kind=self.kind, point_i=p,
            point_j=p - gap[:, None] * self.normal, normal=self.normal, tangent=self.tangent,
            mode=self.mode, gap=gap, key=np.zeros((c, 4), np.int64),
            face_tag=np.zeros(c, np.int64), joint_material=np.zeros(c, np.int64),
            cand_indptr=np.zeros(c + 1, np.int64),
        )
        return Frame(
            step=10 * k, time=t, dt=1e-3, open_close_iterations=2, max_penetration=2e-4,
            centroids=cent, affine=aff, rotation=rotvec, velocity=vel,
            stress=np.zeros((n, 6)),
            energies={"kinetic": 1.0 + t, "elastic": 0.0, "contact": 0.1 * t,
                      "gravity_work": 2.0 * t, "friction_dissipation": 0.5 * t,
                      "external_work": 0.0},
            contacts=cs, normal_force=self.force * (1 + 0.1 * np.sin(t)),
            shear_force=0.3 * self.force[:, None] * self.tangent,
        )


def run(n_blocks: int, n_steps: int, out_dir: Path, **writer_kw: object) -> dict[str, float]:
    """Write one synthetic run; returns sizes and timings."""
    model = grid_model(n_blocks)
    src = FrameSource(model)
    frames = [src.frame(k, 0.01 * k) for k in range(min(n_steps, 20))]  # reuse: cheap input
    path = out_dir / f"bench_{n_blocks}x{n_steps}_{len(list(out_dir.iterdir()))}.h5"
    t0 = time.perf_counter()
    w = ResultWriter(path, **writer_kw)  # type: ignore[arg-type]
    w.begin(model, "{}")
    t_begin = time.perf_counter() - t0
    t_record = 0.0
    worst = 0.0
    for k in range(n_steps):
        fr = frames[k % len(frames)]
        fr.step, fr.time = 10 * k, 0.01 * k
        a = time.perf_counter()
        w.record(fr)
        dt = time.perf_counter() - a
        t_record += dt
        worst = max(worst, dt)
    a = time.perf_counter()
    w.end("completed", "", {"bench": True})
    t_end = time.perf_counter() - a
    size = path.stat().st_size
    a = time.perf_counter()
    with open_result(path) as r:
        assert r.n_steps == n_steps and r.status == "completed"
        r.vertices(n_steps - 1)
        if r.contacts_recorded:
            r.contacts(n_steps - 1)
        r.block_history(0)
    t_read = time.perf_counter() - a
    path.unlink()
    return {"size_mb": size / 1e6, "begin_s": t_begin, "record_s": t_record,
            "end_s": t_end, "per_step_ms": 1e3 * t_record / n_steps, "worst_ms": 1e3 * worst,
            "bytes_per_step": size / n_steps, "read_s": t_read}


# --------------------------------------------------------------------------- real runs


class TimedWriter:
    """A :class:`ResultWriter` whose calls are timed (s): begin, record, end."""

    def __init__(self, writer: ResultWriter) -> None:
        self.writer = writer
        self.seconds = {"begin": 0.0, "record": 0.0, "end": 0.0}

    def _timed(self, name: str, fn: Callable[..., None], *args: Any, **kw: Any) -> None:
        t0 = time.perf_counter()
        fn(*args, **kw)
        self.seconds[name] += time.perf_counter() - t0

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        self._timed("begin", self.writer.begin, model, scene_json)

    def record(self, frame: Frame) -> None:
        self._timed("record", self.writer.record, frame)

    def end(self, status: str, message: str = "", summary: dict[str, Any] | None = None) -> None:
        self._timed("end", self.writer.end, status, message, summary)


def measure_run(model: Model, out_dir: Path | None) -> dict[str, float]:
    """One run of `model`, with the writer into `out_dir` (None: no recorder)."""
    timed = None
    path = None
    if out_dir is not None:
        path = out_dir / f"run_{time.monotonic_ns()}.h5"
        timed = TimedWriter(ResultWriter(path))
    cpu0, wall0 = time.process_time(), time.perf_counter()
    res = run_model(model, recorder=timed)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0  # with end()
    out: dict[str, float] = {"wall_s": wall, "cpu_s": cpu, "steps": res.steps,
                             "output_s": res.summary["timings"].get("output", 0.0)}
    if timed is not None and path is not None:
        n = timed.writer.n_recorded
        out.update(records=n, size_mb=path.stat().st_size / 1e6,
                   writer_s=sum(timed.seconds.values()), **{
                       f"{k}_s": v for k, v in timed.seconds.items()})
        path.unlink()
    return out


def best(rows: list[dict[str, float]]) -> dict[str, float]:
    """Minimum of every timing over repeats (the other numbers from the first)."""
    out = dict(rows[0])
    for key in out:
        if key.endswith("_s"):
            out[key] = min(r[key] for r in rows)
    return out


def bench_pile(steps: int, interval: int, repeat: int, out_dir: Path) -> None:
    """The 1,000-block pile recording every `interval` steps: write time per record against
    a step, and what the writer adds to the run (wall time with its end, CPU time)."""
    from benchmarks.pile import pile_model

    def model() -> Model:
        return pile_model(1000, duration=steps * 1e-3, record_interval=interval)

    measure_run(pile_model(1000, duration=2e-3, record_interval=1), out_dir)  # warm-up
    bare = best([measure_run(model(), None) for _ in range(repeat)])
    rec = best([measure_run(model(), out_dir) for _ in range(repeat)])
    n, k = rec["steps"], rec["records"]
    step_s = bare["wall_s"] / bare["steps"]
    print(f"\npile_1000, {n:.0f} steps, record_interval {interval} ({k:.0f} records), "
          f"{rec['size_mb']:.1f} MB ({1e3 * rec['size_mb'] / k:.0f} kB/record); "
          f"minima of {repeat}")
    print(f"  run without a recorder: {1e3 * step_s:.1f} ms/step wall, "
          f"{1e3 * bare['cpu_s'] / bare['steps']:.1f} ms/step CPU")
    print(f"  run with the writer:    {1e3 * rec['wall_s'] / n:.1f} ms/step wall, "
          f"{1e3 * rec['cpu_s'] / n:.1f} ms/step CPU (end of the file included)")
    print(f"  output phase (frame + record) {1e3 * rec['output_s'] / k:.2f} ms/record = "
          f"{rec['output_s'] / k / step_s:.2f} x a step = "
          f"{100 * rec['output_s'] / rec['wall_s']:.1f} % of the run's wall time")
    print(f"  writer calls: begin {1e3 * rec['begin_s']:.0f} ms, record "
          f"{1e3 * rec['record_s'] / k:.2f} ms/record, end {1e3 * rec['end_s']:.0f} ms "
          f"(waits for the last batches); in all "
          f"{100 * rec['writer_s'] / rec['wall_s']:.1f} % of the wall time")
    print(f"  the writer's share of the run: wall {100 * (1 - bare['wall_s'] / rec['wall_s']):.1f}"
          f" % (extra {100 * (rec['wall_s'] / bare['wall_s'] - 1):+.1f} %), CPU "
          f"{100 * (1 - bare['cpu_s'] / rec['cpu_s']):.1f} % (compression on a second thread)")


def bench_small(repeat: int, out_dir: Path) -> None:
    """The wedge example at its default record interval: share of `output` in the wall time."""
    from schemas.convert import build_model

    def model() -> Model:
        return build_model(EXAMPLES / "wedge.json").model

    m = model()
    measure_run(dataclasses.replace(m, controls=dataclasses.replace(m.controls, duration=0.05)),
                out_dir)  # warm-up
    bare = best([measure_run(model(), None) for _ in range(repeat)])
    rec = best([measure_run(model(), out_dir) for _ in range(repeat)])
    k = rec["records"]
    print(f"\nwedge example, {rec['steps']:.0f} steps, record_interval "
          f"{m.controls.record_interval} ({k:.0f} records), {1e3 * rec['size_mb']:.0f} kB; "
          f"minima of {repeat}")
    print(f"  run: {rec['wall_s']:.2f} s wall with the writer, {bare['wall_s']:.2f} s without")
    print(f"  output phase (frame + record) {1e3 * rec['output_s'] / k:.2f} ms/record = "
          f"{100 * rec['output_s'] / rec['wall_s']:.1f} % of the run's wall time; writer calls "
          f"{1e3 * rec['writer_s']:.0f} ms in all "
          f"({100 * rec['writer_s'] / rec['wall_s']:.1f} %, begin and end included)")


def bench_synthetic(blocks: int, steps: int, variants: bool, out_dir: Path) -> None:
    """Made-up frames of `blocks` blocks written back to back: size and write time."""
    configs: list[tuple[str, dict[str, object]]] = [("gzip-4 + contacts (default)", {})]
    if variants:
        configs += [("no compression", {"compression": None}),
                    ("gzip-1", {"compression_level": 1}),
                    ("gzip-4, no contacts", {"record_contacts": False}),
                    ("gzip-4, flush every 10", {"flush_every": 10})]
    print(f"\nsynthetic: {blocks} blocks x {steps} recorded steps, "
          f"{6 * blocks} contacts per step, written back to back")
    print(f"{'variant':30s} {'size MB':>9s} {'write s':>8s} {'ms/step':>8s} "
          f"{'worst ms':>9s} {'kB/step':>8s} {'read s':>7s}")
    for label, kw in configs:
        r = run(blocks, steps, out_dir, **kw)
        total = r["begin_s"] + r["record_s"] + r["end_s"]
        print(f"{label:30s} {r['size_mb']:9.1f} {total:8.2f} {1e3 * total / steps:8.2f} "
              f"{r['worst_ms']:9.2f} {r['bytes_per_step'] / 1e3:8.1f} {r['read_s']:7.2f}")


def main(argv: list[str] | None = None) -> None:
    """Parse arguments, run the chosen sections, print their numbers."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", choices=("synthetic", "pile", "small"),
                    default=["small", "pile", "synthetic"])
    ap.add_argument("--quick", action="store_true", help="synthetic: 100 steps, not 1,000")
    ap.add_argument("--repeat", type=int, default=3, help="runs per measurement (minimum)")
    ap.add_argument("--pile-steps", type=int, default=100)
    ap.add_argument("--blocks", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--variants", action="store_true",
                    help="synthetic: also without compression, gzip-1, without contacts, "
                         "flush every 10")
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: tmp)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        out = Path(tmp)
        if "small" in args.only:
            bench_small(args.repeat, out)
        if "pile" in args.only:
            for steps, interval in ((args.pile_steps, 1), (3 * args.pile_steps, 10)):
                bench_pile(steps, interval, args.repeat, out)
        if "synthetic" in args.only:
            bench_synthetic(args.blocks, args.steps or (100 if args.quick else 1000),
                            args.variants, out)


if __name__ == "__main__":
    main()
