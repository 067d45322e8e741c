"""Key blocks around an opening (Goodman & Shi's block theory, the table Unwedge gives): for
each block exposed on an excavation's surface, whether it is removable, how it would move
under its weight (falling, sliding on one plane, sliding on two) and the limit-equilibrium
factor of safety of that mode.

Removability is block theory's own (the joint pyramid's extreme rays); the mode and its
factor of safety are the vector method of :mod:`engine.analyses.limit_equilibrium`
(:func:`solve_modes`) on the block's contact planes under its weight alone (dry, no bolts,
no seismic load: Mohr-Coulomb joints), so key blocks and `polydda le` count a plane's
strength the same way.

A block's contact planes are its distinct face planes that are not on the excavation's
surface; `n` is a plane's outward normal (from the block into its neighbour). A motion
`d` separates from a plane when `n · d <= 0`.

- removable: some direction separates from every contact plane (an extreme ray of the
  pyramid does);
- falling: the weight's direction `r` itself does (FS 0);
- sliding on plane i: `r · n_i > 0` and the in-plane part of `r` separates from the others;
  FS = (W (r·n_i) tan φ_i + c_i A_i) / (W |r − (r·n_i) n_i|);
- sliding on planes i and j: along their intersection `I` (`I · r > 0`), separating from
  the others, both pressed (N_i, N_j > 0 from `W (r − (r·I) I) = N_i n_i + N_j n_j`);
  FS = (N_i tan φ_i + N_j tan φ_j + c_i A_i + c_j A_j) / (W r·I).
The mode with the lowest FS is the block's ("stable" when none is admissible or nothing
drives the block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from engine.analyses.le_model import ContactPlane, NotApplicable
from engine.analyses.limit_equilibrium import MODE_NAMES, solve_modes
from engine.geometry.polyhedron import Polyhedron


@dataclass(frozen=True)
class Plane:
    """A contact plane of a block: outward unit normal, area (m²), tag, strength."""

    normal: np.ndarray
    area: float
    tag: int
    tan_phi: float
    cohesion: float


@dataclass
class KeyBlock:
    """One exposed block: `removable`, `mode` ("falling", "sliding on one plane",
    "sliding on two planes" or "stable": no mode under its weight), the `planes` (tags) it
    slides on, the factor of safety (inf: stable; 0: falls), its weight (N)."""

    block: int
    removable: bool
    mode: str
    planes: list[int] = field(default_factory=list)
    factor_of_safety: float = float("inf")
    weight: float = 0.0


def contact_planes(poly: Polyhedron, free_tags: set[int], strength: dict[int, tuple[float,
                   float]], default: tuple[float, float]) -> list[Plane]:
    """The block's distinct face planes off the excavation's surface (faces on one plane
    merged, their areas added), with (tan φ, c) by face tag."""
    out: list[Plane] = []
    for n, area, tag in zip(poly.face_normals, poly.face_areas, poly.face_tags, strict=True):
        if int(tag) in free_tags:
            continue
        for k, pl in enumerate(out):
            if pl.normal @ n > 1 - 1e-9:
                out[k] = Plane(pl.normal, pl.area + float(area), pl.tag, pl.tan_phi,
                               pl.cohesion)
                break
        else:
            tan_phi, c = strength.get(int(tag), default)
            out.append(Plane(np.asarray(n, float), float(area), int(tag), tan_phi, c))
    return out


def removable(planes: list[Plane]) -> bool:
    """Whether some direction separates the block from every contact plane (Shi's theorem
    for a convex block: the joint pyramid is not empty).

    The pyramid `{d : n_i · d <= 0}` is more than the origin when the normals leave a
    direction free (rank < 3) or when one of its extreme rays exists; in three dimensions
    each extreme ray lies on two of the planes, `±(n_i × n_j)`, so trying those (and `-n_i`
    for a pyramid bounded by one plane) decides it exactly, without a linear program
    (microseconds a block instead of milliseconds: the builder's preview colours every
    exposed block)."""
    if not planes:
        return True
    a = np.array([p.normal for p in planes], float)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    if np.linalg.matrix_rank(a, tol=1e-9) < 3:
        return True  # a line every plane contains: the block slides along it
    i, j = np.triu_indices(len(a), 1)
    rays = np.cross(a[i], a[j])
    norm = np.linalg.norm(rays, axis=1)
    rays = rays[norm > 1e-9] / norm[norm > 1e-9, None]
    candidates = np.concatenate([rays, -rays, -a])
    return bool(np.any(np.all(candidates @ a.T <= 1e-9, axis=1)))


def mode_and_factor(planes: list[Plane], weight: float, r: np.ndarray
                    ) -> tuple[str, list[int], float]:
    """The block's mode under its weight `weight` N along the unit direction `r`, the tags
    of the planes it slides on, and its factor of safety (limit_equilibrium.solve_modes:
    its planes' normals point into the block)."""
    contact = [ContactPlane(normal=-p.normal, point=np.zeros(3), area=p.area,
                            outline=np.zeros((0, 3)), block=-1, face_tag=p.tag,
                            joint_material=-1, tan_phi=p.tan_phi, cohesion=p.cohesion,
                            tensile_strength=0.0) for p in planes]
    try:
        best, _ = solve_modes(contact, weight * np.asarray(r, float), np.zeros(3))
    except NotApplicable:  # no mode is admissible: the planes hold it
        return "stable", [], float("inf")
    if not best.planes:
        return "falling", [], 0.0
    if not math.isfinite(best.factor_of_safety):  # nothing drives it along any mode
        return "stable", [], float("inf")
    return (MODE_NAMES[len(best.planes)], [planes[k].tag for k in best.planes],
            float(best.factor_of_safety))


def key_blocks(polys: list[Polyhedron], density: np.ndarray, gravity: np.ndarray,
               exposed: set[int], strength: dict[int, tuple[float, float]],
               default: tuple[float, float], skip: set[int] = frozenset(),
               free: set[int] = frozenset(), fixed: set[int] = frozenset()
               ) -> list[KeyBlock]:
    """The key-block table of every block with a face tagged in `exposed` (an excavation's
    surface), except the blocks in `skip` (the excavated ones) and the `fixed` ones (the
    rock mass that continues beyond the model: never a key block, whatever its faces).
    Faces tagged in `exposed` or `free` (the domain's outer surface, other openings already
    dug) touch nothing."""
    free_tags = set(exposed) | set(free)
    g = np.asarray(gravity, float)
    r = g / np.linalg.norm(g)
    out = []
    for b, poly in enumerate(polys):
        if b in skip or b in fixed or not np.isin(poly.face_tags, list(exposed)).any():
            continue
        planes = contact_planes(poly, free_tags, strength, default)
        weight = float(density[b] * poly.volume * np.linalg.norm(g))
        if not removable(planes):
            out.append(KeyBlock(b, False, "stable", weight=weight))
            continue
        mode, tags, fs = mode_and_factor(planes, weight, r)
        out.append(KeyBlock(b, True, mode, tags, fs, weight))
    return out


@dataclass(frozen=True)
class Motion:
    """What a recorded run did to a block after its release: `verdict` ("stayed", "moved,
    then stopped" or "still moving at the end"), its displacement since the release (m),
    its speed at the end and its peak speed (m/s), and the simulated time watched (s)."""

    verdict: str
    displacement: float
    speed: float
    peak_speed: float
    watched: float


def recorded_motion(times: np.ndarray, displacement: np.ndarray, speed: np.ndarray,
                    release: float, limit: float, rest_speed: float) -> Motion:
    """Judge a block by what a recorded run shows from `release` (s) on, as a strength-
    reduction trial is judged at the end of its window (trials.still_moving): still moving
    when its speed at the end is above `rest_speed`, not decayed to half its peak and not
    slowing over the window's last tenth; else it stopped, having moved (more than `limit`
    m since the release) or stayed. `displacement (K, 3)` and `speed (K,)` are per record."""
    from engine.analyses.trials import LATE_FRACTION, still_moving

    t = np.asarray(times, float)
    after = np.flatnonzero(t >= release - 1e-12)
    if len(after) == 0:
        return Motion("stayed", 0.0, 0.0, 0.0, 0.0)
    k0 = int(after[0])
    d = float(np.linalg.norm(np.asarray(displacement[-1]) - np.asarray(displacement[k0])))
    v = np.asarray(speed, float)[k0:]
    window = float(t[-1] - t[k0])
    late_k = int(np.searchsorted(t[k0:], t[-1] - LATE_FRACTION * window)) if window > 0 else 0
    late = float(v[min(late_k, len(v) - 1)]) if window > 0 and late_k < len(v) - 1 else None
    end, peak = float(v[-1]), float(v.max())
    if still_moving(end, peak, late, rest_speed):
        verdict = "still moving at the end"
    elif d > limit:
        verdict = "moved, then stopped"
    else:
        verdict = "stayed"
    return Motion(verdict, d, end, peak, window)
