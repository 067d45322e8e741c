"""Scene -> engine for excavations and stages: the excavations' solids, the domain cut before
and after the joints, and each stage's complete setting (:class:`engine.step.stages.Stage`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from engine.geometry.excavations import (
    EXCAVATION_TAG_BASE,
    Excavation,
    axis_points,
    cavern,
    excavate,
    section_prism,
    tunnel,
    tunnel_section,
)
from engine.geometry.polyhedron import Polyhedron
from engine.loads.seismic import GroundMotion, SeismicLoad
from engine.model import JointMaterial, Model
from engine.step.stages import Stage
from schemas.errors import Problems
from schemas.stage_checks import bolt_names


def excavation_solids(scene: Any, p: Problems) -> list[Excavation | None]:
    """The engine's excavation of each of the scene's (None after a problem)."""
    out: list[Excavation | None] = []
    for k, e in enumerate(scene.excavations):
        loc = f"excavations[{k}] ('{e.name}')"
        try:
            if e.tunnel is not None:
                t = e.tunnel
                axis = (np.asarray(t.axis, float) if t.axis is not None else
                        axis_points(t.start, t.trend, t.plunge, t.length))
                out.append(tunnel(e.name, tunnel_section(t.shape, t.width, t.height, t.sides),
                                  axis))
            elif e.cavern is not None:
                c = e.cavern
                out.append(cavern(e.name, c.center, c.size, c.trend))
            else:
                b = e.bench
                out.append(section_prism(e.name, np.asarray(b.section, float), b.origin,
                                         b.dip_direction, b.width))
        except ValueError as exc:
            field = "tunnel" if e.tunnel is not None else "bench" if e.bench else "cavern"
            p.add(f"{loc}.{field}", str(exc))
            out.append(None)
    return out


def _reaches(exc: Excavation, domain: Polyhedron) -> bool:
    """Whether an excavation's solids overlap the domain's bounding box."""
    lo, hi = domain.bounds
    return any(bool(np.all((s.bounds[0] < hi) & (lo < s.bounds[1]))) for s in exc.solids)


def excavate_before(scene: Any, solids: list[Excavation | None], domain: Polyhedron,
                    p: Problems) -> list[Polyhedron]:
    """The domain less the excavations cut before the joints (one or more pieces)."""
    pieces = [domain]
    for k, (e, exc) in enumerate(zip(scene.excavations, solids, strict=True)):
        if exc is None or e.cut != "before_joints":
            continue
        if not _reaches(exc, domain):
            p.add(f"excavations[{k}] ('{e.name}')", "lies outside the domain")
            continue
        parts, inside, _ = excavate(pieces, exc, EXCAVATION_TAG_BASE + k)
        pieces = [q for q, i in zip(parts, inside, strict=True) if not i]
    return pieces


def excavate_after(scene: Any, solids: list[Excavation | None], blocks: list[Polyhedron],
                   domain: Polyhedron, joints: list[Any], p: Problems
                   ) -> tuple[list[Polyhedron], list[str | None]]:
    """Blocks cut along the excavations dug after the joints, and the excavation each
    block lies in (None: the rock that stays). Slivers of a cut merge as the domain's do."""
    d = scene.domain
    vols = np.array([b.volume for b in blocks])
    min_vol = d.min_block_volume if d.min_block_volume is not None else 1e-3 * float(
        np.median(vols))
    min_width = d.min_block_width if d.min_block_width is not None else 0.1 * float(
        np.median([b.width for b in blocks]))
    owner: list[str | None] = [None] * len(blocks)
    for k, (e, exc) in enumerate(zip(scene.excavations, solids, strict=True)):
        if exc is None or e.cut != "after_joints":
            continue
        if not _reaches(exc, domain):
            p.add(f"excavations[{k}] ('{e.name}')", "lies outside the domain")
            continue
        blocks, inside, parent = excavate(blocks, exc, EXCAVATION_TAG_BASE + k, min_vol,
                                          min_width, joints)
        owner = [owner[int(q)] if owner[int(q)] is not None or not i else e.name
                 for q, i in zip(parent, inside, strict=True)]
        if not any(i for i in inside):
            p.add(f"excavations[{k}] ('{e.name}')", "takes no rock out of the domain")
    return blocks, owner


def _bolts_of(scene: Any, model: Model, names: list[str]) -> set[str]:
    """The model's bolt names that `names` (bolt names or pattern prefixes) choose."""
    own, prefixes = bolt_names(scene)
    out = {n for n in names if n in own}
    for pre in (n for n in names if n in prefixes):
        out |= {b.name for b in model.bolts if b.name.startswith(pre)
                and b.name[len(pre):].isdigit()}
    return out


def resolve_stages(scene: Any, model: Model, owner: list[str | None], select: Any,
                   water: Any, jmat_names: list[str]) -> list[Stage]:
    """Each stage's complete setting. `select(sel, loc)` -> block indices (problems
    recorded by the caller's locator); `water(spec)` -> engine Water."""
    later = set().union(*(_bolts_of(scene, model, st.add_bolts) for st in scene.stages))
    bolts = [b.name for b in model.bolts if b.name not in later]
    removed: set[int] = set()
    fixed = {k for k, b in enumerate(model.blocks) if b.fixed}
    jm = list(model.joint_materials)
    w, seismic, gm = model.water, model.seismic, model.ground_motion
    t, out = 0.0, []
    for s, st in enumerate(scene.stages):
        loc = f"stages[{s}]"
        removed |= {k for k, o in enumerate(owner) if o is not None and o in st.excavate}
        if st.excavate_region is not None:
            box = st.excavate_region
            c = np.array([b.polyhedron.centroid for b in model.blocks])
            removed |= set(np.flatnonzero(np.all((c >= box.min) & (c <= box.max), axis=1))
                           .tolist())
        gone = _bolts_of(scene, model, st.remove_bolts)
        new = _bolts_of(scene, model, st.add_bolts)
        bolts = [b.name for b in model.bolts if (b.name in bolts or b.name in new)
                 and b.name not in gone]
        for name, spec in st.joint_materials.items():
            jm[jmat_names.index(name)] = JointMaterial(
                float(np.radians(spec.friction_angle)), spec.cohesion, spec.tensile_strength)
        if st.water is not None or st.drain:
            w = None if st.drain else water(st.water)
        if st.seismic is not None:
            seismic = SeismicLoad(kh=st.seismic.kh, azimuth_rad=float(
                np.radians(st.seismic.azimuth)), kv=st.seismic.kv)
        if st.ground_motion is not None:
            g = st.ground_motion
            gm = GroundMotion(np.asarray(g.time, float) + t,
                              g.scale * np.asarray(g.acceleration, float))
        if st.quiet:
            seismic, gm = None, None
        for k, sel in enumerate(st.fix):
            fixed |= set(select(sel, f"{loc}.fix[{k}]"))
        for k, sel in enumerate(st.free):
            fixed -= set(select(sel, f"{loc}.free[{k}]"))
        t += st.duration
        out.append(Stage(st.name, t, frozenset(removed), tuple(bolts), frozenset(fixed), w,
                         tuple(jm), seismic, gm))
    return out


def staged_controls(model: Model, stages: list[Stage]) -> None:
    """The model's duration is the stages' total."""
    if stages:
        model.controls = dataclasses.replace(model.controls, duration=stages[-1].end_time)
