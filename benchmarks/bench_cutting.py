"""Benchmark: a 100 m cube cut by three persistent joint sets into >= 5,000 blocks.

Run as `python benchmarks/bench_cutting.py [spacing_m]`; prints block count and wall time.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from engine.geometry.cutting.cut import cut_blocks
from engine.geometry.joints import joint_set_planes
from engine.geometry.polyhedron import Polyhedron, dip_normal

SETS = [(45.0, 135.0), (45.0, 315.0), (75.0, 45.0)]  #: (dip, dip direction) in degrees


def cube(size: float) -> Polyhedron:
    """Axis-aligned cube `[0, size]³` with outward counter-clockwise faces."""
    v = np.array([[x, y, z] for z in (0, size) for y in (0, size) for x in (0, size)], float)
    f = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    return Polyhedron.from_faces(v, f)


def main(spacing: float = 6.2) -> None:
    """Cut, time, and print the block count, the wall time and the volume error."""
    domain = cube(100.0)
    joints = []
    for tag, (dip, ddir) in enumerate(SETS):
        joints += joint_set_planes(dip_normal(dip, ddir), [50.0, 50.0, 50.0], spacing,
                                   domain, tag)
    t0 = time.perf_counter()
    result = cut_blocks(domain, joints)
    elapsed = time.perf_counter() - t0
    volume = sum(b.volume for b in result.blocks)
    print(f"{len(joints)} joints, spacing {spacing} m: {len(result.blocks)} blocks "
          f"in {elapsed:.2f} s (volume error {abs(volume - domain.volume) / domain.volume:.1e})")
    for w in result.warnings:
        print("warning:", w)


if __name__ == "__main__":
    main(*(float(a) for a in sys.argv[1:2]))
