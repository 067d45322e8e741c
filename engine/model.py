"""Engine inputs: the block model, materials, loads and analysis controls as plain data.

`schemas/` turns a user's scene JSON into a :class:`Model`; the engine never sees JSON.
Units are SI; angles inside the engine are radians (names end in `_rad`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from engine.geometry.polyhedron import Polyhedron
from engine.loads.bolts import Bolt
from engine.loads.seismic import GroundMotion, SeismicLoad
from engine.loads.water import Water


@dataclass(frozen=True)
class Material:
    """Intact rock: density (kg/m³), Young's modulus (Pa), Poisson's ratio (-)."""

    density: float = 2600.0
    young_modulus: float = 10e9
    poisson_ratio: float = 0.25


#: friction angle of a joint material that states none (degrees)
DEFAULT_FRICTION_ANGLE_DEG = 30.0


@dataclass(frozen=True)
class JointMaterial:
    """Joint strength: friction angle (rad), cohesion (Pa), tensile strength (Pa)."""

    friction_angle_rad: float = np.radians(DEFAULT_FRICTION_ANGLE_DEG)
    cohesion: float = 0.0
    tensile_strength: float = 0.0


@dataclass
class Block:
    """One block of the model: geometry, material index, fixed flag, initial velocity.

    `velocity (6,)`: translation (m/s) then spin (rad/s) about the centroid.
    """

    polyhedron: Polyhedron
    name: str = ""
    material: int = 0
    fixed: bool = False
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(6))


@dataclass(frozen=True)
class PointLoad:
    """A force `force (3,)` N applied at `point (3,)` m of block `block`."""

    block: int
    point: np.ndarray
    force: np.ndarray


@dataclass(frozen=True)
class FixedPoint:
    """A point `point (3,)` of block `block` held in place by a stiff penalty spring."""

    block: int
    point: np.ndarray


@dataclass(frozen=True)
class AnalysisControls:
    """How to run: time, penalties, iteration limits, block model.

    `penalty` is the normal stiffness of one contact spring (N/m; None: derived from the
    scene, :func:`default_penalty`); the shear spring is
    `shear_penalty_ratio * penalty`. `contact_damping` is each contact dashpot's fraction
    of critical damping (0.5: a rock impact's restitution coefficient about 0.4).
    `dynamic_ratio` is k01 (1 dynamic, 0 static).
    `max_displacement_ratio` limits the largest displacement in a step to this fraction
    of the model size (paper eq. 50 uses a fraction of the smallest edge instead);
    `max_penetration_ratio` limits a contact's penetration to this fraction of the
    thickness (2 V / A) of the thinner of its blocks: a deeper step is redone with a
    smaller Δt, so nothing tunnels. `open_close_tolerance` is the open-close
    iteration's hysteresis as a fraction of the step displacement limit (default 0: a
    contact that penetrates carries its spring and friction; there is no force-free band).
    """

    duration: float = 1.0
    time_step: float = 1e-3
    penalty: float | None = None
    shear_penalty_ratio: float = 1.0
    record_interval: int = 10
    dynamic_ratio: float = 1.0
    block_model: Literal["rigid", "elastic"] = "rigid"
    max_displacement_ratio: float = 0.01
    max_penetration_ratio: float = 0.25
    max_open_close_iterations: int = 20
    open_close_tolerance: float = 0.0
    contact_damping: float = 0.5
    min_time_step: float = 1e-7
    fixed_point_penalty: float | None = None
    record_contacts: bool = True
    #: how each step's contacts are solved: "open_close", the paper's open-close iteration
    #: on penalty springs (:mod:`engine.contact.solvers.open_close`); "newton", the same
    #: springs' step potential minimised by Newton's method
    #: (:mod:`engine.contact.solvers.newton`); or "complementarity", one solve of the
    #: frictional contact problem without springs
    #: (:mod:`engine.contact.solvers.complementarity`)
    contact_solver: Literal["open_close", "complementarity", "newton"] = "open_close"
    #: the complementarity solve's convergence: the change of the blocks' motion in a sweep
    #: relative to the motion the contacts cause (energy norm); Newton's: every block's
    #: out-of-balance force relative to the median block's weight
    contact_tolerance: float = 1e-6
    #: restitution of an impact (the complementarity solve's impact law): the parting
    #: normal velocity is `e` times the approach velocity; 0 is a plastic impact
    restitution: float = 0.0
    #: sleeping (complementarity solve): a block whose points all move slower than
    #: `sleep_velocity` m/s for `sleep_time` s, with every contact stuck inside its friction
    #: (and tensile) capacity by a margin, leaves the solve until a contact force on it
    #: changes (0: never sleep)
    sleep_velocity: float = 1e-3
    sleep_time: float = 0.05


@dataclass(frozen=True)
class StrengthReductionControls:
    """Settings of the factor-of-safety search (engine.analyses.strength_reduction).

    The model is first settled under its loads with joints that cannot fail; each trial
    (from the equilibrium at F = 1 when the model has one) divides the joints' strength by
    F and runs for at most `observation_time` s. A trial fails when a watched block moves
    more than `displacement_limit` m (None: :data:`DISPLACEMENT_LIMIT_RATIO` × the size
    V^⅓ of the smallest watched block) or is still moving at the end without slowing
    down; it holds, and ends early, once every
    watched block is at rest with every contact stuck. F is searched within
    `[min_factor, max_factor]`; bisection stops when the bracket is narrower than
    `tolerance` relative to F or after `max_runs` trials. The scene schema takes its
    defaults from here.
    """

    observation_time: float = 1.0
    displacement_limit: float | None = None
    tolerance: float = 0.005
    min_factor: float = 0.05
    max_factor: float = 20.0
    max_runs: int = 30
    #: joint materials whose strength is reduced (None: all)
    joint_materials: tuple[int, ...] | None = None
    #: blocks whose motion decides failure (None: every block that is not fixed)
    watch_blocks: tuple[int, ...] | None = None


#: a trial's default displacement limit as a fraction of the smallest watched block's size
DISPLACEMENT_LIMIT_RATIO = 0.02


@dataclass(frozen=True)
class SeismicCoefficientControls:
    """Settings of the critical (yield) seismic coefficient search: bisection on kh (the
    scene's azimuth and kv kept, full strengths) with the trials of the factor of safety
    (from the equilibrium at kh = 0: fail beyond `displacement_limit` m or still moving at
    `observation_time` s), up to
    `max_coefficient`; stops when the bracket is narrower than `tolerance` relative to kh or
    after `max_runs` trials."""

    observation_time: float = 1.0
    displacement_limit: float | None = None
    tolerance: float = 0.005
    max_coefficient: float = 1.0
    max_runs: int = 30
    #: blocks whose motion decides failure (None: every block that is not fixed)
    watch_blocks: tuple[int, ...] | None = None


@dataclass
class Model:
    """Everything the engine needs to run a scene.

    `joint_material_of_tag` maps a face tag (joint id) to a joint material index;
    `pair_joint_material` maps an unordered block-index pair `(min, max)` to one and
    wins over tags; `default_joint_material` applies everywhere else.
    """

    blocks: list[Block]
    materials: list[Material] = field(default_factory=lambda: [Material()])
    joint_materials: list[JointMaterial] = field(default_factory=lambda: [JointMaterial()])
    default_joint_material: int = 0
    joint_material_of_tag: dict[int, int] = field(default_factory=dict)
    pair_joint_material: dict[tuple[int, int], int] = field(default_factory=dict)
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    point_loads: list[PointLoad] = field(default_factory=list)
    fixed_points: list[FixedPoint] = field(default_factory=list)
    #: rock bolts and cables
    bolts: list[Bolt] = field(default_factory=list)
    #: water pressure in the joints (None: dry)
    water: Water | None = None
    #: acceleration time history of the ground (None: none)
    ground_motion: GroundMotion | None = None
    #: pseudo-static seismic body force on every block (None: none)
    seismic: SeismicLoad | None = None
    controls: AnalysisControls = field(default_factory=AnalysisControls)

    @property
    def body_acceleration(self) -> np.ndarray:
        """Acceleration (m/s², (3,)) of the body forces: gravity plus the pseudo-static
        seismic coefficients times |gravity| (gravity itself when there are none)."""
        if self.seismic is None:
            return self.gravity
        g = np.asarray(self.gravity, float)
        return g + self.seismic.acceleration(float(np.linalg.norm(g)))

    @property
    def scale(self) -> float:
        """Model size (m): the largest edge of the bounding box of all blocks."""
        lo = np.min([b.polyhedron.bounds[0] for b in self.blocks], axis=0)
        hi = np.max([b.polyhedron.bounds[1] for b in self.blocks], axis=0)
        return float(np.max(hi - lo))


#: the default penalty makes a contact spring this many times stiffer than the inertia a
#: typical block opposes to a step's motion (2 m / Δt², the mass term of the step's
#: equations): contacts then act as constraints within a step instead of cushions
PENALTY_INERTIA_RATIO = 10.0


def default_penalty(model: Model) -> float:
    """The scene's contact penalty (N/m) when the user gives none: the larger of the rock's
    own stiffness at block size, E L (E the stiffest movable material, L the median movable
    block's size V^⅓), and PENALTY_INERTIA_RATIO × 2 m / Δt² (m the median movable block's
    mass, Δt the asked time step); rounded to one significant figure."""
    free = [b for b in model.blocks if not b.fixed] or list(model.blocks)
    if not free:
        return 1e10
    volume = np.array([b.polyhedron.volume for b in free])
    mass = volume * np.array([model.materials[b.material].density for b in free])
    young = max(model.materials[b.material].young_modulus for b in free)
    dt = model.controls.time_step
    k = max(young * float(np.median(volume)) ** (1 / 3),
            PENALTY_INERTIA_RATIO * 2.0 * float(np.median(mass)) / dt**2)
    lead = 10.0 ** np.floor(np.log10(k))
    return float(np.round(k / lead) * lead)
