"""The printable report of a finished job or of a local result file: it opens with its
conclusion (stable or not, the factor of safety and how it was found, the blocks that moved
more than a threshold and by how much, the warnings), then the moving blocks (fixed blocks and
sub-threshold noise left out), the analyses' details, the plots, and the scene as given in an
appendix. Every number with its unit and a sensible rounding (service.readable).

:func:`report_html` is the service's page (`GET /jobs/{id}/report`); :func:`report_page`
makes the same from :class:`ReportParts` gathered anywhere (`polydda report RESULT.h5`).
"""

from __future__ import annotations

import hashlib
import json
import platform
from collections.abc import Iterable
from dataclasses import dataclass, field
from html import escape
from pathlib import Path
from typing import Any

from service import readable as rd
from service.api.pages import VERSION, _bar, _page, job_links
from service.documents import AT_REST_SPEED, MOVED_THRESHOLD, fos_bracket, movement
from service.jobs.processes import PROCESSES
from service.jobs.store import JobRecord

#: rows of the moving blocks' table (the rest are counted)
MAX_ROWS = 200
#: the raw scene shown in the appendix up to this many characters
MAX_SCENE_CHARS = 200_000


@dataclass
class ReportParts:
    """What a report is made of. `documents`: summary.json, fos.json, seismic.json,
    blocks.json as dicts (those there are); `plots`: (name, src) of the result's figures;
    `figures`: caption -> src after the FS; `kinematics`, `sweep`: the parts
    service.api.results makes; `snapshot`: the src of the last step's image."""

    title: str
    process_title: str
    header: list[tuple[str, Any]]
    scene_text: str
    documents: dict[str, dict[str, Any]] = field(default_factory=dict)
    plots: list[tuple[str, str]] = field(default_factory=list)
    result_meta: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, str] = field(default_factory=dict)
    kinematics: dict[str, Any] | None = None
    snapshot: str | None = None
    sweep: dict[str, Any] | None = None
    threshold: float = MOVED_THRESHOLD


# --------------------------------------------------------------------------- helpers


def _cell(x: Any) -> str:
    return escape(rd.value(x))


def _table(rows: Iterable[Iterable[Any]], head: Iterable[str] = ()) -> str:
    h = "".join(f"<th>{escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table>{f'<tr>{h}</tr>' if h else ''}{body}</table>"


def _figure(src: str, caption: str, ident: str = "") -> str:
    attr = f" id='{ident}'" if ident else ""
    return (f'<figure{attr}><img src="{escape(src)}" alt="{escape(caption)}">'
            f"<figcaption class='muted'>{escape(caption)}</figcaption></figure>")


def _norm(d: list[float]) -> float:
    return float(sum(x * x for x in d) ** 0.5)


# --------------------------------------------------------------------------- conclusion


def _run_sentences(summary: dict[str, Any], meta: dict[str, Any], threshold: float
                   ) -> list[str]:
    """What a run found: how it ended, which free blocks moved more than `threshold` and
    whether they came to rest."""
    status = summary.get("status", "?")
    t = summary.get("simulated_time")
    out = [f"The run {escape(str(status))} after {summary.get('steps', 0):,} steps"
           + (f" ({rd.seconds(t)} simulated)." if isinstance(t, float) else ".")]
    m = movement(summary.get("blocks") or [], meta.get("fixed") or [], threshold)
    limit = rd.length(threshold)
    moved = m["moved"]
    if not moved:
        free = m["still"]
        out.append(f"<b>No free block moved more than {limit}</b>"
                   + (f" (the largest, {escape(m['still_max_name'])}, moved "
                      f"{rd.length(m['still_max'])})" if free else "")
                   + ": the blocks are stable under the scene's loads over the time "
                     "simulated.")
        return out
    speeds = {b.get("name"): _norm((b.get("velocity") or [0.0] * 3)[:3])
              for b in summary.get("blocks") or []}
    moving = [b for b in moved if speeds.get(b["name"], 0.0) > AT_REST_SPEED]
    named = ", ".join(f"{escape(b['name'])} {rd.length(b['magnitude'])}" for b in moved[:5])
    more = f" and {len(moved) - 5} more" if len(moved) > 5 else ""
    out.append(f"<b>{rd.plural(len(moved), 'free block')} moved more than {limit}</b>: "
               f"{named}{more}.")
    if moving:
        out.append(f"<b>{rd.plural(len(moving), 'block')} still moving at the end</b> (faster "
                   f"than {AT_REST_SPEED * 1e3:g} mm/s): not stable.")
    else:
        out.append("They came to rest by the end (every free block slower than "
                   f"{AT_REST_SPEED * 1e3:g} mm/s).")
    if m["still"]:
        out.append(f"{rd.plural(m['still'], 'other free block')} moved less than {limit}.")
    return out


def _fos_sentences(fos: dict[str, Any]) -> list[str]:
    fs = fos.get("factor_of_safety")
    runs = fos.get("runs") or []
    if not isinstance(fs, float):
        return [f"No factor of safety: {escape(str(fos.get('message') or fos.get('status')))}."]
    bracket = fos_bracket(runs)
    how = (f"by strength reduction (bisection on tan φ / F over "
           f"{rd.plural(len(runs), 'trial run')}"
           + (f": holds at F = {bracket[0]:.4g}, fails at F = {bracket[1]:.4g})"
              if bracket else ")"))
    verdict = (f"stable, with a margin of {100 * (fs - 1):.0f} % on the joints' strength"
               if fs >= 1.0 else "the blocks fail under the joints' present strength")
    # a bound: no trial failed up to the largest factor (≥), or every one down to the least
    sign = {"lower": "≥", "upper": "<"}.get(fos.get("bound") or "", "=")
    out = [f"<b>Factor of safety FS {sign} {fs:.2f}</b>, found {how}: {verdict}."]
    if fos.get("message"):
        out.append(escape(str(fos["message"])) + ".")
    return out


def _seismic_sentences(doc: dict[str, Any]) -> list[str]:
    kh = doc.get("critical_seismic_coefficient")
    runs = doc.get("runs") or []
    if not isinstance(kh, float):
        return [f"No critical seismic coefficient: {escape(str(doc.get('message')))}."]
    bracket = fos_bracket(runs, key="kh")
    sign = {"lower": "≥", "upper": "<"}.get(doc.get("bound") or "", "=")
    return [f"<b>Critical seismic coefficient kh {sign} {kh:.3f}</b> (horizontal force towards "
            f"{doc.get('azimuth', 0):03.0f}°, kv {doc.get('kv', 0):g}), found by bisection over "
            f"{rd.plural(len(runs), 'trial run')}"
            + (f" (holds at {bracket[0]:.4g}, fails at {bracket[1]:.4g})" if bracket else "")
            + f": a horizontal acceleration of {kh:.3f} g makes the watched blocks fail."]


def _le_sentences(le: dict[str, Any]) -> list[str]:
    fs = le.get("factor_of_safety")
    planes = ", ".join(le.get("sliding_planes") or [])
    value = ("unbounded (nothing drives the block)" if fs is None else f"{fs:.2f}")
    return [f"<b>Limit equilibrium FS = {escape(value)}</b> of {escape(str(le.get('block')))}"
            f" by the vector method: {escape(str(le.get('mode', '')))}"
            + (f" on {escape(planes)}" if planes else "") + "."]


def _sweep_sentences(sweep: dict[str, Any]) -> list[str]:
    out = []
    for label, a in sweep.get("aggregates", {}).items():
        pof = a.get("probability_of_failure")
        if pof is None or not a.get("n"):
            continue
        lo, hi = a.get("pof_interval_95") or (0.0, 0.0)
        out.append(f"<b>Probability of failure {100 * pof:.1f} %</b> ({escape(label)}; 95 % "
                   f"interval {100 * lo:.1f} to {100 * hi:.1f} %) over "
                   f"{rd.plural(a['n'], 'realisation')}, mean FS {rd.number(a['mean'], 3)}.")
    return out


def _kinematic_sentences(part: dict[str, Any] | None) -> list[str]:
    if not part or "doc" not in part:
        return []
    adm = part["doc"]["admissible"]
    found = [f"{title} on {', '.join('/'.join(x) if isinstance(x, list) else x for x in adm[k])}"
             for k, title, _ in _MODES if adm[k]]
    return ["Kinematic screening: " + ("; ".join(escape(f) for f in found) + " admissible."
                                       if found else "no failure mode is admissible.")]


def conclusion(parts: ReportParts, warnings: list[str]) -> str:
    """The report's opening paragraph."""
    docs = parts.documents
    s: list[str] = []
    if "fos.json" in docs:
        s += _fos_sentences(docs["fos.json"])
    if "seismic.json" in docs:
        s += _seismic_sentences(docs["seismic.json"])
    if "le.json" in docs:
        s += _le_sentences(docs["le.json"])
    if parts.sweep:
        s += _sweep_sentences(parts.sweep)
    if "summary.json" in docs:
        s += _run_sentences(docs["summary.json"], parts.result_meta, parts.threshold)
    elif parts.result_meta:
        s.append(f"The run wrote {rd.plural(parts.result_meta.get('n_steps', 0), 'step')} "
                 "but no summary (it was stopped before its end).")
    if "blocks.json" in docs:
        b = docs["blocks.json"]
        s.append(f"{rd.plural(b.get('count', 0), 'block')} after cutting, "
                 f"{rd.volume(b.get('total_volume', 0.0))} in all.")
    s += _kinematic_sentences(parts.kinematics)
    if warnings:
        first = escape(warnings[0])
        s.append(f"<b>{rd.plural(len(warnings), 'warning')}</b>: {first}"
                 + (" (and the others under Warnings)." if len(warnings) > 1 else "."))
    if not s:
        s.append("Nothing was computed for this job.")
    return "<h2 id='conclusion'>Conclusion</h2><p class='conclusion'>" + " ".join(s) + "</p>"


# --------------------------------------------------------------------------- sections


def _moving_blocks(summary: dict[str, Any], meta: dict[str, Any], threshold: float) -> str:
    """The free blocks that moved more than `threshold`, largest first; the others counted."""
    blocks = summary.get("blocks") or []
    if not blocks:
        return ""
    m = movement(blocks, meta.get("fixed") or [], threshold)
    volume = meta.get("volume") or []
    index = {b.get("name"): k for k, b in enumerate(blocks)}
    rows = []
    unit, scale = rd.lengths_unit([b["magnitude"] for b in m["moved"]])
    d = 3 if unit == "m" else 1
    for b in m["moved"][:MAX_ROWS]:
        k = index.get(b["name"], -1)
        v = (blocks[k].get("velocity") or [0.0] * 3)[:3] if k >= 0 else [0.0] * 3
        rows.append([b["name"], rd.volume(volume[k]) if 0 <= k < len(volume) else "–",
                     rd.fixed(b["magnitude"] * scale, d),
                     *(rd.fixed(x * scale, d) for x in b["displacement"]),
                     rd.direction(b["displacement"]), rd.fixed(_norm(v), 3)])
    limit = rd.length(threshold)
    out = [f"<h2 id='moving'>Blocks that moved more than {limit}</h2>"]
    if rows:
        out.append(_table(rows, ["block", "volume", f"|u| ({unit})", f"u_x ({unit})",
                                 f"u_y ({unit})", f"u_z ({unit})", "trend/plunge (°)",
                                 "final speed (m/s)"]))
        if len(m["moved"]) > MAX_ROWS:
            out.append(f"<p class='muted'>… and {len(m['moved']) - MAX_ROWS} more.</p>")
    else:
        out.append(f"<p>None: no free block moved more than {limit}.</p>")
    notes = []
    if m["still"]:
        notes.append(f"{rd.plural(m['still'], 'free block')} moved less than {limit} (at most "
                     f"{rd.length(m['still_max'])}) and {'is' if m['still'] == 1 else 'are'} "
                     "not listed")
    if m["fixed"]:
        notes.append(f"{rd.plural(m['fixed'], 'fixed block')} not listed")
    if notes:
        out.append(f"<p class='muted'>{'; '.join(notes)}. Centroid displacements; trend "
                   "clockwise from North, plunge below horizontal.</p>")
    return "".join(out)


def _fos_section(fos: dict[str, Any]) -> str:
    fs = fos.get("factor_of_safety")
    out = ["<h2 id='fos'>Factor of safety</h2>",
           f"<p style='font-size:20px'>FS = <b id='fs'>"
           f"{f'{fs:.3f}' if isinstance(fs, float) else '–'}</b> <span class='muted'>"
           f"({escape(str(fos.get('status', '')))}"
           f"{'; ' + escape(fos['message']) if fos.get('message') else ''})</span></p>"]
    phis = fos.get("critical_friction_angle")
    phis = phis if isinstance(phis, list) else [phis]
    names = fos.get("joint_materials") or [""] * len(phis)
    rows = [[n or "all", rd.angle(p)] for n, p in zip(names, phis, strict=False)
            if isinstance(p, float)]
    if rows:
        out.append(_table(rows, ["joint material weakened", "critical friction angle"]))
    if fos.get("watch_blocks"):
        out.append(f"<p class='muted'>Watched blocks: {_cell(fos['watch_blocks'])}.</p>")
    runs = fos.get("runs") or []
    if runs:
        out.append("<h3>Bisection history (trial runs)</h3>" + _trials_table(runs, "factor", "F"))
    return "".join(out)


def _trials_table(runs: list[dict[str, Any]], key: str, label: str) -> str:
    """Each trial: the value tried, its verdict and the reason, the largest displacement of
    a watched block and the fastest watched point's speed at the end."""
    return _table(([k + 1, f"{r.get(key, 0.0):.4f}", "fails" if r.get("failed") else "holds",
                    r.get("reason", ""), rd.length(r.get("displacement") or 0.0),
                    f"{rd.number(r.get('velocity') or 0.0, 3)} m/s", r.get("status", "")]
                   for k, r in enumerate(runs)),
                  ["trial", label, "verdict", "why", "largest displacement", "velocity",
                   "run"])


def _seismic_section(doc: dict[str, Any]) -> str:
    runs = doc.get("runs") or []
    out = ["<h2 id='seismic'>Critical seismic coefficient</h2>"]
    if runs:
        out.append(_trials_table(runs, "kh", "kh"))
    return "".join(out)


def _le_section(le: dict[str, Any]) -> str:
    """Limit equilibrium: the factor of safety, mode, and each plane the block rests on."""
    fs = le.get("factor_of_safety")
    out = ["<h2 id='le'>Limit equilibrium</h2>",
           f"<p>FS = <b id='le-fs'>{'unbounded' if fs is None else f'{fs:.4f}'}</b>, "
           f"{escape(str(le.get('mode', '')))} (the vector method, Hoek &amp; Bray; Low "
           "1997)</p>"]
    planes = le.get("planes") or []
    if planes:
        out.append(_table(([p.get("name"), f"{p.get('dip', 0):.1f}/"
                            f"{p.get('dip_direction', 0):05.1f}",
                            "free" if p.get("normal_force") is None
                            else rd.force(p["normal_force"]),
                            rd.angle(p.get("friction_angle", 0.0)),
                            rd.stress(p.get("cohesion", 0.0)),
                            rd.force(p.get("water_force", 0.0))] for p in planes),
                          ["plane", "dip/dip direction (°)", "normal force", "φ", "c",
                           "water force"]))
    out += [f"<p class='muted'>{escape(str(n))}</p>" for n in le.get("notes") or []]
    return "".join(out)


_MODES = (("planar", "planar sliding", "set"), ("wedge", "wedge sliding", "sets"),
          ("flexural_toppling", "flexural toppling", "set"),
          ("direct_toppling", "direct toppling", "sets"))


def _kinematics_section(part: dict[str, Any] | None) -> str:
    """Admissible modes, every test with the conditions met and not met, the stereonet; or
    why there is no screening."""
    if not part:
        return ""
    head = "<h2 id='kinematics'>Kinematic screening</h2>"
    if "doc" not in part:
        return head + f"<p class='muted'>Not available: {escape(part['reason'])}.</p>"
    doc = part["doc"]
    slope, lim = doc["slope"], doc["lateral_limits"]
    out = [head, f"<p>Slope face {slope['dip']:g}/{slope['dip_direction']:03g} (dip/dip "
                 f"direction), φ {slope['friction_angle']:g}° for joints without their own; "
                 f"lateral limits ±{lim['planar']:g}° planar, ±{lim['flexural_toppling']:g}° "
                 f"flexural, ±{lim['direct_toppling']:g}° direct toppling. Markland tests "
                 "(engine.analyses.kinematics): what <i>can</i> move, not whether it does.</p>"]
    adm = doc["admissible"]
    out.append(_table(([title, ", ".join("/".join(x) if isinstance(x, list) else x
                                         for x in adm[key]) or "none"]
                       for key, title, _ in _MODES), ["mode", "admissible"]))
    rows = []
    for key, title, names in _MODES:
        for r in doc[key]:
            who = "/".join(r[names]) if names == "sets" else r[names]
            line = (f"trend {r['trend']:.2f}°, plunge {r['plunge']:.2f}°"
                    if r.get("trend") is not None else "–")
            met, unmet = ("; ".join(f"{c['test']}: {c['detail']}" for c in r["conditions"]
                                    if c["passed"] is ok) or "–" for ok in (True, False))
            rows.append([title, who, "admissible" if r["admissible"] else "not admissible",
                         line, met, unmet])
    out.append("<h3>Tests</h3>" + _table(rows, ["mode", "set(s)", "result", "intersection",
                                                "conditions met", "conditions not met"]))
    out.append(_figure(part["src"], "Equal-area lower-hemisphere stereonet of the joints, "
                       "the slope face and the tests' zones", "stereonet"))
    return "".join(out)


def _sweep_section(part: dict[str, Any] | None) -> str:
    """Probability of failure with its interval, FS statistics per method, the histogram
    and CDF of the factors of safety."""
    if not part:
        return ""
    doc, spec = part["doc"], part["doc"].get("spec") or {}
    out = ["<h2 id='sweep'>Monte Carlo sweep</h2>",
           f"<p>{doc.get('done', 0)} of {spec.get('n', '?')} realisations done (seed "
           f"{spec.get('seed', '?')}); factor of safety by "
           f"{escape(str(spec.get('mode', '?')))}.</p>"]
    params = doc.get("parameters") or {}
    if params:
        out.append(_table([[name, ", ".join(
            f"{k} {rd.value(v)}" for k, v in p.items() if k not in ("values", "truncated_to"))
            + (f", {len(p['values'])} values" if "values" in p else "")]
            for name, p in params.items()], ["parameter", "distribution"]))
    names = sorted({n for a in part["aggregates"].values() for n in a.get("sensitivity") or {}})
    rows = []
    for label, a in part["aggregates"].items():
        pof, ci = a.get("probability_of_failure"), a.get("pof_interval_95") or [None, None]
        pct = a.get("percentiles") or {}
        rows.append([label, a.get("n", 0), a.get("failures", 0), a.get("excluded", 0),
                     "–" if pof is None else f"{pof:.4g}",
                     "–" if pof is None else f"{ci[0]:.3g} – {ci[1]:.3g}",
                     *(rd.number(a[k], 4) if k in a else "–"
                       for k in ("mean", "sd", "min", "max")),
                     *(rd.number(pct[q], 4) if q in pct else "–" for q in ("5", "50", "95")),
                     *(rd.value((a.get("sensitivity") or {}).get(n)) for n in names)])
    out.append(_table(rows, ["method", "n", "failures (FS < 1)", "excluded", "PoF",
                             "PoF 95 % (Wilson)", "mean FS", "sd", "min", "max", "P5", "P50",
                             "P95", *(f"Spearman ρ({n}, FS)" for n in names)]))
    if part.get("src"):
        out.append(_figure(part["src"], "Factor of safety over the realisations: histogram "
                           "and empirical CDF (FS = 1 dashed)", "sweep-figure"))
    else:
        out.append("<p class='muted'>No realisation has a factor of safety yet.</p>")
    return "".join(out)


_LABELS = {"status": "status", "message": "message", "steps": "solver steps",
           "simulated_time": "simulated time", "wall_time": "wall time",
           "max_penetration": "largest penetration", "time_step_cuts": "time step cuts",
           "relaxed_contacts": "relaxed contacts",
           "reseat_dissipation": "springs' energy lost re-seating contacts"}


def _result_section(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    fixed = meta.get("fixed") or []
    counts = (f"{rd.plural(len(summary.get('blocks') or []), 'block')}"
              + (f", {sum(map(bool, fixed))} fixed" if fixed else ""))
    pen = summary.get("penalty") or {}
    shown = {
        "status": summary.get("status"), "message": summary.get("message") or "–",
        "steps": summary.get("steps"),
        "simulated_time": rd.seconds(summary.get("simulated_time") or 0.0),
        "wall_time": rd.duration(summary.get("wall_time") or 0.0),
        "max_penetration": rd.length(summary.get("max_penetration") or 0.0),
        "time_step_cuts": sum((summary.get("time_step_cuts") or {}).values()),
        "relaxed_contacts": summary.get("relaxed_contacts"),
        "reseat_dissipation": rd.energy(summary.get("reseat_dissipation") or 0.0,
                                        meta.get("energy_scale"))}
    rows = [[_LABELS[k], v] for k, v in shown.items() if v is not None]
    if isinstance(pen, dict) and "normal" in pen:
        rows.append(["contact penalty", f"{pen['normal']:.3g} N/m normal, "
                     f"{pen.get('shear', 0.0):.3g} N/m shear"
                     + (" (derived from the blocks)" if pen.get("derived") else "")])
    return f"<h2>Result</h2><p>{escape(counts)}</p>" + _table(rows)


def _stages_section(summary: dict[str, Any]) -> str:
    """A staged run's stages: each one's time span, steps, status, the blocks it removed,
    the energy that left with them and the bolts acting in it ('' without stages)."""
    stages = summary.get("stages") or []
    if not stages:
        return ""
    rows = [[st["name"], f"{rd.number(st['start_time'])} – {rd.number(st['end_time'])}",
             f"{st['start_step']} – {st['end_step']}", st["status"],
             ", ".join(st["removed_blocks"]) or "—", rd.number(st["removed_energy"]),
             ", ".join(st["bolts"]) or "—"] for st in stages]
    return ("<h3 id='stages'>Stages</h3>"
            + _table(rows, ["stage", "time (s)", "steps", "status", "blocks removed",
                            "energy removed (J)", "bolts acting"]))


def _snapshot_section(src: str | None, meta: dict[str, Any]) -> str:
    """The blocks at the last recorded step, drawn from the result file's vertices."""
    if src is None:
        return ("<p class='muted'>No step was recorded: there is no last frame to draw.</p>"
                if meta.get("n_steps") == 0 else "")
    last = meta.get("last") or {}
    when = (f" (step {last['step']}, t = {last['time']:.4g} s)" if last else "")
    return ("<h3 id='snapshot'>Blocks at the last recorded step</h3>"
            + _figure(src, f"The blocks at the last recorded step{when}, drawn from the "
                      "result file's vertices and seen as the viewer first shows them; each "
                      "face coloured by the mean displacement of its vertices (the colour "
                      "bar spans them), fixed blocks grey.", "snapshot-figure"))


def _scene_section(scene: dict[str, Any], scene_text: str) -> str:
    """Appendix: the scene's materials, joints, domain, boundary and analysis, then the
    scene as given."""
    out = [f"<p>{escape(str(scene.get('description', '')))}</p>"]
    for key, title in (("materials", "Materials"), ("joint_materials", "Joint materials")):
        table = scene.get(key) or {}
        if isinstance(table, dict) and table:
            keys = sorted({k for m in table.values() if isinstance(m, dict) for k in m})
            out.append(f"<h3>{title}</h3>" + _table(
                ([n] + [m.get(k, "–") if isinstance(m, dict) else "–" for k in keys]
                 for n, m in table.items()), ["name", *keys]))
    joints = scene.get("joints") or []
    if isinstance(joints, list) and joints:
        out.append("<h3>Joints</h3>" + _table(
            ([j.get("name") or f"J{k + 1}", j.get("dip"), j.get("dip_direction"),
              j.get("point"), j.get("spacing") or "single",
              "bounded" if j.get("extent") else "persistent",
              j.get("joint_material") or "default"]
             for k, j in enumerate(joints) if isinstance(j, dict)),
            ["name", "dip (°)", "dip direction (°)", "point (m)", "spacing (m)", "extent",
             "joint material"]))
    for key in ("domain", "boundary"):
        if scene.get(key):
            out.append(f"<p>{key.capitalize()}: {_cell(scene[key])}</p>")
    analysis = scene.get("analysis") or {}
    if isinstance(analysis, dict) and analysis:
        out.append("<h3>Analysis</h3>" + _table(analysis.items(), ["parameter", "value"]))
    text = scene_text if len(scene_text) <= MAX_SCENE_CHARS else (
        scene_text[:MAX_SCENE_CHARS] + f"\n… ({len(scene_text) - MAX_SCENE_CHARS:,} more "
                                       "characters)")
    out.append(f"<h3>The scene as given</h3><pre class='mono scene'>{escape(text)}</pre>")
    return "".join(out)


# --------------------------------------------------------------------------- page


def report_body(parts: ReportParts) -> str:
    """The report's content (inside <main>): conclusion first, the scene last."""
    try:
        scene = json.loads(parts.scene_text) if parts.scene_text else {}
        scene = scene.get("inputs", {}).get("scene", scene) if "inputs" in scene else scene
    except (ValueError, AttributeError):
        scene = {}
    scene = scene if isinstance(scene, dict) else {}
    docs = parts.documents
    summary, fos = docs.get("summary.json") or {}, docs.get("fos.json")
    warnings = [str(w) for w in dict.fromkeys(
        [*(summary.get("warnings") or []), *((fos or {}).get("warnings") or []),
         *((docs.get("seismic.json") or {}).get("warnings") or []),
        *((docs.get("le.json") or {}).get("warnings") or [])])]
    s = [f"<h1>{escape(str(scene.get('name') or parts.title))} — "
         f"{escape(parts.process_title)}</h1>", _table(parts.header), conclusion(parts, warnings)]
    if summary:
        s.append(_moving_blocks(summary, parts.result_meta, parts.threshold))
    if fos:
        s.append(_fos_section(fos))
    if "seismic.json" in docs:
        s.append(_seismic_section(docs["seismic.json"]))
    if "le.json" in docs:
        s.append(_le_section(docs["le.json"]))
    s += [_figure(src, caption) for caption, src in parts.figures.items()]
    s.append(_sweep_section(parts.sweep))
    s.append(_kinematics_section(parts.kinematics))
    if summary:
        s.append(_result_section(summary, parts.result_meta))
        s.append(_stages_section(summary))
        s.append(_snapshot_section(parts.snapshot, parts.result_meta))
    elif "blocks.json" in docs:
        blocks = docs["blocks.json"].get("blocks", [])
        s.append(f"<h2>Blocks</h2><p>{rd.plural(len(blocks), 'block')} after cutting.</p>")
    elif parts.result_meta:  # a result file without a summary (a run killed before its end)
        s.append(f"<h2>Result</h2><p>{parts.result_meta.get('n_steps', 0)} recorded steps; the "
                 "run wrote no summary.</p>"
                 + _snapshot_section(parts.snapshot, parts.result_meta))
    if parts.plots:
        s.append("<h2>Plots</h2>" + "".join(_figure(src, name) for name, src in parts.plots))
    s.append("<h2>Warnings</h2>" + ("".join(f"<div class='warn'>{escape(w)}</div>"
                                            for w in warnings) or "<p>None.</p>"))
    s.append("<h2>Appendix: the scene</h2>" + _scene_section(scene, parts.scene_text))
    s.append(_provenance(parts))
    return "".join(s)


def _provenance(parts: ReportParts) -> str:
    import matplotlib
    import numpy
    import scipy

    text = parts.scene_text
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest() if text else "–"
    meta = parts.result_meta
    versions = [["scene SHA-256", digest],
                ["result file scene SHA-256", meta.get("scene_sha256", "–")],
                ["engine", meta.get("engine_version") or _installed("polydda")],
                ["scene schema", meta.get("schema_version", "–")],
                ["service", VERSION], ["python", platform.python_version()],
                ["numpy", numpy.__version__], ["scipy", scipy.__version__],
                ["matplotlib", matplotlib.__version__]]
    return "<h2>Versions and provenance</h2>" + _table(versions)


def report_page(parts: ReportParts, root: str = "", links: str = "",
                standalone: bool = False) -> str:
    """The whole HTML page; `standalone`: the stylesheet inline and no links to a server
    (a file to keep, mail or print)."""
    head = ""
    if standalone:
        css = (Path(__file__).parents[1] / "static" / "pages.css").read_text(encoding="utf-8")
        head = f"<style>{css}</style>"
        bar = "<header class='bar'><h1>PolyDDA</h1><span>report</span></header>"
    else:
        bar = _bar(root, f"<span>report</span> {links}")
    body = (bar + "<main class='report'><p class='noprint'><button id='print'>"
                  "Print / save as PDF</button></p>" + report_body(parts) + "</main>"
                  # a script, not an onclick attribute: the page's CSP allows its scripts by
                  # hash
                  "<script>document.getElementById('print').onclick=()=>window.print();"
                  "</script>")
    page = _page(f"PolyDDA report {parts.title}", root, body, cls="report", head=head)
    if standalone:  # no server: drop the stylesheet and icon links
        page = page.replace(f'<link rel="stylesheet" href="{root}/static/pages.css">', "")
        page = page.replace(f'<link rel="icon" type="image/png" href="{root}/static/'
                            'favicon-32x32.png">', "")
    return page


def report_html(job: JobRecord, root: str, job_dir: Path, scene_text: str,
                plots: list[str], result_meta: dict[str, Any],
                figures: dict[str, str] | None = None, *,
                kinematics: dict[str, Any] | None = None, snapshot: str | None = None,
                sweep: dict[str, Any] | None = None) -> str:
    """The printable report of a finished job (its documents read from `job_dir`; `plots`:
    the names of its plots under /results/plots)."""
    docs = {}
    for name in ("summary.json", "fos.json", "seismic.json", "le.json", "blocks.json"):
        path = job_dir / name
        if path.is_file():
            docs[name] = json.loads(path.read_text(encoding="utf-8"))
    base = f"{root}/jobs/{job.id}"
    parts = ReportParts(
        title=job.id[:8], process_title=PROCESSES[job.process].title,
        header=[("job", job.id), ("status", job.status), ("message", job.message or "–"),
                ("created", _iso(job.created)), ("finished", _iso(job.finished))],
        scene_text=scene_text, documents=docs,
        plots=[(p, f"{base}/results/plots/{p}") for p in plots], result_meta=result_meta,
        figures=dict(figures or {}), kinematics=kinematics, snapshot=snapshot, sweep=sweep)
    links = " · ".join(f'<a href="{escape(h)}">{t}</a>' for t, h in job_links(job, root)
                       if t != "report")
    return report_page(parts, root, links)


def _iso(t: float | None) -> str:
    from service.api.models import iso_time

    return iso_time(t) or "–"


def _installed(dist: str) -> str:
    """The installed version of a distribution ("–" if it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "–"
