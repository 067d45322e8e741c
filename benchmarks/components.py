"""The engine's parts on their own: cutting a large domain into blocks, and full contact
detection on cut rock masses (blocks touching along their joints) and jittered box grids
of 100 to 5,000 blocks, with the scaling exponent, and the fixed cost of one call.

Detection runs as compiled (numba) loops over piece pairs, chosen by measurement: the
vectorised numpy implementation it replaced (the parent of commit 5474a88) took 55 / 630 /
4,719 ms on the 100 / 1,000 / 5,120 jittered boxes on this machine (2026-11-24) against
10.5 / 96 / 441 ms now, 5-11 × longer. Reproduce the numpy side with
`git worktree add /tmp/numpy-detection 5474a88^ && cd /tmp/numpy-detection &&
PYTHONPATH=. python benchmarks/bench_detection.py`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from benchmarks.bench_cutting import SETS, cube
from benchmarks.bench_detection import cube_on_slab, jittered_grid, time_detection, time_per_call
from engine.geometry.cutting.cut import cut_blocks
from engine.geometry.joints import joint_set_planes
from engine.geometry.polyhedron import Polyhedron, dip_normal

#: spacing (m) of the three joint sets in the 100 m cube: ~100, ~1,000 and ~5,000 blocks
SPACINGS = (28.0, 11.5, 6.2)
#: grids of jittered 1 m boxes: 100, 1,000 and 5,120 boxes
GRIDS = ((5, 5, 4), (10, 10, 10), (20, 16, 16))
#: the numpy implementation's times (ms) on GRIDS, measured as the module docstring says
NUMPY_MS = (54.6, 630.5, 4719.1)


def cut_cube(spacing: float, size: float = 100.0) -> tuple[list[Polyhedron], float, int]:
    """A `size` m cube cut by the three joint sets at `spacing` m: `(blocks, wall time of
    the cut (s), number of joint planes)`."""
    domain = cube(size)
    joints = []
    for tag, (dip, ddir) in enumerate(SETS):
        joints += joint_set_planes(dip_normal(dip, ddir), [size / 2] * 3, spacing, domain,
                                   tag)
    t0 = time.perf_counter()
    blocks = cut_blocks(domain, joints).blocks
    return blocks, time.perf_counter() - t0, len(joints)


def run_components(out: Path, full: bool) -> dict[str, Any]:
    """Time cutting and detection; store `results/components.json`."""
    repeats = 5 if full else 2
    cutting, rock = [], []
    for spacing in SPACINGS:
        blocks, wall, planes = cut_cube(spacing)
        volume = sum(b.volume for b in blocks)
        cutting.append({"spacing_m": spacing, "planes": planes, "blocks": len(blocks),
                        "wall_s": wall, "volume_error": abs(volume - 1e6) / 1e6})
        print(f"  cut at {spacing} m: {len(blocks)} blocks in {wall:.2f} s", flush=True)
        # the first step's search of a simulation: twice its step displacement limit,
        # 1 % of the model size or half the thinnest block (AnalysisControls defaults)
        thin = min(2.0 * b.volume / b.face_areas.sum() for b in blocks)
        search = 2.0 * min(0.01 * 100.0, 0.5 * thin)
        t, nc = time_detection(blocks, search, repeats)
        rock.append({"blocks": len(blocks), "search_m": search, "contacts": nc,
                     "wall_s": t})
        print(f"  detection, cut rock mass of {len(blocks)}: {nc} contacts in "
              f"{1e3 * t:.1f} ms", flush=True)
    boxes = []
    for side in GRIDS:
        blocks = jittered_grid(side)
        t, nc = time_detection(blocks, 0.005, repeats)
        boxes.append({"blocks": len(blocks), "search_m": 0.005, "contacts": nc, "wall_s": t})
        print(f"  detection, {len(blocks)} jittered boxes: {nc} contacts in {1e3 * t:.1f} ms",
              flush=True)
    t_call, nc = time_per_call(cube_on_slab(), 0.002, 1000 if full else 200)

    def exponent(rows: list[dict[str, Any]]) -> float:
        return float(np.polyfit(np.log([r["blocks"] for r in rows]),
                                np.log([r["wall_s"] for r in rows]), 1)[0])

    data = {"cutting": cutting, "rock_mass": rock, "boxes": boxes,
            "exponent_rock_mass": exponent(rock), "exponent_boxes": exponent(boxes),
            "call_2_blocks_s": t_call, "call_2_blocks_contacts": nc}
    h.save_json(out, "components", data)
    return data


def components_part(cp: dict[str, Any]) -> str:
    """The report section of :func:`run_components`."""
    lines = ["## 6. Cutting and contact detection on their own", "",
             "A 100 m cube cut by the three joint sets of the paper's example 6.3 (45/135, "
             "45/315, 75/45) at three spacings; full contact detection on the cut rock "
             "masses as cut (every block touching its neighbours along joint faces; search "
             "= the first step's, twice the step displacement limit) and on grids of "
             "jittered 1 m boxes (search 5 mm), beside the numpy implementation the compiled "
             "kernels replaced (measured once, see `benchmarks/components.py`). Best of "
             "several runs. "
             "Reproduce: `python -m benchmarks --only components` (or "
             "`python benchmarks/bench_cutting.py`, `python benchmarks/bench_detection.py`).",
             "", "| joint spacing (m) | joint planes | blocks | cutting (s) | volume error |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['spacing_m']:g} | {r['planes']} | {r['blocks']} | {r['wall_s']:.2f} | "
              f"{r['volume_error']:.1e} |" for r in cp["cutting"]]
    lines += ["", "| scene | blocks | constraints | search (m) | detection (ms) |",
              "|---|---|---|---|---|"]
    lines += [f"| cut rock mass | {r['blocks']} | {r['contacts']} | {r['search_m']:.3g} | "
              f"{1e3 * r['wall_s']:.1f} |" for r in cp["rock_mass"]]
    lines += [f"| jittered boxes | {r['blocks']} | {r['contacts']} | {r['search_m']:.3g} | "
              f"{1e3 * r['wall_s']:.1f} (numpy implementation: {ms:g}) |"
              for r, ms in zip(cp["boxes"], NUMPY_MS, strict=True)]
    lines += [f"| cube on a slab (one call) | 2 | {cp['call_2_blocks_contacts']} | 0.002 | "
              f"{1e3 * cp['call_2_blocks_s']:.3f} |", "",
              f"Growth exponents (time ~ blocks^p): cut rock mass p = "
              f"{cp['exponent_rock_mass']:.2f}, jittered boxes p = {cp['exponent_boxes']:.2f}."]
    return "\n".join(lines)
