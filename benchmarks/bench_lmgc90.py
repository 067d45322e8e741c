"""LMGC90 on the same cut rock mass as our contact solvers, measured in the same run (issue 38).

The 134-block rock mass of `benchmarks.pile.rock_mass_model(2.5)` (10 m cube, three joint
sets, φ 30°, fixed base; asked Δt 1 ms) is exported to LMGC90 (`benchmarks.lmgc90`: rigid
polyhedra, IQS_CLB, restitution 0, θ = ½) and stepped from rest through the same simulated
time as our three solvers (`bench_contact_solvers.one`, each run preceded in its process by an
untimed one-step run that loads the compiled kernels). Every run has a process of its own,
one after the other, repeated; `/proc/loadavg` is recorded before and after each. Both sides
report the wall and CPU of the stepping loop, per step and per simulated second, the Δt
held, iterations (ours; LMGC90's binding does not return its NLGS count), and where the
blocks went: mean and largest displacement, settlement, rotation and the kinetic energy of
the last step's mean velocities, computed by one formula from each engine's positions.
Run: `python -m benchmarks.bench_lmgc90 [--seconds 0.01 0.2] [--repeat 2]`; writes
`benchmarks/results/lmgc90.json`; `report_part` renders REPORT.md's section from it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

SOLVERS = ("open_close", "complementarity", "newton")
#: LMGC90 as compas_lmgc90's binding ships it (contacts of the first step kept), and with its
#: contacts re-detected every step (short cases only: it costs ~10× more here)
LMGC90 = ("LMGC90", "LMGC90 redetect")
#: the solvers run on the longer cases (complementarity needs ~2e4 s per simulated second here)
LONG_SOLVERS = ("open_close", "newton")
SPACING = 2.5  #: the rock mass of issue 38: 134 free blocks
OUT = Path(__file__).parent / "results" / "lmgc90.json"
ROOT = Path(__file__).resolve().parents[1]


ASKED_DT = 1e-3  #: the asked Δt of issue 38


def builder(seconds: float, dt: float = ASKED_DT) -> str:
    """The rock mass at asked Δt `dt`, run to `seconds` exactly (our last step shortened to
    land there)."""
    return f"rock_mass_model({SPACING}, dt={dt!r}, duration={seconds!r})"


def ours_probe(sim: Any) -> dict[str, Any]:
    """Where our blocks went, in the same terms as `benchmarks.lmgc90.run` reports LMGC90's,
    plus the engine's own end-of-step kinetic energy and deepest penetration."""
    from benchmarks.lmgc90 import (
        deepest_overlap,
        inertia_tensors,
        motion_summary,
        rotation_angle,
    )
    from engine.dynamics.block_terms import kinetic_energy
    from engine.dynamics.motion import mass_matrices

    system, state = sim.system, sim.state
    free = ~system.fixed
    mass, inertia = inertia_tensors(system.model, state.rotation)
    d = state.last_d if state.last_d is not None else np.zeros((system.n, 12))
    out = motion_summary(mass[free], inertia[free], (state.centroid - system.c0)[free],
                         rotation_angle(state.rotation)[free], d[free, :3], d[free, 3:6],
                         max(state.last_dt, 1e-300))
    out["kinetic_engine_J"] = kinetic_energy(state.velocity, mass_matrices(system, state))
    out["max_penetration_m"] = float(state.diagnostics.max_penetration)
    out["overlap_end_m"] = deepest_overlap(system.model, state.centroid, state.rotation)
    return out


def ours_in_process(expr: str, solver: str, seconds: float, cap: float) -> dict[str, Any]:
    """One of our solvers on `expr` through `seconds`: an untimed one-step run first (the
    compiled kernels loaded), then `bench_contact_solvers.one` with `cap` s of wall."""
    from benchmarks import bench_contact_solvers as bcs

    bcs.one(expr, solver, 1)
    bcs.WALL_CAP = cap
    return bcs.one(expr, solver, 0, seconds, probe=ours_probe)


def _subprocess(code: str, timeout: float) -> dict[str, Any]:
    """Run python `code` (printing `RESULT {json}`) in a fresh process from the repository."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=timeout)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"exit {p.returncode}: {(p.stdout + p.stderr)[-600:]}")


def run_one(engine: str, seconds: float, cap: float, dt: float = ASKED_DT) -> dict[str, Any]:
    """One timed run at asked Δt `dt` in its own process (LMGC90 or one of our solvers) with
    the load average before and after; an error row when it fails."""
    expr = builder(seconds, dt)
    if engine in LMGC90:
        code = ("import json; from benchmarks.lmgc90 import run; "
                f"print('RESULT ' + json.dumps(run({expr!r}, {seconds!r}, "
                f"redetect={engine != 'LMGC90'}, cap={cap!r})))")
    else:
        code = ("import json; from benchmarks.bench_lmgc90 import ours_in_process; "
                f"print('RESULT ' + json.dumps(ours_in_process({expr!r}, {engine!r}, "
                f"{seconds!r}, {cap!r})))")
    before = list(os.getloadavg())
    try:
        row = _subprocess(code, timeout=cap + 1200.0)
    except (RuntimeError, subprocess.SubprocessError) as exc:
        row = {"solver": engine, "status": "error", "message": str(exc)[-400:]}
    row.update(case_s=seconds, asked_dt=dt, load_before=before, load_after=list(os.getloadavg()),
               when=time.strftime("%Y-%m-%d %H:%M:%S"))
    return row


def lmgc90_available() -> str | None:
    """None when compas_lmgc90's binding imports, else why not."""
    try:
        from compas_lmgc90 import _lmgc90  # noqa: F401
    except ImportError as exc:
        return f"compas_lmgc90 not installed ({exc}): run benchmarks/setup_peers.sh"
    return None


def measure(cases: list[float], repeat: int, cap: float, solvers: tuple[str, ...] = SOLVERS,
            long_solvers: tuple[str, ...] = LONG_SOLVERS, out: Path = OUT,
            extra_dt: float | None = None, extra_engines: tuple[str, ...] = ("LMGC90",)
            ) -> dict[str, Any]:
    """Every case (simulated seconds) `repeat` times: LMGC90, then ours, one after the other;
    then, with `extra_dt`, `extra_engines` once on the shortest case at that asked Δt (how
    far each answer is from its small-Δt limit). Saved after every run (a crash loses only
    itself)."""
    from benchmarks.harness import machine_info

    why = lmgc90_available()
    data: dict[str, Any] = {"machine": machine_info(), "spacing": SPACING, "repeat": repeat,
                            "cap_s": cap, "rows": [], "note": why,
                            "command": "python -m benchmarks.bench_lmgc90 " + " ".join(
                                sys.argv[1:])}
    if why is None:
        from benchmarks.lmgc90 import in_subprocess

        data["verify"] = in_subprocess("verify", builder(cases[0]))
        print("export verified:", {k: f"{v:.1e}" for k, v in data["verify"].items()
                                   if isinstance(v, float)}, flush=True)
    for rep in range(repeat):
        for seconds in cases:
            short = seconds == min(cases)
            engines = ([e for e in LMGC90 if short or e == "LMGC90"] if why is None else []
                       ) + list(solvers if short else long_solvers)
            for engine in engines:
                row = run_one(engine, seconds, cap)
                row["repeat"] = rep
                _keep(data, row, out)
    if extra_dt is not None:
        for engine in extra_engines:
            if engine not in LMGC90 or why is None:
                _keep(data, run_one(engine, min(cases), cap, extra_dt), out)
    return data


def _keep(data: dict[str, Any], row: dict[str, Any], out: Path) -> None:
    """Add `row` to `data`, save, print it."""
    data["rows"].append(row)
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(data, indent=1))
    print(summary_line(row), flush=True)


def summary_line(r: dict[str, Any]) -> str:
    """One printed line per run."""
    if r.get("status") == "error":
        return f"{r['case_s']:g} s {r['solver']:16s} error {r['message'][-200:]}"
    return (f"{r['case_s']:g} s {r['solver']:16s} {r['steps']:5d} steps {r['per_step_s']:.3f} "
            f"s/step {r['per_sim_second_s']:.4g} s per simulated s (cpu {r['cpu_s']:.1f} s) "
            f"dt {r['mean_dt']:.2g}; disp mean {r['disp_mean_m']:.3e} max "
            f"{r['disp_max_m']:.3e} m, KE {r['kinetic_step_mean_J']:.4g} J; "
            f"load {r['load_before'][0]:.1f}/{r['load_after'][0]:.1f}; {r['status']}")


def _median(rows: list[dict[str, Any]], key: str) -> float:
    """Median of `key` over runs."""
    return float(np.median([r[key] for r in rows]))


def _delta(rows: list[dict[str, Any]], d_ref: np.ndarray) -> float:
    """Mean over blocks of |d − d_ref| over the mean |d_ref|: how far the runs' mean block
    displacements `d` are from the reference's `d_ref (n, 3)`."""
    d = np.mean([np.array(r["displacements"]) for r in rows], axis=0)
    return float(np.linalg.norm(d - d_ref, axis=1).mean()
                 / max(float(np.linalg.norm(d_ref, axis=1).mean()), 1e-300))


def report_part(data: dict[str, Any] | None) -> str:
    """REPORT.md's section on LMGC90 against our solvers on the cut rock mass, from
    `results/lmgc90.json` (medians over the repeats; every run's load average listed)."""
    title = "## 7b. LMGC90 on the same cut rock mass (issue 38)"
    if not data:
        return f"{title}\n\n(section not run)\n"
    lines = [title, "",
             "`python -m benchmarks.bench_lmgc90`: the 134-block rock mass of section 7 "
             f"(`rock_mass_model({data['spacing']})`) exported to LMGC90 and stepped from "
             "rest through the same simulated time as our solvers, in one run: every engine "
             f"in a process of its own, one after the other, {data['repeat']} times "
             "(medians below). Wall and CPU of the stepping loop; where the blocks went, "
             "by one formula from each engine's positions (kinetic energy of the last "
             "step's mean velocities, both schemes moving a block by Δt (v₀ + v₁)/2)."]
    if data.get("note"):
        return "\n".join(lines + ["", f"LMGC90 not run: {data['note']}.", ""])
    rows = [r for r in data["rows"] if r.get("status") != "error"]
    errors = [r for r in data["rows"] if r.get("status") == "error"]
    v = data.get("verify")
    if v:
        lines += ["", f"Export checked in LMGC90 itself ({v['blocks']} bodies, spread apart): "
                  f"centroids to {v['centroid']:.0e} of the block size, masses (ρV, by the "
                  f"drift under a lift equal to our weight) to {v['mass']:.0e}, principal "
                  f"moments to {v['principal_moments']:.0e}; the exported triangles against "
                  f"our blocks: volume {v['export_volume']:.0e}, centroid "
                  f"{v['export_centroid']:.0e}, second moments {v['export_second_moments']:.0e}."]
    lines += ["", "| simulated | engine | steps | Δt held (s) | s/step | s per simulated s | "
              "CPU s | iterations/step | contacts | mean / max displacement (mm) | "
              "settlement (mm) | max rotation (mrad) | KE (J) | max penetration (m) | "
              "overlap at end (m) | Δ vs LMGC90 | status |", "|---" * 17 + "|"]
    for seconds in sorted({r["case_s"] for r in rows}):
        here = [r for r in rows if r["case_s"] == seconds]
        at_dt = [r for r in here if r.get("asked_dt", ASKED_DT) == ASKED_DT]
        ref = ([r for r in at_dt if r["solver"] == "LMGC90 redetect"]
               or [r for r in at_dt if r["solver"] == "LMGC90"])
        d_ref = np.mean([np.array(r["displacements"]) for r in ref], axis=0) if ref else None
        order = [*LMGC90, *SOLVERS]
        kinds = sorted({(r["solver"], r.get("asked_dt", ASKED_DT)) for r in here},
                       key=lambda k: (-k[1], order.index(k[0])))
        for engine, dt in kinds:
            rs = [r for r in here if (r["solver"], r.get("asked_dt", ASKED_DT)) == (engine, dt)]
            its = None if rs[0].get("iterations_mean") is None else _median(
                rs, "iterations_mean")
            is_ref = bool(ref) and (engine, dt) == (ref[0]["solver"], ASKED_DT)
            delta = "–" if d_ref is None or is_ref else f"{_delta(rs, d_ref):.0%}"
            label = engine if dt == ASKED_DT else f"{engine}, asked Δt {dt:g} s"
            if any(r.get("apart") for r in rs):
                label += " (run apart)"
            status = ", ".join(sorted({r["status"] for r in rs}))
            lines.append(
                f"| {seconds:g} s | {label} | {_median(rs, 'steps'):.0f} | "
                f"{_median(rs, 'mean_dt'):.2g} | {_median(rs, 'per_step_s'):.3f} | "
                f"{_median(rs, 'per_sim_second_s'):.3g} | {_median(rs, 'cpu_s'):.1f} | "
                f"{'n/a' if its is None else f'{its:.0f}'} | {_median(rs, 'contacts_mean'):.0f} | "
                f"{1e3 * _median(rs, 'disp_mean_m'):.3g} / {1e3 * _median(rs, 'disp_max_m'):.3g} | "
                f"{1e3 * _median(rs, 'settlement_mean_m'):.3g} | "
                f"{1e3 * _median(rs, 'rotation_max_rad'):.3g} | "
                f"{_median(rs, 'kinetic_step_mean_J'):.4g} | "
                f"{_median(rs, 'max_penetration_m'):.1e} | "
                f"{_median(rs, 'overlap_end_m'):.1e} | {delta} | {status} |")
    pairs = [f"{r['solver']} at {r['case_s']:g} s: {r['pairs_end']} body pairs, "
             f"{r['contacts_end']} contact points" for r in rows if "pairs_end" in r
             and r.get("repeat") in (0, "apart")]
    if pairs:
        lines += ["", "LMGC90's contacts at the end (as shipped, the binding keeps those of the "
                  "first step; the contacts of our first step join 995 block pairs, counted "
                  "apart): "
                  + "; ".join(pairs) + "."]
    loads = ", ".join(f"{r['solver']} {r['case_s']:g} s: {r['load_before'][0]:.1f}→"
                      f"{r['load_after'][0]:.1f}" for r in data["rows"] if "load_before" in r)
    m = data["machine"]
    lines += ["", f"Machine: {m['nproc']} cores ({m['cpu']}), shared: 1-minute load average "
              f"before→after each run: {loads}. CPU s is the process's CPU time in the loop "
              "(less sensitive to the sharing than the wall).", "",
              "Δ vs LMGC90: mean over blocks of |d − d_LMGC90| over the mean |d_LMGC90| "
              "(d: each block's displacement at the end; the reference is LMGC90 with its "
              "contacts re-detected where it was run, else the binding as shipped). "
              "Overlap at end: how deep a vertex of one block lies inside another at the "
              "end, by our geometry, for every engine alike (a contact never detected shows "
              "there). Iterations: open-close cycles, "
              "Gauss–Seidel sweeps or Newton iterations a step; LMGC90's NLGS count is not "
              "returned by compas_lmgc90's binding, whose settings are fixed "
              f"({rows[0].get('nlgs', '') if rows else ''}).", "",
              "Caveats: LMGC90 is non-smooth contact dynamics (velocity-level Signorini and "
              "Coulomb, impulses, no contact stiffness: its penetration is the drift of the "
              "position from velocity-level constraints), ours are penalty DDA with Δt cut "
              "where the solver needs it; LMGC90 detects contacts on the blocks' "
              "triangulated faces (STO), and its wall includes copying every contact into "
              "Python after each step (the binding does it)."]
    if errors:
        lines += ["", "Runs that failed: " + "; ".join(
            f"{r['solver']} {r['case_s']:g} s: {r['message'][-160:]}" for r in errors)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Measure (or only re-render with --render) and print the section."""
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_lmgc90")
    ap.add_argument("--seconds", type=float, nargs="+", default=[0.01, 0.2],
                    help="simulated times (the shortest runs every solver)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--cap", type=float, default=1800.0, help="wall cap of one run (s)")
    ap.add_argument("--solvers", nargs="+", default=list(SOLVERS))
    ap.add_argument("--long-solvers", nargs="+", default=list(LONG_SOLVERS))
    ap.add_argument("--extra-dt", type=float, default=None,
                    help="also run --extra-engines once on the shortest case at this Δt")
    ap.add_argument("--extra-engines", nargs="+", default=["LMGC90"])
    ap.add_argument("--add", nargs=2, metavar=("ENGINE", "SECONDS"),
                    help="append one run to the stored results (its row says it was run "
                         "apart, e.g. LMGC90 redetect over the long case)")
    ap.add_argument("--render", action="store_true", help="only print the section")
    args = ap.parse_args(argv)
    if args.add:
        data = json.loads(OUT.read_text())
        row = run_one(args.add[0], float(args.add[1]), args.cap)
        row.update(repeat="apart", apart=True)
        _keep(data, row, OUT)
    elif not args.render:
        measure(sorted(args.seconds), args.repeat, args.cap, tuple(args.solvers),
                tuple(args.long_solvers), extra_dt=args.extra_dt,
                extra_engines=tuple(args.extra_engines))
    print(report_part(json.loads(OUT.read_text()) if OUT.exists() else None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
