"""A local result file without a server: its report (`polydda report RESULT.h5`) and a small
app that serves the service's own 3-D viewer for it (`polydda view RESULT.h5`).

The app answers the URLs the viewer and its links use for a job (`/jobs/{id}`, `/viewer`,
`/results/frames`, `/report`, `/static`), for one job whose id is the file's stem, so the
viewer's page and script are the service's, unchanged.
"""

import re
import tempfile
import time
from pathlib import Path
from typing import Annotated, Any

from service.api.report import ReportParts, report_page
from service.jobs.store import JobRecord

#: the viewer's request bounds (as the service's frames route)
MAX_STEP = 100_000_000


def local_job(path: Path, status: str) -> JobRecord:
    """A simulation job standing for the result file at `path` (id: its stem): successful
    when the run completed, running while it is written (the viewer follows it), else
    failed."""
    ident = re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem) or "result"
    now = path.stat().st_mtime
    state = {"completed": "successful", "running": "running"}.get(status, "failed")
    return JobRecord(id=ident, process="simulation", status=state, client="local",
                     idempotency_key=None, request_hash=None, created=now, started=now,
                     finished=now, updated=now, progress=100.0, step=None,
                     simulated_time=None, duration=None, message=f"run {status}",
                     error_kind=None, cancel_requested=None, attempts=1, worker_pid=None)


def _build_warnings(scene_text: str | None) -> list[str]:
    """The scene's build warnings (cutting, fixed blocks, friction), which the result
    file's summary does not hold; none when the scene does not build here."""
    if not scene_text:
        return []
    from schemas.convert import build_model
    from schemas.errors import SceneError

    try:
        return list(build_model(scene_text).warnings)
    except (SceneError, ValueError):
        return []


def result_parts(path: Path, work_dir: Path, threshold: float | None = None) -> ReportParts:
    """Everything the report of the result file at `path` shows; its plots are made in
    `work_dir` and carried inline (data: URIs), so the page stands alone."""
    from engine.results.plots import plot_all
    from engine.results.reader import open_result
    from service.api.results import kinematics_part, png_uri, result_meta, scene_of

    with open_result(path) as r:
        scene_text = r.scene_json or ""
        meta = result_meta(r)
        summary = r.summary
        status, message = r.status, r.message
        pngs = plot_all(r, work_dir / "plots")
    documents = {}
    if summary:
        summary = dict(summary)
        summary["warnings"] = list(dict.fromkeys(
            [*_build_warnings(scene_text), *(summary.get("warnings") or [])]))
        documents["summary.json"] = summary
    snapshot = None
    plots = []
    for p in pngs:
        if p.name == "snapshot_final.png":
            snapshot = png_uri(p)
        else:
            plots.append((p.name, png_uri(p)))
    header = [("result file", str(path)), ("status", status), ("message", message or "–"),
              ("written", time.strftime("%Y-%m-%d %H:%M:%S",
                                        time.localtime(path.stat().st_mtime)))]
    parts = ReportParts(title=path.stem, process_title="DDA simulation", header=header,
                        scene_text=scene_text, documents=documents, plots=plots,
                        result_meta=meta, snapshot=snapshot,
                        kinematics=kinematics_part(work_dir, scene_of(scene_text)))
    if threshold is not None:
        parts.threshold = threshold
    return parts


def write_report(path: Path, out: Path, threshold: float | None = None) -> Path:
    """The standalone HTML report of the result file at `path`, written to `out`."""
    with tempfile.TemporaryDirectory(prefix="polydda-report-") as work:
        html = report_page(result_parts(path, Path(work), threshold), standalone=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(html, encoding="utf-8")
    return out


def _with_builder(app: Any) -> None:
    """The scene builder's page and API on a local app (no jobs: it previews, checks and
    downloads scenes), with the service's rate limits off and a local client."""
    from service.api.builder import router
    from service.api.problems import install_handlers
    from service.settings import Settings

    app.state.settings = Settings()
    app.state.rate_limiter = None
    app.state.auth_failures = None
    app.include_router(router)
    install_handlers(app)


def local_app(path: Path, max_frames: int = 2000) -> Any:
    """A FastAPI app serving the viewer, the frames and the report of one result file."""
    from fastapi import FastAPI, Query
    from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
    from fastapi.staticfiles import StaticFiles

    from engine.results.reader import open_result
    from service.api.frames import RangeError, encode_binary, to_json
    from service.api.frames import frames as make_frames
    from service.api.pages import viewer_html

    with open_result(path) as r:
        job = local_job(path, r.status)
    base = f"/jobs/{job.id}"
    app = FastAPI(title=f"PolyDDA viewer: {path.name}", docs_url=None, redoc_url=None,
                  openapi_url=None)
    app.mount("/static", StaticFiles(directory=Path(__file__).parents[1] / "static"),
              name="static")
    _with_builder(app)
    work = Path(tempfile.mkdtemp(prefix="polydda-view-"))
    app.state.work_dir = work

    @app.get("/")
    def home() -> RedirectResponse:
        return RedirectResponse(f"{base}/viewer")

    @app.get(base)
    def status() -> JSONResponse:
        with open_result(path) as r:  # a run still writing the file ends meanwhile
            now = local_job(path, r.status)
        return JSONResponse({"id": now.id, "process": now.process, "status": now.status,
                             "message": now.message, "result": str(path)})

    @app.get(f"{base}/viewer", response_class=HTMLResponse)
    def viewer() -> HTMLResponse:
        return HTMLResponse(viewer_html(job, "", max_frames=max_frames))

    @app.get(f"{base}/results")
    def results() -> JSONResponse:
        return JSONResponse({"id": job.id, "files": [str(path)]})

    @app.get(f"{base}/results/frames")
    def frames(start: Annotated[int, Query(ge=0, le=MAX_STEP)] = 0,
               stop: Annotated[int | None, Query(ge=0, le=MAX_STEP)] = None,
               stride: Annotated[int, Query(ge=1, le=MAX_STEP)] = 1,
               geometry: bool = True, contacts: bool = False,
               format: str = "binary") -> Response:
        with open_result(path) as r:
            try:
                payload = make_frames(r, start, stop, stride, with_geometry=geometry,
                                      contacts=contacts)
            except RangeError as exc:
                return JSONResponse({"detail": str(exc)}, status_code=422)
        if format == "json":
            return JSONResponse(to_json(payload))
        return Response(encode_binary(payload), media_type="application/octet-stream",
                        headers={"Cache-Control": "no-cache"})

    @app.get(f"{base}/report", response_class=HTMLResponse)
    def report() -> HTMLResponse:
        return HTMLResponse(report_page(result_parts(path, work), standalone=True))

    return app



def standalone_viewer(path: Path, max_frames: int = 300) -> str:
    """The viewer page of the result file at `path` as one HTML document that needs no
    server: the stylesheet, three.js, viewer.js and the frames (every k-th recorded step,
    at most `max_frames`) are inline, the frames answered by a fetch the page makes of its
    own data. For `polydda.Result._repr_html_` (Jupyter) and files to send."""
    import base64
    import json
    import math
    from html import escape as escape_html

    from engine.results.reader import open_result
    from service.api.frames import encode_binary
    from service.api.frames import frames as make_frames
    from service.api.pages import viewer_html

    static = Path(__file__).parents[1] / "static"
    with open_result(path) as r:
        job = local_job(path, r.status)
        stride = max(1, math.ceil(r.n_steps / max(1, max_frames)))
        payload = make_frames(r, 0, None, stride, with_geometry=True)
    # one payload holds every frame the page shows: as the viewer's first fetch it leaves
    # nothing to page on, and no contacts to ask for
    payload.header.update(n_steps=payload.header["count"], stride=1, start=0,
                          next_start=None, contacts_recorded=False)
    data = base64.b64encode(encode_binary(payload)).decode()

    def module(name: str, text: str | None = None) -> str:
        text = (static / name).read_text(encoding="utf-8") if text is None else text
        return "data:text/javascript;base64," + base64.b64encode(text.encode()).decode()

    three = (static / "three" / "three.module.min.js").read_text(encoding="utf-8")
    importmap = {"imports": {
        "three": module("", three.replace('"./three.core.min.js"', '"three/core"')),
        "three/core": module("three/three.core.min.js"),
        "three/addons/OrbitControls.js": module("three/OrbitControls.js"),
        "polydda/section.js": module("section.js")}}
    page = viewer_html(job, "", max_frames=max_frames, play=False)
    page = re.sub(r'<script type="importmap">.*?</script>',
                  f'<script type="importmap">{json.dumps(importmap)}</script>', page)
    page = re.sub(r'<link rel="(modulepreload|icon)"[^>]*>', "", page)
    page = page.replace('<link rel="stylesheet" href="/static/pages.css">',
                        f"<style>{(static / 'pages.css').read_text(encoding='utf-8')}</style>")
    first = ("(async () => { const b = atob('" + data + "'); const a = new Uint8Array(b.length);"
             " for (let i = 0; i < b.length; i++) a[i] = b.charCodeAt(i);"
             " return new Response(a.buffer); })()")
    page = re.sub(r"<script>window\.polyddaFirst = fetch\(.*?</script>",
                  lambda _: f"<script>window.polyddaFirst = {first};</script>", page)
    page = re.sub(r'<header class="bar">.*?</header>',
                  lambda _: f'<header class="bar"><h1>PolyDDA</h1>'
                            f"<span>{escape_html(path.name)} · "
                            "<span id='title-blocks'></span></span></header>", page, flags=re.S)
    script = (static / "viewer.js").read_text(encoding="utf-8")
    return page.replace('<script type="module" src="/static/viewer.js"></script>',
                        f'<script type="module">{script}</script>')
