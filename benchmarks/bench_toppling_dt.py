"""The paper's toppling train (6.2) at several Δt under every contact solver: column T1's
rotation after 1 s (issues 29 and 38: is an answer independent of the time step?).

Run: `python -m benchmarks.bench_toppling_dt` (about 10 min on 2 cores); prints a row per
run and writes `benchmarks/results/toppling_dt.json`.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from pathlib import Path

RUNS = (("open_close", 1e-2), ("open_close", 1e-3), ("open_close", 1e-4),
        ("open_close", 3e-5), ("newton", 1e-2), ("newton", 1e-3), ("newton", 1e-4),
        ("complementarity", 1e-2), ("complementarity", 1e-3), ("complementarity", 1e-4))
ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    warnings.simplefilter("ignore")
    from engine.step.simulation import run
    from schemas.convert import build_model

    rows = []
    for solver, dt in RUNS:
        built = build_model(ROOT / "examples" / "toppling.json")
        built.model.controls = dataclasses.replace(built.model.controls, contact_solver=solver,
                                                   time_step=dt, duration=1.0)
        t0 = time.perf_counter()
        res = run(built.model)
        rot = {n: b["rotation"] for n, b in zip(built.block_names, res.summary["blocks"],
                                                  strict=True)}
        row = {"solver": solver, "dt": dt, "status": res.status, "steps": res.steps,
               "wall_s": time.perf_counter() - t0, "T1_rotation": rot["T1"][1],
               "columns": [rot[f"T{k}"][1] for k in range(1, 7)]}
        rows.append(row)
        print(f"{solver:16s} dt {dt:g} s: T1 {row['T1_rotation']:.4f} rad after 1 s "
              f"({res.steps} steps, {row['wall_s']:.1f} s, {res.status})", flush=True)
    out = ROOT / "benchmarks" / "results" / "toppling_dt.json"
    out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
