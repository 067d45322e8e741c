"""Cutting a terrain: from its convex columns (what the scene's `terrain` does) against the
standard path for a concave domain (its bounding box cut by every facet's plane, then the
cells outside dropped). The same blocks (volumes compared), and the times.

    python benchmarks/bench_terrain.py [--nodes 5 7]

(at 9 × 9 nodes the bounding-box path takes minutes.)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from engine.geometry.cutting.cut import cut_blocks
from engine.geometry.domains import terrain
from engine.geometry.joints import joint_set_planes
from engine.geometry.polyhedron import dip_normal


def hill(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An n × n grid over 40 × 40 m of a rolling hillside (every facet its own plane)."""
    x = y = np.linspace(0.0, 40.0, n)
    xx, yy = np.meshgrid(x, y)
    return x, y, 10.0 + 0.3 * yy + 2.0 * np.sin(xx / 7.0) * np.cos(yy / 9.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--nodes", type=int, nargs="+", default=[5, 7])
    args = ap.parse_args()
    print("nodes  facets  blocks (columns / box)  volume (columns / box) m³  columns (s)  "
          "box (s)  ratio")
    for n in args.nodes:
        t = terrain(*hill(n), base=0.0)
        joints = (joint_set_planes(dip_normal(40, 180), [1, 2, 3], 6.0, t.domain, 0)
                  + joint_set_planes(dip_normal(75, 20), [1, 2, 3], 7.0, t.domain, 1)
                  + joint_set_planes(dip_normal(85, 100), [1, 2, 3], 9.0, t.domain, 2))
        t0 = time.perf_counter()
        a = cut_blocks(t.domain, joints, tiles=t.columns).blocks
        t1 = time.perf_counter()
        b = cut_blocks(t.domain, joints).blocks
        t2 = time.perf_counter()
        va, vb = sum(q.volume for q in a), sum(q.volume for q in b)
        print(f"{n:5d}  {2 * (n - 1) ** 2:6d}  {len(a):8d} / {len(b):<8d}  {va:12.2f} / "
              f"{vb:<12.2f}  {t1 - t0:11.2f}  {t2 - t1:7.2f}  {(t2 - t1) / (t1 - t0):5.1f}")


if __name__ == "__main__":
    main()
