"""HTML pages for people: the home page (jobs with links), a job's 3-D viewer and its
printable report. Every asset is served from /static (no internet needed)."""

from __future__ import annotations

import hashlib
import json
import platform
from collections.abc import Iterable
from html import escape
from pathlib import Path
from typing import Any

from service.jobs.processes import PROCESSES, RESULT_FILE
from service.jobs.store import JobRecord

VERSION = "0.1.0"


def _page(title: str, root: str, body: str, cls: str = "", head: str = "") -> str:
    return (f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{escape(title)}</title>"
            f'<link rel="icon" type="image/png" href="{root}/static/favicon-32x32.png">'
            f'<link rel="stylesheet" href="{root}/static/pages.css">{head}</head>'
            f'<body class="{cls}">{body}</body></html>\n')


def _bar(root: str, extra: str = "") -> str:
    return (f'<header class="bar"><h1><a href="{root}/">PolyDDA</a></h1>{extra}'
            f'<a href="{root}/docs">API docs</a></header>')


def job_links(job: JobRecord, root: str) -> list[tuple[str, str]]:
    """(title, href) of the pages and documents of a job."""
    base = f"{root}/jobs/{job.id}"
    links = [("status", base)]
    if RESULT_FILE in PROCESSES[job.process].artifacts:
        links.append(("viewer", f"{base}/viewer"))
    if job.is_final:
        links += [("report", f"{base}/report"), ("results", f"{base}/results")]
    return links


def home_html(root: str, jobs: Iterable[JobRecord] | None, total: int = 0) -> str:
    """The home page: recent jobs with links (None: the caller needs an API key first)."""
    if jobs is None:
        body = ("<main><p>This service needs an API key. It is kept in this browser "
                "(a cookie sent with GET requests only) for the viewer and reports.</p>"
                '<form id="key-form"><label>API key <input id="key" type="password" '
                'autocomplete="off" size="40"></label> <button>Use key</button></form>'
                "<script>document.getElementById('key-form').onsubmit=(e)=>{e.preventDefault();"
                "document.cookie='polydda_key='+encodeURIComponent("
                "document.getElementById('key').value)+';path=/;SameSite=Strict';"
                "location.reload();};</script></main>")
        return _page("PolyDDA", root, _bar(root) + body)
    rows = []
    for j in jobs:
        links = " · ".join(f'<a href="{escape(h)}">{t}</a>' for t, h in job_links(j, root))
        rows.append(f"<tr><td class='mono'>{escape(j.id[:8])}</td><td>{escape(j.process)}</td>"
                    f"<td>{escape(j.status)}</td><td class='num'>{int(j.progress)} %</td>"
                    f"<td>{escape(j.message)}</td><td>{links}</td></tr>")
    table = ("<table id='jobs'><tr><th>job</th><th>process</th><th>status</th><th>progress</th>"
             "<th>message</th><th>links</th></tr>" + "".join(rows) + "</table>"
             if rows else "<p>No jobs yet: submit a scene with <code>polydda submit</code> or "
                          f"<code>POST {root}/jobs</code>.</p>")
    body = (f"<main><h2>Jobs</h2><p class='muted'>{total} job(s); the newest first. "
            f"<a href='{root}/jobs'>as JSON</a></p>{table}</main>")
    return _page("PolyDDA jobs", root, _bar(root) + body)


def _script_json(value: Any) -> str:
    """JSON to put inside a <script> element (no `<`, `>` or `&` that HTML would read)."""
    return (json.dumps(value).replace("<", "\\u003c").replace(">", "\\u003e")
            .replace("&", "\\u0026"))


def viewer_html(job: JobRecord, root: str, poll_ms: int = 2000, max_frames: int = 2000) -> str:
    """The 3-D viewer of a job's result (loads service/static/viewer.js); it loads at most
    `max_frames` steps (every k-th recorded step beyond)."""
    base = f"{root}/jobs/{job.id}"
    cfg = {"job": base, "frames": f"{base}/results/frames", "poll_ms": poll_ms,
           "max_frames": max_frames, "max_bytes": 48_000_000}
    importmap = {"imports": {"three": f"{root}/static/three/three.module.min.js",
                             "three/addons/": f"{root}/static/three/"}}
    first = f"{cfg['frames']}?start=0&stop={cfg['max_frames']}&geometry=true"
    head = (f'<script type="importmap">{_script_json(importmap)}</script>'
            + "".join(f'<link rel="modulepreload" href="{root}/static/{m}">' for m in (
                "viewer.js", "three/three.module.min.js", "three/three.core.min.js",
                "three/OrbitControls.js"))
            + f'<script type="application/json" id="viewer-config">'
            f"{_script_json({**cfg, 'first': first})}</script>"
            # the first frames load while the scripts do
            "<script>window.polyddaFirst = fetch(JSON.parse(document.getElementById("
            "'viewer-config').textContent).first, {credentials: 'same-origin'});</script>")
    extra = (f"<span>job <span class='mono'>{escape(job.id[:8])}</span> · "
             f"<span id='title-blocks'></span></span>"
             + "".join(f'<a href="{escape(h)}">{t}</a>' for t, h in job_links(job, root)
                       if t != "viewer"))
    body = (_bar(root, extra) +
            '<div class="stage"><canvas id="view"></canvas>'
            '<div id="legend">drag: rotate · right-drag: pan · wheel: zoom · click: pick a block'
            "</div>"
            '<div id="colourbar" hidden><div id="cb-title"></div><div class="ramp"></div>'
            '<div class="ends"><span id="cb-min"></span><span id="cb-max"></span></div></div>'
            '<div id="info" hidden><h2 id="pick-name"></h2><div id="pick-kind" class="muted">'
            "</div><div>final displacement: <b id='pick-disp'></b></div>"
            "<div class='mono' id='pick-comp'></div>"
            '<canvas id="history" width="320" height="150"></canvas>'
            "<div class='muted'>|u| black, u<sub>x</sub> red, u<sub>y</sub> green, "
            "u<sub>z</sub> blue (m)</div></div></div>"
            '<div class="controls"><button id="play">Play</button>'
            '<input id="slider" type="range" min="0" max="0" value="0">'
            '<span id="frame-label"></span>'
            '<label>colour <select id="colour"><option value="displacement">displacement'
            '</option><option value="velocity">velocity</option><option value="block">block'
            "</option></select></label>"
            '<label><input id="contacts" type="checkbox"> contacts</label>'
            '<span class="muted" title="contact modes"><span style="color:#8c8c8c">●</span>'
            ' open <span style="color:#2666f2">●</span> locked '
            '<span style="color:#f2731a">●</span> sliding '
            '<span style="color:#c2185b">→</span> normal force</span>'
            '<span id="contact-count" class="muted"></span>'
            '<label><input id="joints" type="checkbox"> joint planes</label>'
            '<label><input id="follow" type="checkbox" checked> follow</label>'
            '<button id="save" title="download the view as PNG">Save image</button>'
            '<label>fps <input id="fps" type="number" min="1" max="60" value="15" '
            'style="width:3.5em"></label>'
            '<span id="stride" class="muted"></span><span id="status" class="muted"></span>'
            '<span id="load-time" class="muted"></span>'
            "</div>"
            f'<script type="module" src="{root}/static/viewer.js"></script>')
    return _page(f"PolyDDA viewer {job.id[:8]}", root, body, cls="viewer", head=head)


# --------------------------------------------------------------------------- report


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return f"{x:.6g}"
    if isinstance(x, list | dict):
        return escape(json.dumps(x))
    return escape(str(x))


def _table(rows: Iterable[Iterable[Any]], head: Iterable[str] = ()) -> str:
    h = "".join(f"<th>{escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table>{f'<tr>{h}</tr>' if h else ''}{body}</table>"


def _scene_section(scene: dict[str, Any]) -> str:
    out = [f"<p>{escape(str(scene.get('description', '')))}</p>"]
    mats = scene.get("materials") or {}
    if mats:
        keys = sorted({k for m in mats.values() for k in m})
        out.append("<h3>Materials</h3>" + _table(
            ([n] + [m.get(k, "") for k in keys] for n, m in mats.items()), ["name", *keys]))
    jm = scene.get("joint_materials") or {}
    if jm:
        keys = sorted({k for m in jm.values() for k in m})
        out.append("<h3>Joint materials</h3>" + _table(
            ([n] + [m.get(k, "") for k in keys] for n, m in jm.items()), ["name", *keys]))
    joints = scene.get("joints") or []
    if joints:
        out.append("<h3>Joints</h3>" + _table(
            ([j.get("name") or f"J{k + 1}", j.get("dip"), j.get("dip_direction"),
              j.get("point"), j.get("spacing") or "single",
              "bounded" if j.get("extent") else "persistent",
              j.get("joint_material") or "default"] for k, j in enumerate(joints)),
            ["name", "dip (°)", "dip direction (°)", "point (m)", "spacing (m)", "extent",
             "joint material"]))
    if scene.get("domain"):
        out.append(f"<p>Domain: <code>{_fmt(scene['domain'])}</code></p>")
    if scene.get("boundary"):
        out.append(f"<p>Boundary: <code>{_fmt(scene['boundary'])}</code></p>")
    analysis = scene.get("analysis") or {}
    if analysis:
        out.append("<h3>Analysis</h3>" + _table(analysis.items(), ["parameter", "value"]))
    return "".join(out)


_LABELS = {"steps": "solver steps", "simulated_time": "simulated time (s)",
           "wall_time": "wall time (s)", "penalty": "contact penalty (N/m)",
           "max_penetration": "largest penetration (m)", "time_step_cuts": "time step cuts",
           "relaxed_contacts": "relaxed contacts",
           "reseat_dissipation": "springs' energy lost re-seating contacts (J)"}


def _blocks_section(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    blocks = summary.get("blocks") or []
    if not blocks:
        return ""
    fixed, volume = meta.get("fixed") or [], meta.get("volume") or []
    rows = []
    for k, b in enumerate(blocks):
        d = b.get("displacement") or [0.0, 0.0, 0.0]
        rows.append([b.get("name") or k,
                     ("fixed" if fixed[k] else "free") if k < len(fixed) else "",
                     _num(volume[k]) if k < len(volume) else "", *(_num(x) for x in d),
                     _num(_norm(d)), *_trend_plunge(d)])
    shown = rows[:200]
    more = f"<p class='muted'>… and {len(rows) - 200} more blocks</p>" if len(rows) > 200 else ""
    return ("<h3>Blocks (final displacement of the centroid)</h3>" + _table(
        shown, ["block", "", "volume (m³)", "u_x (m)", "u_y (m)", "u_z (m)", "|u| (m)",
                "trend (°)", "plunge (°)"]) + more)


def _num(x: Any) -> str:
    return f"{x:.4g}" if isinstance(x, int | float) else str(x)


def _norm(d: list[float]) -> float:
    return float(sum(x * x for x in d) ** 0.5)


def trend_plunge(d: list[float]) -> tuple[float, float] | None:
    """Trend (° clockwise from North, y) and plunge (° below horizontal) of a vector
    (x East, y North, z up); None for a zero vector."""
    import math

    dx, dy, dz = (float(x) for x in d)
    if _norm([dx, dy, dz]) == 0:
        return None
    return (math.degrees(math.atan2(dx, dy)) % 360.0,
            math.degrees(math.atan2(-dz, math.hypot(dx, dy))))


def _trend_plunge(d: list[float]) -> list[str]:
    tp = trend_plunge(d)
    return ["–", "–"] if tp is None else [f"{tp[0]:.1f}", f"{tp[1]:.1f}"]


_MODES = (("planar", "planar sliding", "set"), ("wedge", "wedge sliding", "sets"),
          ("flexural_toppling", "flexural toppling", "set"),
          ("direct_toppling", "direct toppling", "sets"))


def _figure(src: str, caption: str, ident: str = "") -> str:
    attr = f" id='{ident}'" if ident else ""
    return (f'<figure{attr}><img src="{escape(src)}" alt="{escape(caption)}">'
            f"<figcaption class='muted'>{escape(caption)}</figcaption></figure>")


def _kinematics_section(part: dict[str, Any] | None) -> str:
    """Admissible modes, every test with the conditions that failed, the stereonet; or why
    there is no screening."""
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
            line = (f"trend {r['trend']:.2f}°, plunge {r['plunge']:.2f}°; "
                    if r.get("trend") is not None else "")
            met, unmet = ("; ".join(f"{c['test']}: {c['detail']}" for c in r["conditions"]
                                    if c["passed"] is ok) or "–" for ok in (True, False))
            rows.append([title, who, "admissible" if r["admissible"] else "not admissible",
                         line.rstrip("; ") or "–", met, unmet])
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
            f"{k} {v}" for k, v in p.items() if k not in ("values", "truncated_to"))
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
                     *(_num(a[k]) if k in a else "–" for k in ("mean", "sd", "min", "max")),
                     *(_num(pct[q]) if q in pct else "–" for q in ("5", "50", "95")),
                     *(_num((a.get("sensitivity") or {}).get(n, "–")) for n in names)])
    out.append(_table(rows, ["method", "n", "failures (FS < 1)", "excluded", "PoF",
                             "PoF 95 % (Wilson)", "mean FS", "sd", "min", "max", "P5", "P50",
                             "P95", *(f"Spearman ρ({n}, FS)" for n in names)]))
    if part.get("src"):
        out.append(_figure(part["src"], "Factor of safety over the realisations: histogram "
                           "and empirical CDF (FS = 1 dashed)", "sweep-figure"))
    else:
        out.append("<p class='muted'>No realisation has a factor of safety yet.</p>")
    return "".join(out)


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


def report_html(job: JobRecord, root: str, job_dir: Path, scene_text: str,
                plots: list[str], result_meta: dict[str, Any],
                figures: dict[str, str] | None = None, *,
                kinematics: dict[str, Any] | None = None, snapshot: str | None = None,
                sweep: dict[str, Any] | None = None) -> str:
    """The printable report of a finished job: FS or sweep, kinematic screening, scene,
    result with the blocks at the last step, plots, warnings, versions and the scene hash.
    `figures`: more images (caption -> src) after the FS; `kinematics`, `sweep`: the parts
    service.api.results makes; `snapshot`: the src of the last step's image."""
    base = f"{root}/jobs/{job.id}"
    try:
        scene = json.loads(scene_text) if scene_text else {}
        scene = scene.get("inputs", {}).get("scene", scene) if "inputs" in scene else scene
    except ValueError:
        scene = {}
    docs = {}
    for name in ("summary.json", "fos.json", "blocks.json"):
        path = job_dir / name
        if path.is_file():
            docs[name] = json.loads(path.read_text(encoding="utf-8"))
    s = []
    s.append(f"<h1>{escape(str(scene.get('name') or 'Scene'))} — "
             f"{escape(PROCESSES[job.process].title)}</h1>")
    s.append(_table([["job", job.id], ["status", job.status], ["message", job.message],
                     ["created", _iso(job.created)], ["finished", _iso(job.finished)]],
                    ()))
    summary = docs.get("summary.json") or {}
    fos = docs.get("fos.json")
    if fos:
        fs = fos.get("factor_of_safety")
        s.append("<h2>Factor of safety</h2>")
        s.append(f"<p style='font-size:20px'>FS = <b id='fs'>{_fmt(fs)}</b> "
                 f"<span class='muted'>({escape(str(fos.get('status', '')))}"
                 f"{'; ' + escape(fos['message']) if fos.get('message') else ''})</span></p>")
        runs = fos.get("runs") or []
        if runs:
            keys = [k for k in runs[0] if not isinstance(runs[0][k], list | dict)]
            s.append("<h3>Bisection history (trial runs)</h3>"
                     + _table(([r.get(k) for k in keys] for r in runs), keys))
        extra = {k: v for k, v in fos.items() if k not in ("runs", "warnings", "message",
                                                           "status", "factor_of_safety")}
        if extra:
            s.append(_table(extra.items(), ()))
    for caption, src in (figures or {}).items():
        s.append(_figure(src, caption))
    s.append(_sweep_section(sweep))
    s.append(_kinematics_section(kinematics))
    s.append("<h2>Scene</h2>" + _scene_section(scene))
    if summary:
        keys = ("status", "message", "steps", "simulated_time", "wall_time", "penalty",
                "max_penetration", "time_step_cuts", "relaxed_contacts", "reseat_dissipation")
        fixed = result_meta.get("fixed") or []
        counts = (f"{len(summary.get('blocks') or [])} blocks"
                  + (f", {sum(map(bool, fixed))} fixed" if fixed else ""))
        s.append(f"<h2>Result</h2><p>{escape(counts)}</p>"
                 + _table((_LABELS.get(k, k), summary[k]) for k in keys if k in summary))
        s.append(_snapshot_section(snapshot, result_meta))
        s.append(_blocks_section(summary, result_meta))
    elif "blocks.json" in docs:
        blocks = docs["blocks.json"].get("blocks", [])
        s.append(f"<h2>Blocks</h2><p>{len(blocks)} blocks after cutting.</p>")
    elif result_meta:  # a result file without a summary (a run killed before its end)
        s.append(f"<h2>Result</h2><p>{result_meta.get('n_steps', 0)} recorded steps; the run "
                 "wrote no summary.</p>" + _snapshot_section(snapshot, result_meta))
    if plots:
        s.append("<h2>Plots</h2>" + "".join(
            f'<figure><img src="{base}/results/plots/{escape(p)}" alt="{escape(p)}">'
            f"<figcaption class='muted'>{escape(p)}</figcaption></figure>" for p in plots))
    warnings = list(dict.fromkeys([*(summary.get("warnings") or []),
                                   *((fos or {}).get("warnings") or [])]))
    s.append("<h2>Warnings</h2>" + ("".join(f"<div class='warn'>{escape(str(w))}</div>"
                                            for w in warnings) or "<p>None.</p>"))
    digest = hashlib.sha256(scene_text.encode("utf-8")).hexdigest() if scene_text else "–"
    import matplotlib
    import numpy
    import scipy

    versions = [["scene SHA-256", digest],
                ["result file scene SHA-256", result_meta.get("scene_sha256", "–")],
                ["engine", result_meta.get("engine_version") or _installed("polydda")],
                ["scene schema", result_meta.get("schema_version", "–")],
                ["service", VERSION], ["python", platform.python_version()],
                ["numpy", numpy.__version__], ["scipy", scipy.__version__],
                ["matplotlib", matplotlib.__version__]]
    s.append("<h2>Versions and provenance</h2>" + _table(versions, ()))
    links = " · ".join(f'<a href="{escape(h)}">{t}</a>' for t, h in job_links(job, root)
                       if t != "report")
    body = (_bar(root, f"<span>report</span> {links}")
            + "<main class='report'><p class='noprint'><button onclick='window.print()'>"
              "Print / save as PDF</button></p>" + "".join(s) + "</main>")
    return _page(f"PolyDDA report {job.id[:8]}", root, body, cls="report")


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
