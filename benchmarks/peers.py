"""Other engines on the same scenes: MuJoCo (in process), LMGC90 and YADE (subprocesses).

Peers are benchmark-only (installed by `benchmarks/setup_peers.sh`); a missing one is
skipped with a note. Every peer point is the down-slope displacement of the incline cube
at 1 s against the analytic ½ a t² (a = 1.812815 m/s²), with the wall time of its
stepping loop. `python -m benchmarks.peers lmgc90 DT` runs one LMGC90 point and prints
JSON (LMGC90 keeps one simulation per process).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import harness as h
from benchmarks.cases import DOWN_DIP, INCLINE_AXES, INCLINE_D1, STRIKE, UP_NORMAL

A_INCLINE = 2.0 * INCLINE_D1  #: m/s², ½ a t² = 0.906407 m at 1 s
#: tilted gravity equivalent to the 30° incline (docs/validation.md, optional variant)
TILTED_G = (4.905, 0.0, -8.495709)


def _box_vf(origin: np.ndarray, size: list[float]) -> dict[str, Any]:
    ax = INCLINE_AXES * np.asarray(size, float)[:, None]
    c = [origin, origin + ax[0], origin + ax[0] + ax[1], origin + ax[1]]
    v = np.array(c + [x + ax[2] for x in c])
    f = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    return {"vertices": v.tolist(), "faces": f}


# --------------------------------------------------------------------------- MuJoCo


def mujoco_incline(dt: float, phi_deg: float = 20.0) -> dict[str, Any]:
    """The cube on a horizontal plate under tilted gravity, MuJoCo's default solver and
    pyramidal cone, sliding friction tan φ; down-slope displacement at 1 s."""
    import mujoco

    mu = math.tan(math.radians(phi_deg))
    xml = f"""<mujoco><option timestep="{dt}" gravity="{TILTED_G[0]} {TILTED_G[1]} {TILTED_G[2]}"/>
<worldbody><geom type="box" size="12 2 0.5" pos="0 0 -0.5" friction="{mu} 0 0"/>
<body pos="0 0 0.5"><freejoint/>
<geom type="box" size="0.5 0.5 0.5" mass="2600" friction="{mu} 0 0"/></body>
</worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    x0 = float(d.qpos[0])
    n = int(round(1.0 / dt))
    t0 = time.perf_counter()
    for _ in range(n):
        mujoco.mj_step(m, d)
    wall = time.perf_counter() - t0
    s = float(d.qpos[0]) - x0
    exact = 0.5 * A_INCLINE * d.time**2
    return {"engine": "MuJoCo", "case": "incline", "dt": dt, "penalty": float("nan"),
            "status": "completed", "steps": n, "wall_s": wall, "value": s, "exact": exact,
            "rel_error": abs(s / exact - 1.0), "note": f"mujoco {mujoco.__version__}"}


def mujoco_pile(n: int, dt: float = 1e-3, duration: float = 1.0) -> dict[str, Any]:
    """The shared pile of `n` blocks in MuJoCo (convex mesh per body, box walls): loop wall
    time."""
    import mujoco

    from benchmarks.pile import pile_scene

    scene = pile_scene(n)
    mu = math.tan(math.radians(30))
    assets, bodies = [], []
    for k, b in enumerate(scene["bodies"]):
        verts = " ".join(f"{x:.9g}" for x in np.asarray(b["verts"], float).ravel())
        assets.append(f'<mesh name="m{k}" vertex="{verts}"/>')
        p = " ".join(f"{x:.9g}" for x in b["pos"])
        bodies.append(f'<body pos="{p}"><freejoint/><geom type="mesh" mesh="m{k}" '
                      f'density="{scene["rho"]}" friction="{mu} 0 0"/></body>')
    walls = [f'<geom type="box" pos="{" ".join(map(str, c))}" size="{" ".join(map(str, e))}" '
             f'friction="{mu} 0 0"/>' for c, e in scene["walls"]]
    xml = (f'<mujoco><option timestep="{dt}" gravity="0 0 -9.81"/><asset>{"".join(assets)}'
           f'</asset><worldbody>{"".join(walls)}{"".join(bodies)}</worldbody></mujoco>')
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    n = int(round(duration / dt))
    t0 = time.perf_counter()
    for _ in range(n):
        mujoco.mj_step(m, d)
    wall = time.perf_counter() - t0
    z = d.xpos[1:, 2]
    return {"engine": "MuJoCo", "N": len(scene["bodies"]), "dt": dt, "steps": n,
            "wall_s": wall, "contacts_end": int(d.ncon), "mean_z_end": float(z.mean())}


# --------------------------------------------------------------------------- LMGC90


def lmgc90_incline_point(dt: float, phi_deg: float = 20.0) -> dict[str, Any]:
    """One LMGC90 (compas_lmgc90's binding, NSCD with IQS_CLB Coulomb law) incline run, 1 s
    (driven as `benchmarks.lmgc90` drives it: no COMPAS needed)."""
    from benchmarks.lmgc90 import LmgcBlock, LmgcScene, start

    blocks = []
    for k, (origin, size) in enumerate([(-DOWN_DIP - STRIKE - UP_NORMAL, [22.0, 3.0, 1.0]),
                                        (np.zeros(3), [1.0, 1.0, 1.0])]):
        vf = _box_vf(origin, size)  # quads, outward: two triangles each
        tris = [[f[0], f[i], f[i + 1]] for f in vf["faces"] for i in (1, 2)]
        blocks.append(LmgcBlock(np.array(vf["vertices"]), np.array(tris), 2600.0, k == 0))
    s, init = start(LmgcScene(blocks, math.tan(math.radians(phi_deg)), dt), theta=0.5)
    c0 = np.array(init.init_bodies[1], float)
    n = int(round(1.0 / dt))
    t0 = time.perf_counter()
    r = None
    for _ in range(n):
        r = s.compute_one_step()
    wall = time.perf_counter() - t0
    dist = float((np.array(r.bodies[1], float) - c0) @ DOWN_DIP)
    exact = 0.5 * A_INCLINE * (n * dt) ** 2
    return {"engine": "LMGC90", "case": "incline", "dt": dt, "penalty": float("nan"),
            "status": "completed", "steps": n, "wall_s": wall, "value": dist, "exact": exact,
            "rel_error": abs(dist / exact - 1.0), "note": "compas_lmgc90, IQS_CLB, theta 0.5"}


def lmgc90_incline(dt: float) -> dict[str, Any]:
    """Run :func:`lmgc90_incline_point` in a fresh process (LMGC90 is one sim per process)."""
    p = subprocess.run([sys.executable, "-m", "benchmarks.peers", "lmgc90", str(dt)],
                       capture_output=True, text=True, timeout=600, cwd=h.ROOT)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"LMGC90 run failed: {p.stderr[-400:]}")


# --------------------------------------------------------------------------- YADE

YADE_SCRIPT = r"""
import json, math, sys, time
import numpy as np
from yade import polyhedra_utils
dt, young = float(sys.argv[1]), float(sys.argv[2])
a = math.radians(30)
D = np.array([math.cos(a), 0, -math.sin(a)]); S = np.array([0, 1.0, 0])
N = np.array([math.sin(a), 0, math.cos(a)])
def obox(o, size):
    ax = np.array([D, S, N]) * np.array(size)[:, None]
    c = [o, o + ax[0], o + ax[0] + ax[1], o + ax[1]]
    return [Vector3(*x) for x in c + [x + ax[2] for x in c]]
mat = PolyhedraMat(density=2600, young=young, poisson=0.25, frictionAngle=math.radians(20))
O.materials.append(mat)
O.bodies.append(polyhedra_utils.polyhedra(mat, v=obox(-D - S - N, [22, 3, 1]), fixed=True))
ci = O.bodies.append(polyhedra_utils.polyhedra(mat, v=obox(np.zeros(3), [1, 1, 1]), fixed=False))
O.engines = [ForceResetter(), InsertionSortCollider([Bo1_Polyhedra_Aabb()]),
    InteractionLoop([Ig2_Polyhedra_Polyhedra_PolyhedraGeom()],
                    [Ip2_PolyhedraMat_PolyhedraMat_PolyhedraPhys()],
                    [Law2_PolyhedraGeom_PolyhedraPhys_Volumetric()]),
    NewtonIntegrator(damping=0.0, gravity=(0, 0, -9.81))]
O.dt = dt
p0 = Vector3(O.bodies[ci].state.pos)
n = int(round(1.0 / dt)); t = time.perf_counter(); O.run(n, True); w = time.perf_counter() - t
d = O.bodies[ci].state.pos - p0
print("RESULT " + json.dumps({"d": d[0] * D[0] + d[2] * D[2], "wall": w, "time": O.time,
                              "steps": n}))
"""


def yade_incline(dt: float, young: float) -> dict[str, Any]:
    """YADE polyhedra (volumetric law, stiffness from `young`) incline run, 1 s."""
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "incline.py"
        script.write_text(YADE_SCRIPT)
        p = subprocess.run(["yade", "-n", "-x", str(script), str(dt), str(young)],
                           capture_output=True, text=True, timeout=900, cwd=tmp)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            r = json.loads(line[7:])
            exact = 0.5 * A_INCLINE * r["time"] ** 2
            return {"engine": "YADE", "case": "incline", "dt": dt, "penalty": young,
                    "status": "completed", "steps": r["steps"], "wall_s": r["wall"],
                    "value": r["d"], "exact": exact, "rel_error": abs(r["d"] / exact - 1.0),
                    "note": f"polyhedra, volumetric law, young = {young:g} Pa"}
    raise RuntimeError(f"YADE run failed: {(p.stdout + p.stderr)[-400:]}")


# --------------------------------------------------------------------------- section


def reported_table() -> str:
    """The peers' numbers from benchmarks/scenes/README.md (the shared scenes' README,
    copied verbatim below its line `---`), not re-run."""
    from benchmarks.pile import SCENES

    text = (SCENES / "README.md").read_text()
    lines = text.split("\n---\n", 1)[-1].splitlines()
    table = [ln for ln in lines if ln.startswith("|")]
    start = next((i for i, ln in enumerate(lines) if ln.startswith("Single 1 m cube")), None)
    para = " ".join(lines[start:]).strip() if start is not None else ""
    return "\n".join(table) + ("\n\n> " + para if para else "")


def run_peers(out: Path, full: bool) -> dict[str, Any]:
    """Section 2: every installed peer on the incline (and MuJoCo on the piles)."""
    rows: list[dict[str, Any]] = []
    notes: dict[str, str] = {}
    piles: list[dict[str, Any]] = []
    try:
        import mujoco  # noqa: F401

        for dt in ([1e-2, 3e-3, 1e-3, 3e-4, 1e-4] if not full
                   else [1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5]):
            rows.append(mujoco_incline(dt))
            print(f"  MuJoCo dt={dt:g} err={rows[-1]['rel_error']:.2e}", flush=True)
        for n in (100, 400, 1000):
            piles.append(mujoco_pile(n))
            print(f"  MuJoCo pile_{n}: {piles[-1]['wall_s']:.2f} s", flush=True)
        notes["MuJoCo"] = "installed (pip install mujoco), re-run here"
    except ImportError:
        notes["MuJoCo"] = "not installed: run benchmarks/setup_peers.sh"
    try:
        import compas_lmgc90  # noqa: F401

        for dt in ([1e-2, 1e-3] if not full else [3e-2, 1e-2, 3e-3, 1e-3]):
            try:
                rows.append(lmgc90_incline(dt))
                print(f"  LMGC90 dt={dt:g} err={rows[-1]['rel_error']:.2e}", flush=True)
            except (RuntimeError, subprocess.SubprocessError) as exc:
                notes["LMGC90"] = f"run failed: {exc}"
        notes.setdefault("LMGC90", "installed (pip install --no-deps compas-lmgc90), re-run here")
    except ImportError:
        notes["LMGC90"] = "not installed: run benchmarks/setup_peers.sh"
    if shutil.which("yade"):
        grid = [(1e-4, 1e9), (1e-4, 1e8)] if not full else [
            (1e-4, 1e9), (1e-4, 1e8), (3e-5, 1e9), (3e-5, 1e10), (1e-5, 1e10)]
        for dt, young in grid:
            try:
                rows.append(yade_incline(dt, young))
                print(f"  YADE dt={dt:g} E={young:g} err={rows[-1]['rel_error']:.2e}",
                      flush=True)
            except (RuntimeError, subprocess.SubprocessError) as exc:
                notes["YADE"] = f"run failed: {exc}"
        notes.setdefault("YADE", "installed (apt-get install yade), re-run here")
    else:
        notes["YADE"] = "not installed: run benchmarks/setup_peers.sh (Debian package yade)"
    data = {"rows": rows, "piles": piles, "notes": notes}
    h.save_json(out, "peers", data)
    return data


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "lmgc90":
        print("RESULT " + json.dumps(lmgc90_incline_point(float(sys.argv[2]))), flush=True)
