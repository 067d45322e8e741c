"""Scene -> engine :class:`~engine.model.Model`: units, joints, cutting, names, selections.

Degrees become radians, dip / dip direction become unit normals, joint sets become planes,
the domain is cut into blocks, explicit blocks are checked (closed, oriented, not
overlapping) and every block reference is resolved to an index. Every user mistake is
reported as a :class:`~schemas.errors.SceneError` naming the field.

Block order in the model: cut blocks first, sorted by centroid z, then y, then x (lowest
first, named `prefix`1, 2, ...), then explicit blocks in the order given.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from engine import user_entry
from engine.analyses.kinematics import JointSet, SlopeFace
from engine.geometry.boxes import box_pairs
from engine.geometry.joints import JointPlane
from engine.geometry.polyhedron import (
    Polyhedron,
    dip_normal,
    face_normals_areas,
    polyhedron_problems,
    winding_numbers,
)
from engine.loads.bolts import Bolt
from engine.loads.seismic import GroundMotion, SeismicLoad
from engine.loads.water import Water
from engine.model import (
    AnalysisControls,
    Block,
    FixedPoint,
    JointMaterial,
    Material,
    Model,
    PointLoad,
    SeismicCoefficientControls,
    StrengthReductionControls,
)
from engine.tolerances import DEFAULT_TOLERANCES
from schemas.errors import Problems, SceneError, fmt_num, fmt_point, format_loc
from schemas.scene import (
    BoltPatternSpec,
    BoltSpec,
    BoxSpec,
    CriticalSeismicSpec,
    FactorOfSafetySpec,
    Scene,
    Selection,
    load_scene,
    scene_problems,
)

if TYPE_CHECKING:  # the stages' module imports the dynamics (numba): only staged scenes
    from engine.step.stages import Stage

#: interiors of two blocks that overlap deeper than this fraction of the model size clash
OVERLAP_TOLERANCE = 1e-6
#: a point within this fraction of the model size of a block's surface is on the block
ON_SURFACE_TOLERANCE = 1e-6


@dataclass
class BuildResult:
    """The engine model and what the scene called things.

    `block_names[k]`, `block_sources[k]` ("cut" or "explicit") describe `model.blocks[k]`;
    `warnings` are notes that did not stop the build (e.g. from the block cutting).
    """

    model: Model
    block_names: list[str]
    block_sources: list[str]
    material_names: list[str]
    joint_material_names: list[str]
    joint_names: list[str]
    warnings: list[str] = field(default_factory=list)
    factor_of_safety: StrengthReductionControls | None = None
    seismic_coefficient: SeismicCoefficientControls | None = None
    #: a staged run's stages (empty: one run of the model as it is)
    stages: list[Stage] = field(default_factory=list)
    #: the excavation each block lies in (None: rock that stays), by block index
    excavated: list[str | None] = field(default_factory=list)
    #: the scene's excavations in order (excavation k's surface carries face tag
    #: engine.geometry.excavations.EXCAVATION_TAG_BASE + k)
    excavation_names: list[str] = field(default_factory=list)

    def block_index(self, name: str) -> int:
        """Index of the block called `name` (KeyError if none)."""
        try:
            return self.block_names.index(name)
        except ValueError:
            raise KeyError(name) from None


# --------------------------------------------------------------------------- shapes


BOX_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def box_vertices(lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
    """The 8 corners `(8, 3)` of a box, bottom ring then top ring (counter-clockwise)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return np.array(
        [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
         [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=float
    )


def box_polyhedron(box: BoxSpec) -> Polyhedron:
    """A box as a Polyhedron with 6 quads, counter-clockwise seen from outside."""
    return Polyhedron.from_faces(box_vertices(box.min, box.max), BOX_FACES)


def _geometry_loc(base: str, msg: str) -> str:
    """`base.vertices` for problems with the vertex list, `base.faces` for the rest."""
    vertex_problem = msg.startswith(("needs at least 4 vertices", "vertex coordinates"))
    return f"{base}.vertices" if vertex_problem else f"{base}.faces"


# --------------------------------------------------------------------------- joints


def _polygon_problem(poly: np.ndarray, normal: np.ndarray, point: np.ndarray) -> str | None:
    """Why `poly (k, 3)` is not a convex polygon on the plane (normal, point), or None."""
    size = float(np.ptp(poly, axis=0).max())
    if size <= 0:
        return "the polygon has no size"
    off = np.abs((poly - point) @ normal).max()
    if off > 1e-4 * size + 1e-9:
        return (f"the polygon is not on the joint plane: a corner is {off:.3g} m off it "
                "(the plane goes through 'point' with the given dip and dip direction)")
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    q = np.stack([(poly - point) @ u, (poly - point) @ v], axis=1)
    e = np.roll(q, -1, axis=0) - q
    cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    eps = 1e-9 * size * size
    if np.any(np.linalg.norm(e, axis=1) <= 1e-9 * size):
        return "the polygon repeats a corner"
    if not (np.all(cross >= -eps) or np.all(cross <= eps)) or np.all(np.abs(cross) <= eps):
        return "the polygon must be convex with its corners in order around it"
    return None


def _joint_planes(scene: Scene, domain: Polyhedron, p: Problems) -> list[JointPlane]:
    from engine.geometry.joints import disc_polygon, joint_set_planes

    planes: list[JointPlane] = []
    for k, j in enumerate(scene.joints):
        loc = f"joints[{k}]" + (f" ('{j.name}')" if j.name else "")
        normal = dip_normal(j.dip, j.dip_direction)
        point = np.asarray(j.point, float)
        extent = None
        if j.extent is not None and j.extent.polygon is not None:
            extent = np.asarray(j.extent.polygon, float)
            problem = _polygon_problem(extent, normal, point)
            if problem:
                p.add(f"{loc}.extent.polygon", problem)
                continue
            extent = extent - np.outer((extent - point) @ normal, normal)  # onto the plane
        elif j.extent is not None:
            disc = j.extent.disc
            center = point if disc.center is None else np.asarray(disc.center, float)
            off = abs(float((center - point) @ normal))
            if off > 1e-4 * disc.radius + 1e-9:
                p.add(f"{loc}.extent.disc.center",
                      f"the disc center is {off:.3g} m off the joint plane")
                continue
            center = center - ((center - point) @ normal) * normal
            extent = np.asarray(disc_polygon(center, normal, disc.radius, sides=disc.sides))
        if j.spacing is not None:
            planes.extend(joint_set_planes(normal, point, j.spacing, domain, k, extent=extent))
        else:
            planes.append(JointPlane(normal=normal, point=point, tag=k, extent=extent))
    return planes


def _name_joints(text: str, scene: Scene) -> str:
    """An engine warning with its joint tags named as errors name joints
    (`joint 0` -> `joints[0] ('J1')`; the engine's internal plane numbers dropped)."""
    text = re.sub(r" \(joint plane \d+\)", "", text)
    return re.sub(r"\bjoint (\d+)\b",
                  lambda m: f"joints[{m.group(1)}] ('{scene.joint_name(int(m.group(1)))}')",
                  text)


def _domain(scene: Scene, p: Problems, base_dir: Path | None
            ) -> tuple[Polyhedron | None, list[Polyhedron] | None]:
    """The domain's closed surface and, for a terrain, its convex columns."""
    from schemas.domains import mesh_domain, slope_domain, terrain_domain

    d = scene.domain
    if d.box is not None:
        return box_polyhedron(d.box), None
    if d.slope is not None:
        return slope_domain(d.slope, "domain.slope", p), None
    if d.terrain is not None:
        t = terrain_domain(d.terrain, "domain.terrain", base_dir, p)
        return (None, None) if t is None else (t.domain, list(t.columns))
    if d.mesh is not None:
        return mesh_domain(d.mesh, "domain.mesh", base_dir, p), None
    problems = polyhedron_problems(np.asarray(d.polyhedron.vertices, float),
                                   d.polyhedron.faces)
    for msg in problems:
        p.add(_geometry_loc("domain.polyhedron", msg), msg)
    if problems:
        return None, None
    return Polyhedron.from_faces(d.polyhedron.vertices, d.polyhedron.faces), None


#: the last few cuts, by the domain, the joint planes and the terrain's columns: the
#: realisations of a sweep that vary strengths, water or loads cut the same blocks (and the
#: blocks are immutable)
_CUTS: dict[tuple[Any, ...], Any] = {}
_CUTS_KEPT = 4


def _shape_key(q: Polyhedron) -> tuple[bytes, bytes, bytes]:
    return q.vertices.tobytes(), q.face_indptr.tobytes(), q.face_indices.tobytes()


def _cut(domain: Polyhedron, planes: list[JointPlane], min_volume: float | None,
         min_width: float | None, tiles: list[Polyhedron] | None = None) -> Any:
    """`cut_blocks` of the domain by the planes, from the cache when cut before."""
    from engine.geometry.cutting.cut import cut_blocks

    key = (_shape_key(domain), min_volume, min_width,
           tuple((pl.normal.tobytes(), pl.point.tobytes(), pl.tag,
                  None if pl.extent is None else np.asarray(pl.extent).tobytes())
                 for pl in planes),
           None if tiles is None else tuple(_shape_key(t) for t in tiles))
    hit = _CUTS.get(key)
    if hit is None:
        hit = cut_blocks(domain, planes, min_block_volume=min_volume,
                         min_block_width=min_width, tiles=tiles)
        if len(_CUTS) >= _CUTS_KEPT:
            _CUTS.pop(next(iter(_CUTS)))
        _CUTS[key] = hit
    return hit


def _cut_domain(scene: Scene, p: Problems, warnings: list[str], base_dir: Path | None = None
                ) -> tuple[list[Polyhedron], list[str | None]]:
    """The blocks cut from the domain, sorted by centroid z, y, x (empty if no domain), and
    the excavation each lies in (None: rock that stays)."""
    d = scene.domain
    if d is None:
        return [], []
    from engine.geometry.cutting.cut import cut_blocks
    from engine.geometry.excavations import _tiles
    from schemas.stage_convert import excavate_after, excavate_before, excavation_solids

    domain, tiles = _domain(scene, p, base_dir)
    solids = excavation_solids(scene, p)
    if domain is None or p:
        return [], []
    pieces = excavate_before(scene, solids, domain, p) if scene.excavations else [domain]
    if len(pieces) != 1 or pieces[0] is not domain:
        tiles = None
    planes: list[JointPlane] = []
    if not scene.joints:  # one block per piece, a concave one with its convex pieces
        from engine.geometry.cutting.cut import convex_decomposition

        blocks = [q if q.is_convex or q.pieces else
                  cut_blocks(q, [], min_block_volume=0.0, min_block_width=0.0,
                             tiles=tiles).blocks[0] if tiles is not None else
                  convex_decomposition(q) for q in pieces]
    else:
        planes = _joint_planes(scene, domain, p)
        if p:
            return [], []
        blocks = []
        for piece in pieces:
            result = _cut(piece, planes, d.min_block_volume, d.min_block_width,
                          tiles if tiles is not None else
                          (_tiles(piece) if piece.pieces else None))
            for w in result.warnings:
                w = _name_joints(w, scene)
                if w not in warnings:
                    warnings.append(w)
            blocks.extend(result.blocks)
    if not blocks:
        p.add("joints" if scene.joints else "domain", "cutting the domain left no blocks")
        return [], []
    owner: list[str | None] = [None] * len(blocks)
    if scene.excavations:
        blocks, owner = excavate_after(scene, solids, blocks, domain, planes, p)
        used = {int(t) for b in blocks for t in b.face_tags}
        warnings[:] = [w for w in warnings if not any(
            w.startswith(f"joints[{k}] ") and k in used for k in range(len(scene.joints)))]
    scale = float(np.ptp(domain.bounds, axis=0).max())
    grid = DEFAULT_TOLERANCES.lengths(scale).on_plane * 1e3
    c = np.array([b.centroid for b in blocks]) / grid
    order = np.lexsort((np.round(c[:, 0]), np.round(c[:, 1]), np.round(c[:, 2])))
    return [blocks[i] for i in order], [owner[i] for i in order]


def _explicit_blocks(scene: Scene, p: Problems) -> list[Polyhedron | None]:
    out: list[Polyhedron | None] = []
    for k, b in enumerate(scene.blocks):
        loc = f"blocks[{k}]" + (f" ('{b.name}')" if b.name else "")
        problems = polyhedron_problems(np.asarray(b.vertices, float), b.faces)
        for msg in problems:
            p.add(_geometry_loc(loc, msg), msg)
        if problems:
            out.append(None)
            continue
        poly = Polyhedron.from_faces(b.vertices, b.faces)
        if not poly.is_convex:
            from engine.geometry.cutting.cut import convex_decomposition

            poly = convex_decomposition(poly)
        out.append(poly)
    return out


# --------------------------------------------------------------------------- overlap


def _halfspaces(poly: Polyhedron) -> list[tuple[np.ndarray, np.ndarray]]:
    """`(normals (m, 3), offsets (m,))` of every convex piece: inside is `n . x <= d`."""
    out = []
    for piece in poly.convex_pieces():
        normals, _ = face_normals_areas(poly.vertices, piece.face_indptr, piece.face_indices)
        first = poly.vertices[piece.face_indices[piece.face_indptr[:-1]]]
        out.append((normals, np.einsum("ij,ij->i", normals, first)))
    return out


def overlap_depth(a: Polyhedron, b: Polyhedron) -> float:
    """Radius (m) of the largest ball inside both blocks (<= 0: they do not overlap).

    Exact for convex pieces (a linear program per pair of pieces).
    """
    from scipy.optimize import linprog  # imported here: 0.3 s, only scenes with such pairs

    best = -np.inf
    for na, da in _halfspaces(a):
        for nb, db in _halfspaces(b):
            A = np.vstack([na, nb])
            rhs = np.concatenate([da, db])
            res = linprog(
                c=[0.0, 0.0, 0.0, -1.0],
                A_ub=np.hstack([A, np.ones((len(A), 1))]),
                b_ub=rhs,
                bounds=[(None, None)] * 3 + [(None, float(np.ptp(a.bounds, axis=0).max()))],
                method="highs",
            )
            if res.status == 0:
                best = max(best, -float(res.fun))
    return float(best)


def _check_overlaps(
    polys: list[Polyhedron], names: list[str], locs: dict[int, str], fixed: list[bool],
    scale: float, p: Problems,
) -> None:
    """Report every pair of overlapping blocks where one is explicit (in `locs`).

    Two fixed blocks may overlap: they never touch each other in the analysis.
    """
    if len(polys) < 2 or not locs:
        return
    tol = OVERLAP_TOLERANCE * scale
    lo = np.array([q.bounds[0] for q in polys]) + tol
    hi = np.array([q.bounds[1] for q in polys]) - tol
    for i, j in box_pairs(lo, np.maximum(hi, lo)).tolist():
        if (i not in locs and j not in locs) or (fixed[i] and fixed[j]):
            continue  # two cut blocks are disjoint by construction
        if not np.all((lo[i] < hi[j]) & (lo[j] < hi[i])):
            continue
        depth = overlap_depth(polys[i], polys[j])
        if depth > tol:
            first, second = (j, i) if j in locs and i not in locs else (i, j)
            p.add(locs[first], f"blocks '{names[first]}' and '{names[second]}' overlap "
                  f"(by up to {2 * depth:.3g} m)")


# --------------------------------------------------------------------------- selections


def _on_surface(poly: Polyhedron, point: np.ndarray, tol: float) -> bool:
    """True if `point` is within `tol` of a face polygon of `poly`."""
    dist = poly.face_normals @ point - poly.face_offsets
    for f in np.flatnonzero(np.abs(dist) <= tol):
        n = poly.face_normals[f]
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        ring = poly.vertices[poly.faces[f]]
        a = np.stack([ring @ u, ring @ v], axis=1)
        b = np.roll(a, -1, axis=0)
        x, y = float(point @ u), float(point @ v)
        crosses = (a[:, 1] > y) != (b[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            xi = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        if np.count_nonzero(crosses & (x < xi)) % 2 == 1:
            return True
        e = b - a
        t = np.clip(((x - a[:, 0]) * e[:, 0] + (y - a[:, 1]) * e[:, 1])
                    / np.maximum((e * e).sum(axis=1), 1e-300), 0.0, 1.0)
        gap = np.hypot(a[:, 0] + t * e[:, 0] - x, a[:, 1] + t * e[:, 1] - y).min()
        if gap <= tol:
            return True
    return False


class _Locator:
    """Finds blocks by name, by a point inside, or by centroid box."""

    def __init__(self, polys: list[Polyhedron], names: list[str], scale: float):
        self.polys, self.names = polys, names
        self.index = {n: k for k, n in enumerate(names)}
        self.tol = ON_SURFACE_TOLERANCE * scale
        self.lo = np.array([q.bounds[0] for q in polys]) - self.tol
        self.hi = np.array([q.bounds[1] for q in polys]) + self.tol

    def status(self, k: int, point: np.ndarray) -> str:
        """Where `point` is for block `k`: "inside", "surface" (within tolerance) or "outside"."""
        if not np.all((self.lo[k] <= point) & (point <= self.hi[k])):
            return "outside"
        q = self.polys[k]
        if _on_surface(q, point, self.tol):
            return "surface"
        w = winding_numbers(point[None], q.vertices, q.face_indptr, q.face_indices)[0]
        return "inside" if w > 0.5 else "outside"

    def inside(self, point: np.ndarray) -> tuple[list[int], list[int]]:
        """Blocks the point is strictly inside, and blocks it lies on the surface of."""
        cand = np.flatnonzero(np.all((self.lo <= point) & (point <= self.hi), axis=1))
        where = {int(k): self.status(int(k), point) for k in cand}
        return ([k for k, s in where.items() if s == "inside"],
                [k for k, s in where.items() if s == "surface"])

    def on_or_in(self, k: int, point: np.ndarray) -> bool:
        """True if `point` is inside block `k` or within the tolerance of its surface."""
        return self.status(k, point) != "outside"

    def select(self, sel: Selection, loc: str, p: Problems) -> list[int]:
        """Block indices chosen by `sel` (problems recorded at `loc`)."""
        if sel.name is not None:
            if sel.name not in self.index:
                known = ", ".join(self.names[:20]) + (", ..." if len(self.names) > 20 else "")
                p.add(f"{loc}.name", f"unknown block '{sel.name}' (known: {known})")
                return []
            return [self.index[sel.name]]
        if sel.contains is not None:
            point = np.asarray(sel.contains, float)
            inside, surface = self.inside(point)
            if len(inside) == 1:
                return inside
            if len(inside) > 1:
                p.add(f"{loc}.contains", f"point {fmt_point(point)} is inside several blocks: "
                      + ", ".join(f"'{self.names[k]}'" for k in inside))
            elif surface:
                p.add(f"{loc}.contains", f"point {fmt_point(point)} lies on the surface of "
                      + " and ".join(f"'{self.names[k]}'" for k in surface)
                      + "; give a point inside the block")
            else:
                p.add(f"{loc}.contains", f"point {fmt_point(point)} is inside no block")
            return []
        box = sel.centroid_in
        c = np.array([q.centroid for q in self.polys])
        hit = np.flatnonzero(np.all((c >= box.min) & (c <= box.max), axis=1))
        if not len(hit):
            p.add(f"{loc}.centroid_in", f"no block has its centroid between "
                  f"{fmt_point(box.min)} and {fmt_point(box.max)}")
        return [int(k) for k in hit]

    def one(self, sel: Selection | None, point: np.ndarray, loc: str, p: Problems) -> int | None:
        """The single block `sel` chooses, or the block at `point` if `sel` is None."""
        if sel is not None:
            found = self.select(sel, f"{loc}.block", p)
            if len(found) > 1:
                p.add(f"{loc}.block", f"selects {len(found)} blocks; choose exactly one")
                return None
            if not found:
                return None
            k = found[0]
            if not self.on_or_in(k, point):
                p.add(f"{loc}.point",
                      f"point {fmt_point(point)} is not on or inside block '{self.names[k]}'")
                return None
            return k
        inside, surface = self.inside(point)
        if len(inside) == 1:
            return inside[0]
        if not inside and len(surface) == 1:
            return surface[0]
        if not inside and not surface:
            p.add(f"{loc}.point", f"point {fmt_point(point)} is on or inside no block")
        else:
            p.add(f"{loc}.point", f"point {fmt_point(point)} touches several blocks ("
                  + ", ".join(f"'{self.names[k]}'" for k in inside + surface)
                  + "); name the block with 'block'")
        return None


# --------------------------------------------------------------------------- bolts


def pattern_bolts(spec: BoltPatternSpec, loc: str, p: Problems
                  ) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The (name, head, anchor) of each bolt of a pattern: heads on a grid in the face
    (`columns` along the row direction, `rows` along face_normal × row direction), anchors
    `length` m away along trend / plunge."""
    n = np.asarray(spec.face_normal, float)
    if not np.linalg.norm(n) > 0:
        p.add(f"{loc}.face_normal", "must not be the zero vector")
        return []
    n = n / np.linalg.norm(n)
    u = np.asarray(spec.row_direction, float)
    u = u - (u @ n) * n
    if not np.linalg.norm(u) > 1e-9:
        p.add(f"{loc}.row_direction", "must not be parallel to face_normal")
        return []
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    t, pl = np.radians(spec.trend), np.radians(spec.plunge)
    d = np.array([np.sin(t) * np.cos(pl), np.cos(t) * np.cos(pl), -np.sin(pl)])
    if d @ n >= 0:
        p.add(f"{loc}.trend", f"trend {fmt_num(spec.trend)}° / plunge {fmt_num(spec.plunge)}°"
              " points out of the face (along its outward normal); bolts go into the rock")
        return []
    rs = spec.row_spacing or spec.spacing
    o = np.asarray(spec.origin, float)
    out = []
    for r in range(spec.rows):
        for c in range(spec.columns):
            head = o + c * spec.spacing * u + r * rs * v
            out.append((f"{spec.name_prefix}{len(out) + 1}", head, head + spec.length * d))
    return out


def _bolt(spec: BoltSpec | BoltPatternSpec, name: str, head: np.ndarray,
          anchor: np.ndarray, block: int, anchor_block: int) -> Bolt:
    inf = float("inf")
    return Bolt(block=block, head=head, anchor=anchor, anchor_block=anchor_block,
                axial_stiffness=spec.axial_stiffness, shear_stiffness=spec.shear_stiffness,
                pretension=spec.pretension,
                capacity=inf if spec.capacity is None else spec.capacity,
                shear_capacity=spec.shear_capacity,
                rupture_displacement=inf if spec.rupture_displacement is None
                else spec.rupture_displacement, name=name)


def _find_at(find: _Locator, sel: Selection | None, point: np.ndarray, loc: str, field: str,
             p: Problems, block_field: str = "block") -> int | None:
    """:meth:`_Locator.one` with its problems about the point named `field` (not `point`)
    and about the selection named `block_field` (not `block`)."""
    q = Problems()
    k = find.one(sel, point, loc, q)
    for item in q.items:
        where = item["loc"]
        for old, new in ((".point", f".{field}"), (".block", f".{block_field}")):
            if where.startswith(f"{loc}{old}"):
                where = f"{loc}.{new[1:]}{where[len(loc) + len(old):]}"
                break
        p.add(where, item["msg"])
    return k


def _anchor_block(find: _Locator, sel: Selection | None, anchor: np.ndarray, head_block: int,
                  loc: str, p: Problems) -> int | None:
    """The anchor's block: the one `sel` chooses, else the block other than the head's that
    contains the anchor, else the ground (-1); None after a problem."""
    if sel is not None:
        return _find_at(find, sel, anchor, loc, "anchor", p, "anchor_block")
    inside, surface = find.inside(anchor)
    found = [k for k in (inside or surface) if k != head_block]
    if len(found) > 1:
        p.add(f"{loc}.anchor", f"point {fmt_point(anchor)} touches several blocks ("
              + ", ".join(f"'{find.names[k]}'" for k in found)
              + "); name the block with 'anchor_block'")
        return None
    return found[0] if found else -1


def _bolts(scene: Scene, find: _Locator, p: Problems) -> list[Bolt]:
    """The engine's bolts of the scene's `bolts` and `bolt_patterns`."""
    out: list[Bolt] = []
    for k, spec in enumerate(scene.bolts):
        loc = f"bolts[{k}]"
        head, anchor = np.asarray(spec.head, float), np.asarray(spec.anchor, float)
        if np.linalg.norm(anchor - head) <= 0:
            p.add(f"{loc}.anchor", "must differ from head")
            continue
        i = _find_at(find, spec.block, head, loc, "head", p)
        if i is None:
            continue
        j = _anchor_block(find, spec.anchor_block, anchor, i, loc, p)
        if j is not None:
            out.append(_bolt(spec, spec.name or f"bolt{k + 1}", head, anchor, i, j))
    for k, spec in enumerate(scene.bolt_patterns):
        loc = f"bolt_patterns[{k}]"
        for name, head, anchor in pattern_bolts(spec, loc, p):
            i = _find_at(find, None, head, f"{loc}", "origin", p)
            if i is None:
                continue
            j = _anchor_block(find, None, anchor, i, f"{loc} ({name})", p)
            if j is not None:
                out.append(_bolt(spec, name, head, anchor, i, j))
    seen: set[str] = set()
    for b in out:
        if b.name in seen:
            p.add("bolts", f"bolt name '{b.name}' is used twice")
        seen.add(b.name)
    return out


def _water(scene: Scene, jmat_names: list[str]) -> Water | None:
    """The engine's water of the scene's `water` (None: dry)."""
    w = scene.water
    if w is None:
        return None
    ps = w.phreatic_surface
    return Water(
        unit_weight=w.unit_weight,
        surface_point=None if ps is None else np.asarray(ps.point, float),
        surface_normal=None if ps is None else dip_normal(ps.dip, ps.dip_direction),
        joint_pressure={jmat_names.index(jp.joint_material): jp.pressure
                        for jp in w.joint_pressures})


# --------------------------------------------------------------------------- build


#: a friction angle below this (degrees, and above 0) looks like tan φ typed as degrees
SUSPICIOUS_FRICTION_ANGLE = 1.5


def _oddities(scene: Scene, blocks: list[Block], fixed_points: list[FixedPoint]) -> list[str]:
    """Warnings about a valid scene that is probably not what its author meant: a friction
    angle that reads as tan φ, nothing fixed, everything fixed."""
    out = []
    for name, jm in scene.joint_materials.items():
        phi = jm.friction_angle
        if 0 < phi < SUSPICIOUS_FRICTION_ANGLE:
            loc = format_loc(("joint_materials", name, "friction_angle"))
            out.append(f"{loc}: {fmt_num(phi)}° is a very low friction angle; if {fmt_num(phi)}"
                       f" is tan φ, the angle is {np.degrees(np.arctan(phi)):.1f}° (friction "
                       "angles are in degrees)")
    if all(b.fixed for b in blocks):
        out.append("every block is fixed: nothing can move")
    elif not any(b.fixed for b in blocks) and not fixed_points:
        out.append("nothing is fixed (no fixed block, no fixed point): every block is free "
                   "to fall; fix the base ('fixed': true on a block, or boundary.fixed_blocks)")
    return out


@user_entry("polydda.Scene.load(...).build()")
def build_model(scene: Scene | str | Path | dict[str, Any],
                base_dir: str | Path | None = None) -> BuildResult:
    """The engine Model of a scene (or of a path / JSON text / dict, loaded first).

    Files the scene names (a terrain grid, a mesh) are read from `base_dir` (default: the
    scene file's folder when `scene` is a path; none for a dict or JSON text: such a scene
    must give them inline). Raises SceneError listing every problem found.
    """
    if base_dir is None and isinstance(scene, Path | str) and not str(scene).lstrip() \
            .startswith(("{", "[")):
        base_dir = Path(scene).resolve().parent
    base = None if base_dir is None else Path(base_dir)
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    else:
        problems = scene_problems(scene)
        if problems:
            raise SceneError(problems)
    p = Problems()
    warnings: list[str] = []

    mat_names = list(scene.materials)
    jmat_names = list(scene.joint_materials)
    materials = [Material(m.density, m.young_modulus, m.poisson_ratio)
                 for m in scene.materials.values()]
    joint_materials = [
        JointMaterial(float(np.radians(j.friction_angle)), j.cohesion, j.tensile_strength)
        for j in scene.joint_materials.values()
    ]

    def mat_index(name: str | None) -> int:
        return mat_names.index(name or scene.default_material)

    # geometry
    cut, owner = _cut_domain(scene, p, warnings, base)
    explicit = _explicit_blocks(scene, p)
    p.raise_if_any()
    prefix = scene.domain.name_prefix if scene.domain is not None else "B"
    names = [f"{prefix}{k + 1}" for k in range(len(cut))]
    cut_names = set(names)
    locs: dict[int, str] = {}
    for k in range(len(scene.blocks)):
        name = scene.block_name(k)
        loc = f"blocks[{k}]" + (f" ('{scene.blocks[k].name}')" if scene.blocks[k].name else "")
        locs[len(names)] = loc
        if name in cut_names:
            p.add(f"{loc}.name", f"'{name}' is also the name of a block cut from the domain "
                  f"(cut blocks are named {prefix}1 to {prefix}{len(cut)}); choose another name")
        names.append(name)
    polys: list[Polyhedron] = cut + [q for q in explicit if q is not None]
    lo = np.min([q.bounds[0] for q in polys], axis=0)
    hi = np.max([q.bounds[1] for q in polys], axis=0)
    scale = float(np.max(hi - lo))
    p.raise_if_any()

    blocks = [Block(polyhedron=q, name=names[k], material=mat_index(scene.domain.material))
              for k, q in enumerate(cut)]
    for k, (b, q) in enumerate(zip(scene.blocks, explicit, strict=True)):
        velocity = np.array(list(b.velocity.translation) + list(b.velocity.spin), float)
        blocks.append(Block(polyhedron=q, name=names[len(cut) + k], material=mat_index(b.material),
                            fixed=b.fixed, velocity=velocity))

    # selections
    find = _Locator(polys, names, scale)
    for k, sel in enumerate(scene.boundary.fixed_blocks):
        for i in find.select(sel, f"boundary.fixed_blocks[{k}]", p):
            blocks[i].fixed = True
    fixed_points = []
    for k, fp in enumerate(scene.boundary.fixed_points):
        point = np.asarray(fp.point, float)
        i = find.one(fp.block, point, f"boundary.fixed_points[{k}]", p)
        if i is not None:
            fixed_points.append(FixedPoint(block=i, point=point))
    loads = []
    for k, pl in enumerate(scene.boundary.point_loads):
        point = np.asarray(pl.point, float)
        i = find.one(pl.block, point, f"boundary.point_loads[{k}]", p)
        if i is not None:
            loads.append(PointLoad(block=i, point=point, force=np.asarray(pl.force, float)))
    find_bolts = _Locator(polys, names, scale)  # bolts never hold rock to be dug out
    dug = np.array([k < len(owner) and owner[k] is not None for k in range(len(polys))])
    find_bolts.lo[dug], find_bolts.hi[dug] = np.inf, -np.inf
    bolts = _bolts(scene, find_bolts, p)
    pairs: dict[tuple[int, int], int] = {}
    for k, pair in enumerate(scene.block_pairs):
        found = []
        for s, sel in enumerate(pair.blocks):
            got = find.select(sel, f"block_pairs[{k}].blocks[{s}]", p)
            if len(got) > 1:
                p.add(f"block_pairs[{k}].blocks[{s}]",
                      f"selects {len(got)} blocks; choose exactly one")
            found.append(got[0] if len(got) == 1 else None)
        if None in found:
            continue
        a, b = found
        if a == b:
            p.add(f"block_pairs[{k}].blocks", f"both entries are block '{names[a]}'")
            continue
        pairs[(min(a, b), max(a, b))] = jmat_names.index(pair.joint_material)

    _check_overlaps(polys, names, locs, [b.fixed for b in blocks], scale, p)

    fos = None
    spec = scene.analysis.factor_of_safety
    if spec is None and scene.analysis.type == "factor_of_safety":
        spec = FactorOfSafetySpec()
    if spec is not None:
        watch: list[int] = []
        for k, sel in enumerate(spec.watch):
            watch.extend(find.select(sel, f"analysis.factor_of_safety.watch[{k}]", p))
        if not watch:
            watch = [k for k, b in enumerate(blocks) if not b.fixed]
        weak = (range(len(jmat_names)) if spec.joint_materials is None
                else [jmat_names.index(n) for n in spec.joint_materials])
        fos = StrengthReductionControls(
            observation_time=spec.observation_time,
            displacement_limit=spec.displacement_limit, tolerance=spec.tolerance,
            min_factor=spec.min_factor, max_factor=spec.max_factor, max_runs=spec.max_runs,
            joint_materials=tuple(sorted(set(weak))), watch_blocks=tuple(sorted(set(watch))))
        warnings += spec.old_criterion("analysis.factor_of_safety")
    kc = None
    kspec = scene.analysis.critical_seismic_coefficient
    if kspec is None and scene.analysis.type == "critical_seismic_coefficient":
        kspec = CriticalSeismicSpec()
    if kspec is not None:
        watch = []
        for k, sel in enumerate(kspec.watch):
            watch.extend(find.select(
                sel, f"analysis.critical_seismic_coefficient.watch[{k}]", p))
        if not watch:
            watch = [k for k, b in enumerate(blocks) if not b.fixed]
        kc = SeismicCoefficientControls(
            observation_time=kspec.observation_time,
            displacement_limit=kspec.displacement_limit, tolerance=kspec.tolerance,
            max_coefficient=kspec.max_coefficient, max_runs=kspec.max_runs,
            watch_blocks=tuple(sorted(set(watch))))
        warnings += kspec.old_criterion("analysis.critical_seismic_coefficient")
    p.raise_if_any()

    warnings.extend(_oddities(scene, blocks, fixed_points))

    a = scene.analysis
    controls = AnalysisControls(
        duration=a.duration,
        time_step=a.time_step,
        penalty=a.penalty,
        shear_penalty_ratio=a.shear_penalty_ratio,
        record_interval=a.record_interval,
        dynamic_ratio=a.dynamic_ratio_value,
        block_model=a.block_model,
        max_displacement_ratio=a.max_displacement_ratio,
        max_penetration_ratio=a.max_penetration_ratio,
        max_open_close_iterations=a.max_open_close_iterations,
        open_close_tolerance=a.open_close_tolerance,
        contact_damping=a.contact_damping,
        min_time_step=a.min_time_step,
        fixed_point_penalty=a.fixed_point_penalty,
        record_contacts=a.record_contacts,
        contact_solver=a.contact_solver,
        contact_tolerance=a.contact_tolerance,
        restitution=a.restitution,
        sleep_velocity=a.sleep_velocity,
        sleep_time=a.sleep_time,
    )
    default_jm = jmat_names.index(scene.default_joint_material)
    model = Model(
        blocks=blocks,
        materials=materials,
        joint_materials=joint_materials,
        default_joint_material=default_jm,
        joint_material_of_tag={
            k: jmat_names.index(j.joint_material) if j.joint_material else default_jm
            for k, j in enumerate(scene.joints)
        },
        pair_joint_material=pairs,
        gravity=np.asarray(scene.gravity, float),
        seismic=None if scene.seismic is None else SeismicLoad(
            kh=scene.seismic.kh, azimuth_rad=float(np.radians(scene.seismic.azimuth)),
            kv=scene.seismic.kv),
        point_loads=loads,
        fixed_points=fixed_points,
        bolts=bolts,
        water=_water(scene, jmat_names),
        ground_motion=None if scene.ground_motion is None else GroundMotion(
            np.asarray(scene.ground_motion.time, float),
            scene.ground_motion.scale * np.asarray(scene.ground_motion.acceleration, float)),
        controls=controls,
    )
    _physical_problems(scene, model)
    stages = _stages(scene, model, owner, find, jmat_names)
    return BuildResult(
        model=model, stages=stages, excavated=owner + [None] * len(scene.blocks),
        excavation_names=[e.name for e in scene.excavations],
        block_names=names,
        block_sources=["cut"] * len(cut) + ["explicit"] * len(scene.blocks),
        material_names=mat_names,
        joint_material_names=jmat_names,
        joint_names=[scene.joint_name(k) for k in range(len(scene.joints))],
        warnings=warnings,
        factor_of_safety=fos,
        seismic_coefficient=kc,
    )


def _physical_problems(scene: Scene, model: Model) -> None:
    """SceneError when the built model spans more than a model's physical size (a terrain
    or mesh read from its file too) or a given penalty lies too far from the derived one
    (schemas.physical), unless the scene allows the unphysical."""
    from schemas.physical import SIZE, penalty_problems, unphysical_allowed

    a = scene.analysis
    with unphysical_allowed(a.allow_unphysical):
        problems = penalty_problems(model, a.penalty, a.fixed_point_penalty)
        where = SIZE.outside(model.scale) if model.blocks else None
    if where is not None:
        problems.append({"loc": "domain" if scene.domain is not None else "blocks",
                         "msg": f"the model spans {model.scale:.6g} m, {where}"})
    if problems:
        raise SceneError(problems)


def _stages(scene: Scene, model: Model, owner: list[str | None], find: _Locator,
            jmat_names: list[str]) -> list[Stage]:
    """The scene's stages resolved on the model (SceneError naming the field)."""
    if not scene.stages:
        return []
    from schemas.stage_convert import resolve_stages, staged_controls

    p = Problems()
    stages = resolve_stages(
        scene, model, owner + [None] * len(scene.blocks),
        lambda sel, loc: find.select(sel, loc, p),
        lambda spec: _water(scene.model_copy(update={"water": spec}), jmat_names),
        jmat_names)
    p.raise_if_any()
    staged_controls(model, stages)
    return stages


# --------------------------------------------------------------------------- kinematics


def kinematic_inputs(scene: Scene | str | Path | dict[str, Any]) -> tuple[list[JointSet],
                                                                         SlopeFace]:
    """The joints' orientations and friction angles and the slope face, for
    :func:`engine.analyses.kinematics.kinematic_analysis`; nothing is cut.

    Each joint (a set or a single plane) is one orientation; its friction angle is the
    `slope_face.friction_angle` when given, else its joint material's. SceneError when the
    scene has no `slope_face` or no joints.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    p = Problems()
    face = scene.slope_face
    if face is None:
        p.add("slope_face", "kinematic screening needs the slope face: give 'slope_face' "
              "{\"dip\": degrees, \"dip_direction\": degrees} (optionally 'friction_angle')")
    if not scene.joints:
        p.add("joints", "kinematic screening needs joints (their dip and dip direction)")
    p.raise_if_any()
    default = scene.joint_materials[scene.default_joint_material].friction_angle
    sets = [
        JointSet(
            name=scene.joint_name(k), dip=float(j.dip), dip_direction=float(j.dip_direction) % 360,
            friction_angle=None if face.friction_angle is not None else float(
                scene.joint_materials[j.joint_material or scene.default_joint_material]
                .friction_angle))
        for k, j in enumerate(scene.joints)
    ]
    phi = face.friction_angle if face.friction_angle is not None else default
    return sets, SlopeFace(float(face.dip), float(face.dip_direction) % 360, float(phi))
