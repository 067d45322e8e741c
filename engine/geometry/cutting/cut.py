"""The two runs of the cutting pipeline: `cut_blocks` (a domain by joint planes, into
blocks) and `convex_decomposition` (a concave block by its own face planes, into pieces)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from engine.geometry.cutting import slivers
from engine.geometry.cutting.blocks import attach_pieces, build_block, closed_cells
from engine.geometry.cutting.cells import arrange, initial_cells, inside
from engine.geometry.cutting.facets import build_facets, real_joints
from engine.geometry.cutting.planes import Planes, joints_of, set_spacing
from engine.geometry.joints import JointPlane
from engine.geometry.polyhedron import Polyhedron
from engine.tolerances import DEFAULT_TOLERANCES, Tolerances


@dataclass
class CutResult:
    """Blocks from cutting, and what went wrong on the way (slivers, idle joints)."""

    blocks: list[Polyhedron]
    warnings: list[str] = field(default_factory=list)


def _idle_joint_warnings(joints: Sequence[JointPlane], separating: set[int]) -> list[str]:
    """One warning per joint tag whose planes (some or all) separate no blocks."""
    planes_of: dict[int, list[int]] = {}
    for j, jp in enumerate(joints):
        planes_of.setdefault(int(jp.tag), []).append(j)
    out = []
    for tag, js in planes_of.items():
        idle = [j for j in js if j not in separating]
        if len(js) == 1 and idle:
            out.append(f"joint {tag} cuts nothing (joint plane {idle[0]})")
        elif len(idle) == len(js):
            out.append(f"joint {tag}: none of its {len(js)} planes cuts anything")
        elif idle:
            out.append(f"joint {tag}: {len(idle)} of its {len(js)} planes cut nothing")
    return out


def cut_blocks(
    domain: Polyhedron, joints: Sequence[JointPlane], tol: Tolerances = DEFAULT_TOLERANCES,
    min_block_volume: float | None = None, min_block_width: float | None = None,
    tiles: Sequence[Polyhedron] | None = None,
) -> CutResult:
    """Cut `domain` into blocks by `joints` (persistent or bounded by an extent polygon).

    Faces carry the tag of the joint they lie on, or FACE_TAG_BOUNDARY on the domain
    surface; concave blocks carry their convex pieces (the arrangement cells). Blocks
    smaller than `min_block_volume` m³ (default MIN_BLOCK_VOLUME_RATIO of the median
    block volume; 0 keeps all but numerical slivers) merge into the neighbour they share
    the largest face with: corner slivers weigh nothing, and their tiny inertia would force
    the time step down to microseconds. Slivers - blocks thinner than `min_block_width` m
    (default MIN_BLOCK_WIDTH_RATIO of the joint sets' median spacing, or of the median
    block width without sets; 0 keeps them), however
    large - merge the same way: a thin block bounds every step's displacement (nothing may
    tunnel through it) and its narrow faces confuse the contact search. A merged block may
    be concave; its convex pieces are cells of the same arrangement, so it touches its
    neighbours exactly as the cells did. `tiles` (convex solids tiling a concave domain face
    to face, :func:`engine.geometry.cutting.cells.initial_cells`) start the cut instead of
    the domain's bounding box cut by every face plane of the domain.
    """
    warnings: list[str] = []
    scale = float(np.ptp(domain.vertices[domain.surface_vertex_ids], axis=0).max())
    planes = Planes(tol.lengths(scale).on_plane)
    cells, cut, filter_inside = initial_cells(domain, planes, tiles)
    jlist, jcut = joints_of(joints, planes)
    cells = arrange(cells, planes, cut + jcut)
    if filter_inside:
        cells = inside(cells, domain)
    if not cells:
        return CutResult([], ["the domain has no volume to cut"])
    fac = build_facets(cells, planes, tol.lengths(scale).point_merge)
    if fac.multi:
        warnings.append(f"{fac.multi} facet(s) shared by more than two cells (degenerate cut)")
    owner = real_joints(fac, planes, jlist)
    real = owner >= 0
    tag_of_pair = np.where(real, np.array([j.tag for j in jlist] + [-1])[owner], -1)
    vol_dom = abs(domain.volume)
    sliver = tol.sliver_volume * vol_dom
    glued = slivers.glued(fac, real, len(cells))
    if min_block_volume is None:
        vols = np.bincount(glued[0], weights=fac.cell_volume)
        min_block_volume = slivers.MIN_BLOCK_VOLUME_RATIO * float(np.median(vols[vols > 0]))
    if min_block_width is None:
        typical = set_spacing(planes)
        if typical is None:
            widths = np.full(int(glued[0].max()) + 1, -np.inf)
            np.maximum.at(widths, glued[0], slivers.cell_widths(fac, len(cells)))
            typical = float(np.median(widths[widths > 0]))
        min_block_width = slivers.MIN_BLOCK_WIDTH_RATIO * typical
    group, dropped = slivers.groups(fac, glued, sliver, min_block_volume, min_block_width, warnings)
    cell_facets: list[list[int]] = [[] for _ in cells]
    for f, c in enumerate(fac.cell.tolist()):
        cell_facets[c].append(f)
    members: dict[int, list[int]] = {}
    for c, g in enumerate(group.tolist()):
        if not dropped[c]:
            members.setdefault(g, []).append(c)
    singles = np.array([cs[0] for cs in members.values() if len(cs) == 1], dtype=np.int64)
    trusted = set(singles[closed_cells(fac, singles, scale, tol)].tolist())
    blocks: list[Polyhedron] = []
    n_small = n_bad = 0
    for cs in members.values():
        if float(fac.cell_volume[cs].sum()) < sliver:
            n_small += 1
            continue
        block = build_block(cs, cell_facets, fac, group, tag_of_pair, planes.eps)
        if not (len(cs) == 1 and cs[0] in trusted) and block.problems(tol):
            n_bad += 1
            continue
        blocks.append(block)
    if n_small:
        warnings.append(f"{n_small} sliver block(s) dropped")
    if n_bad:
        warnings.append(f"{n_bad} block(s) dropped because the cut produced invalid geometry")
    apart = real & ~dropped[fac.cell] & (group[fac.cell] != group[fac.cell[fac.other]])
    warnings.extend(_idle_joint_warnings(joints, set(owner[apart].tolist())))
    return CutResult(blocks, warnings)


def convex_decomposition(block: Polyhedron, tol: Tolerances = DEFAULT_TOLERANCES) -> Polyhedron:
    """The same block surface with `.pieces` set to a convex decomposition.

    Pieces are the cells of the arrangement of the block's own face planes; a convex
    block comes back with no pieces (it is its own single piece).
    """
    base = Polyhedron(block.vertices, block.face_indptr, block.face_indices, block.face_tags)
    if block.is_convex:
        return base
    scale = float(np.ptp(block.vertices[block.surface_vertex_ids], axis=0).max())
    planes = Planes(tol.lengths(scale).on_plane)
    cells, cut, _ = initial_cells(block, planes)
    cells = inside(arrange(cells, planes, cut), block)
    return attach_pieces(base, cells, tol, scale)
