"""The work around the contact solve (issue 39): time per phase against blocks, before and
after, on the cut rock masses and the pile of 1,000; numba's threads alone and beside a
busy process; peak memory.

Each scene runs in a process of its own (its peak RSS is its own), once with this tree and,
with `--baseline COMMIT`, once with that commit's engine (a detached worktree made under
/tmp), one after the other in the same invocation, so the ratios share the machine's load.

- rock masses (`benchmarks.pile.rock_mass_model`, the 10 m cube cut at 1.2 / 0.62 / 0.5 m:
  854 / 5,272 / 9,716 blocks, penalty 1e10, Δt asked 1 ms): one untimed step, then STEPS
  timed steps; wall time per step by phase, amortised over the steps (the skin's full
  detections included), and the growth exponent of each phase;
- the pile of 1,000 (`benchmarks.pile.pile_model`): its whole first simulated second after
  two untimed steps; the work outside the contact solve per step (detection, assembly,
  update and the dashpots after the step, which the baseline timed inside its update);
- threads: each per-contact loop of the step at 854 and 5,272 blocks, serial against on
  numba's threads (best of 5 calls), alone and beside a process that spins on a core.

Writes `results/work.json` and regenerates `REPORT.md` (section 8 is made from it).
Run: `python -m benchmarks.bench_work [--steps 20] [--baseline COMMIT] [--quick]`
(`--quick`: the 854-block mass and the pile's first 200 steps only).
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

from benchmarks import harness as h

SPACINGS = (1.2, 0.62, 0.5)
#: phases of the diagnostics' timings; the baseline timed `damping` inside `update`
PHASES = ("detection", "assembly", "solve", "open_close", "update", "damping")
AROUND = ("detection", "assembly", "update", "damping")
#: the targets of issue 39 (ms per step, 2 cores)
TARGETS = {"detection": 10.0, "assembly": 10.0, "update": 10.0}
PILE_TARGET_MS = 8.0
GROWTH_TARGET = 6.0
EXPONENT_TARGET = 1.1

#: run in a fresh interpreter with PYTHONPATH set to the tree measured: only the API both
#: trees share (the scenes, Simulation, the diagnostics' timings)
_STEPS = r"""
import json, resource, sys, time, warnings
warnings.simplefilter("ignore")
wall = time.perf_counter
if sys.argv[5] == "cpu":  # every phase clock of the engine reads this thread's CPU time
    time.perf_counter = time.thread_time
from benchmarks.pile import pile_model, rock_mass_model
from engine.step.simulation import Simulation
kind, size, steps, warm = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
t0 = wall()
model = (rock_mass_model(size, dt=1e-3, penalty=1e10) if kind == "rock"
         else pile_model(int(size), dt=1e-3, penalty=1e10, duration=2.0))
cut = wall() - t0
sim = Simulation(model)
for _ in range(warm):
    sim.step()
timings = sim.state.diagnostics.timings
timings.clear()
step0, time0, contacts = sim.state.step, sim.state.time, []
t1, c1 = wall(), time.thread_time()
while sim.state.step - step0 < steps and (kind == "rock" or sim.state.time - time0 < 1.0 - 1e-12):
    contacts.append(len(sim.step().contacts))
elapsed, cpu = wall() - t1, time.thread_time() - c1
n = max(sim.state.step - step0, 1)
skin = getattr(sim.state, "workspace", {}).get("skin")
print(json.dumps({
    "blocks": len(model.blocks) - (1 if kind == "rock" else 0), "steps": n, "cut_s": cut,
    "wall_s": elapsed, "per_step_ms": 1e3 * elapsed / n, "cpu_per_step_ms": 1e3 * cpu / n,
    "clock": sys.argv[5], "simulated_s": sim.state.time - time0,
    "contacts_mean": sum(contacts) / max(len(contacts), 1),
    "phases_ms": {k: 1e3 * v / n for k, v in timings.items()},
    "skin": None if skin is None else {"refreshes": skin.refreshes, "reuses": skin.reuses,
                                       "margin_m": skin.margin},
    "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))
"""


def _run(tree: Path, kind: str, size: float, steps: int, warm: int,
         clock: str) -> dict[str, Any]:
    """One scene's steps in a fresh interpreter on the engine of `tree`; phases timed by
    `clock`: "cpu" (this thread's CPU time, with numba and BLAS on one thread: what the
    load of a shared machine disturbs least) or "wall"."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    if clock == "cpu":
        env.update(NUMBA_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    load = os.getloadavg()[0]
    out = subprocess.run([sys.executable, "-c", _STEPS, kind, str(size), str(steps), str(warm),
                          clock], capture_output=True, text=True, check=True, env=env,
                         cwd=tree)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    r["load"] = [load, os.getloadavg()[0]]
    ph = r["phases_ms"]
    r["around_ms"] = sum(ph.get(p, 0.0) for p in AROUND)
    return r


def _baseline_tree(commit: str) -> Path:
    """A detached worktree of `commit` under /tmp (made once)."""
    sha = subprocess.run(["git", "rev-parse", commit], capture_output=True, text=True,
                         check=True, cwd=h.ROOT).stdout.strip()
    tree = Path(f"/tmp/polydda-baseline-{sha[:10]}")
    if not tree.exists():
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), sha], check=True,
                       cwd=h.ROOT, capture_output=True)
    return tree


def _exponents(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Growth exponent (log time against log blocks) of each phase and of their sum."""
    x = [r["blocks"] for r in rows]
    out = {p: h.growth_exponent(x, [max(r["phases_ms"].get(p, 0.0), 1e-9) for r in rows])
           for p in PHASES}
    out["around the solve"] = h.growth_exponent(x, [r["around_ms"] for r in rows])
    out["per step"] = h.growth_exponent(x, [r["per_step_ms"] for r in rows])
    return out


#: thread measurement, run in a fresh interpreter of this tree
_THREADS = r"""
import json, os, sys, time, warnings
warnings.simplefilter("ignore")
import numpy as np
from benchmarks.bench_work import thread_kernels
print(json.dumps(thread_kernels(float(sys.argv[1]))))
"""


def thread_kernels(spacing: float) -> dict[str, Any]:
    """Serial against threaded wall time (best of 5, ms) of each per-contact loop of a step
    of the rock mass at `spacing`, on the state after one step."""
    import numba
    import numpy as np

    from benchmarks.pile import rock_mass_model
    from engine.contact import _detection_kernels as kern
    from engine.contact import detection
    from engine.contact.search import find_contacts
    from engine.contact.solvers import _open_close_kernels as ock
    from engine.contact.solvers.open_close import _terms, initial_modes
    from engine.dynamics import _assembly_kernels as ak
    from engine.dynamics import assembly as asm
    from engine.dynamics.block_terms import block_terms
    from engine.dynamics.motion import current_vertices
    from engine.geometry import _transform_kernels as tk
    from engine.step import stepping
    from engine.step.simulation import Simulation

    sim = Simulation(rock_mass_model(spacing, dt=1e-3, penalty=1e10))
    sim.step()
    system, state = sim.system, sim.state
    att = stepping.first_attempt(system, state)
    reach = stepping.reach(system, state, att)
    cs, patches = find_contacts(system, state, reach)
    t = _terms(system, state, cs, patches, initial_modes(system, state, cs, att.dt).shear)
    kb, _, _ = block_terms(system, state, att.dt)
    plan = asm.plan_system(system.block_row, kb, t.bi, t.bj, t.ti, t.tj, t.normal)
    kn, ks = np.full(len(cs), system.kn), np.full(len(cs), system.ks)
    rows = ak.row_contacts(plan.m, plan.fi, plan.fj)
    blocks = ak.row_contacts(system.n, t.bi, t.bj)
    fill = (plan.base, plan.ti, plan.tj, plan.normal, plan.slot_ii, plan.slot_jj,
            plan.slot_ij, plan.slot_ji, kn, ks)
    mode = np.ones(len(cs), dtype=np.int8)
    f0 = np.zeros(system.n_unknowns)
    loads = (t.dmap, t.bi, t.bj, t.ti, t.tj, t.normal, t.d0, mode, t.shear0,
             np.zeros((len(cs), 3)), cs.tangent, np.zeros(len(cs)), t.tan_phi, system.kn,
             system.ks, t.cn, att.dt)
    x = np.random.default_rng(0).normal(size=system.n_unknowns) * 1e-6
    pts, cen, nd = cs.point_i, state.centroid, system.ndof
    search = detection.start_search(system.polys0, reach, vertices=current_vertices(
        system, state))
    pa, pb = detection.broad_phase(search, search.reach + search.snap,
                                   state.awake(system.fixed))
    pieces = np.zeros(len(search.scene.pv_start), dtype=bool)
    pieces[pa] = pieces[pb] = True
    s = search.scene
    tol = search.tol
    geo = kern.SceneGeometry(*kern.geometry(
        search.x, s.f_vtx, s.f_nxt, s.e_vtx, s.e_faces, s.pv_vtx, s.pv_nb, s.f_start,
        s.f_count, s.e_start, s.e_count, s.pv_start, s.pv_count, pieces, tol.parallel),
        search.p_lo, search.p_hi)

    def narrow(threads: bool) -> None:
        detection.THREADED_MIN_PAIRS = 1 if threads else 10**9
        detection.spare_core = lambda: threads
        detection._narrow_phase(pa, pb, search.x, s.topology, geo, search.reach, search.snap,
                                tol.parallel, tol.entrance, kern.no_skin())

    cases = {
        "narrow phase (slices on Python threads)": (lambda: narrow(False),
                                                    lambda: narrow(True)),
        "K fill": (lambda: ak.fill_bsr(*fill), lambda: ak.fill_bsr_threads(*fill, *rows)),
        "open-close loads (a cycle)": (lambda: ock.contact_loads(f0.copy(), *loads),
                                       lambda: ock.contact_loads_threads(f0.copy(), *loads,
                                                                         *blocks)),
        "relative displacements (a cycle)": (
            lambda: ak.relative_displacement(x, t.dmap, t.bi, t.bj, t.ti, t.tj),
            lambda: ak.relative_displacement_threads(x, t.dmap, t.bi, t.bj, t.ti, t.tj)),
        "contact T matrices": (lambda: tk.contact_matrices(pts, cen, t.bi, nd),
                               lambda: tk.contact_matrices_threads(pts, cen, t.bi, nd)),
    }

    def best(fn: Any) -> float:
        fn()
        out = np.inf
        for _ in range(5):
            t0 = time.perf_counter()
            fn()
            out = min(out, time.perf_counter() - t0)
        return 1e3 * out

    result: dict[str, Any] = {"blocks": system.n - 1, "contacts": len(cs),
                              "threads": numba.config.NUMBA_NUM_THREADS,
                              "layer": None, "kernels": {}}
    for name, (serial, threaded) in cases.items():
        result["kernels"][name] = {"serial_ms": best(serial), "threads_ms": best(threaded)}
    result["layer"] = numba.threading_layer()
    return result


def _threads(spacing: float, busy: bool) -> dict[str, Any]:
    """:func:`thread_kernels` in a fresh interpreter, beside a spinning process if `busy`."""
    spinner = (subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy
               else None)
    try:
        time.sleep(1.0 if busy else 0.0)
        load = os.getloadavg()[0]
        out = subprocess.run([sys.executable, "-c", _THREADS, str(spacing)],
                             capture_output=True, text=True, check=True,
                             env={**os.environ, "PYTHONPATH": str(h.ROOT)}, cwd=h.ROOT)
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    r = json.loads(out.stdout.strip().splitlines()[-1])
    r["busy"], r["load"] = busy, [load, os.getloadavg()[0]]
    return r


def run_work(out: Path, steps: int, baseline: str | None, quick: bool,
             clock: str = "cpu") -> dict[str, Any]:
    """Measure everything (this tree, and the baseline's when given); save work.json."""
    trees = {"after": h.ROOT}
    if baseline:
        trees["before"] = _baseline_tree(baseline)
    spacings = SPACINGS[:1] if quick else SPACINGS
    data: dict[str, Any] = {"steps": steps, "baseline": baseline, "quick": quick,
                            "clock": clock,
                            "rock": {k: [] for k in trees}, "pile": {},
                            "threads": []}
    for sp_ in spacings:
        for label, tree in trees.items():
            r = _run(tree, "rock", sp_, steps, 1, clock)
            r["spacing"] = sp_
            data["rock"][label].append(r)
            print(f"  rock {sp_} m {label}: {r['blocks']} blocks, {r['per_step_ms']:.0f} "
                  f"ms/step, around the solve {r['around_ms']:.1f} ms, "
                  f"{r['rss_peak_mb']:.0f} MB, load {r['load'][0]:.1f}", flush=True)
    pile_steps = 200 if quick else 10**6
    for label, tree in trees.items():
        r = _run(tree, "pile", 1000, pile_steps, 2, clock)
        data["pile"][label] = r
        print(f"  pile {label}: {r['steps']} steps, around the solve {r['around_ms']:.1f} "
              f"ms/step, load {r['load'][0]:.1f}", flush=True)
    for sp_ in spacings[:2]:
        for busy in (False, True):
            r = _threads(sp_, busy)
            data["threads"].append(r)
            print(f"  threads {r['blocks']} blocks {'busy' if busy else 'alone'}: " + ", ".join(
                f"{k} {v['serial_ms']:.2f}/{v['threads_ms']:.2f}"
                for k, v in r["kernels"].items()), flush=True)
    for label in trees:
        if len(data["rock"][label]) > 1:
            data.setdefault("exponents", {})[label] = _exponents(data["rock"][label])
    h.save_json(out, "work", data)
    return data


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_work",
                                description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=20, help="timed steps per rock mass")
    p.add_argument("--baseline", default=None, help="commit measured alongside (before)")
    p.add_argument("--quick", action="store_true", help="854 blocks and 200 pile steps")
    p.add_argument("--clock", choices=("cpu", "wall"), default="cpu",
                   help="time the phases by CPU time on one thread (default) or wall time")
    p.add_argument("--out", type=Path, default=h.RESULTS)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    run_work(args.out, args.steps, args.baseline, args.quick, args.clock)
    from benchmarks.__main__ import refresh_report

    cmd = "python -m benchmarks.bench_work " + " ".join(argv or sys.argv[1:])
    refresh_report(args.out, "work", cmd.strip(), time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


# --------------------------------------------------------------------------- report


def _f(x: float | None, digits: int = 1) -> str:
    """A number for a table ('–' for none)."""
    return "–" if x is None else f"{x:.{digits}f}"


def _phase_rows(data: dict[str, Any]) -> list[str]:
    """Markdown rows: each rock mass and phase, before / after and their ratio."""
    before = {r["spacing"]: r for r in data["rock"].get("before", [])}
    rows = []
    for a in data["rock"]["after"]:
        b = before.get(a["spacing"])
        pa, pb = a["phases_ms"], (b or {}).get("phases_ms", {})
        cells = []
        for p in PHASES:
            # the baseline timed the dashpots after the step inside its update
            old = (pb.get("update", 0.0) if p == "update" else pb.get(p)) if b else None
            new = pa.get(p, 0.0) + (pa.get("damping", 0.0) if p == "update" else 0.0)
            cells.append(f"{_f(old)} → {_f(new)}" if b else _f(new))
        cells.append(f"{_f(b['around_ms'])} → {_f(a['around_ms'])}" if b
                     else _f(a["around_ms"]))
        wall = (f"{_f(b['per_step_ms'], 0)} → " if b else "") + _f(a["per_step_ms"], 0)
        rss = (f"{b['rss_peak_mb']:.0f} → " if b else "") + f"{a['rss_peak_mb']:.0f}"
        rows.append(f"| {a['blocks']:,} | " + " | ".join(cells) +
                    f" | {wall} | {rss} | {a['load'][0]:.1f} |")
    return rows


def _target_rows(data: dict[str, Any]) -> list[str]:
    """Markdown rows: each target of the issue against what was measured."""
    rock = {r["blocks"]: r for r in data["rock"]["after"]}
    rows = []
    small = min(rock) if rock else None
    for p, limit in TARGETS.items():
        if small is None:
            break
        v = rock[small]["phases_ms"].get(p, 0.0)
        rows.append(f"| {p} at {small:,} blocks ≤ {limit:.0f} ms | {v:.1f} ms | "
                    f"{'met' if v <= limit else f'missed, ×{v / limit:.1f}'} |")
        for n, r in sorted(rock.items())[1:2]:
            ratio = r["phases_ms"].get(p, 0.0) / max(v, 1e-9)
            rows.append(f"| {p} at {n:,} ≤ {GROWTH_TARGET:.0f} × its {small:,}-block "
                        f"figure | ×{ratio:.1f} | {'met' if ratio <= GROWTH_TARGET else 'missed'}"
                        " |")
    if small is not None:
        d = rock[small]["phases_ms"].get("damping", 0.0)
        rows.append(f"| (the dashpots after an open-close step, `damping`, at {small:,} "
                    f"blocks: timed in `update` before) | {d:.1f} ms | – |")
    pile = data["pile"].get("after")
    if pile:
        v = pile["around_ms"]
        verdict = "met" if v <= PILE_TARGET_MS else f"missed, ×{v / PILE_TARGET_MS:.1f}"
        rows.append(f"| the pile of 1,000 outside the solve ≤ {PILE_TARGET_MS:.0f} ms | "
                    f"{v:.1f} ms | {verdict} |")
    for p, e in (data.get("exponents", {}).get("after") or {}).items():
        if p in ("detection", "assembly", "update", "damping"):
            rows.append(f"| exponent of {p} ≤ {EXPONENT_TARGET} | {e:.2f} | "
                        f"{'met' if e <= EXPONENT_TARGET else 'missed'} |")
    big = max(rock) if rock else None
    if big is not None:
        mb = rock[big]["rss_peak_mb"]
        rows.append(f"| peak RSS at {big:,} blocks < 2 GB | {mb:.0f} MB | "
                    f"{'met' if mb < 2048 else 'missed'} |")
    return rows


def report_part(data: dict[str, Any]) -> str:
    """Section 8 of REPORT.md from `results/work.json`."""
    steps = data["steps"]
    base = data.get("baseline")
    clock = data.get("clock", "wall")
    what = ("CPU ms of the stepping thread, numba and BLAS on one thread (on 2 cores shared "
            "with other work, the measure the load disturbs least; the per-step wall time "
            "is given beside it)" if clock == "cpu" else "wall ms")
    lines = ["## 8. The work around the contact solve (issue 39)", "",
             f"Per step, {what}, amortised over {steps} steps after the first (the rock "
             "masses) or over the pile's whole first second; "
             + (f"before (commit `{base}`) → after, measured one after the other in the same "
                "run" if base else "after only") +
             ". *around the solve* is detection + assembly + update + the dashpots after "
             "the step (`damping`, which the baseline timed inside `update`; the update "
             "column shows them together to compare like with like). The 2 cores are shared "
             "with other work: the load column is the one-minute load average when the run "
             "started. Made by `python -m benchmarks.bench_work` from `results/work.json`.", "",
             "| blocks | " + " | ".join(PHASES) + " | around the solve | per step (wall) | "
             "peak RSS MB | load |",
             "|" + "---|" * (len(PHASES) + 5)]
    lines += _phase_rows(data)
    for label in ("before", "after"):
        e = (data.get("exponents") or {}).get(label)
        if e:
            lines += ["", f"Growth exponents {label} (log time against log blocks): " +
                      ", ".join(f"{k} {v:.2f}" for k, v in e.items())]
    pile = data.get("pile") or {}
    if pile.get("after"):
        a, b = pile["after"], pile.get("before")
        lines += ["", f"The pile of 1,000 over {a['steps']:,} steps: around the solve "
                  + (f"{b['around_ms']:.1f} → " if b else "") + f"{a['around_ms']:.1f} ms a "
                  "step (" + ", ".join(f"{p} {a['phases_ms'].get(p, 0.0):.1f}" for p in AROUND)
                  + f"), the whole step {a['per_step_ms']:.1f} ms (load {a['load'][0]:.1f})."]
    skins = [(r["blocks"], r["skin"]) for r in data["rock"]["after"] if r.get("skin")]
    if pile.get("after", {}).get("skin"):
        skins.append(("pile", pile["after"]["skin"]))
    if skins:
        lines += ["", "The skin: " + "; ".join(
            f"{n if isinstance(n, str) else f'{n:,} blocks'}: margin "
            f"{1e3 * s['margin_m']:.2f} mm, {s['refreshes']} full detections, "
            f"{s['reuses']} searches on its lists" for n, s in skins) + "."]
    lines += ["", "| target (issue 39) | measured | |", "|---|---|---|"]
    lines += _target_rows(data)
    if data.get("threads"):
        lines += ["", "Numba's threads (ms, best of 5 calls, serial / threaded), on the state "
                  "after one step; *busy*: beside a process spinning on one core:", "",
                  "| blocks | contacts | beside | load | " +
                  " | ".join(data["threads"][0]["kernels"]) + " |",
                  "|" + "---|" * (4 + len(data["threads"][0]["kernels"]))]
        for r in data["threads"]:
            lines.append(f"| {r['blocks']:,} | {r['contacts']:,} | "
                         f"{'busy' if r['busy'] else 'alone'} | {r['load'][0]:.1f} | " +
                         " | ".join(f"{v['serial_ms']:.2f} / {v['threads_ms']:.2f}"
                                   for v in r["kernels"].values()) + " |")
        lines += ["", f"({data['threads'][0]['threads']} threads, numba's "
                  f"{data['threads'][0]['layer']} layer.)"]
    return "\n".join(lines)
