"""HTML pages for people: the home page (jobs with links) and a job's 3-D viewer (its
printable report: :mod:`service.api.report`). Every asset is served from /static (no
internet needed)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from datetime import UTC, datetime
from html import escape
from typing import Any

from service.jobs.processes import PROCESSES, RESULT_FILE
from service.jobs.store import JobRecord

VERSION = "0.1.0"
#: characters no page shows raw (control characters but tab and line breaks, lone
#: surrogates): a scene stored before they were refused shows U+FFFD in their place
_UNPRINTABLE = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f\ud800-\udfff]")


def _page(title: str, root: str, body: str, cls: str = "", head: str = "") -> str:
    """A whole page around `body`, with no unprintable character left in it."""
    return _UNPRINTABLE.sub(
        "\ufffd", f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
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


def _when(seconds: float | None) -> str:
    """A job's time as `YYYY-MM-DD HH:MM` UTC in a <time> element (ISO in its datetime)."""
    if not seconds:
        return ""
    moment = datetime.fromtimestamp(seconds, tz=UTC)
    return (f"<time datetime='{moment.isoformat(timespec='seconds')}'>"
            f"{moment:%Y-%m-%d %H:%M} UTC</time>")


def _job_name(job: JobRecord, names: dict[str, tuple[str, str]]) -> str:
    """The scene's name (and its description as a tooltip), or the job id's start."""
    name, description = names.get(job.id, ("", ""))
    label = escape(name) if name and name != "scene" else (
        escape(description[:60]) if description else f"job {escape(job.id[:8])}")
    return (f"<span class='job-name' title='{escape(description)}'>{label}</span> "
            f"<span class='mono muted'>{escape(job.id[:8])}</span>")


def _upload_form(root: str) -> str:
    """A form that posts a scene file to POST /jobs (service/static/home.js sends the key
    cookie as X-API-Key: the cookie alone is accepted for GET requests only)."""
    options = "".join(f'<option value="{escape(p.id)}">{escape(p.title)}</option>'
                      for p in PROCESSES.values())
    return (
        "<section id='start'><h2>Start a process</h2>"
        "<form id='upload-form'><label>Scene (JSON) <input id='scene-file' type='file' "
        "accept='.json,application/json' required></label> "
        "<label>Process <select id='process'><option value=''>as the scene says "
        f"(analysis.type)</option>{options}</select></label> "
        "<button id='upload' type='submit'>Start</button> "
        "<span id='upload-status' role='status'></span></form>"
        "<ul id='upload-problems' class='problems'></ul></section>"
        f'<script type="application/json" id="home-config">'
        f'{_script_json({"root": root, "poll_ms": 2000})}</script>'
        f'<script type="module" src="{root}/static/home.js"></script>')


def home_html(root: str, jobs: Iterable[JobRecord] | None, total: int = 0,
              names: dict[str, tuple[str, str]] | None = None) -> str:
    """The home page: the caller's jobs (named by their scene, with status and dates) and a
    form to upload a scene and start a process; None: the caller needs an API key first."""
    if jobs is None:
        body = ("<main><p>This service needs an API key. It is kept in this browser "
                "(a cookie sent with GET requests only; the upload form sends it as the "
                "X-API-Key header) for the viewer, reports and uploads.</p>"
                '<form id="key-form"><label>API key <input id="key" type="password" '
                'autocomplete="off" size="40"></label> <button>Use key</button></form>'
                "<script>document.getElementById('key-form').onsubmit=(e)=>{e.preventDefault();"
                "document.cookie='polydda_key='+encodeURIComponent("
                "document.getElementById('key').value)+';path=/;SameSite=Strict';"
                "location.reload();};</script></main>")
        return _page("PolyDDA", root, _bar(root) + body)
    names = names or {}
    rows = []
    for j in jobs:
        links = " · ".join(f'<a href="{escape(h)}">{t}</a>' for t, h in job_links(j, root))
        active = "" if j.is_final else " data-active"
        rows.append(f"<tr data-job='{escape(j.id)}'{active}><td>{_job_name(j, names)}</td>"
                    f"<td>{escape(j.process)}</td>"
                    f"<td class='status status-{escape(j.status)}'>{escape(j.status)}</td>"
                    f"<td class='num progress'>{int(j.progress)} %</td>"
                    f"<td>{_when(j.created)}</td><td>{_when(j.finished)}</td>"
                    f"<td>{escape(j.message)}</td><td>{links}</td></tr>")
    table = ("<table id='jobs'><tr><th>scene</th><th>process</th><th>status</th>"
             "<th>progress</th><th>submitted</th><th>ended</th><th>message</th>"
             "<th>links</th></tr>" + "".join(rows) + "</table>"
             if rows else "<p id='no-jobs'>No jobs yet: upload a scene above, or submit one "
                          f"with <code>polydda submit</code> or <code>POST {root}/jobs</code>."
                          "</p>")
    body = (f"<main>{_upload_form(root)}<h2>Jobs</h2><p class='muted'>{total} job(s); the "
            f"newest first. <a href='{root}/jobs'>as JSON</a></p>{table}</main>")
    return _page("PolyDDA jobs", root, _bar(root) + body)


def _script_json(value: Any) -> str:
    """JSON to put inside a <script> element (no `<`, `>` or `&` that HTML would read)."""
    return (json.dumps(value).replace("<", "\\u003c").replace(">", "\\u003e")
            .replace("&", "\\u0026"))


def viewer_html(job: JobRecord, root: str, poll_ms: int = 2000, max_frames: int = 2000,
                play: bool = True) -> str:
    """The 3-D viewer of a job's result (loads service/static/viewer.js); it loads at most
    `max_frames` steps (every k-th recorded step beyond), shows the first and plays the run
    (unless `play` is false), with an axes triad (E, N, Up; north as the bold arrow) and a
    scale bar at the centre of rotation."""
    base = f"{root}/jobs/{job.id}"
    cfg = {"job": base, "frames": f"{base}/results/frames", "poll_ms": poll_ms,
           "max_frames": max_frames, "max_bytes": 48_000_000, "play": play}
    importmap = {"imports": {"three": f"{root}/static/three/three.module.min.js",
                             "three/addons/": f"{root}/static/three/",
                             "polydda/": f"{root}/static/"}}
    first = f"{cfg['frames']}?start=0&stop={cfg['max_frames']}&geometry=true"
    head = (f'<script type="importmap">{_script_json(importmap)}</script>'
            + "".join(f'<link rel="modulepreload" href="{root}/static/{m}">' for m in (
                "viewer.js", "three/three.module.min.js", "three/three.core.min.js",
                "three/OrbitControls.js", "section.js"))
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
            '<svg id="triad" width="110" height="110" role="img" aria-label="axes: East, '
            'North (bold arrow), Up"></svg>'
            '<div id="scalebar" title="length at the centre of rotation"><div class="bar">'
            '</div><span class="label"></span></div>'
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
            '<span id="section-controls" class="section-controls"></span>'
            '<label><input id="follow" type="checkbox" checked> follow</label>'
            '<button id="save" title="download the view as PNG">Save image</button>'
            '<label>fps <input id="fps" type="number" min="1" max="60" value="15" '
            'style="width:3.5em"></label>'
            '<span id="stride" class="muted"></span><span id="status" class="muted"></span>'
            '<span id="load-time" class="muted"></span>'
            "</div>"
            f'<script type="module" src="{root}/static/viewer.js"></script>')
    return _page(f"PolyDDA viewer {job.id[:8]}", root, body, cls="viewer", head=head)


def builder_html(root: str, can_run: bool, processes: dict[str, str]) -> str:
    """The scene builder (service/static/builder.js): a form bound to the scene's JSON,
    checked by POST /builder/validate as it changes, the blocks previewed in 3-D (POST
    /builder/preview), run as a job (`can_run`: this app has the job API)."""
    cfg = {"root": root, "can_run": can_run, "processes": processes,
           "schema": f"{root}/builder/schema"}
    importmap = {"imports": {"three": f"{root}/static/three/three.module.min.js",
                             "three/addons/": f"{root}/static/three/",
                             "polydda/": f"{root}/static/"}}
    head = (f'<script type="importmap">{_script_json(importmap)}</script>'
            f'<link rel="stylesheet" href="{root}/static/builder.css">'
            f'<script type="application/json" id="builder-config">{_script_json(cfg)}</script>')
    extra = ('<span>scene builder</span>'
             '<label class="file">Open scene <input id="open-scene" type="file" '
             'accept=".json,application/json"></label>'
             '<button id="download-scene" type="button">Download scene</button>')
    run = ("<div id='run-box'><label>Analysis <select id='run-process'>"
           "<option value='simulation'>run (DDA simulation)</option>"
           "<option value='limit-equilibrium'>le (limit equilibrium)</option>"
           "<option value='factor-of-safety'>fos (strength reduction)</option></select>"
           "</label> <button id='run' type='button'>Run</button> "
           "<progress id='run-progress' max='100' value='0' hidden></progress> "
           "<span id='run-status' role='status'></span> <span id='run-links'></span>"
           "<p id='run-conclusion'></p></div>"
           if can_run else
           "<div id='run-box'><p class='muted'>This page was opened without the job service "
           "(<code>polydda view RESULT.h5</code>): download the scene and run it with "
           "<code>polydda run</code>, or open the builder with <code>polydda view</code> "
           "alone or <code>polydda serve</code> to run it from here.</p></div>")
    body = (_bar(root, extra) +
            "<main class='builder'>"
            "<form id='scene-form' autocomplete='off' novalidate></form>"
            "<section id='side'>"
            "<div id='status-line'><span id='valid' role='status'></span> "
            "<span id='estimate' class='muted'></span></div>"
            "<ul id='problems' class='problems'></ul>"
            "<div id='preview-bar'><button id='preview' type='button'>Preview blocks</button> "
            "<span id='block-count'></span> <span id='preview-time' class='muted'></span> "
            "<label>colour <select id='preview-colour'><option value='verdict'>key-block "
            "verdict</option><option value='mode'>kinematic mode</option>"
            "<option value='block'>block</option></select></label></div>"
            "<div class='stage' id='preview-stage'><canvas id='preview-view'></canvas>"
            "<div id='preview-legend'></div></div>"
            "<div id='section-controls' class='section-controls'></div>"
            f"{run}"
            "<details id='json-box'><summary>Scene JSON (what Download gives)</summary>"
            "<pre id='scene-json'></pre></details>"
            "</section></main>"
            f'<script type="module" src="{root}/static/builder.js"></script>')
    return _page("PolyDDA scene builder", root, body, cls="builder", head=head)
