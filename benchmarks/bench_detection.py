"""Contact detection time for ~100, 1,000 and 5,000 jittered boxes in contact, and per
call for a 1 m cube on a slab (2 blocks, the fixed cost of a call).

Run: `python benchmarks/bench_detection.py [--quick]`. Prints the time per full
detection (best of several), the number of constraints and the fitted scaling exponent
(time ~ n^p). The first call of a process compiles or loads the numba kernels; it is
not timed.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from engine.contact.detection import detect_contacts
from engine.geometry.polyhedron import Polyhedron

BOX_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def jittered_grid(n_side: tuple[int, int, int], seed: int = 0) -> list[Polyhedron]:
    """Boxes on a grid of pitch 1 m, size 1 m minus up to 0.5 mm, shifted by up to
    0.5 mm and rotated by up to 1 mrad: every neighbour pair within a few mm."""
    rng = np.random.default_rng(seed)
    unit = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
                     (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)], float) - 0.5
    blocks = []
    for ix in range(n_side[0]):
        for iy in range(n_side[1]):
            for iz in range(n_side[2]):
                size = 1.0 - rng.uniform(0, 5e-4, 3)
                a = rng.uniform(-1e-3, 1e-3, 3)
                rot = np.array([[1, -a[2], a[1]], [a[2], 1, -a[0]], [-a[1], a[0], 1]])
                v = (unit * size) @ rot.T + [ix, iy, iz] + rng.uniform(-5e-4, 5e-4, 3)
                blocks.append(Polyhedron.from_faces(v, BOX_FACES))
    return blocks


def time_detection(blocks: list[Polyhedron], search: float, repeats: int) -> tuple[float, int]:
    """Best wall time (s) of `repeats` detections (the first call warms the caches)."""
    c = detect_contacts(blocks, search)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        c = detect_contacts(blocks, search)
        best = min(best, time.perf_counter() - t0)
    return best, len(c)


def cube_on_slab() -> list[Polyhedron]:
    """A 1 m cube resting on a 4 x 4 x 1 m slab (four vertex-face contacts)."""
    unit = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
                     (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)], float)
    slab = Polyhedron.from_faces(unit * [4.0, 4.0, 1.0] - [1.5, 1.5, 1.0], BOX_FACES)
    return [slab, Polyhedron.from_faces(unit, BOX_FACES)]


def time_per_call(blocks: list[Polyhedron], search: float, calls: int, repeats: int = 5
                  ) -> tuple[float, int]:
    """Best mean wall time (s) per call over `repeats` batches of `calls` detections."""
    active = np.arange(len(blocks)) > 0
    c = detect_contacts(blocks, search, active=active)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            c = detect_contacts(blocks, search, active=active)
        best = min(best, (time.perf_counter() - t0) / calls)
    return best, len(c)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="100 and 1,000 blocks only")
    args = parser.parse_args()
    sizes = [(5, 5, 4), (10, 10, 10)] if args.quick else [(5, 5, 4), (10, 10, 10), (20, 16, 16)]
    ns, ts = [], []
    for side in sizes:
        blocks = jittered_grid(side)
        t, nc = time_detection(blocks, search=0.005, repeats=2 if args.quick else 5)
        ns.append(len(blocks))
        ts.append(t)
        print(f"{len(blocks):6d} blocks  {nc:7d} constraints  {t * 1e3:8.1f} ms")
    p = np.polyfit(np.log(ns), np.log(ts), 1)[0]
    print(f"scaling exponent p (time ~ n^p): {p:.2f}")
    t, nc = time_per_call(cube_on_slab(), search=0.002, calls=200 if args.quick else 1000)
    print(f"     2 blocks  {nc:7d} constraints  {t * 1e3:8.3f} ms per call (cube on slab)")


if __name__ == "__main__":
    main()
