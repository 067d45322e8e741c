"""Rock masses of ~1,000 to ~10,000 blocks: a few steps each, time per phase, peak memory
and growth exponents (issue 14).

The 10 m cube of `benchmarks.pile.rock_mass_model` (three joint sets, φ 30°, fixed base,
penalty 1e10, asked Δt 1 ms) cut at spacings that give ~1,000, ~5,000 and ~10,000 blocks;
each size runs in its own process (its peak RSS is its own): the cutting, the set-up, one
untimed step, then STEPS timed steps. Run: `python -m benchmarks.bench_large [STEPS]`
(default 3; ~10 min on 2 cores).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

from benchmarks import harness as h

#: spacing (m) → about how many blocks the 10 m cube gives
SPACINGS = (1.2, 0.62, 0.5)
PHASES = ("detection", "assembly", "solve", "open_close", "update", "damping")


def one(spacing: float, steps: int) -> dict:
    """Cut, set up and step the rock mass at `spacing` (in this process)."""
    import warnings

    warnings.simplefilter("ignore")
    from benchmarks.pile import rock_mass_model
    from benchmarks.scaling import time_steps

    t0 = time.perf_counter()
    model = rock_mass_model(spacing, dt=1e-3, penalty=1e10)
    cut = time.perf_counter() - t0
    r = time_steps(model, steps, warmup=1)
    return {"spacing": spacing, "cut_s": cut, "N": r["blocks"] - 1, **r}


def main() -> None:
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    rows = []
    for s in SPACINGS:
        out = subprocess.run([sys.executable, "-c", (
            "import json, sys; from benchmarks.bench_large import one; "
            f"print(json.dumps(one({s}, {steps})))")], capture_output=True, text=True,
            check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        mean_dt = r["simulated"] / max(r["steps"], 1)
        print(f"spacing {s} m: {r['N']} blocks, {r['unknowns']} unknowns, "
              f"{r['contacts_mean']:.0f} contacts; cut {r['cut_s']:.1f} s, set-up "
              f"{r['setup_s']:.1f} s; {r['steps']} steps, {r['per_step_s']:.2f} s/step (" +
              ", ".join(f"{p} {r[f't_{p}']:.2f}" for p in PHASES) +
              f"), mean dt {mean_dt:.2g} s, {r['per_sim_second_s']:.3g} s per simulated s; "
              f"peak RSS {r['rss_peak_mb']:.0f} MB; {r['status']}", flush=True)
    x = [r["N"] for r in rows]
    exps = {p: h.growth_exponent(x, [r[f"t_{p}"] for r in rows]) for p in PHASES}
    exps["per step"] = h.growth_exponent(x, [r["per_step_s"] for r in rows])
    exps["contacts"] = h.growth_exponent(x, [r["contacts_mean"] for r in rows])
    exps["cutting"] = h.growth_exponent(x, [r["cut_s"] for r in rows])
    exps["peak RSS"] = h.growth_exponent(x, [r["rss_peak_mb"] for r in rows])
    print("growth exponents (log time against log blocks): " +
          ", ".join(f"{k} {v:.2f}" for k, v in exps.items()))


if __name__ == "__main__":
    main()
