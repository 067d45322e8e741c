"""Stability map v2 (benchmarks.trust) under the complementarity solve (issue 29): the
stay-put scenes over Δt × start state (no penalty to sweep: one run per Δt and start) and
the paper's toppling and block-system examples at ×0.1, ×1 and ×10 their own Δt; verdicts
as in the map (a silent failure is a completed run that moved, or created energy).

Run: `python -m benchmarks.bench_trust_complementarity` (~10 min on 2 cores); writes
`benchmarks/results/trust_complementarity.json` and prints a line per run and the totals.
"""

from __future__ import annotations

from collections import Counter

from benchmarks import harness as h
from benchmarks import trust

SOLVER = "complementarity"


def main() -> None:
    rows = []
    cap = trust.WALL_CAP[False]
    for scene in trust.MAP_SCENES.values():
        for start in trust.STARTS:
            for dt in trust.QUICK_DTS:
                rows.append(trust.run_map_one(scene, dt, 1e10, start, cap, solver=SOLVER))
    for sweep in trust.EXAMPLE_SWEEPS.values():
        for factor in trust.QUICK_FACTORS:
            rows.append(trust.run_example_one(sweep, factor, 1.0, cap, solver=SOLVER))
    h.save_json(h.RESULTS, "trust_complementarity", {"rows": rows, "solver": SOLVER})
    counts = Counter((r["case"], r["verdict"]) for r in rows)
    for (case, verdict), n in sorted(counts.items()):
        print(f"{case:16s} {verdict:24s} {n}")
    print(f"silent failures: {len(trust.silent(rows))} of {len(rows)} runs")


if __name__ == "__main__":
    main()
