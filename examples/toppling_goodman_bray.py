"""Write examples/toppling_goodman_bray.json: Goodman & Bray's (1976) multi-block toppling.

Twelve rigid columns 5 m wide (along dip) and 5 m long (along strike) stand on a fixed
stepped base whose treads dip 28° to the east, toward the toe; each tread is 0.5 m (b,
normal to the tread) above the next one toe-ward. With a1 = a2 = 2.5 m the heights are
y_n = n (a1 − b) up to the crest column 8, then 3 m less per column: 2, 4, ..., 16, 13, 10,
7, 4 m. Column C1 is at the toe; step S_n carries C_n, and S1 runs on 5 m past the toe so
a sliding toe column stays on rock. Limit equilibrium (engine/toppling.py) is critical at
φ = 33.93° on bases and interfaces: C1–C3 slide, C4–C10 topple, C11–C12 stand.

Run from the repository root: ``python examples/toppling_goodman_bray.py``.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

OUT = Path(__file__).with_suffix(".json")

DIP_DEG = 28.0          # treads (column bases) dip toward the toe, to the east
WIDTH = 5.0             # Δx, column width along dip (m)
LENGTH = 5.0            # along strike (m)
A1 = A2 = 2.5           # slope-face rise and upper-slope fall per column (m)
RISE = 0.5              # b, step between treads, normal to them (m)
CREST = 8               # the tallest column
N_COLUMNS = 12
STEP_DEPTH = 2.0        # thickness of the fixed steps under the treads (m)
TOE_APRON = 5.0         # the toe step runs on this far past C1 (m)
FRICTION_DEG = 31.0     # below the critical 33.93°: a plain run shows the failure


def heights() -> list[float]:
    """y_n of columns 1..12 (toe first), Goodman & Bray's y_n = n (a1 − b) to the crest."""
    y: list[float] = []
    for n in range(1, N_COLUMNS + 1):
        y.append(n * (A1 - RISE) if n <= CREST else y[-1] - A2 - RISE)
    return y


def frame() -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors up-dip along the treads (toward the crest, west) and along the columns."""
    d = math.radians(DIP_DEG)
    return np.array([-math.cos(d), 0.0, math.sin(d)]), np.array([math.sin(d), 0.0, math.cos(d)])


def prism(s0: float, s1: float, t0: float, t1: float) -> dict:
    """A box from s0 to s1 up-dip (from C1's toe corner) and t0 to t1 normal to the treads,
    0 to LENGTH along strike; faces counter-clockwise seen from outside."""
    up, axis = frame()
    corners = [(s0, 0), (s1, 0), (s1, LENGTH), (s0, LENGTH)]
    verts = [s * up + t * axis + np.array([0.0, y, 0.0])
             for t in (t0, t1) for s, y in corners]
    faces = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    centre = np.mean(verts, axis=0)
    for f in faces:  # turn each face to face away from the centre
        a, b, c = (verts[i] for i in f[:3])
        if np.dot(np.cross(b - a, c - a), a - centre) < 0:
            f.reverse()
    return {"vertices": [[round(float(x), 9) + 0.0 for x in v] for v in verts], "faces": faces}


def scene(setback: float = 0.0) -> dict:
    """The scene; `setback` (m) moves every step's edge that far up-dip from its column's toe
    corner (0: Goodman & Bray's geometry, the toe corners on the step edges)."""
    y = heights()
    blocks, pairs = [], []
    for k, h in enumerate(y):
        base = k * RISE
        s0 = k * WIDTH
        blocks.append({"name": f"C{k + 1}", **prism(s0, s0 + WIDTH, base, base + h)})
    for k in range(N_COLUMNS):
        s0 = k * WIDTH + setback - (TOE_APRON if k == 0 else 0.0)
        step = prism(s0, (k + 1) * WIDTH + setback, k * RISE - STEP_DEPTH, k * RISE)
        blocks.append({"name": f"S{k + 1}", **step, "fixed": True})
        # each column on its tread; the column below touches the riser in front of it
        pairs.append({"blocks": [f"S{k + 1}", f"C{k + 1}"], "joint_material": "base"})
        if k > 0:
            pairs.append({"blocks": [f"S{k + 1}", f"C{k}"], "joint_material": "base"})
    return {
        "name": "toppling_goodman_bray",
        "description": (
            "Goodman & Bray (1976) block toppling: 12 rigid columns 5 m wide on a fixed "
            "stepped base, treads dipping 28 deg to the east (toe), step 0.5 m, heights 2, 4, "
            "..., 16 (crest, C8), 13, 10, 7, 4 m (a1 = a2 = 2.5 m, b = 0.5 m), 5 m along "
            "strike; C1 is the toe column. The same friction on bases and interfaces, no "
            "cohesion. Limit equilibrium: critical friction 33.93 deg, where C1-C3 slide, "
            "C4-C10 topple and C11-C12 stand. At the 31 deg given here the slope fails; "
            "'polydda fos' finds F = tan 31 / tan phi_c (0.893 by limit equilibrium). "
            "Written by examples/toppling_goodman_bray.py."),
        "materials": {"rock": {"density": 2600}},
        "joint_materials": {"base": {"friction_angle": FRICTION_DEG},
                            "interface": {"friction_angle": FRICTION_DEG}},
        "default_joint_material": "interface",
        "blocks": blocks,
        "block_pairs": pairs,
        "analysis": {
            "duration": 3.0,
            "time_step": 0.001,
            "block_model": "rigid",
            "factor_of_safety": {"tolerance": 0.005, "observation_time": 3.0},
        },
    }


def main() -> None:
    text = json.dumps(scene(), indent=2)
    # one line per vertex and per face
    text = re.sub(r"\[\s+([-0-9.e,\s]+?)\s+\]",
                  lambda m: "[" + ", ".join(m.group(1).split()).replace(",,", ",") + "]", text)
    OUT.write_text(text + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
