"""The documents PolyDDA answers with, built once for the CLI and the REST service.

Blocks after cutting, contact lists (of a scene as given, or of a recorded step of a
result), the run summary (the engine's, with the scene's block names and every warning:
the build's and the engine's), strength-reduction controls read from the scene (watched
blocks, weakened joint materials) and the factor-of-safety document. `polydda blocks /
contacts / run / fos` print or write these; the service's jobs write the same ones, so
the two cannot drift apart. The kinematic screening document (Markland tests) too.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from engine.jsonable import finite

if TYPE_CHECKING:
    from engine.analyses.kinematics import KinematicResult
    from engine.analyses.limit_equilibrium import LimitEquilibriumResult
    from engine.analyses.strength_reduction import (
        FactorOfSafetyResult,
        SeismicCoefficientControls,
        SeismicCoefficientResult,
        StrengthReductionControls,
    )
    from engine.geometry.polyhedron import Polyhedron
    from engine.results.reader import Result
    from schemas.convert import BuildResult

#: default contact search distance for the contacts of a scene, as a fraction of its size
SEARCH_DISTANCE_RATIO = 1e-3


class NotRecorded(LookupError):
    """The result file has no such data (contacts not recorded, no such step)."""

    def __init__(self, message: str, loc: str = "") -> None:
        super().__init__(message)
        self.message, self.loc = message, loc


# --------------------------------------------------------------------------- JSON


def json_default(obj: Any) -> Any:
    """numpy scalars and arrays as plain JSON values."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def _umask() -> int:
    """The process's umask, read without changing it where Linux shows it (os.umask sets
    it: two threads asking at once could leave the wrong one)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_json_atomic(path: Path, doc: Any) -> None:
    """Write `doc` as JSON to `path` via a temporary file, fsync and rename (never half a
    file for a reader); the file gets the mode a plain new file gets (0644 under the usual
    umask, like the HDF5 result), not mkstemp's 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2, allow_nan=False, default=json_default)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def rounded(x: np.ndarray | float, digits: int = 9) -> Any:
    """Rounded plain-Python numbers for JSON (no -0.0)."""
    return (np.round(np.asarray(x, float), digits) + 0.0).tolist()


# --------------------------------------------------------------------------- blocks


def surface(poly: Polyhedron) -> tuple[np.ndarray, list[list[int]]]:
    """The surface vertices `(k, 3)` and faces re-indexed to them (seam points dropped)."""
    used = poly.surface_vertex_ids
    remap = np.full(len(poly.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return poly.vertices[used], [remap[f].tolist() for f in poly.faces]


def blocks_document(build: BuildResult) -> dict[str, Any]:
    """`{"blocks": [...], "count", "total_volume", "warnings"}`: each block's name, volume
    (m³), centroid, concave, fixed, surface vertices and faces."""
    docs = []
    for name, b in zip(build.block_names, build.model.blocks, strict=True):
        verts, faces = surface(b.polyhedron)
        docs.append({
            "name": name,
            "volume": float(b.polyhedron.volume),
            "centroid": rounded(b.polyhedron.centroid),
            "concave": not b.polyhedron.is_convex,
            "fixed": bool(b.fixed),
            "vertices": rounded(verts),
            "faces": faces,
        })
    return {"blocks": docs, "count": len(docs),
            "total_volume": float(sum(d["volume"] for d in docs)),
            "warnings": list(build.warnings)}


# --------------------------------------------------------------------------- contacts


def scene_contacts_document(build: BuildResult,
                            search_distance: float | None = None) -> dict[str, Any]:
    """The contact constraints of the scene as given (before any step), found within
    `search_distance` m (default SEARCH_DISTANCE_RATIO × the model size)."""
    from engine.contact.constraints import KIND_NAMES, MODE_NAMES
    from engine.contact.detection import detect_contacts

    model = build.model
    search = (search_distance if search_distance is not None
              else SEARCH_DISTANCE_RATIO * model.scale)
    active = np.array([not b.fixed for b in model.blocks], dtype=bool)
    cs = detect_contacts([b.polyhedron for b in model.blocks], search, active=active)
    names, joints = build.block_names, build.joint_names
    rows = []
    for k in range(len(cs)):
        tag = int(cs.face_tag[k])
        rows.append({
            "block_i": names[int(cs.block_i[k])],
            "block_j": names[int(cs.block_j[k])],
            "type": KIND_NAMES[int(cs.kind[k])],
            "point_i": rounded(cs.point_i[k]),
            "point_j": rounded(cs.point_j[k]),
            "normal": rounded(cs.normal[k]),
            "tangent": rounded(cs.tangent[k]),
            "mode": MODE_NAMES[int(cs.mode[k])],
            "penetration": float(max(0.0, -cs.gap[k])),
            "gap": float(cs.gap[k]),
            "joint": joints[tag] if 0 <= tag < len(joints) else None,
        })
    return {"search_distance": search, "count": len(rows), "contacts": rows}


def result_contacts_document(result: Result, step: int | None = None) -> dict[str, Any]:
    """The contacts of one recorded solver `step` of a result (default: the last recorded);
    NotRecorded when the file has none or not that step."""
    from engine.contact.constraints import KIND_NAMES, MODE_NAMES

    if not result.contacts_recorded:
        raise NotRecorded("the scene set analysis.record_contacts to false")
    if result.n_steps == 0:
        raise NotRecorded("the run recorded no step")
    steps = result.steps
    if step is None:
        k = result.n_steps - 1
    else:
        hits = np.flatnonzero(steps == step)
        if not len(hits):
            raise NotRecorded(f"step {step} was not recorded; recorded steps run from "
                              f"{int(steps[0])} to {int(steps[-1])} ({result.n_steps} "
                              "records)", loc="query.step")
        k = int(hits[0])
    c = result.contacts(k)
    names = result.block_names
    rows = []
    for i in range(len(c["gap"])):
        rows.append({
            "block_i": names[int(c["block_i"][i])], "block_j": names[int(c["block_j"][i])],
            "kind": KIND_NAMES.get(int(c["kind"][i]), str(int(c["kind"][i]))),
            "mode": MODE_NAMES.get(int(c["mode"][i]), str(int(c["mode"][i]))),
            "point_i": c["point_i"][i].tolist(), "point_j": c["point_j"][i].tolist(),
            "normal": c["normal"][i].tolist(), "tangent": c["tangent"][i].tolist(),
            "gap": float(c["gap"][i]), "normal_force": float(c["normal_force"][i]),
            "shear_force": c["shear_force"][i].tolist(),
        })
    return {"step": int(steps[k]), "time": float(result.times[k]), "count": len(rows),
            "contacts": rows}


def contacts_csv(doc: dict[str, Any]) -> str:
    """A `result_contacts_document` as CSV, one row per contact, vectors split into _x,
    _y, _z; floats written with repr (round-trip exact)."""
    vectors = ("point_i", "point_j", "normal", "tangent", "shear_force")
    cols = ["step", "time", "block_i", "block_j", "kind", "mode"]
    for v in ("point_i", "point_j", "normal", "tangent"):
        cols += [f"{v}_{a}" for a in "xyz"]
    cols += ["gap", "normal_force"] + [f"shear_force_{a}" for a in "xyz"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for c in doc["contacts"]:
        row: dict[str, Any] = {"step": doc["step"], "time": repr(doc["time"])}
        for k, v in c.items():
            if k in vectors:
                row.update({f"{k}_{a}": repr(x) for a, x in zip("xyz", v, strict=True)})
            else:
                row[k] = repr(v) if isinstance(v, float) else v
        w.writerow([row[k] for k in cols])
    return buf.getvalue()


# --------------------------------------------------------------------------- runs


def run_summary(summary: dict[str, Any], build: BuildResult) -> dict[str, Any]:
    """The engine's run summary with the scene's block names (`blocks[k].name`,
    `block_names`) and every warning: the build's (cutting, fixed blocks) first, then the
    engine's (soft penalty, ...); NaN and infinities as null."""
    doc = dict(summary)
    doc["blocks"] = [dict(b) for b in summary.get("blocks", [])]
    for b, name in zip(doc["blocks"], build.block_names, strict=False):
        b["name"] = name
    doc["block_names"] = list(build.block_names)
    doc["warnings"] = list(dict.fromkeys([*build.warnings, *summary.get("warnings", [])]))
    return finite(doc)


#: a free block whose centroid moved less than this (m) counts as not moved in the summaries
#: and reports (the penalty springs settle blocks by micrometres; sliding is centimetres)
MOVED_THRESHOLD = 0.01


def movement(blocks: list[dict[str, Any]], fixed: list[bool],
             threshold: float = MOVED_THRESHOLD) -> dict[str, Any]:
    """The summary's blocks split for people: the free blocks whose centroid moved more than
    `threshold` m, largest first (`moved`: name, displacement, magnitude), how many free
    blocks moved less (`still`, the largest of them `still_max_name` by `still_max`) and
    how many are fixed."""
    free = [(b, float(np.linalg.norm(b.get("displacement") or [0.0, 0.0, 0.0])))
            for k, b in enumerate(blocks) if not (k < len(fixed) and fixed[k])]
    moved = sorted(((b, u) for b, u in free if u > threshold), key=lambda x: -x[1])
    still = [(b, u) for b, u in free if u <= threshold]
    top = max(still, key=lambda x: x[1], default=({}, 0.0))
    return {"threshold": threshold,
            "moved": [{"name": b.get("name", ""), "displacement": list(b["displacement"]),
                       "magnitude": u} for b, u in moved],
            "still": len(still), "still_max": top[1], "still_max_name": top[0].get("name", ""),
            "fixed": len(blocks) - len(free)}


#: a block slower than this (m/s) at the end of a run has come to rest (the report's and the
#: run's verdict)
AT_REST_SPEED = 1e-3


def run_verdict(summary: dict[str, Any], fixed: list[bool],
                threshold: float = MOVED_THRESHOLD) -> str:
    """The last line of `polydda run`, the report's conclusion in one line: stable (no free
    block moved more than `threshold`), not stable (blocks still moving at the end: the
    fastest and its speed), or moved and came to rest; a run that did not complete says so."""
    from service import readable as rd

    if summary.get("status") != "completed":
        return (f"Verdict: none — the run {summary.get('status', 'did not complete')} at "
                f"{rd.seconds(summary.get('simulated_time') or 0.0)}")
    m = movement(summary.get("blocks") or [], fixed, threshold)
    limit = rd.length(threshold)
    if not m["moved"]:
        largest = (f" (largest {rd.length(m['still_max'])}, {m['still_max_name']})"
                   if m["still"] else "")
        return f"Verdict: stable — no free block moved more than {limit}{largest}"
    speeds = {b.get("name"): float(np.linalg.norm((b.get("velocity") or [0.0] * 3)[:3]))
              for b in summary.get("blocks") or []}
    moving = sorted((b for b in m["moved"] if speeds.get(b["name"], 0.0) > AT_REST_SPEED),
                    key=lambda b: -speeds[b["name"]])
    top = m["moved"][0]
    if moving:
        fast = moving[0]
        return (f"Verdict: not stable — {rd.plural(len(moving), 'block')} still moving at "
                f"the end ({fast['name']} at {rd.number(speeds[fast['name']], 3)} m/s, "
                f"moved {rd.length(fast['magnitude'])})")
    return (f"Verdict: moved, then came to rest — {top['name']} moved "
            f"{rd.length(top['magnitude'])}; every free block slower than "
            f"{AT_REST_SPEED * 1e3:g} mm/s at the end")


def fos_bracket(runs: list[dict[str, Any]], key: str = "factor") -> tuple[float, float] | None:
    """The last bisection bracket of a factor-of-safety (or kh) search: the largest value
    that held and the smallest that failed (None without both)."""
    held = [r[key] for r in runs if not r.get("failed") and isinstance(r.get(key), float)]
    fail = [r[key] for r in runs if r.get("failed") and isinstance(r.get(key), float)]
    return (max(held), min(fail)) if held and fail else None


def fos_controls(build: BuildResult) -> StrengthReductionControls:
    """Strength-reduction controls from the scene's `analysis.factor_of_safety` (built by
    the schema with the engine's defaults): times, tolerance, bounds, the weakened joint
    materials and the watched blocks."""
    from engine.analyses.strength_reduction import StrengthReductionControls

    return build.factor_of_safety or StrengthReductionControls()


def dynamic_trials(analysis: Any, what: str = "the factor of safety") -> None:
    """SceneError (at `analysis.mode`) when a bisection of trials (factor of safety,
    critical seismic coefficient) is asked of a quasi-static scene (`analysis`: the
    scene's AnalysisSpec)."""
    from engine.analyses.trials import quasi_static_reason
    from schemas.errors import SceneError

    reason = quasi_static_reason(analysis.dynamic_ratio_value, what)
    if reason:
        loc = "analysis.dynamic_ratio" if analysis.dynamic_ratio is not None else "analysis.mode"
        raise SceneError([{"loc": loc, "msg": reason}])


def _named_runs(runs: list[dict[str, Any]], build: BuildResult) -> list[dict[str, Any]]:
    """Trials with the deciding block's name instead of its index."""
    out = []
    for r in runs:
        r = dict(r)
        b = r.get("block", -1)
        r["block"] = build.block_names[b] if isinstance(b, int) and b >= 0 else None
        out.append(r)
    return out


def fos_document(result: FactorOfSafetyResult, build: BuildResult) -> dict[str, Any]:
    """The factor-of-safety answer: factor (or its bound), critical friction angle(s),
    every trial with its displacement, velocity and the reason of its verdict, status, and
    the names of the joint materials weakened and the blocks watched."""
    doc = result.as_dict()
    doc["runs"] = _named_runs(doc["runs"], build)
    c = fos_controls(build)
    jm = c.joint_materials if c.joint_materials is not None else range(
        len(build.joint_material_names))
    doc["joint_materials"] = [build.joint_material_names[k] for k in jm]
    doc["watch_blocks"] = _watched_names(build, c.watch_blocks)
    doc["warnings"] = list(build.warnings)
    return finite(doc)


def _watched_names(build: BuildResult, watch_blocks: Any) -> list[str]:
    """Names of the blocks a bisection job watches: the controls' list, or every free block."""
    watched = watch_blocks if watch_blocks is not None else [
        k for k, b in enumerate(build.model.blocks) if not b.fixed]
    return [build.block_names[k] for k in watched]


def seismic_controls(build: BuildResult) -> SeismicCoefficientControls:
    """Critical seismic coefficient controls from the scene's
    `analysis.critical_seismic_coefficient` (engine defaults when absent)."""
    from engine.analyses.strength_reduction import SeismicCoefficientControls

    return build.seismic_coefficient or SeismicCoefficientControls()


def seismic_document(result: SeismicCoefficientResult, build: BuildResult) -> dict[str, Any]:
    """The critical seismic coefficient answer: kh, azimuth (deg), kv, trials (kh tried,
    verdict and its reason, displacement, velocity), status, and the blocks watched."""
    doc = result.as_dict()
    doc["runs"] = _named_runs(doc["runs"], build)
    doc["watch_blocks"] = _watched_names(build, seismic_controls(build).watch_blocks)
    doc["warnings"] = list(build.warnings)
    return finite(doc)
# --------------------------------------------------------------------------- limit equilibrium


def le_result(build: BuildResult) -> LimitEquilibriumResult:
    """Limit equilibrium of the scene's one free block (the vector method; the joint
    materials the scene's factor of safety weakens give its strength-reduction factor);
    SceneError naming why when it does not apply."""
    from engine.analyses.limit_equilibrium import NotApplicable, limit_equilibrium
    from schemas.errors import SceneError

    c = fos_controls(build)
    try:
        return limit_equilibrium(build.model, c.joint_materials, c.watch_blocks)
    except NotApplicable as exc:
        raise SceneError([{"loc": "limit equilibrium", "msg": str(exc)}]) from None


def le_plane_names(result: LimitEquilibriumResult, build: BuildResult) -> list[str]:
    """A name for each plane the block rests on: its joint's, else the block it is
    against's ("on B2"); repeated names numbered."""
    names = []
    for pl in result.loads.planes:
        tag = pl.face_tag
        names.append(build.joint_names[tag] if 0 <= tag < len(build.joint_names)
                     else f"on {build.block_names[pl.block]}")
    seen: dict[str, int] = {}
    for k, n in enumerate(names):
        if names.count(n) > 1:
            seen[n] = seen.get(n, 0) + 1
            names[k] = f"{n} ({seen[n]})"
    return names


def le_document(result: LimitEquilibriumResult, build: BuildResult) -> dict[str, Any]:
    """The limit-equilibrium answer: factor of safety, strength-reduction factor, mode,
    sliding planes and direction, each plane (joint material, area, normal force, water),
    every force, the modes tried, notes and warnings."""
    doc = result.as_dict(le_plane_names(result, build), build.block_names)
    for d, pl in zip(doc["planes"], result.loads.planes, strict=True):
        d["joint_material"] = build.joint_material_names[pl.joint_material]
    doc["warnings"] = list(build.warnings)
    return finite(doc)


def le_text(doc: dict[str, Any]) -> str:
    """A few lines: the factor of safety and mode, the planes, the forces (kN / MN, one unit
    per vector, round-off as 0), the notes, and the verdict last."""
    from service import readable as rd

    fs = doc["factor_of_safety"]
    srf = doc["strength_reduction_factor"]
    lines = [f"limit equilibrium of {doc['block']}: factor of safety "
             f"{'unbounded (nothing drives it)' if fs is None else f'{fs:.4f}'}, "
             f"{doc['mode']}" + (f" ({', '.join(doc['sliding_planes'])})"
                                 if doc["sliding_planes"] else "")]
    if srf is not None and (fs is None or abs(srf - fs) > 1e-9 * abs(fs)):
        lines.append(f"strength-reduction factor {srf:.4f} (passive bolts in the driving "
                     "force: what `polydda fos` finds)")
    scale = max([abs(doc.get("driving_force") or 0.0), abs(doc.get("resisting_force") or 0.0)]
                + [abs(x) for f in doc["forces"] for x in f["vector"]])
    if doc["direction"]:
        d = doc["direction"]
        lines.append(f"direction: trend {rd.azimuth(d['trend'])}, plunge "
                     f"{rd.angle(d['plunge'], 2)}; driving "
                     f"{rd.force(doc['driving_force'], scale)}, resisting "
                     f"{rd.force(doc['resisting_force'], scale)}")
    for p in doc["planes"]:
        n = p["normal_force"]
        lines.append(f"  {p['name']} {p['dip']:.1f}/{p['dip_direction'] % 360:05.1f}: "
                     f"{'slides, N ' + rd.force(n, scale) if n is not None else 'free'}"
                     f"; area {rd.area(p['area'])}, φ {rd.degrees(p['friction_angle'])}, "
                     f"c {rd.stress(p['cohesion'])}, water {rd.force(p['water_force'], scale)}")
    for f in doc["forces"]:
        lines.append(f"  {f['kind'].replace('_', ' ')} ({f['name']}): {rd.forces(f['vector'])}")
    lines += [f"note: {n}" for n in doc["notes"]]
    lines.append(verdict_line(fs, "FS"))
    return "\n".join(lines)


def verdict_line(value: float | None, what: str = "FS", limit: float = 1.0,
                 bound: str | None = None, digits: int = 2) -> str:
    """The last line of an analysis: `Verdict: stable — FS 1.37` or `Verdict: not stable —
    FS 0.83 < 1`, with the number it rests on (`bound` "lower": the value is at least it;
    "upper": less than it); the report's conclusion in one line."""
    if value is None or not math.isfinite(value):
        return f"Verdict: stable — nothing drives the block ({what} unbounded)"
    while digits < 6 and (value < limit) != (round(value, digits) < limit):
        digits += 1  # 0.9996 is not "1.00 < 1"
    shown = f"{value:.{digits}f}"
    if bound == "lower":
        return f"Verdict: stable — {what} ≥ {shown}"
    if bound == "upper" or value < limit:
        return f"Verdict: not stable — {what} {'< ' if bound == 'upper' else ''}{shown} < {limit:g}"
    return f"Verdict: stable — {what} {shown}"


# --------------------------------------------------------------------------- kinematics


def kinematic_result(scene: Any) -> KinematicResult:
    """Markland tests of the scene's joints against its `slope_face` (a Scene, path, JSON
    text or dict; SceneError without a slope face or joints). Nothing is cut."""
    from engine.analyses.kinematics import kinematic_analysis
    from schemas.convert import kinematic_inputs

    sets, face = kinematic_inputs(scene)
    return kinematic_analysis(sets, face)


def kinematics_document(result: KinematicResult) -> dict[str, Any]:
    """The kinematic screening answer: slope face, sets, lateral limits, every test of every
    set and pair with its conditions, and the admissible sets / pairs per failure mode."""
    return finite(result.as_dict())


def kinematics_text(result: KinematicResult) -> str:
    """A short plain-text report: the admissible sets and pairs of each mode, then every
    test with each of its conditions, met or not, and the numbers."""
    from service import readable as rd

    s = result.slope
    lines = [f"slope face {s.dip:g}/{s.dip_direction % 360:03g} (dip/dip direction), friction "
             f"angle {s.friction_angle:g}° (joints with their own joint material's φ use it)",
             f"lateral limits: planar ±{result.limits.planar:g}°, flexural toppling "
             f"±{result.limits.flexural_toppling:g}°, direct toppling "
             f"±{result.limits.direct_toppling:g}°"]
    for w in result.wedge:
        if w.trend is not None:
            lines.append(f"intersection {w.sets[0]}/{w.sets[1]}: trend {rd.azimuth(w.trend)}, "
                         f"plunge {rd.angle(w.plunge, 2)}")
    groups = (("planar sliding", result.planar, lambda r: r.set),
              ("wedge sliding", result.wedge, lambda r: "/".join(r.sets)),
              ("flexural toppling", result.flexural_toppling, lambda r: r.set),
              ("direct toppling", result.direct_toppling, lambda r: "/".join(r.sets)))
    for title, rows, name in groups:
        ok = [name(r) for r in rows if r.admissible]
        lines.append(f"{title}: " + (", ".join(ok) + " admissible" if ok else "none admissible"))
        for r in rows:
            extra = ""
            if r.admissible and getattr(r, "sliding_on", None):
                extra = (" (slides on both planes)" if r.sliding_on == "both"
                         else f" (slides on {r.sliding_on} alone)")
            lines.append(f"  {name(r)}: {'admissible' if r.admissible else 'not admissible'}"
                         f"{extra}")
            lines.extend(f"    {'met    ' if c.passed else 'not met'}  {c.test}: {c.detail}"
                         for c in r.conditions)
    return "\n".join(lines)


# --------------------------------------------------------------------------- measurements

#: header names accepted for the two columns (case, spaces and underscores ignored)
DIP_NAMES = {"dip"}
DIP_DIRECTION_NAMES = {"dipdirection", "dipdir", "dipazimuth", "dd", "azimuth", "ddir"}


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def parse_measurements(text: str, path: str) -> tuple[list[float], list[float]]:
    """Dips and dip directions (degrees) from CSV text: a header naming the columns `dip`
    and `dip_direction` (or dipdir, dd, azimuth), or two numeric columns dip, dip direction;
    lines starting with # are comments. SceneError naming the line (of `path`, the name the
    text is known by) of any bad value. `polydda stereonet` and the scene builder read
    measurements with it."""
    import math

    from schemas.errors import SceneError

    def _key(cell: str) -> str:
        return "".join(ch for ch in cell.lower() if ch.isalnum())

    text = text.removeprefix("\ufeff")
    rows = [(n, r) for n, r in enumerate(csv.reader(text.splitlines()), 1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise SceneError([{"loc": "", "msg": f"{path}: no measurements"}])
    head = [_key(c) for c in rows[0][1]]
    columns = (0, 1)
    if not _is_number(rows[0][1][0]):
        dip = next((i for i, h in enumerate(head) if h in DIP_NAMES), None)
        ddir = next((i for i, h in enumerate(head) if h in DIP_DIRECTION_NAMES), None)
        if dip is None or ddir is None:
            raise SceneError([{"loc": "", "msg": f"{path} line {rows[0][0]}: the header needs "
                               "the columns 'dip' and 'dip_direction' (or dipdir, dd, "
                               f"azimuth); found {', '.join(rows[0][1])}"}])
        columns, rows = (dip, ddir), rows[1:]
    dips, ddirs, problems = [], [], []
    for n, row in rows:
        try:
            d, a = (float(row[i]) for i in columns)
        except (ValueError, IndexError):
            problems.append(f"{path} line {n}: expected numbers in columns {columns[0] + 1} "
                            f"and {columns[1] + 1}, got {','.join(row)}")
            continue
        if not (math.isfinite(d) and 0.0 <= d <= 90.0):
            problems.append(f"{path} line {n}: dip {d:g} is not in 0 to 90 degrees")
        elif not (math.isfinite(a) and -360.0 <= a <= 360.0):
            problems.append(f"{path} line {n}: dip direction {a:g} is not in 0 to 360 degrees")
        else:
            dips.append(d)
            ddirs.append(a % 360.0)
    if problems:
        raise SceneError([{"loc": "", "msg": p} for p in problems[:20]])
    return dips, ddirs


