"""Benchmark: HDF5 result writing for 1,000 blocks x 1,000 recorded steps, ~6 contacts/block.

Run as `python benchmarks/bench_results.py [--quick] [--blocks N] [--steps K] [--variants]`
(quick: 100 steps). Prints file size, write time, cost per step and bytes per step; with
`--variants` also without compression and without contacts, for comparison.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from engine.contacts import ContactSet
from engine.frame import Frame
from engine.geometry import Polyhedron
from engine.model import Block, Model
from engine.results import ResultWriter, open_result

CUBE_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
UNIT = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                 [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)


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


def main() -> None:
    """Parse arguments, run the benchmark (and variants), print a table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="100 steps instead of 1,000")
    ap.add_argument("--blocks", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--variants", action="store_true",
                    help="also without compression, without contacts, flush every 10")
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: tmp)")
    args = ap.parse_args()
    steps = args.steps or (100 if args.quick else 1000)
    configs: list[tuple[str, dict[str, object]]] = [("gzip-4 + contacts (default)", {})]
    if args.variants:
        configs += [("no compression", {"compression": None}),
                    ("gzip-1", {"compression_level": 1}),
                    ("gzip-4, no contacts", {"record_contacts": False}),
                    ("gzip-4, flush every 10", {"flush_every": 10})]
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        print(f"{args.blocks} blocks x {steps} recorded steps, "
              f"{6 * args.blocks} contacts per step")
        print(f"{'variant':30s} {'size MB':>9s} {'write s':>8s} {'ms/step':>8s} "
              f"{'worst ms':>9s} {'kB/step':>8s} {'read s':>7s}")
        for label, kw in configs:
            r = run(args.blocks, steps, Path(tmp), **kw)
            total = r["begin_s"] + r["record_s"] + r["end_s"]
            print(f"{label:30s} {r['size_mb']:9.1f} {total:8.2f} {r['per_step_ms']:8.2f} "
                  f"{r['worst_ms']:9.2f} {r['bytes_per_step'] / 1e3:8.1f} {r['read_s']:7.2f}")


if __name__ == "__main__":
    main()
