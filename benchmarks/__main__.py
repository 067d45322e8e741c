"""`python -m benchmarks [--full] [--only NAME ...] [--out DIR]`: run the benchmark sections
and regenerate REPORT.md, the charts and the CSVs.

Sections: accuracy (cases incline, wedge0, wedge10, fall, pushed can be named alone),
peers, stability (or one of its cases by name), trust (the stability map v2 of issue 12:
start states, the examples' own Δt and penalty, the jointed slope; or one of its scenes by
name), scaling, timestep (what limits Δt on a cut rock mass), savings, components (cutting
and contact detection on their own). The
quick default runs a small grid of each; `--full` runs everything. Sections not run keep
their previous numbers (stored in `results/<section>.json`), and the report says when they
were made.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import (
    bench_contact_solvers,
    bench_lmgc90,
    bench_work,
    cases,
    components,
    peers,
    scaling,
    stability,
    timestep,
    trust,
)
from benchmarks import harness as h

SECTIONS = ("accuracy", "peers", "stability", "trust", "scaling", "timestep", "savings",
            "components")
#: sections written by a benchmark of their own (`python -m benchmarks.bench_work`), shown
#: from their stored numbers
OWN_SECTIONS = ("work",)
#: scenes of the trust section that can be named alone
TRUST_NAMES = (*trust.MAP_SCENES, *trust.EXAMPLE_SWEEPS, "jointed_slope")


def _g(x: Any, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, float):
        return f"{x:.{digits}g}"
    return str(x)


def _table(header: list[str], rows: list[list[Any]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(_g(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def _esc(s: str) -> str:
    return s.replace("|", "\\|").replace("\n", " ")


# --------------------------------------------------------------------------- report parts


def accuracy_part(acc: dict[str, Any], charts: list[str]) -> str:
    lines = ["## 1. Speed against accuracy (analytic cases)", "",
             f"Grid: Δt ∈ {{{', '.join(f'{x:g}' for x in acc['grid']['dts'])}}} s, penalty k ∈ "
             f"{{{', '.join(f'{x:g}' for x in acc['grid']['penalties'])}}} N/m "
             f"(per vertex spring), open-close iterations {acc['grid']['oc']} plus "
             f"{acc['grid']['oc_extra']} at the stiffest k and the two largest Δt"
             + (f"; and Δt ∈ {{{', '.join(f'{x:g}' for x in acc['grid']['big_dts'])}}} s at "
                f"the stiffest k with a step displacement limit of "
                f"{', '.join(f'{x:.0%}' for x in acc['grid']['ratio'])} of the model size "
                "instead of the default 1 % (`analysis.max_displacement_ratio`)"
                if acc["grid"].get("big_dts") else "") + ". Error: "
             "incline / pushed — d(1 s); wedges — acceleration along the line of "
             "intersection (slope of v over 0.5–1 s); fall — static penetration W/(4k) after "
             "2 s. Wall time is the run without recording. Every point is in "
             "`results/accuracy.csv`.", ""]
    rows = []
    for case in dict.fromkeys(r["case"] for r in acc["rows"]):
        pts = [r for r in acc["rows"] if r["case"] == case]
        ok = [r for r in pts if r["status"] == "completed" and math.isfinite(r["rel_error"])]
        best = min(ok, key=lambda r: r["rel_error"]) if ok else None
        within = [r for r in ok if r["rel_error"] < 1e-2]
        cheap = min(within, key=lambda r: r["wall_s"]) if within else None
        fails = len(pts) - len(ok)
        rows.append([case, cases.CASES[case].quantity if case in cases.CASES else "",
                     _g(best["rel_error"]) if best else "–",
                     f"Δt {best['dt']:g}, k {best['penalty']:g}, {best['wall_s']:.2f} s"
                     if best else "–",
                     f"{cheap['wall_s']:.3f} s (Δt {cheap['dt']:g}, k {cheap['penalty']:g}, "
                     f"err {cheap['rel_error']:.1e})" if cheap else "none",
                     f"{fails} / {len(pts)}"])
    lines.append(_table(["case", "measured", "smallest error", "at", "cheapest run within 1 %",
                         "runs failed / total"], rows))
    lines.append("")
    for case in dict.fromkeys(r["case"] for r in acc["rows"]):
        pts = [r for r in acc["rows"] if r["case"] == case and r["status"] == "completed"
               and math.isfinite(r["rel_error"])]
        if not pts:
            continue
        front = h.pareto_front([r["wall_s"] for r in pts], [r["rel_error"] for r in pts])
        lines.append(f"**{case}** Pareto front: " + "; ".join(
            f"{pts[i]['wall_s']:.3g} s → {pts[i]['rel_error']:.2e} (Δt {pts[i]['dt']:g}, "
            f"k {pts[i]['penalty']:g}, oc {pts[i]['oc_iterations']})" for i in front))
        lines.append("")
    bad = [r for r in acc["rows"] if r["status"] != "completed"]
    if bad:
        lines.append("Runs that did not complete:")
        lines.append("")
        for r in bad:
            lines.append(f"- {r['case']} Δt {r['dt']:g}, k {r['penalty']:g}, oc "
                         f"{r['oc_iterations']}: {r['status']} — {_esc(r['message'])}")
        lines.append("")
    lines += [f"![{c}](results/{c})" for c in charts]
    return "\n".join(lines)


def peers_part(pe: dict[str, Any] | None, acc: dict[str, Any] | None) -> str:
    lines = ["## 2. Other engines on the same scenes", ""]
    if pe is None:
        return "\n".join(lines + ["(section not run)"])
    for eng, note in pe["notes"].items():
        lines.append(f"- **{eng}**: {note}")
    lines.append("")
    rows = [[r["engine"], r["dt"], _g(r.get("penalty")), r["steps"], f"{r['wall_s']:.4f}",
             f"{r['value']:.6f}", f"{r['rel_error']:.2e}", r.get("note", "")]
            for r in pe["rows"]]
    if acc:
        inc = [r for r in acc["rows"] if r["case"] == "incline" and r["status"] == "completed"
               and r["oc_iterations"] in acc["grid"]["oc"]]
        rows += [["PolyDDA", r["dt"], r["penalty"], r["steps"], f"{r['wall_s']:.4f}",
                  f"{r['value']:.6f}", f"{r['rel_error']:.2e}",
                  "rigid, this repo" + (
                      f"; step limit {r['max_displacement_ratio']:.0%} of the model size"
                      if r.get("max_displacement_ratio", 0.01) != 0.01 else "")]
                 for r in sorted(inc, key=lambda r: (r["penalty"], -r["dt"]))]
    lines.append("Incline cube (φ = 20°, exact d(1 s) = 0.906407 m), re-run on this machine; "
                 "wall time is the stepping loop for the peers and the whole `run()` "
                 "(setup, detection, solve, no recording) for PolyDDA. MuJoCo: tilted gravity "
                 "(4.905, 0, −8.495709), default Newton solver and pyramidal cone; LMGC90: "
                 "tilted slab, non-smooth contact dynamics (IQS_CLB); YADE: tilted slab, "
                 "polyhedra with the volumetric penalty law (stiffness through `young`).")
    lines.append("")
    lines.append(_table(["engine", "Δt (s)", "stiffness", "steps", "wall (s)", "d(1 s) m",
                         "rel. error", "note"], rows))
    lines.append("")
    if pe.get("piles"):
        lines.append("MuJoCo on the shared piles, re-run here (1 ms, 1 s, loop only): " + "; ".join(
            f"N = {r['N']}: {r['wall_s']:.2f} s" for r in pe["piles"]) + ".")
        lines.append("")
    lines += ["### Reported, not re-run (from benchmarks/scenes/README.md, verbatim)", "",
              peers.reported_table()]
    return "\n".join(lines)


def stability_part(st: dict[str, Any], chart: str) -> tuple[str, list[tuple[str, str]]]:
    table = stability.summarize(st)
    lines = ["## 3. Stability map", "",
             "Each case is run over a Δt sweep at its reference penalty and a penalty sweep "
             "at its reference Δt. **pass** = completed, within the case's tolerance and the "
             "mechanical energy (kinetic + elastic + contact − work of gravity and loads, "
             f"from the recorded frames) never rose more than {st['energy_tol']:.0%} of the "
             "reference energy (initial KE + m g × the case's height) above its start; "
             "**wrong** = completed but outside tolerance or energy grew, and said nothing; "
             f"**{stability.WARNED}** = the same, but the run's summary warned (soft penalty); "
             "**failed (clear "
             "status)** = status `failed` with a message; **blew up** = non-finite or no "
             f"message; **{stability.STOPPED}** = cancelled after {st.get('wall_cap', 0):g} s of "
             "wall time (5× that for pile100; energy still checked). Requested Δt: the "
             "engine cuts Δt itself (steps taken are in the table, mean Δt in the CSV).",
             ""]
    rows = []
    for t in table:
        rows.append([t["case"], _esc(t["criterion"]), ", ".join(f"{x:g}" for x in t["dt_tested"]),
                     _g(t["largest_dt_pass"]), ", ".join(f"{x:g}" for x in t["k_tested"]),
                     f"{t['k_pass'][0]:g} – {t['k_pass'][1]:g}" if t["k_pass"] else "none",
                     f"{t['wrong']} / {t.get('warned', 0)} / {t['failed_clean']} / "
                     f"{t['blew_up']} / {t['stopped']} of {t['runs']}"])
    lines.append(_table(["case", "tolerance", "Δt tested", "largest Δt passing",
                         "k tested", "k passing (any Δt tested)",
                         "wrong / warned / failed clean / blew up / stopped"], rows))
    lines += ["", f"![stability](results/{chart})", "", "Every run:", ""]
    lines.append(_table(["case", "sweep", "Δt", "k", "verdict", "detail", "energy growth",
                         "balance residual", "steps", "wall (s)"],
                        [[r["case"], r["sweep"], r["dt"], r["penalty"], r["verdict"],
                          _esc(r["detail"]), r["energy_growth"], r["energy_residual"],
                          r["steps"], f"{r['wall_s']:.2f}"] for r in st["rows"]]))
    failures = []
    for t in table:
        for r in t["bad"]:
            repro = ("python -c \"from benchmarks.stability import STAB_CASES, run_one; "
                     f"run_one(STAB_CASES['{r['case']}'], {r['dt']!r}, {r['penalty']!r}, 'x')\"")
            why = r["message"] or r["detail"]
            if r["message"] and r["detail"]:
                why += f" ({r['detail']})"
            if not r["energy_ok"] and math.isfinite(r["energy_growth"]):
                why += f"; mechanical energy grew by {r['energy_growth']:.3g} × reference"
            kind = {"wrong": "silent", "blew up": "silent", stability.STOPPED: "slow",
                    stability.WARNED: "warned"}.get(r["verdict"], "clean")
            failures.append((kind, f"**{r['case']}** ({t['title']}), Δt {r['dt']:g}, k "
                                   f"{r['penalty']:g}: {r['verdict']} after {r['steps']} steps "
                                   f"— {_esc(why)}. Reproduce: `{repro}`"))
    return "\n".join(lines), failures


def trust_part(tr: dict[str, Any], chart: str) -> tuple[str, list[tuple[str, str]]]:
    """Section 3b: the stability map v2 (issue 12)."""
    rows = tr["rows"]
    lines = ["## 3b. Stability map v2: the scenes users build, started as real models start",
             "", _esc(trust.__doc__.split("\n\n", 1)[1].replace("\n", " ")).strip(), "",
             f"Map runs simulate 3,000 steps, between 0.1 and 0.5 s; wall cap "
             f"{tr['wall_cap']:g} s per run. Energy created: the largest rise of kinetic + "
             "stored − work of gravity and loads above its start (from the recorded frames), "
             "as a fraction of gravity's largest work in the run.", ""]
    table = []
    for case in dict.fromkeys(r["case"] for r in rows):
        rs = [r for r in rows if r["case"] == case]
        count = {v: sum(r["verdict"] == v for r in rs) for v in trust.COLOURS}
        worst = max((r["created_ratio"] for r in rs if math.isfinite(r["created_ratio"])),
                    default=float("nan"))
        table.append([case, _esc(tr["scenes"].get(case, "")), len(rs), count[trust.PASS],
                      count[trust.FAILED], count[trust.STOPPED],
                      count[trust.WRONG] + count[trust.BLEW_UP], _g(worst)])
    lines.append(_table(["scene", "what", "runs", "pass", "failed (clear status)",
                         "stopped", "silent failures", "largest energy created"], table))
    lines += ["", f"![trust](results/{chart})", "", "Every run:", ""]
    lines.append(_table(
        ["scene", "start / sweep", "Δt (s)", "k (N/m)", "verdict", "detail", "created",
         "steps", "wall (s)"],
        [[r["case"], r.get("start", r.get("sweep", "")), r["dt"], r["penalty"], r["verdict"],
          _esc(r["detail"] + (f" — {r['message']}" if r["message"] else "")),
          r["created_ratio"], r["steps"], f"{r['wall_s']:.2f}"] for r in rows]))
    failures = []
    for r in rows:
        if r["verdict"] == trust.PASS:
            continue
        if r["group"] == "map":
            repro = ("python -c \"from benchmarks.trust import MAP_SCENES, run_map_one; "
                     f"print(run_map_one(MAP_SCENES['{r['case']}'], {r['dt']!r}, "
                     f"{r['penalty']!r}, '{r['start']}'))\"")
        elif r["group"] == "example":
            repro = ("python -c \"from benchmarks.trust import EXAMPLE_SWEEPS, "
                     f"run_example_one; print(run_example_one(EXAMPLE_SWEEPS['{r['case']}'], "
                     f"{r['dt_factor']!r}, {r['k_factor']!r}))\"")
        else:
            repro = "python -m benchmarks --only jointed_slope"
        kind = {trust.WRONG: "silent", trust.BLEW_UP: "silent", trust.STOPPED: "slow"}.get(
            r["verdict"], "clean")
        failures.append((kind, f"**{r['case']}** ({r.get('start', r.get('sweep', ''))}), "
                               f"Δt {r['dt']:g}, k {r['penalty']:g}: {r['verdict']} after "
                               f"{r['steps']} steps — {_esc(r['message'] or r['detail'])}. "
                               f"Reproduce: `{repro}`"))
    return "\n".join(lines), failures


def scaling_part(sc: dict[str, Any], chart: str, pe: dict[str, Any] | None,
                 st: dict[str, Any] | None = None) -> tuple[str, list[tuple[str, str]]]:
    steps = sc["pile_steps"]
    whole_second = all(v is None for v in steps.values())
    lines = ["## 4. Scaling with block count", "",
             "After 2 untimed warm-up steps, shared piles at Δt ≤ 1 ms, k = 1e10 N/m, "
             + ("each stepped through one whole simulated second (the fall, the impacts and "
                "the settling; the engine cuts Δt where it must)" if whole_second else
                f"stepped {steps} steps (the first steps of the fall: blocks start apart, so "
                "contacts are few — the per simulated second figure extrapolates those "
                "steps to 1 s and is a lower bound for a settling pile)")
             + "; cut rock masses (10 m cube, three joint sets, on a "
             "fixed base, every block touching its neighbours) stepped a few steps. Peak "
             "memory: tracemalloc peak of the Python allocations in a separate short run "
             "(setup and a few steps; tracemalloc would slow the timed steps), and the "
             "process's peak RSS so far.", ""]
    rows = []
    for r in sc["rows"]:
        rows.append([r["scene"], r["N"], r["unknowns"], r["steps"], f"{r['contacts_mean']:.0f}",
                     f"{r['per_step_s'] * 1e3:.1f}",
                     *[f"{r[f't_{p}'] * 1e3:.1f}" for p in scaling.PHASES],
                     f"{r['simulated'] / max(r['steps'], 1):.2g}",
                     _g(r["per_sim_second_s"]), f"{r['tracemalloc_peak_mb']:.0f}",
                     f"{r['rss_peak_mb']:.0f}", r["status"]])
    lines.append(_table(["scene", "blocks", "unknowns", "steps", "contacts", "ms/step",
                         *[f"{p} ms" for p in scaling.PHASES], "mean Δt (s)",
                         "wall per simulated s (s)", "tracemalloc MB", "RSS MB", "status"], rows))
    lines += ["", "Growth exponents (least-squares slope of log time against log blocks):", ""]
    keys = [*scaling.PHASES, "total per step", "per simulated second", "contacts"]
    lines.append(_table(["scene", *keys], [[s, *[f"{e[k]:.2f}" for k in keys]]
                                           for s, e in sc["exponents"].items()]))
    if pe and pe.get("piles"):
        lines += ["", "Against MuJoCo re-run here on the same piles (1 s at 1 ms, loop only): "
                  "PolyDDA extrapolated from its measured early steps, and measured over the "
                  "whole 1 s where a run of it exists (pile100 of the stability map, k = 1e10; "
                  "with `--full` every pile runs its whole second here):", ""]
        pr = {r["N"]: r for r in sc["rows"] if r["scene"] == "pile"}
        whole = {n: r["wall_s"] for n, r in pr.items()
                 if r["simulated"] >= 1.0 - 1e-9 and r["status"] == "completed"}
        for r in (st or {}).get("rows", []):
            if (r["case"] == "pile100" and r["sweep"] == "dt" and r["verdict"] == "pass"
                    and 100 not in whole):
                whole[100] = r["wall_s"]
        lines.append(_table(["N", "MuJoCo 1 s (s)", "PolyDDA per simulated s (s, extrapolated)",
                             "ratio", "PolyDDA whole 1 s (s, measured)", "ratio"],
                            [[r["N"], f"{r['wall_s']:.2f}",
                              _g(pr[r["N"]]["per_sim_second_s"]) if r["N"] in pr else "–",
                              _g(pr[r["N"]]["per_sim_second_s"] / r["wall_s"])
                              if r["N"] in pr else "–",
                              _g(whole[r["N"]]) if r["N"] in whole else "–",
                              _g(whole[r["N"]] / r["wall_s"]) if r["N"] in whole else "–"]
                             for r in pe["piles"]]))
    lines += ["", f"![scaling](results/{chart})"]
    failures = []
    for r in sc["rows"]:
        if r["status"] != "completed":
            failures.append(("clean",
                f"**{r['scene']} N = {r['N']}** stops after {r['steps']} steps: "
                f"{_esc(r['message'])}. Reproduce: `python -c \"from benchmarks.scaling import "
                f"time_steps; from benchmarks.pile import *; print(time_steps("
                + (f"pile_model({r['N']})" if r["scene"] == "pile"
                   else f"rock_mass_model({r['spacing']})") + f", {r['steps'] + 1}))\"`"))
    return "\n".join(lines), failures


def savings_part(sv: dict[str, Any]) -> str:
    lines = ["## 5. No more than a scene needs", ""]
    rows = []
    for r in sv["rows"]:
        extra = []
        if "incline_rel_error" in r:
            extra.append(f"incline error {_g(r['incline_rel_error'])}")
        if "max_penetration" in r:
            extra.append(f"max penetration {_g(r['max_penetration'])} m")
        rows.append([r["group"], r["variant"], r["unknowns"], r["steps"],
                     _g(r["contacts_mean"]), f"{r['per_step_s'] * 1e3:.2f}",
                     f"{r['wall_s']:.2f}", f"{r['t_detection'] * 1e3:.2f}",
                     f"{r['t_assembly'] * 1e3:.2f}", r["status"], "; ".join(extra)])
    lines.append(_table(["option", "variant", "unknowns", "steps", "contacts", "ms/step",
                         "wall (s)", "detection ms", "assembly ms", "status", "result"], rows))
    lines += ["", "Savings (heavier variant ÷ lighter one, wall time of the same steps or "
              "the same simulated time):", ""]
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in sv["rows"]:
        groups.setdefault(r["group"], []).append(r)
    for g, rs in groups.items():
        if g == "time step":
            for a, b in zip(rs[0::2], rs[1::2], strict=False):
                lines.append(f"- {g}: *{b['variant']}* takes {b['steps']} steps in "
                             f"{b['wall_s']:.2f} s, *{a['variant']}* {a['steps']} steps in "
                             f"{a['wall_s']:.2f} s → ×{b['wall_s'] / max(a['wall_s'], 1e-9):.2f}"
                             f" (max penetration {_g(b.get('max_penetration'))} vs "
                             f"{_g(a.get('max_penetration'))} m)")
        elif g == "search distance":
            for a, b in zip(rs[0::2], rs[1::2], strict=False):
                if b["status"] != "completed":
                    lines.append(f"- {g}: *{b['variant']}* does not run: {_esc(b['message'])}"
                                 f" (*{a['variant']}*: {a['per_step_s'] * 1e3:.1f} ms/step, "
                                 f"{a['contacts_mean']:.0f} contacts)")
                    continue
                lines.append(f"- {g}: *{b['variant']}* {b['per_step_s'] * 1e3:.1f} ms/step, "
                             f"{b['contacts_mean']:.0f} contacts vs *{a['variant']}* "
                             f"{a['per_step_s'] * 1e3:.1f} ms/step, {a['contacts_mean']:.0f} "
                             f"contacts → ×{b['per_step_s'] / max(a['per_step_s'], 1e-12):.2f}")
        else:
            a, b = rs[0], rs[1]
            lines.append(f"- {g}: *{b['variant']}* ({b['unknowns']} unknowns) "
                         f"{b['per_step_s'] * 1e3:.2f} ms/step vs *{a['variant']}* "
                         f"({a['unknowns']} unknowns) {a['per_step_s'] * 1e3:.2f} ms/step → "
                         f"×{b['per_step_s'] / max(a['per_step_s'], 1e-12):.2f}")
    return "\n".join(lines)


def savings_failures(sv: dict[str, Any]) -> list[tuple[str, str]]:
    """Savings runs that stopped, with reproducers."""
    out = []
    for r in sv["rows"]:
        if r["status"] == "completed" or r["group"] != "search distance":
            continue
        scene = ("rock_mass_model(3.4)" if r["variant"].startswith("rock")
                 else "pile_model(100)")
        adaptive = "adaptive" in r["variant"]
        out.append(("clean", f"**{r['variant']}** stops after {r['steps']} steps: "
                    f"{_esc(r['message'])}. Reproduce: `python -c \"from benchmarks.pile "
                    "import *; from benchmarks.scaling import time_steps; print(time_steps("
                    f"{scene}, {r['steps'] + 1}, adaptive_search={adaptive}))\"`"))
    return out


def write_report(out: Path, report: Path, meta: dict[str, Any]) -> None:
    """Assemble REPORT.md from whatever sections are stored in `out`."""
    acc = h.load_json(out, "accuracy")
    pe = h.load_json(out, "peers")
    st = h.load_json(out, "stability")
    tr = h.load_json(out, "trust")
    sc = h.load_json(out, "scaling")
    sv = h.load_json(out, "savings")
    m = meta["machine"]
    rel = os.path.relpath(out, report.parent)
    parts = [
        "# PolyDDA benchmarks: speed against accuracy, stability, scaling", "",
        "Generated by `benchmarks/__main__.py`; every number below comes from the run "
        "that wrote this file (or from the earlier run that stored the section, see "
        "*sections* below). Reproduce:", "",
        "```bash", "bash benchmarks/setup_peers.sh   # optional: MuJoCo, LMGC90, YADE",
        meta["command"], "```", "",
        f"- machine: {m['nproc']} cores, {m['cpu']}, {m['platform']}",
        f"- load average before / after: {', '.join(f'{x:.2f}' for x in meta['load_before'])}"
        f" / {', '.join(f'{x:.2f}' for x in meta['load_after'])} (the 2 cores are shared "
        "with other work; wall times carry that noise)",
        f"- python {m['python']}, numpy {m['numpy']}, scipy {m['scipy']}, polydda "
        f"{m['engine']} (commit {m['commit'] or 'unknown'})",
        f"- mode: {'full' if meta['full'] else 'quick'}; this invocation ran "
        f"{', '.join(meta['ran'])} in {meta['wall']:.0f} s at {meta['when']}",
        "- sections: " + "; ".join(
            f"{s}: {meta['stamps'].get(s, 'not run')}" for s in (*SECTIONS, *OWN_SECTIONS)),
        "",
    ]
    failures: list[tuple[str, str]] = []
    if acc:
        charts = cases.plot_accuracy(out, acc, pe)
        parts += [accuracy_part(acc, charts), ""]
    else:
        parts += ["## 1. Speed against accuracy", "", "(section not run)", ""]
    parts += [peers_part(pe, acc), ""]
    if st:
        text, fl = stability_part(st, stability.plot_stability(out, st))
        parts += [text, ""]
        failures += fl
    else:
        parts += ["## 3. Stability map", "", "(section not run)", ""]
    if tr:
        text, fl = trust_part(tr, trust.plot_trust(out, tr))
        parts += [text, ""]
        failures += fl
    else:
        parts += ["## 3b. Stability map v2", "", "(section not run)", ""]
    if sc:
        text, fl = scaling_part(sc, scaling.plot_scaling(out, sc, pe), pe, st)
        parts += [text, ""]
        failures += fl
    else:
        parts += ["## 4. Scaling", "", "(section not run)", ""]
    ts = h.load_json(out, "timestep")
    parts += [timestep.timestep_part(ts) if ts else
              "## 4b. Why Δt is what it is on a cut rock mass\n\n(section not run)", ""]
    parts += [savings_part(sv) if sv else "## 5. No more than a scene needs\n\n(section not run)",
              ""]
    cp = h.load_json(out, "components")
    parts += [components.components_part(cp) if cp else
              "## 6. Cutting and contact detection on their own\n\n(section not run)", ""]
    cs = h.load_json(out, "contact_solvers")
    maps = {solver: h.load_json(out, f"trust_{solver}") for solver in ("complementarity",
                                                                         "newton")}
    parts += [bench_contact_solvers.report_part(cs, "contact_solvers.png",
                                                {k: v for k, v in maps.items() if v})
              if cs else
              "## 7. Contact solvers side by side\n\n(section not run)", ""]
    lm = h.load_json(out, "lmgc90")
    parts += [bench_lmgc90.report_part(lm) if lm else
              "## 7b. LMGC90 on the same cut rock mass\n\n(section not run)", ""]
    wk = h.load_json(out, "work")
    parts += [bench_work.report_part(wk) if wk else
              "## 8. The work around the contact solve\n\n(section not run)", ""]
    if sv:
        failures += savings_failures(sv)
    parts += ["## Failures found", "",
              "Every run that did not pass, each with a reproducer (run from the repository "
              "root).", ""]
    for kind, title in (("silent", "Completed but wrong, energy grew, or raised instead of "
                                   "returning a status (silent failures)"),
                        ("warned", "Completed outside tolerance, with a warning in the "
                                   "run's summary"),
                        ("clean", "Stopped with status `failed` and a message (clean stops: "
                                  "the method's limits at these settings, or a scene it "
                                  "cannot finish)"),
                        ("slow", "Stopped at the wall-time cap")):
        items = [f for k, f in failures if k == kind]
        parts += [f"### {title}", ""]
        parts += [f"{i}. {f}" for i, f in enumerate(items, 1)] or ["none"]
        parts.append("")
    text = "\n".join(parts) + "\n"
    if rel != "results":
        text = text.replace("](results/", f"]({rel}/")
    report.write_text(text)


def refresh_report(out: Path, section: str, command: str, wall: float) -> None:
    """Write REPORT.md again from the stored sections after `section` was measured by
    `command` (a benchmark of its own) in `wall` s; the header keeps the last
    `python -m benchmarks` invocation."""
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    stored = h.load_json(out, "meta") or {}
    stamps = stored.get("stamps", {})
    stamps[section] = f"`{command}` ({wall:.0f} s), {now}"
    last = stored.get("last") or {"load_before": list(os.getloadavg()),
                                  "load_after": list(os.getloadavg()), "full": False,
                                  "ran": [], "wall": 0.0, "when": now,
                                  "command": "python -m benchmarks"}
    last["stamps"] = stamps
    h.save_json(out, "meta", {"stamps": stamps, "last": last})
    report = (Path(__file__).resolve().parent / "REPORT.md" if out == h.RESULTS
              else out / "REPORT.md")
    write_report(out, report, {**last, "machine": h.machine_info()})
    print(f"wrote {report}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n")[0])
    p.add_argument("--full", action="store_true", help="run the full grids (long)")
    p.add_argument("--only", nargs="+", default=None,
                   help="sections or case names: " + ", ".join(
                       [*SECTIONS, *cases.CASES, *stability.STAB_CASES, *TRUST_NAMES]))
    p.add_argument("--out", type=Path, default=h.RESULTS, help="results directory")
    p.add_argument("--report", type=Path, default=None, help="report path "
                   "(default benchmarks/REPORT.md, or OUT/REPORT.md with --out)")
    p.add_argument("--dts", type=float, nargs="+", default=None, help="accuracy Δt grid")
    p.add_argument("--penalties", type=float, nargs="+", default=None, help="accuracy k grid")
    args = p.parse_args(argv)
    out: Path = args.out.resolve()
    report = args.report or (out / "REPORT.md" if args.out != h.RESULTS
                             else Path(__file__).resolve().parent / "REPORT.md")
    only = args.only or list(SECTIONS)
    acc_cases = [o for o in only if o in cases.CASES]
    stab_cases = [o for o in only if o in stability.STAB_CASES and o not in cases.CASES]
    trust_names = [o for o in only if o in TRUST_NAMES and o not in stability.STAB_CASES]
    unknown = [o for o in only if o not in SECTIONS and o not in cases.CASES
               and o not in stability.STAB_CASES and o not in TRUST_NAMES]
    if unknown:
        p.error(f"unknown section or case: {', '.join(unknown)}")
    out.mkdir(parents=True, exist_ok=True)
    stamps = (h.load_json(out, "meta") or {}).get("stamps", {})
    t0 = time.perf_counter()
    load_before = list(os.getloadavg())
    ran = []
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    mode = "full" if args.full else "quick"
    if "accuracy" in only or acc_cases:
        grid = {"dts": args.dts, "penalties": args.penalties}
        if args.dts or args.penalties:
            grid.update({"oc_extra": [], "oc": [20], "big_dts": []})
        cases.run_accuracy(out, args.full, acc_cases or None, grid)
        ran.append("accuracy" + (f" ({', '.join(acc_cases)})" if acc_cases else ""))
        stamps["accuracy"] = f"{mode}, {now}"
    if "peers" in only:
        peers.run_peers(out, args.full)
        ran.append("peers")
        stamps["peers"] = f"{mode}, {now}"
    if "stability" in only or stab_cases:
        stability.run_stability(out, args.full, stab_cases or None)
        ran.append("stability" + (f" ({', '.join(stab_cases)})" if stab_cases else ""))
        stamps["stability"] = f"{mode}, {now}"
    if "trust" in only or trust_names:
        trust.run_trust(out, args.full, trust_names or None)
        ran.append("trust" + (f" ({', '.join(trust_names)})" if trust_names else ""))
        stamps["trust"] = f"{mode}, {now}"
    if "scaling" in only:
        print("[scaling]", flush=True)
        scaling.run_scaling(out, args.full)
        ran.append("scaling")
        stamps["scaling"] = f"{mode}, {now}"
    if "timestep" in only:
        print("[timestep]", flush=True)
        timestep.run_timestep(out, args.full)
        ran.append("timestep")
        stamps["timestep"] = f"{mode}, {now}"
    if "savings" in only:
        print("[savings]", flush=True)
        scaling.run_savings(out, args.full)
        ran.append("savings")
        stamps["savings"] = f"{mode}, {now}"
    if "components" in only:
        print("[components]", flush=True)
        components.run_components(out, args.full)
        ran.append("components")
        stamps["components"] = f"{mode}, {now}"
    cmd = "python -m benchmarks" + (" " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
                                    if (argv or sys.argv[1:]) else "")
    meta = {"machine": h.machine_info(), "load_before": load_before,
            "load_after": list(os.getloadavg()), "full": args.full, "ran": ran,
            "wall": time.perf_counter() - t0, "when": now, "command": cmd, "stamps": stamps}
    h.save_json(out, "meta", {"stamps": stamps, "last": {k: v for k, v in meta.items()
                                                          if k != "machine"}})
    write_report(out, report, meta)
    print(f"wrote {report} ({meta['wall']:.0f} s)")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
