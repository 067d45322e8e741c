"""Our models as LMGC90 scenes: rigid convex polyhedra (vertices and outward triangles), the
fixed blocks held, one density per material, gravity, Coulomb friction tan φ and Δt.

LMGC90 (non-smooth contact dynamics: Moreau–Jean θ-scheme, NLGS, law IQS_CLB: inelastic
impacts, restitution 0, Coulomb) runs through compas_lmgc90's compiled binding
(`compas_lmgc90._lmgc90`), driven here exactly as its `Solver.preprocess` / `run` drive it
but without `Solver`, whose module imports COMPAS: `pip install --no-deps compas-lmgc90`
is then all a benchmark needs. LMGC90 keeps one simulation per process, so every run here
is meant for a process of its own: `python -m benchmarks.lmgc90 run BUILDER SECONDS` or
`python -m benchmarks.lmgc90 verify BUILDER` print one line `RESULT {json}`.

Benchmark-only: nothing in `engine/` or `service/` imports this module.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.model import Model

#: the gravity LMGC90's binding sets (its `set_materials`), m/s²
LMGC90_GRAVITY = (0.0, 0.0, -9.81)
#: NLGS settings fixed inside the binding (not settable from Python; read from the source of
#: compas_lmgc90's Fortran wrapper, wrap_lmgc90_compas.f90): tolerance, norm, relaxation,
#: sweeps between convergence checks, checks at most
NLGS_SETTINGS = "tol 1.666e-4 (QM/16), relaxation 0.1, a check every 50 sweeps, ≤ 500 checks"
#: how the binding detects contacts: STO, "explicit" (the contacts found at the first step
#: are kept for the whole run: masonry that barely moves), or re-detected every step
#: (`redetect`, set through the Fortran module's own setter, which the binding does not expose)
DETECTION = {False: "STO explicit (contacts of the first step kept)",
             True: "STO re-detected every step"}


def _redetect_every_step() -> None:
    """Switch LMGC90's STO detection from explicit (contacts found once) to every step: the
    PRPRx module's setter, called through ctypes on the binding's own library (the binding
    fixes the choice in `initialize` and exposes no setter). Call after `initialize`."""
    import ctypes

    from compas_lmgc90 import _lmgc90

    lib = ctypes.CDLL(_lmgc90.__file__)  # the loaded library: same module variables
    lib.__prprx_MOD_sto_set_explicit_detection_prprx(ctypes.byref(ctypes.c_int(0)))


@dataclass
class LmgcBlock:
    """One rigid body: surface vertices `(k, 3)` m (global), outward triangles `(t, 3)`,
    density kg/m³ and whether it is held fixed."""

    vertices: np.ndarray
    triangles: np.ndarray
    density: float
    fixed: bool


@dataclass
class LmgcScene:
    """A model exported for LMGC90: its blocks in model order, friction coefficient, Δt (s)."""

    blocks: list[LmgcBlock]
    friction: float
    dt: float
    notes: list[str] = field(default_factory=list)


def triangulate(vertices: np.ndarray, indptr: np.ndarray, indices: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangles of convex polygon faces, renumbered onto the vertices the faces use:
    `(used vertices (k, 3), triangles (t, 3))`; zero-area triangles (collinear vertices)
    are dropped, which changes no surface integral."""
    from engine.geometry.polyhedron import fan_triangles

    tris, _ = fan_triangles(indptr, indices)
    used = np.unique(tris)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    v = np.asarray(vertices, float)[used]
    t = remap[tris]
    a, b, c = (v[t[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    return v, t[area > 1e-14 * max(float(area.max()), 1e-300)]


def export_model(model: Model) -> LmgcScene:
    """The scene LMGC90 can run for `model`: rigid convex blocks, fixed ones held, gravity
    (0, 0, −9.81), one joint material without cohesion or tension. Raises ValueError for
    what the export cannot carry (loads, bolts, water, concave blocks, ...)."""
    c = model.controls
    if not np.allclose(np.asarray(model.gravity, float), LMGC90_GRAVITY, rtol=0, atol=1e-12):
        raise ValueError(f"LMGC90's binding fixes gravity to {LMGC90_GRAVITY}")
    if c.block_model != "rigid":
        raise ValueError("LMGC90's POLYR bodies are rigid")
    extras = {"point loads": model.point_loads, "fixed points": model.fixed_points,
              "bolts": model.bolts, "water": model.water, "ground motion": model.ground_motion,
              "seismic load": model.seismic}
    present = [name for name, v in extras.items() if v]
    if present:
        raise ValueError(f"not exported: {', '.join(present)}")
    used = {model.default_joint_material, *model.joint_material_of_tag.values(),
            *model.pair_joint_material.values()}
    joints = {(float(model.joint_materials[j].friction_angle_rad),
               float(model.joint_materials[j].cohesion),
               float(model.joint_materials[j].tensile_strength)) for j in used}
    if len(joints) != 1:
        raise ValueError("LMGC90's binding takes one contact law: one joint material only")
    phi, cohesion, tension = joints.pop()
    if cohesion or tension:
        raise ValueError("IQS_CLB has no cohesion or tensile strength")
    blocks = []
    for k, b in enumerate(model.blocks):
        p = b.polyhedron
        if not p.is_convex:
            raise ValueError(f"block {k} ({b.name}) is concave: POLYR bodies must be convex")
        v, t = triangulate(p.vertices, p.face_indptr, p.face_indices)
        blocks.append(LmgcBlock(v, t, float(model.materials[b.material].density), b.fixed))
    moving = [k for k, b in enumerate(model.blocks) if np.any(b.velocity)]
    notes = [f"initial velocities dropped ({len(moving)} blocks)"] if moving else []
    return LmgcScene(blocks, math.tan(phi), float(c.time_step), notes)


def triangle_mass(vertices: np.ndarray, triangles: np.ndarray
                  ) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume m³, centroid `(3,)` and `∫ x xᵀ dV` about it `(3, 3)` of a closed triangle
    surface (signed tetrahedra): what LMGC90 will compute from the export, computed
    independently of the engine's own routine."""
    ref = vertices.mean(axis=0)
    a, b, c = (vertices[triangles[:, k]] - ref for k in range(3))
    v6 = np.einsum("ij,ij->i", a, np.cross(b, c))
    vol = v6.sum() / 6.0
    s = a + b + c
    cen = (v6[:, None] * s).sum(axis=0) / 24.0 / vol
    outer = sum(np.einsum("i,ij,ik->jk", v6, x, x) for x in (a, b, c, s)) / 120.0
    return float(vol), cen + ref, outer - vol * np.outer(cen, cen)


def export_errors(model: Model, scene: LmgcScene) -> dict[str, float]:
    """Largest relative differences between the exported triangles and our blocks: volume,
    centroid (over the block's size V^⅓) and second moments (over their largest)."""
    dv = dc = dm = 0.0
    for b, e in zip(model.blocks, scene.blocks, strict=True):
        p = b.polyhedron
        vol, cen, sec = triangle_mass(e.vertices, e.triangles)
        dv = max(dv, abs(vol / p.volume - 1.0))
        dc = max(dc, float(np.linalg.norm(cen - p.centroid)) / p.volume ** (1 / 3))
        dm = max(dm, float(np.abs(sec - p.second_moments).max()
                           / np.abs(p.second_moments).max()))
    return {"volume": dv, "centroid": dc, "second_moments": dm}


# --------------------------------------------------------------------------- LMGC90


def start(scene: LmgcScene, theta: float = 0.5, alert: float = 1e-3,
          offsets: np.ndarray | None = None,
          forces: dict[int, dict[int, float]] | None = None,
          redetect: bool = False) -> tuple[Any, Any]:
    """Build `scene` in LMGC90 (its compiled binding) and return `(solver, initial state)`;
    `redetect`: contacts detected every step (:data:`DETECTION`).

    `offsets (n, 3)` m moves block k by offsets[k] (the verification spreads the blocks
    apart); `forces[k][dof]` adds a constant driven force (dofs 1–3, N, global) or moment
    (4–6, N·m, about the body's principal axes) on block k. Mirrors
    `compas_lmgc90.solver.Solver.preprocess`: law, materials, see table, bodies."""
    from compas_lmgc90 import _lmgc90

    forces = forces or {}
    s = _lmgc90.LMGC90Solver()
    s.initialize(scene.dt, theta, False)
    if redetect:
        _redetect_every_step()
    s.add_one_tact_behav("iqsc0", "IQS_CLB", [scene.friction])
    densities = sorted({b.density for b in scene.blocks})
    name = {d: f"s{i + 1:04d}" for i, d in enumerate(densities)}
    s.set_materials(densities)
    s.set_see_tables(alert)
    s.set_nb_bodies(len(scene.blocks))
    for k, b in enumerate(scene.blocks):
        v = b.vertices + (0.0 if offsets is None else offsets[k])
        ref = v.mean(axis=0)  # the body's reference; LMGC90 moves it to the centre of mass
        f = forces.get(k, {})
        s.set_one_polyr(name[b.density], ref.tolist(), (b.triangles + 1).ravel().tolist(),
                        (v - ref).ravel().tolist(), 6 if b.fixed else 0, len(f))
        if b.fixed:
            for dof in range(1, 7):
                s.set_drvdof(k + 1, dof, [0.0] * 6, True, False)
        for dof, value in f.items():  # f(t) = value · min(1, 1 + 0 t)
            s.set_drvdof(k + 1, dof, [float(value), 0.0, 0.0, 0.0, 1.0, 0.0], False, False)
    s.close_before_computing()
    return s, s.get_initial_state()


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Angles (rad) of rotation matrices `(n, 3, 3)`."""
    cos = (np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def rotation_vectors(r: np.ndarray) -> np.ndarray:
    """Rotation vectors `(n, 3)` (axis × angle) of rotation matrices `(n, 3, 3)`."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_rotvec()


def motion_summary(mass: np.ndarray, inertia: np.ndarray, disp: np.ndarray,
                   angle: np.ndarray, step_d: np.ndarray, step_rot: np.ndarray,
                   step_dt: float) -> dict[str, Any]:
    """What both engines report about a run, from positions only: block displacements
    `(n, 3)` m and rotation angles `(n,)` rad since the start, and the kinetic energy of
    the last step's mean velocities (translation `step_d (n, 3)` m, rotation vectors
    `step_rot (n, 3)` over `step_dt` s; both θ = ½ schemes move a block by Δt (v₀ + v₁)/2),
    with masses `(n,)` kg and global inertia tensors `(n, 3, 3)` kg·m²."""
    v, w = step_d / step_dt, step_rot / step_dt
    ke = 0.5 * float(np.sum(mass * np.einsum("ij,ij->i", v, v))
                     + np.einsum("ni,nij,nj->", w, inertia, w))
    norm = np.linalg.norm(disp, axis=1)
    return {"disp_mean_m": float(norm.mean()), "disp_max_m": float(norm.max()),
            "settlement_mean_m": float(-disp[:, 2].mean()),
            "rotation_mean_rad": float(angle.mean()), "rotation_max_rad": float(angle.max()),
            "kinetic_step_mean_J": ke, "moved_over_1mm": int(np.sum(norm > 1e-3)),
            "displacements": disp.round(9).tolist()}


def deepest_overlap(model: Model, centroids: np.ndarray, turns: np.ndarray) -> float:
    """How deep (m) a vertex of one block lies inside another when each block k is moved to
    `centroids[k]` turned by `turns[k]` from where the model has it: the same check, by our
    geometry, of both engines' end states (a missed contact shows as a deep overlap)."""
    verts, planes = [], []
    for k, b in enumerate(model.blocks):
        p = b.polyhedron
        rel = p.vertices - p.centroid
        verts.append(centroids[k] + rel[p.surface_vertex_ids] @ turns[k].T)
        first = centroids[k] + rel[p.face_indices[p.face_indptr[:-1]]] @ turns[k].T
        normals = p.face_normals @ turns[k].T
        planes.append((normals, np.einsum("ij,ij->i", normals, first)))
    lo = np.array([v.min(axis=0) for v in verts])
    hi = np.array([v.max(axis=0) for v in verts])
    deepest = 0.0
    for i in range(len(verts)):
        near = np.flatnonzero(np.all(lo[i] <= hi, axis=1) & np.all(lo <= hi[i], axis=1))
        for j in near[near != i]:
            normals, offsets = planes[j]
            inside = (offsets[None, :] - verts[i] @ normals.T).min(axis=1)
            deepest = max(deepest, float(inside.max()))
    return deepest


def inertia_tensors(model: Model, rotations: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """Masses `(n,)` kg and global inertia tensors `(n, 3, 3)` of the model's blocks, turned
    by `rotations (n, 3, 3)` when given."""
    mass, inertia = [], []
    for b in model.blocks:
        p, rho = b.polyhedron, model.materials[b.material].density
        c = p.second_moments
        mass.append(rho * p.volume)
        inertia.append(rho * (np.trace(c) * np.eye(3) - c))
    inertia_a = np.array(inertia)
    if rotations is not None:
        inertia_a = rotations @ inertia_a @ rotations.transpose(0, 2, 1)
    return np.array(mass), inertia_a


def run(builder: str, seconds: float, redetect: bool = False, theta: float = 0.5,
        cap: float = 1800.0) -> dict[str, Any]:
    """Run the model `builder` (an expression over benchmarks.pile's builders) in LMGC90 for
    `seconds` of simulated time at the model's Δt (stopped after `cap` s of wall): the wall
    of the stepping loop (each step also copies the contacts into Python: the binding
    returns them), and what :func:`motion_summary` reports. Call in a process of its own."""
    import compas_lmgc90

    from benchmarks.pile import pile_model, rock_mass_model  # noqa: F401 (the builders)

    model = eval(builder)  # one of the benchmark's builder expressions
    t0 = time.perf_counter()
    scene = export_model(model)
    s, init = start(scene, theta, redetect=redetect)
    setup = time.perf_counter() - t0
    free = np.array([not b.fixed for b in scene.blocks])
    c0 = np.array(init.init_bodies, float)
    f0 = np.array(init.init_body_frames, float).reshape(-1, 3, 3)
    centroids = np.array([b.polyhedron.centroid for b in model.blocks])
    size = np.array([b.polyhedron.volume ** (1 / 3) for b in model.blocks])
    n = int(round(seconds / scene.dt))
    prev_c, prev_f, contacts, walls, deepest, pairs = c0, f0, [], [], 0.0, 0
    t1, cpu1 = time.perf_counter(), time.process_time()
    r = prev_r = None
    status = "completed"
    for _ in range(n):
        if time.perf_counter() - t1 > cap:
            status = f"stopped: wall cap {cap:.0f} s"
            break
        prev_r = r
        walls.append(time.perf_counter())
        r = s.compute_one_step()
        gaps = r.interaction_gap
        contacts.append(len(gaps))
        deepest = max(deepest, -min(gaps, default=0.0))
    wall, cpu = time.perf_counter() - t1, time.process_time() - cpu1
    step_walls = np.diff([*walls, t1 + wall])
    pairs = len({tuple(sorted(p)) for p in r.interaction_bodies})
    done = len(step_walls)
    c1 = np.array(r.bodies, float)
    f1 = np.array(r.body_frames, float).reshape(-1, 3, 3)
    if prev_r is not None:
        prev_c = np.array(prev_r.bodies, float)
        prev_f = np.array(prev_r.body_frames, float).reshape(-1, 3, 3)
    # the body frame's rows are its principal axes: the turn since the start is F1ᵀ F0
    turn = f1.transpose(0, 2, 1) @ f0
    step_turn = f1.transpose(0, 2, 1) @ prev_f
    mass, inertia = inertia_tensors(model, turn)
    overlap = deepest_overlap(model, c1, turn)
    out = {"engine": "LMGC90", "solver": "LMGC90 redetect" if redetect else "LMGC90",
           "builder": builder, "detection": DETECTION[redetect],
           "blocks": int(free.sum()), "dt": scene.dt, "theta": theta,
           "steps": done, "simulated_s": done * scene.dt, "wall_s": wall, "cpu_s": cpu,
           "setup_s": setup, "per_step_s": wall / max(done, 1),
           "per_sim_second_s": wall / max(done * scene.dt, 1e-12),
           "mean_dt": scene.dt, "iterations_mean": None, "contacts_mean": float(
               np.mean(contacts or [0])), "contacts_end": contacts[-1] if contacts else 0,
           "pairs_end": pairs, "max_penetration_m": deepest, "overlap_end_m": overlap,
           "status": status,
           "centroid_error": float(np.max(np.linalg.norm(c0 - centroids, axis=1) / size)),
           "version": compas_lmgc90.__version__, "law": "IQS_CLB", "friction": scene.friction,
           "nlgs": NLGS_SETTINGS, "step_walls_s": step_walls.round(4).tolist()}
    out.update(motion_summary(mass[free], inertia[free], (c1 - c0)[free],
                              rotation_angle(turn)[free], (c1 - prev_c)[free],
                              rotation_vectors(step_turn)[free], scene.dt))
    return out


def verify(builder: str, h: float = 0.01) -> dict[str, Any]:
    """Check LMGC90's own mass properties of the exported blocks against ours: centroids
    where they stand, then, with the blocks spread apart (no contact), one step of `h` s
    under a lift equal to our weight plus a unit acceleration along x (LMGC90's mass must
    give exactly h²/2 of drift) and moments about the principal axes (LMGC90's principal
    moments must give h²/2 M/I). Relative errors; call in a process of its own."""
    from benchmarks.pile import pile_model, rock_mass_model  # noqa: F401 (the builders)

    model = eval(builder)  # one of the benchmark's builder expressions
    scene = export_model(model)
    n = len(scene.blocks)
    centroids = np.array([b.polyhedron.centroid for b in model.blocks])
    size = np.array([b.polyhedron.volume ** (1 / 3) for b in model.blocks])
    mass, inertia = inertia_tensors(model)
    moments = np.linalg.eigvalsh(inertia)  # ascending, as LMGC90 orders its axes
    span = float(np.max([np.ptp(b.vertices, axis=0).max() for b in scene.blocks]))
    side = int(np.ceil(n ** (1 / 3)))
    grid = np.array(np.unravel_index(np.arange(n), (side,) * 3)).T
    offsets = 3.0 * span * grid - centroids
    torque = np.array([1.0, 2.0, 3.0]) * 1e-3  # rad/s² about each principal axis: a turn
    # of ~1e-7 rad (the measured turn departs from h²/2 M/I by about the turn itself)
    forces = {k: {1: mass[k] * 1.0, 3: mass[k] * 9.81,
                  **{4 + a: torque[a] * moments[k, a] for a in range(3)}}
              for k in range(n) if not scene.blocks[k].fixed}
    s, init = start(LmgcScene(scene.blocks, scene.friction, h), 0.5, 1e-3, offsets, forces)
    c0 = np.array(init.init_bodies, float)
    f0 = np.array(init.init_body_frames, float).reshape(-1, 3, 3)
    r = s.compute_one_step()
    c1 = np.array(r.bodies, float)
    f1 = np.array(r.body_frames, float).reshape(-1, 3, 3)
    free = np.array([not b.fixed for b in scene.blocks])
    expect = 0.5 * h * h
    drift = (c1 - c0)[free] / expect - np.array([1.0, 0.0, 0.0])
    # the turn in the body's principal frame: F1 F0ᵀ (rows of F are the principal axes)
    spin = np.abs(rotation_vectors(f1 @ f0.transpose(0, 2, 1))[free]) / expect / torque
    return {"builder": builder, "blocks": n, "contacts": len(r.interaction_gap),
            "centroid": float(np.max(np.linalg.norm(c0 - offsets - centroids, axis=1) / size)),
            "mass": float(np.abs(drift).max()),
            "principal_moments": float(np.abs(spin - 1.0).max()),
            **{f"export_{k}": v for k, v in export_errors(model, scene).items()}}


def in_subprocess(*args: str, timeout: float = 3600.0) -> dict[str, Any]:
    """`python -m benchmarks.lmgc90 ARGS` in a fresh process (LMGC90 keeps one simulation
    per process): its RESULT line, or RuntimeError with the end of its output."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "benchmarks.lmgc90", *args], cwd=root, env=env,
                       capture_output=True, text=True, timeout=timeout)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"LMGC90 {' '.join(args)} failed (exit {p.returncode}): "
                       f"{(p.stdout + p.stderr)[-600:]}")


def main(argv: list[str]) -> None:
    """`run BUILDER SECONDS [redetect]` or `verify BUILDER`: one RESULT line of JSON."""
    if argv[0] == "run":
        res = run(argv[1], float(argv[2]), redetect=argv[3:4] == ["redetect"])
    elif argv[0] == "verify":
        res = verify(argv[1])
    else:
        raise SystemExit(f"unknown command {argv[0]!r}: run or verify")
    print("RESULT " + json.dumps(res), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
