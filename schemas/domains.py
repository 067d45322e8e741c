"""Domain shapes beyond a box and a polyhedron: a slope's section profile, a terrain (grid of
elevations, ESRI ASCII grid, CSV of x y z, or a surface mesh) and any closed mesh; and
their conversion to the engine's :mod:`engine.geometry.domains`.

A file is named by `file` (read from the scene's folder: the command line only; the REST
service refuses it and takes the same content inline as `data`, the file's text). Every
problem names the field and the file: an open mesh, a self-intersecting one, a grid with a
hole or a NaN.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, Field, model_validator

from engine.geometry.domains import (
    Terrain,
    crop_grid,
    grid_problems,
    profile_problems,
    slope_polyhedron,
    terrain,
)
from engine.geometry.polyhedron import Polyhedron, polyhedron_problems
from schemas.errors import Problems
from schemas.fields import MAX_COORDINATE, Coordinate, FilePath, Length, Point2, StrictModel


class _Model(StrictModel):
    """A part of the scene (strict JSON types: schemas.fields)."""


def _exactly_one(obj: BaseModel, names: tuple[str, ...]) -> None:
    given = [n for n in names if getattr(obj, n) is not None]
    if len(given) != 1:
        got = "none" if not given else " and ".join(f"'{n}'" for n in given)
        raise ValueError(f"give exactly one of {', '.join(repr(n) for n in names)} "
                         f"(got {got})")


DipDirection = Annotated[float, Field(ge=-360, le=360)]
#: the most triangles a mesh domain may have (its facets' planes all cut its bounding box)
MAX_MESH_PLANES = 200
#: the most nodes a terrain grid may have (two convex columns per cell)
MAX_GRID_NODES = 40_000


class SlopeSpec(_Model):
    """A slope's section extruded along its strike: `profile` points `[s, z]` from the toe
    to the crest (s m horizontal into the slope, against `dip_direction`; z the elevation
    m), closed by vertical ends down to `base`; `width` m along the strike from `origin`
    (the x, y of s = 0; the strike runs to the left seen from the valley)."""

    profile: Annotated[list[Point2], Field(min_length=2, max_length=1000)]
    dip_direction: DipDirection = Field(description="degrees: the direction the slope "
                                                    "faces (its face dips towards it)")
    width: Length = Field(description="m along the strike")
    base: Coordinate = Field(description="m, elevation of the flat base")
    origin: Point2 = Field(default_factory=lambda: [0.0, 0.0],
                           description="m, x and y of the profile's s = 0")


class GridSpec(_Model):
    """A regular grid of ground elevations given inline: nodes at `x0 + i dx`, `y0 + j dy`;
    `elevations[j][i]` m (rows from south to north)."""

    x0: Coordinate
    y0: Coordinate
    dx: Length
    dy: Length
    elevations: Annotated[list[list[Coordinate | None]], Field(min_length=2)]


class TerrainSpec(_Model):
    """The rock under a ground surface, closed down to `base` with vertical sides: a grid
    (`grid` inline, or `file`/`data` in ESRI ASCII grid `asc`, CSV of x y z `csv`), or a
    surface mesh (`stl`, `obj`, `ply`) sampled every `grid_spacing` m; clipped to
    `footprint` [x0, y0, x1, y1] (snapped inward to the grid's lines)."""

    grid: GridSpec | None = None
    file: FilePath | None = Field(None, description="path of the file, relative to the scene")
    data: str | None = Field(None, description="the file's text inline")
    format: Literal["asc", "csv", "stl", "obj", "ply"] | None = Field(
        None, description="of `data` (default: the file's extension)")
    footprint: Annotated[list[Coordinate], Field(min_length=4, max_length=4)] | None = None
    base: Coordinate = Field(description="m, elevation of the flat base")
    grid_spacing: Length | None = Field(
        None, description="m: a surface mesh is sampled on a grid this fine (required)")

    @model_validator(mode="after")
    def _one_source(self) -> TerrainSpec:
        _exactly_one(self, ("grid", "file", "data"))
        return self


class MeshSpec(_Model):
    """Any closed triangle mesh as the domain (`file` or inline `data`, STL/OBJ/PLY)."""

    file: FilePath | None = Field(None, description="path of the file, relative to the scene")
    data: str | None = Field(None, description="the file's text inline")
    format: Literal["stl", "obj", "ply"] | None = None

    @model_validator(mode="after")
    def _one_source(self) -> MeshSpec:
        _exactly_one(self, ("file", "data"))
        return self


# --------------------------------------------------------------------------- files


class _Source:
    """The text of a `file` or `data` field and the name to report it by."""

    def __init__(self, spec: TerrainSpec | MeshSpec, loc: str, base_dir: Path | None,
                 p: Problems) -> None:
        self.loc, self.text, self.fmt = loc, None, spec.format
        self.name = "the inline data"
        if spec.data is not None:
            self.text, self.field = spec.data, f"{loc}.data"
            return
        self.field = f"{loc}.file"
        if spec.file is None:
            return
        self.name = spec.file
        if base_dir is None:
            p.add(self.field, "files are read only by the command line; send the file's "
                  "text inline as 'data' (with 'format')")
            return
        path = (base_dir / spec.file)
        self.fmt = self.fmt or path.suffix.lower().lstrip(".")
        try:
            self.text = path.read_text(encoding="utf-8", errors="strict")
        except (OSError, UnicodeDecodeError) as exc:
            reason = "file not found" if isinstance(exc, FileNotFoundError) else str(exc)
            p.add(self.field, f"{spec.file}: cannot read ({reason})")


def read_esri_ascii(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Node x `(nx,)`, y `(ny,)` ascending and elevations `(ny, nx)` of an ESRI ASCII grid
    (values at cell centres; NODATA cells become NaN). ValueError on a bad header."""
    lines = text.splitlines()
    head: dict[str, float] = {}
    k = 0
    while k < len(lines) and lines[k].split() and lines[k].split()[0][0].isalpha():
        key, value = lines[k].split()[:2]
        head[key.lower()] = float(value)
        k += 1
    for need in ("ncols", "nrows", "cellsize"):
        if need not in head:
            raise ValueError(f"the ESRI ASCII grid's header has no '{need}'")
    nx, ny, cs = int(head["ncols"]), int(head["nrows"]), head["cellsize"]
    if not any(ln.strip() for ln in lines[k:]):
        raise ValueError("the grid has no values after its header")
    values = np.loadtxt(io.StringIO("\n".join(lines[k:])), dtype=float, ndmin=2)
    if values.shape != (ny, nx):
        raise ValueError(f"the grid has {values.shape[0]} rows of {values.shape[1]} values; "
                         f"its header says {ny} of {nx}")
    if "nodata_value" in head:
        values[values == head["nodata_value"]] = np.nan
    x0 = head.get("xllcenter", head.get("xllcorner", 0.0) + 0.5 * cs)
    y0 = head.get("yllcenter", head.get("yllcorner", 0.0) + 0.5 * cs)
    return x0 + cs * np.arange(nx), y0 + cs * np.arange(ny), values[::-1].copy()


def read_xyz_csv(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A regular grid from CSV rows `x, y, z` (any order; a header line is skipped): node
    x, y and elevations `(ny, nx)`, NaN where the grid has no row."""
    rows = [r for r in text.splitlines() if r.strip()]
    if rows and not rows[0].replace(",", " ").split()[0].lstrip("+-").replace(".", "", 1) \
            .replace("e", "", 1).replace("E", "", 1).isdigit():
        rows = rows[1:]
    if not rows:
        raise ValueError("the file has no rows 'x, y, z'")
    a = np.loadtxt(io.StringIO("\n".join(r.replace(",", " ") for r in rows)), ndmin=2)
    if a.shape[1] != 3:
        raise ValueError(f"rows must be 'x, y, z'; got {a.shape[1]} values per row")
    x, ix = np.unique(a[:, 0], return_inverse=True)
    y, iy = np.unique(a[:, 1], return_inverse=True)
    z = np.full((len(y), len(x)), np.nan)
    z[iy, ix] = a[:, 2]
    if len(x) < 2 or len(y) < 2:
        raise ValueError("the grid needs at least 2 x 2 nodes")
    steps = np.concatenate([np.diff(x) / np.diff(x).mean(), np.diff(y) / np.diff(y).mean()])
    if np.abs(steps - 1).max() > 1e-6:
        raise ValueError("the points do not lie on a regular grid (uneven spacing)")
    return x, y, z


def _load_mesh(src: _Source, p: Problems):  # noqa: ANN202 (trimesh.Trimesh)
    """The trimesh of a source, or None after a problem (its coordinates are checked
    before trimesh merges its vertices, which overflows on coordinates like 1e155)."""
    import trimesh

    try:
        mesh = trimesh.load(io.BytesIO(src.text.encode("utf-8")), file_type=src.fmt,
                            force="mesh", process=False)
        if len(mesh.faces) and _coordinates_problem(mesh.vertices, src.field, src.name, p):
            return None
        mesh.process()  # what trimesh.load(process=True) does after reading
    except Exception as exc:  # trimesh raises many kinds on a bad file
        p.add(src.field, f"{src.name}: not a readable {src.fmt} mesh ({exc})")
        return None
    if len(mesh.faces) == 0:
        p.add(src.field, f"{src.name}: the mesh has no triangles")
        return None
    return mesh


def _coordinates_problem(values: np.ndarray, field: str, name: str, p: Problems) -> bool:
    """True after recording a problem at `field`: coordinates (read from a file, or a
    grid's nodes) that are not finite or lie beyond ±MAX_COORDINATE m, the bound of the
    scene's own points."""
    with np.errstate(all="ignore"):
        a = np.asarray(values, float)
    if not np.all(np.isfinite(a)):
        p.add(field, f"{name}: a coordinate is not a finite number")
        return True
    if a.size and float(np.abs(a).max()) > MAX_COORDINATE:
        p.add(field, f"{name}: coordinates must lie within ±{MAX_COORDINATE:g} m "
              f"(got {float(np.abs(a).max()):g})")
        return True
    return False


def _self_intersections(vertices: np.ndarray, faces: np.ndarray) -> int:
    """How many pairs of triangles that share no vertex cross each other (an edge of one
    passes through the other)."""
    tri = vertices[faces]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    tol = 1e-9 * float(np.ptp(vertices, axis=0).max())
    count = 0
    for i in range(len(faces)):
        cand = np.flatnonzero(np.all((lo <= hi[i] + tol) & (hi >= lo[i] - tol), axis=1))
        cand = cand[cand > i]
        cand = cand[~np.isin(faces[cand], faces[i]).any(axis=1)]
        for j in cand:
            if _edges_cross(tri[i], tri[j], tol) or _edges_cross(tri[j], tri[i], tol):
                count += 1
    return count


def _edges_cross(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether an edge of triangle `a (3, 3)` passes through the interior of triangle `b`."""
    n = np.cross(b[1] - b[0], b[2] - b[0])
    n /= np.linalg.norm(n)
    d = (a - b[0]) @ n
    for k in range(3):
        p, q = a[k], a[(k + 1) % 3]
        dp, dq = d[k], d[(k + 1) % 3]
        if (dp > tol and dq < -tol) or (dp < -tol and dq > tol):
            x = p + (q - p) * dp / (dp - dq)
            inside = all(np.cross(b[(m + 1) % 3] - b[m], x - b[m]) @ n > tol for m in range(3))
            if inside:
                return True
    return False


def _closed_mesh(src: _Source, p: Problems) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices and triangles of a closed, outward, non-self-intersecting mesh."""
    mesh = _load_mesh(src, p)
    if mesh is None:
        return None
    if not mesh.is_watertight:
        p.add(src.field, f"{src.name}: the mesh is open (it has edges with one triangle): a "
              "domain must be a closed surface")
        return None
    if not mesh.is_winding_consistent:
        p.add(src.field, f"{src.name}: the triangles are not consistently oriented")
        return None
    v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    if mesh.volume < 0:
        f = f[:, ::-1]
    crossing = _self_intersections(v, f)
    if crossing:
        p.add(src.field, f"{src.name}: the mesh intersects itself ({crossing} pair(s) of "
              "triangles cross)")
        return None
    return v, f


def _mesh_heights(src: _Source, spacing: float, p: Problems
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A surface mesh sampled on a grid of `spacing` m over its footprint (vertical lines
    through each node; the highest crossing, NaN where none)."""
    mesh = _load_mesh(src, p)
    if mesh is None:
        return None
    v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    # the node counts first (floats): a fine spacing over a wide mesh is refused, not built
    nx, ny = (np.floor((hi[:2] - lo[:2]) / spacing + 1e-9) + 1).tolist()
    if nx * ny > MAX_GRID_NODES:
        p.add(f"{src.loc}.grid_spacing", f"samples {nx * ny:,.0f} nodes; the limit is "
              f"{MAX_GRID_NODES:,} (a coarser grid_spacing)")
        return None
    x = lo[0] + spacing * np.arange(int(nx))
    y = lo[1] + spacing * np.arange(int(ny))
    xx, yy = np.meshgrid(x, y)
    z = np.full(xx.shape, np.nan)
    eps = 1e-9 * float(np.ptp(v, axis=0).max())
    for t in v[f]:
        (x0, y0, _), (x1, y1, _), (x2, y2, _) = t
        det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if abs(det) <= eps * eps:
            continue  # a vertical triangle
        sel = ((xx >= t[:, 0].min() - eps) & (xx <= t[:, 0].max() + eps)
               & (yy >= t[:, 1].min() - eps) & (yy <= t[:, 1].max() + eps))
        px, py = xx[sel], yy[sel]
        a = ((y1 - y2) * (px - x2) + (x2 - x1) * (py - y2)) / det
        b = ((y2 - y0) * (px - x2) + (x0 - x2) * (py - y2)) / det
        c = 1 - a - b
        hit = (a >= -1e-9) & (b >= -1e-9) & (c >= -1e-9)
        h = a * t[0, 2] + b * t[1, 2] + c * t[2, 2]
        cur = z[sel]
        z[sel] = np.where(hit, np.fmax(cur, h), cur)
    return x, y, z


# --------------------------------------------------------------------------- build


def slope_domain(spec: SlopeSpec, loc: str, p: Problems) -> Polyhedron | None:
    """The slope's polyhedron, or None after a problem (recorded at `loc`)."""
    prof = np.asarray(spec.profile, float)
    problems = profile_problems(prof, spec.base)
    for msg in problems:
        p.add(f"{loc}.profile", msg)
    if problems:
        return None
    return slope_polyhedron(prof, spec.width, spec.dip_direction, spec.origin, spec.base)


def _grid(spec: TerrainSpec, loc: str, base_dir: Path | None, p: Problems
          ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, str, str]:
    """The grid of a terrain spec (None after a problem), its field and its name."""
    if spec.grid is not None:
        g = spec.grid
        rows = [[np.nan if v is None else v for v in r] for r in g.elevations]
        if len({len(r) for r in rows}) != 1:
            p.add(f"{loc}.grid.elevations", "every row must have as many values")
            return None, f"{loc}.grid.elevations", "the grid"
        z = np.asarray(rows, float)
        x, y = g.x0 + g.dx * np.arange(z.shape[1]), g.y0 + g.dy * np.arange(z.shape[0])
        if _coordinates_problem(np.concatenate([x, y]), f"{loc}.grid", "the grid's nodes", p):
            return None, f"{loc}.grid.elevations", "the grid"
        return (x, y, z), f"{loc}.grid.elevations", "the grid"
    src = _Source(spec, loc, base_dir, p)
    if src.text is None:
        return None, src.field, src.name
    grid = _read_grid(spec, src, p)
    if grid is not None:
        x, y, z = grid
        nodes = np.concatenate([x, y, z[np.isfinite(z)]])
        if _coordinates_problem(nodes, src.field, src.name, p):
            return None, src.field, src.name
    return grid, src.field, src.name


def _read_grid(spec: TerrainSpec, src: _Source, p: Problems
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The grid of a terrain's file or inline data (None after a problem)."""
    if src.fmt in ("stl", "obj", "ply"):
        if spec.grid_spacing is None:
            p.add(f"{src.loc}.grid_spacing", "a terrain given as a surface mesh needs "
                  "'grid_spacing' (m) to sample it on")
            return None
        return _mesh_heights(src, spec.grid_spacing, p)
    try:
        reader = read_esri_ascii if src.fmt == "asc" else read_xyz_csv
        if src.fmt not in ("asc", "csv"):
            raise ValueError(f"unknown format '{src.fmt}' (asc, csv, stl, obj or ply)")
        with np.errstate(all="ignore"):
            return reader(src.text)
    except (ValueError, IndexError) as exc:  # what numpy's text reader raises on bad text
        p.add(src.field, f"{src.name}: not a readable {src.fmt} grid ({exc})")
        return None


def terrain_domain(spec: TerrainSpec, loc: str, base_dir: Path | None, p: Problems
                   ) -> Terrain | None:
    """The terrain's polyhedron and columns, or None after a problem."""
    grid, field, name = _grid(spec, loc, base_dir, p)
    if grid is None:
        return None
    x, y, z = grid
    if spec.footprint is not None:
        x, y, z = crop_grid(x, y, z, np.asarray(spec.footprint, float))
    if len(x) * len(y) > MAX_GRID_NODES:
        p.add(field, f"{name}: {len(x) * len(y):,} nodes; the limit is {MAX_GRID_NODES:,} "
              "(clip it with 'footprint')")
        return None
    problems = grid_problems(x, y, z, spec.base)
    for msg in problems:
        p.add(field, f"{name}: {msg}")
    return None if problems else terrain(x, y, z, spec.base)


def mesh_domain(spec: MeshSpec, loc: str, base_dir: Path | None, p: Problems
                ) -> Polyhedron | None:
    """The closed mesh as a polyhedron, or None after a problem."""
    src = _Source(spec, loc, base_dir, p)
    if src.text is None:
        return None
    if src.fmt not in ("stl", "obj", "ply"):
        p.add(src.field, f"{src.name}: unknown mesh format '{src.fmt}' (stl, obj or ply)")
        return None
    got = _closed_mesh(src, p)
    if got is None:
        return None
    v, f = got
    poly = Polyhedron.from_faces(v, f.tolist())
    planes = np.unique(np.round(np.column_stack([poly.face_normals, poly.face_offsets]), 9),
                       axis=0)
    if len(planes) > MAX_MESH_PLANES:
        p.add(src.field, f"{src.name}: {len(planes)} distinct facet planes; the limit is "
              f"{MAX_MESH_PLANES} (for a ground surface use 'terrain')")
        return None
    for msg in polyhedron_problems(v, f.tolist()):
        p.add(src.field, f"{src.name}: {msg}")
        return None
    return poly
