"""The scene builder: a page (service/static/builder.js) that makes a scene from a form, and
the small API it calls. Every rule is the scene schema's: the page sends the scene as it
stands and shows the problems these routes return (the messages of POST /jobs).

- `GET /builder`: the page (offline: its scripts and three.js come from /static);
- `POST /builder/validate`: the scene's structure checked (milliseconds: the 422 of POST
  /jobs, or the blocks the joints would cut the domain into, estimated);
- `POST /builder/preview`: the blocks cut, as meshes with their key-block verdict and
  kinematic mode (service.api.preview), in the scene-checking processes within the
  service's size limits, the preview's time limit and the client's checking budget;
- `POST /builder/stereonet`: measured dip / dip direction (CSV text) fitted into sets as
  `polydda stereonet` fits them, with the contoured stereonet as a PNG;
- `POST /builder/terrain`: a GeoTIFF elevation model as the scene's inline terrain grid.
"""

from __future__ import annotations

import base64
import io
import json
import math
import time
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from service.api.dependencies import ClientDep, RootDep, SceneBody, _client
from service.api.problems import Problem, invalid_scene, problem_responses
from service.settings import Settings

router = APIRouter(dependencies=[Depends(_client)], tags=["builder"])

#: the body of the validate and preview routes: a scene, as POST /jobs takes it
_SCENE_BODY = {"requestBody": {"required": True, "description": "the scene", "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/Scene"}}}}}

#: the most measurements the stereonet route fits
MAX_MEASUREMENTS = 20_000


def _settings(request: Request) -> Settings:
    """The app's settings (the service's; `polydda view`'s app has defaults)."""
    return getattr(request.app.state, "settings", None) or Settings()


def _checking(request: Request, settings: Settings) -> Any:
    """The app's scene-checking pool, limiter and budget (made on first use by an app
    that has none: `polydda view`)."""
    state = request.app.state
    if getattr(state, "validation_pool", None) is None:
        import anyio

        from service.api.validation import ValidationBudget, shared_pool

        state.validation_pool = shared_pool(settings.validation_workers,
                                            settings.worker_env(), settings.worker_nice)
        state.validation_limiter = anyio.CapacityLimiter(settings.validation_workers)
        state.validation_threads = anyio.CapacityLimiter(settings.validation_workers)
        state.validation_budget = ValidationBudget(settings.validation_budget)
    return state


@router.get("/builder", response_class=HTMLResponse, operation_id="builderPage",
            summary="The scene builder: a form that makes a scene, validated as you type, "
                    "its blocks previewed in 3-D; runs it as a job",
            responses={200: {"content": {"text/html": {"schema": {"type": "string"}}}}})
def builder_page(request: Request, root: RootDep) -> HTMLResponse:
    from service.api.pages import builder_html
    from service.jobs.processes import PROCESSES

    can_run = hasattr(request.app.state, "store")
    return HTMLResponse(builder_html(root, can_run, {p.id: p.title for p in
                                                     PROCESSES.values()}))


@router.get("/builder/schema", operation_id="builderSchema",
            summary="The scene's JSON Schema (the builder's field help and bounds)")
def builder_schema() -> dict[str, Any]:
    from schemas.scene import scene_json_schema

    return scene_json_schema()


def _structure(data: Any, settings: Settings) -> Any:
    from service.api.submission import check_structure, unwrap

    _, scene = unwrap(data)
    return check_structure(scene, settings), scene


@router.post("/builder/validate", operation_id="builderValidate", openapi_extra=_SCENE_BODY,
             summary="Check a scene's fields (what POST /jobs checks before cutting): 200 "
                     "with the blocks its joints would cut the domain into, or 422 naming "
                     "every bad field",
             responses=problem_responses(413, 415, 422))
async def builder_validate(data: SceneBody, request: Request) -> dict[str, Any]:
    from schemas.scene import estimate_cut_blocks

    settings = _settings(request)
    scene, _ = await run_in_threadpool(_structure, data, settings)
    return {"valid": True, "estimated_blocks": round(estimate_cut_blocks(scene)),
            "problems": []}


@router.post("/builder/preview", operation_id="builderPreview", openapi_extra=_SCENE_BODY,
             summary="Cut a scene's blocks and give them as meshes with each block's "
                     "key-block verdict and kinematic mode (nothing runs)",
             description="Bounded as POST /jobs is: the service's size limits first "
                         "(POLYDDA_MAX_BLOCKS: the blocks the joints would cut the domain "
                         "into, estimated), then the cutting in the scene-checking processes "
                         "within POLYDDA_PREVIEW_TIMEOUT seconds (longer: 422) and the "
                         "client's checking budget (429).",
             responses=problem_responses(413, 415, 422, 429, 503))
async def builder_preview(data: SceneBody, request: Request,
                          client: ClientDep) -> JSONResponse:
    import anyio

    settings = _settings(request)
    _, scene_data = await run_in_threadpool(_structure, data, settings)
    state = _checking(request, settings)
    timeout = min(settings.preview_timeout, settings.validation_timeout)
    text = json.dumps(scene_data, ensure_ascii=False)
    async with state.validation_limiter:
        wait = state.validation_budget.wait_for(client.id)
        if wait > 0:
            raise Problem(429, "validation-budget-exhausted", "Scene-checking budget used up",
                          f"this client may use {settings.validation_budget:g} s of scene "
                          "checking per minute (POLYDDA_VALIDATION_BUDGET); retry in "
                          f"{wait:.0f} s", headers={"Retry-After": str(max(1, math.ceil(wait)))})
        start = time.monotonic()
        try:
            verdict = await anyio.to_thread.run_sync(
                lambda: _check_preview(state.validation_pool, text, timeout),
                limiter=state.validation_threads)
        finally:
            state.validation_budget.charge(client.id, time.monotonic() - start)
    if verdict.problems:
        raise invalid_scene(verdict.problems)
    doc = dict(verdict.preview or {})
    doc["seconds"] = round(verdict.seconds, 3)
    return JSONResponse(doc)


def _check_preview(pool: Any, text: str, timeout: float) -> Any:
    """The pool's preview of a scene; its time limit named as the preview's."""
    from service.api.submission import _check

    class _Preview:
        def check(self, text: str, timeout: float) -> Any:
            return pool.check(text, timeout, preview=True)

    try:
        return _check(_Preview(), text, timeout)
    except Problem as exc:
        if exc.status == 422 and exc.errors and "longer than" in exc.errors[0]["msg"]:
            raise invalid_scene([{"loc": "", "msg": (
                f"cutting the scene's blocks for the preview took longer than {timeout:g} s "
                "(POLYDDA_PREVIEW_TIMEOUT): make it smaller (fewer blocks: larger "
                "spacings or a smaller domain)")}]) from None
        raise


class Measurements(BaseModel):
    """Measured planes as CSV text (columns dip and dip_direction, as `polydda stereonet`
    reads them) and how many sets to pick."""

    csv: Annotated[str, Field(max_length=2_000_000)]
    sets: Annotated[int, Field(ge=1, le=12)] = 2
    seed: Annotated[int, Field(ge=0)] = 0
    names: list[Annotated[str, Field(min_length=1, max_length=100)]] | None = None


@router.post("/builder/stereonet", operation_id="builderStereonet",
             summary="Fit measured orientations (CSV) into joint sets as `polydda "
                     "stereonet` does: each set's Fisher mean, κ and cone, and the "
                     "stereonet as PNG",
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/json": {"schema": Measurements.model_json_schema()}}}},
             responses=problem_responses(413, 415, 422))
async def builder_stereonet(data: SceneBody) -> dict[str, Any]:
    from pydantic import ValidationError

    try:  # the body read as the scenes are (size, JSON), then its fields checked
        body = Measurements.model_validate(data)
    except ValidationError as exc:
        raise invalid_scene([{"loc": ".".join(str(p) for p in e["loc"]) or "body",
                              "msg": e["msg"]} for e in exc.errors()]) from None
    return await run_in_threadpool(_stereonet, body)


def _stereonet(body: Measurements) -> dict[str, Any]:
    import tempfile
    from pathlib import Path

    from engine.analyses.orientations import fit_sets, plot_pole_density
    from schemas.errors import SceneError
    from service.documents import parse_measurements

    try:
        dips, ddirs = parse_measurements(body.csv, "the measurements")
    except SceneError as exc:
        raise invalid_scene([{"loc": "csv", "msg": p["msg"]} for p in exc.problems]) from None
    if len(dips) > MAX_MEASUREMENTS:
        raise invalid_scene([{"loc": "csv", "msg": f"{len(dips):,} measurements; the limit "
                              f"is {MAX_MEASUREMENTS:,}"}])
    if body.sets > len(dips):
        raise invalid_scene([{"loc": "sets", "msg": f"cannot pick {body.sets} sets from "
                              f"{len(dips)} measurements"}])
    if body.names is not None and len(body.names) != body.sets:
        raise invalid_scene([{"loc": "names", "msg": f"{len(body.names)} names for "
                              f"{body.sets} sets"}])
    sets, labels = fit_sets(dips, ddirs, body.sets, seed=body.seed, names=body.names)
    with tempfile.TemporaryDirectory(prefix="polydda-stereonet-") as work:
        png = plot_pole_density(dips, ddirs, sets, labels, Path(work) / "net.png")
        uri = "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode()
    return {"measurements": len(dips), "sets": [s.as_dict() for s in sets],
            "stereonet": uri}


@router.post("/builder/terrain", operation_id="builderTerrain",
             summary="A GeoTIFF elevation model as the scene's inline terrain grid "
                     "(domain.terrain.grid: x0, y0, dx, dy, elevations south to north)",
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string",
                                                         "format": "binary"}}}}},
             responses=problem_responses(413, 422))
async def builder_terrain(request: Request, step: Annotated[int, Query(
        ge=1, le=1000, description="keep every step-th node along each axis")] = 1
                          ) -> dict[str, Any]:
    settings = _settings(request)
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > settings.max_body_bytes:
            raise Problem(413, "body-too-large", "Request body too large",
                          f"the body may have at most {settings.max_body_bytes:,} bytes")
    return await run_in_threadpool(geotiff_grid, bytes(raw), step)


def geotiff_grid(data: bytes, step: int = 1) -> dict[str, Any]:
    """The grid of a GeoTIFF (its first band; the model tie point and pixel scale give the
    nodes, at the pixels' centres; GDAL's no-data value and NaN become gaps): `{"grid":
    {...}}` as domain.terrain.grid takes it. 422 naming what is wrong."""
    import numpy as np
    import tifffile

    from schemas.domains import MAX_GRID_NODES

    def bad(msg: str) -> Problem:
        return invalid_scene([{"loc": "terrain", "msg": msg}])

    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            page = tif.pages[0]
            tags = {t.name: t.value for t in page.tags.values()}
            z = np.asarray(page.asarray(), float)
    except Exception as exc:  # tifffile raises many kinds on a file that is not a TIFF
        raise bad(f"not a readable GeoTIFF ({exc})") from None
    if z.ndim == 3:
        z = z[..., 0] if z.shape[-1] <= 4 else z[0]
    if z.ndim != 2 or min(z.shape) < 2:
        raise bad(f"the image is not a grid of elevations (shape {z.shape})")
    scale, tie = tags.get("ModelPixelScaleTag"), tags.get("ModelTiepointTag")
    if not scale or not tie or len(tie) < 6:
        raise bad("the TIFF has no GeoTIFF georeference (ModelPixelScale and ModelTiepoint "
                  "tags): export it as a GeoTIFF, or as CSV of x, y, z")
    nodata = tags.get("GDAL_NODATA")
    if nodata not in (None, ""):
        try:
            z[z == float(str(nodata).strip("\x00 "))] = np.nan
        except ValueError:
            pass
    sx, sy = float(scale[0]), float(scale[1])
    i0, j0, x_tie, y_tie = float(tie[0]), float(tie[1]), float(tie[3]), float(tie[4])
    z = z[::step, ::step]
    ny, nx = z.shape
    if nx * ny > MAX_GRID_NODES:
        raise bad(f"{nx * ny:,} nodes; the limit is {MAX_GRID_NODES:,} (keep every k-th "
                  f"node: step={math.ceil(math.sqrt(nx * ny / MAX_GRID_NODES))})")
    # raster rows run from north to south, pixel (0, 0) at the tie point's corner
    x0 = x_tie + (0.5 - i0) * sx
    y_top = y_tie - (0.5 - j0) * sy
    dx, dy = sx * step, sy * step
    rows = z[::-1]
    y0 = y_top - (ny - 1) * dy
    elevations = [[None if not math.isfinite(v) else round(float(v), 4) for v in row]
                  for row in rows]
    return {"grid": {"x0": x0, "y0": y0, "dx": dx, "dy": dy, "elevations": elevations},
            "nodes": nx * ny}
