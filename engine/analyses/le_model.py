"""What limit equilibrium sees of a model: the one block that can move, the planes it rests on
(its faces against fixed rock, with their joint material and contact area) and every force
on it (weight, pseudo-static seismic load, water in the joints, point loads, rock bolts and
tendons). A model this does not describe (several free blocks, fixed points, a ground-motion
history, a passive bolt with no capacity, no face on fixed rock) raises
:class:`NotApplicable` saying why: a load limit equilibrium cannot take is never dropped.

The vector method on these planes and forces is :mod:`engine.analyses.limit_equilibrium`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from engine.geometry.polyhedron import Polyhedron
from engine.loads.water import overlap, water_loads
from engine.model import Model

#: faces touch when their outward normals are opposite within this (1 - cos) ...
TOUCH_COS = 1e-5
#: ... and their planes are closer than this fraction of the model size
TOUCH_GAP = 1e-5
#: contact polygons smaller than this fraction of the block's largest face are edges or
#: corners, not planes the block rests on
MIN_AREA_RATIO = 1e-6


class NotApplicable(ValueError):
    """Limit equilibrium does not apply to this model; the message says why."""


@dataclass
class ContactPlane:
    """A plane the block rests on: unit `normal (3,)` from the fixed rock into the block,
    a point on it, the contact polygons' total `area` m² and `outline (k, 3)` their
    vertices, the fixed block, the face tag (joint id, -1: none), joint material index,
    tan φ, cohesion (Pa), and whether the strength reduction weakens it."""

    normal: np.ndarray
    point: np.ndarray
    area: float
    outline: np.ndarray
    block: int
    face_tag: int
    joint_material: int
    tan_phi: float
    cohesion: float
    tensile_strength: float
    weakened: bool = True
    #: the water force on the block on this plane, normal to it (N; pushing the block off)
    water: float = 0.0


@dataclass
class Force:
    """A force on the block: what it is (`kind`: weight, seismic, water, point_load,
    active_bolt, passive_bolt), a name, the vector `(3,)` N and its point `(3,)` m."""

    kind: str
    name: str
    vector: np.ndarray
    point: np.ndarray
    #: the plane it acts on (water on a plane the block rests on; -1: none)
    plane: int = -1


@dataclass
class BlockLoads:
    """The block that can move (index), its mass (kg) and centroid, the planes it rests
    on, every force on it, and notes (what was counted and how)."""

    block: int
    mass: float
    centroid: np.ndarray
    planes: list[ContactPlane]
    forces: list[Force]
    notes: list[str] = field(default_factory=list)


def moving_block(model: Model, watch: tuple[int, ...] | None = None) -> int:
    """The one block limit equilibrium solves for (NotApplicable unless exactly one block
    is free; `watch`, when it names one block, must be that one)."""
    free = [k for k, b in enumerate(model.blocks) if not b.fixed]
    names = ", ".join(model.blocks[k].name or f"block{k}" for k in free[:6])
    if not free:
        raise NotApplicable("the scene has no free block: nothing can move")
    if len(free) != 1:
        raise NotApplicable(
            "limit equilibrium takes one free block resting on fixed rock; the scene has "
            f"{len(free)} free blocks" + (f" ({names}{', ...' if len(free) > 6 else ''})"
                                          if free else "") + ": use `polydda fos`")
    if watch is not None and tuple(watch) not in ((), (free[0],)):
        raise NotApplicable("the watched blocks are not the scene's one free block")
    return free[0]


def _joint_material(model: Model, pair: tuple[int, int], tags: tuple[int, int]) -> int:
    """The joint material of two faces in contact, as the contacts choose it: the block
    pair's, else a face's joint (tag), else the default."""
    key = (min(pair), max(pair))
    if key in model.pair_joint_material:
        return model.pair_joint_material[key]
    for t in tags:
        if t >= 0:
            return model.joint_material_of_tag.get(t, model.default_joint_material)
    return model.default_joint_material


def _touching_faces(block: Polyhedron, other: Polyhedron, tol: float
                    ) -> list[tuple[int, int, np.ndarray]]:
    """(face of `block`, face of `other`, their overlap polygon `(k, 3)`) for every pair
    of faces that lie against each other."""
    out = []
    cos = block.face_normals @ other.face_normals.T
    for fi, fj in zip(*np.nonzero(cos < -(1.0 - TOUCH_COS)), strict=True):
        face_i = block.vertices[block.faces[fi]]
        face_j = other.vertices[other.faces[fj]]
        if np.abs((face_j - face_i[0]) @ block.face_normals[fi]).max() > tol:
            continue
        poly = overlap(face_i, block.face_normals[fi], face_j)
        if len(poly) >= 3:
            out.append((int(fi), int(fj), poly))
    return out


def _polygon_area(poly: np.ndarray, normal: np.ndarray) -> float:
    """Area (m²) of the planar polygon `poly (k, 3)` with unit normal `normal`."""
    cross = np.cross(poly - poly[0], np.roll(poly, -1, axis=0) - poly[0]).sum(axis=0)
    return abs(float(cross @ normal)) * 0.5


def contact_planes(model: Model, b: int, weakened: tuple[int, ...] | None = None
                   ) -> list[ContactPlane]:
    """The planes block `b` rests on: its faces lying against faces of fixed blocks,
    grouped by plane (and by fixed block and joint material). `weakened`: the joint
    materials the strength reduction divides (None: all)."""
    blk = model.blocks[b].polyhedron
    scale = model.scale
    tol = TOUCH_GAP * scale
    lo, hi = blk.bounds[0] - tol, blk.bounds[1] + tol
    min_area = MIN_AREA_RATIO * float(blk.face_areas.max())
    planes: list[ContactPlane] = []
    for j, other in enumerate(model.blocks):
        if j == b or not other.fixed:
            continue
        p = other.polyhedron
        if np.any(p.bounds[0] > hi) or np.any(p.bounds[1] < lo):
            continue
        for fi, fj, poly in _touching_faces(blk, p, tol):
            normal = -blk.face_normals[fi]
            area = _polygon_area(poly, normal)
            if area < min_area:
                continue
            tag = int(blk.face_tags[fi]) if blk.face_tags[fi] >= 0 else int(p.face_tags[fj])
            jm = _joint_material(model, (b, j), (int(blk.face_tags[fi]), int(p.face_tags[fj])))
            _add_to_plane(planes, model, ContactPlane(
                normal=normal, point=poly.mean(axis=0), area=area, outline=poly, block=j,
                face_tag=tag, joint_material=jm, tan_phi=0.0, cohesion=0.0,
                tensile_strength=0.0, weakened=weakened is None or jm in weakened), tol)
    for pl in planes:
        mat = model.joint_materials[pl.joint_material]
        pl.tan_phi = math.tan(mat.friction_angle_rad)
        pl.cohesion, pl.tensile_strength = mat.cohesion, mat.tensile_strength
    return planes


def _add_to_plane(planes: list[ContactPlane], model: Model, new: ContactPlane,
                  tol: float) -> None:
    """Merge the contact polygon `new` into the plane it lies on (same normal, offset,
    joint material), or start a plane."""
    for pl in planes:
        if (float(pl.normal @ new.normal) > 1.0 - TOUCH_COS
                and abs(float(pl.normal @ (new.point - pl.point))) <= tol
                and pl.joint_material == new.joint_material):
            total = pl.area + new.area
            pl.point = (pl.point * pl.area + new.point * new.area) / total
            pl.area = total
            pl.outline = np.vstack([pl.outline, new.outline])
            if pl.face_tag < 0:
                pl.face_tag = new.face_tag
            return
    planes.append(new)


def _bolt_forces(model: Model, b: int, notes: list[str]) -> list[Force]:
    """The bolts and tendons on block `b` as forces at incipient sliding: a constant-force
    tendon (axial stiffness 0) pulls with its pretension (active); a stiff bolt pulls with
    its pretension (active) and mobilizes up to its capacity as the block moves (the rest
    passive). NotApplicable for a stiff bolt without a capacity."""
    out = []
    for k, bolt in enumerate(model.bolts):
        name = bolt.name or f"bolt{k + 1}"
        if bolt.block == b and bolt.anchor_block != b:
            at, toward = np.asarray(bolt.head, float), np.asarray(bolt.anchor, float)
        elif bolt.anchor_block == b and bolt.block != b:
            at, toward = np.asarray(bolt.anchor, float), np.asarray(bolt.head, float)
        else:
            continue
        axis = (toward - at) / max(float(np.linalg.norm(toward - at)), 1e-300)
        if bolt.pretension > 0:
            out.append(Force("active_bolt", name, bolt.pretension * axis, at))
        if bolt.axial_stiffness > 0:
            if not math.isfinite(bolt.capacity):
                raise NotApplicable(
                    f"bolt '{name}' is passive (axial stiffness > 0) with no capacity: the "
                    "force it mobilizes as the block moves has no bound; give its capacity")
            if bolt.capacity > bolt.pretension:
                out.append(Force("passive_bolt", name,
                                 (bolt.capacity - bolt.pretension) * axis, at))
        if bolt.shear_stiffness > 0:
            notes.append(f"bolt '{name}': its shear (dowel) resistance is not counted "
                         "(on the safe side)")
    return out


def _water_forces(model: Model, b: int, planes: list[ContactPlane]) -> list[Force]:
    """The water forces on block `b` (the scene's water model on its faces at rest), one
    per plane it rests on and one for the other wetted faces (a tension crack's thrust);
    each plane's normal share is kept in `ContactPlane.water`."""
    polys = [blk.polyhedron for blk in model.blocks]
    fixed = np.array([blk.fixed for blk in model.blocks])
    w = water_loads(model.water, polys, fixed, model.scale, model.pair_joint_material,
                    model.joint_material_of_tag, model.default_joint_material)
    mine = w.block == b
    pts, f = w.point[mine], w.force[mine]
    left = np.ones(len(pts), dtype=bool)
    out = []
    tol = TOUCH_GAP * model.scale
    along = np.abs(f @ np.array([pl.normal for pl in planes]).T) / np.maximum(
        np.linalg.norm(f, axis=1), 1e-300)[:, None]  # (points, planes): water acts normally
    for k, pl in enumerate(planes):
        on = left & (np.abs((pts - pl.point) @ pl.normal) <= tol) & (along[:, k] > 1 - TOUCH_COS)
        if np.any(on):
            total = f[on].sum(axis=0)
            pl.water = float(total @ pl.normal)
            out.append(Force("water", f"plane {k + 1}", total, _centre(pts[on], f[on]), k))
            left &= ~on
    if np.any(left) and np.any(f[left] != 0):
        out.append(Force("water", "other faces", f[left].sum(axis=0),
                         _centre(pts[left], f[left])))
    return out


def _centre(points: np.ndarray, forces: np.ndarray) -> np.ndarray:
    """A point of application of parallel forces (weighted by their magnitudes)."""
    w = np.linalg.norm(forces, axis=1)
    return (points * w[:, None]).sum(axis=0) / max(float(w.sum()), 1e-300)


def block_loads(model: Model, weakened: tuple[int, ...] | None = None,
                watch: tuple[int, ...] | None = None) -> BlockLoads:
    """The moving block, the planes it rests on and the forces on it (NotApplicable when
    limit equilibrium does not describe the model)."""
    b = moving_block(model, watch)
    if model.fixed_points:
        raise NotApplicable("the scene holds blocks by fixed points: limit equilibrium "
                            "has no such support")
    if model.ground_motion is not None:
        raise NotApplicable("the scene has a ground-motion history: limit equilibrium is "
                            "pseudo-static (give seismic kh / kv instead)")
    poly = model.blocks[b].polyhedron
    planes = contact_planes(model, b, weakened)
    if not planes:
        raise NotApplicable(f"block {model.blocks[b].name or b} rests on no face of fixed "
                            "rock: limit equilibrium needs one or more sliding planes")
    mass = float(model.materials[model.blocks[b].material].density * poly.volume)
    c = np.asarray(poly.centroid, float)
    g = np.asarray(model.gravity, float)
    forces = [Force("weight", "weight", mass * g, c)]
    notes: list[str] = []
    seismic = np.asarray(model.body_acceleration, float) - g
    if np.any(seismic != 0):
        forces.append(Force("seismic", "pseudo-static seismic load", mass * seismic, c))
    for k, ld in enumerate(model.point_loads):
        if ld.block == b:
            forces.append(Force("point_load", f"point load {k + 1}",
                                np.asarray(ld.force, float), np.asarray(ld.point, float)))
    forces += _bolt_forces(model, b, notes)
    if model.water is not None:
        forces += _water_forces(model, b, planes)
    if any(pl.tensile_strength > 0 for pl in planes):
        notes.append("tensile strength is not counted: a plane the block lifts off carries "
                     "nothing (Hoek & Bray)")
    return BlockLoads(b, mass, c, planes, forces, notes)
