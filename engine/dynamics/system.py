"""The fixed data of a run (as MuJoCo's model): block constants, the map of unknowns, the
initial geometry and masses, penalties and the limits that derive from them.

A :class:`BlockSystem` never changes during a run; everything that does lives in
:class:`engine.dynamics.state.State`. Built once from a :class:`engine.model.Model`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.dynamics import assembly as asm
from engine.geometry.polyhedron import Polyhedron
from engine.loads.bolts import BoltSet, bolt_set
from engine.loads.water import Water
from engine.model import (  # noqa: F401  (the penalty's rule, re-exported here)
    PENALTY_INERTIA_RATIO,
    AnalysisControls,
    Model,
    default_penalty,
)
from engine.tolerances import DEFAULT_TOLERANCES


@dataclass(frozen=True, eq=False)
class BlockSystem:
    """Constants of one model's run. Shapes: `n` blocks, `V` vertices of all blocks.

    - `polys0`: the blocks at the start; `c0 (n, 3)` their centroids (m)
    - `vertex_block (V,)`, `vertex_start (n,)`, `vertex_rel0 (V, 3)`: all vertices stacked
      in block order, relative to their block's initial centroid
    - `volume0 (n,)` m³, `second0 (n, 3, 3)` m⁵ (∫ x_t x_tᵀ dV), `density (n,)` kg/m³
    - `fixed (n,)`, `ndof` (6 rigid, 12 elastic), `dof_map (n, 12)` global unknown of each
      block column (-1: none), `block_row (n,)` each block's block row in K (-1: fixed)
    - `emat (n, 6, 6)` Pa; `kn`, `ks`, `kf` N/m (normal, shear and fixed-point penalties)
    - `thickness (n,)` 2V/A m, `radius (n,)` m (farthest surface vertex from the centroid)
    - `max_step_displacement` m: no point moves more in a step; `search_distance` m
    - `touch_gap` m: closer blocks touch; `open_close_gap` m: the open-close hysteresis
    - `bond_gap` m: joint faces closer at the start are bonded (cohesion, tensile strength)
    - `tan_phi`, `cohesion` (Pa), `tension` (Pa) per joint material
    - `gravity` m/s²: body force per unit mass (gravity plus any pseudo-static seismic
      load, :attr:`engine.model.Model.body_acceleration`)
    - `loads`: (block, point m, force N) per point load; `fixed_points`: (block, point m)
    - `energy_floor` J: spring energies below it are round-off; `energy_round_off` J: the
      energy balance's round-off (1e-10 of the free blocks' potential energy over the
      model's size, and of the bolts' pretension over it)
    - `adaptive_search`: search each step within its own predicted limit
    - `bolts`: the rock bolts and cables (None: none), :mod:`engine.loads.bolts`
    - `water`: the water in the joints (None: dry), :mod:`engine.loads.water`
    """

    model: Model
    n: int
    polys0: tuple[Polyhedron, ...]
    c0: np.ndarray
    vertex_block: np.ndarray
    vertex_start: np.ndarray
    vertex_rel0: np.ndarray
    volume0: np.ndarray
    second0: np.ndarray
    density: np.ndarray
    fixed: np.ndarray
    elastic: bool
    ndof: int
    dof_map: np.ndarray
    n_unknowns: int
    block_row: np.ndarray
    emat: np.ndarray
    kn: float
    ks: float
    kf: float
    scale: float
    thickness: np.ndarray
    radius: np.ndarray
    max_step_displacement: float
    search_distance: float
    touch_gap: float
    bond_gap: float
    open_close_gap: float
    tan_phi: np.ndarray
    cohesion: np.ndarray
    tension: np.ndarray
    needs_areas: bool
    loads: tuple[tuple[int, np.ndarray, np.ndarray], ...]
    fixed_points: tuple[tuple[int, np.ndarray], ...]
    gravity: np.ndarray
    energy_floor: float
    energy_round_off: float
    adaptive_search: bool = True
    bolts: BoltSet | None = None
    water: Water | None = None

    @property
    def controls(self) -> AnalysisControls:
        return self.model.controls


def _dof_map(fixed: np.ndarray, ndof: int) -> tuple[np.ndarray, int]:
    """Global unknown of each block column `(n, 12)` (-1 where none) and their count: `ndof`
    unknowns per free block, in block order; fixed blocks have none."""
    dof_map = np.full((len(fixed), 12), -1, dtype=np.int64)
    k = 0
    for b in range(len(fixed)):
        if not fixed[b]:
            dof_map[b, :ndof] = np.arange(k, k + ndof)
            k += ndof
    return dof_map, k


def _stacked_vertices(polys: list[Polyhedron], c0: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All vertices stacked: `(vertex_block (V,), vertex_start (n,), rel0 (V, 3))`."""
    counts = [len(p.vertices) for p in polys]
    block = np.repeat(np.arange(len(polys), dtype=np.int64), counts)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    rel0 = (np.concatenate([p.vertices for p in polys]) - c0[block] if polys
            else np.zeros((0, 3)))
    return block, start, rel0


def build_system(model: Model, adaptive_search: bool = True) -> BlockSystem:
    """The :class:`BlockSystem` of `model`."""
    c = model.controls
    blocks = model.blocks
    n = len(blocks)
    polys = [b.polyhedron for b in blocks]
    c0 = np.array([p.centroid for p in polys]).reshape(n, 3)
    vertex_block, vertex_start, rel0 = _stacked_vertices(polys, c0)
    fixed = np.array([b.fixed for b in blocks], dtype=bool)
    elastic = c.block_model == "elastic"
    ndof = 12 if elastic else 6
    dof_map, n_unknowns = _dof_map(fixed, ndof)
    mats = [model.materials[b.material] for b in blocks]
    density = np.array([m.density for m in mats])
    volume0 = np.array([p.volume for p in polys])
    kn = float(c.penalty) if c.penalty is not None else default_penalty(model)
    scale = model.scale
    # thin blocks, fixed or not, bound the step so nothing tunnels through them: no
    # point moves more than half the width of the thinnest block in a step
    thin = min(p.width for p in polys) if n else scale
    max_step = min(c.max_displacement_ratio * scale, 0.5 * thin)
    cohesion = np.array([j.cohesion for j in model.joint_materials])
    tension = np.array([j.tensile_strength for j in model.joint_materials])
    return BlockSystem(
        model=model, n=n, polys0=tuple(polys), c0=c0, vertex_block=vertex_block,
        vertex_start=vertex_start, vertex_rel0=rel0, volume0=volume0,
        second0=np.array([p.second_moments for p in polys]).reshape(n, 3, 3),
        density=density, fixed=fixed, elastic=elastic, ndof=ndof, dof_map=dof_map,
        n_unknowns=n_unknowns, block_row=np.where(fixed, -1, dof_map[:, 0] // ndof),
        emat=np.array([asm.elastic_matrix(m.young_modulus, m.poisson_ratio)
                       for m in mats]).reshape(n, 6, 6),
        kn=kn, ks=kn * float(c.shear_penalty_ratio),
        kf=float(c.fixed_point_penalty or 10.0 * kn), scale=scale,
        thickness=np.array([2.0 * p.volume / max(p.face_areas.sum(), 1e-300) for p in polys]),
        radius=np.array([np.linalg.norm(p.vertices[p.surface_vertex_ids] - p.centroid,
                                        axis=1).max() for p in polys]),
        max_step_displacement=max_step, search_distance=2.0 * max_step,
        touch_gap=DEFAULT_TOLERANCES.lengths(scale).touching,
        bond_gap=DEFAULT_TOLERANCES.lengths(scale).bonding,
        open_close_gap=c.open_close_tolerance * max_step,
        tan_phi=np.array([np.tan(j.friction_angle_rad) for j in model.joint_materials]),
        cohesion=cohesion, tension=tension,
        needs_areas=bool(np.any(cohesion > 0) or np.any(tension > 0)),
        loads=tuple((ld.block, np.asarray(ld.point, float), np.asarray(ld.force, float))
                    for ld in model.point_loads),
        fixed_points=tuple((fp.block, np.asarray(fp.point, float))
                           for fp in model.fixed_points),
        gravity=model.body_acceleration,
        # J: energy differences below this are round-off (1e-6 of the model's potential
        # energy scale or of a spring pressed by a whole step limit)
        energy_floor=1e-6 * max(
            float(np.sum((density * volume0)[~fixed]))
            * float(np.linalg.norm(model.body_acceleration))
            * scale, 0.5 * kn * max_step**2),
        energy_round_off=1e-10 * float(np.sum((density * volume0)[~fixed]))
        * float(np.linalg.norm(model.body_acceleration)) * scale
        + 1e-10 * float(sum(b.pretension for b in model.bolts)) * scale,
        adaptive_search=adaptive_search,
        bolts=bolt_set(model.bolts) if model.bolts else None,
        water=model.water,
    )
