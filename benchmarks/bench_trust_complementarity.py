"""Stability map v2 (benchmarks.trust) under a contact solver other than the default (issues
29 and 38): the stay-put scenes over Δt × start state — and, for a solver with springs
(`newton`), × penalty — and the paper's toppling and block-system examples at ×0.1, ×1 and
×10 their own Δt (and penalty, for springs); verdicts as in the map (a silent failure is a
completed run that moved, or created energy).

Run: `python -m benchmarks.bench_trust_complementarity [SOLVER]` (default
`complementarity`; ~10 min on 2 cores, more with the penalty sweep); writes
`benchmarks/results/trust_<SOLVER>.json` and prints a line per run and the totals.
"""

from __future__ import annotations

import sys
from collections import Counter

from benchmarks import harness as h
from benchmarks import trust

#: the solvers whose contacts are penalty springs: their map sweeps the penalty too
SPRINGS = ("open_close", "newton")


def main() -> None:
    solver = sys.argv[1] if len(sys.argv) > 1 else "complementarity"
    rows = []
    cap = trust.WALL_CAP[False]
    penalties = trust.QUICK_PENALTIES if solver in SPRINGS else (1e10,)
    factors = trust.QUICK_FACTORS if solver in SPRINGS else (1.0,)
    for scene in trust.MAP_SCENES.values():
        for start in trust.STARTS:
            for dt in trust.QUICK_DTS:
                for k in penalties:
                    rows.append(trust.run_map_one(scene, dt, k, start, cap, solver=solver))
                    print(rows[-1]["case"], dt, k, start, rows[-1]["verdict"], flush=True)
    for sweep in trust.EXAMPLE_SWEEPS.values():
        for factor in trust.QUICK_FACTORS:
            for kf in factors:
                rows.append(trust.run_example_one(sweep, factor, kf, cap, solver=solver))
                print(rows[-1]["case"], factor, kf, rows[-1]["verdict"], flush=True)
    h.save_json(h.RESULTS, f"trust_{solver}", {"rows": rows, "solver": solver})
    counts = Counter((r["case"], r["verdict"]) for r in rows)
    for (case, verdict), n in sorted(counts.items()):
        print(f"{case:16s} {verdict:24s} {n}")
    print(f"silent failures: {len(trust.silent(rows))} of {len(rows)} runs")


if __name__ == "__main__":
    main()
