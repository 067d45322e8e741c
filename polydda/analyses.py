"""What the command line does, as functions: `run` (a simulation to an HDF5 result, with a
progress bar), `le` (limit equilibrium), `fos` (strength reduction), `keyblocks` and
`sweep`. Each takes a :class:`~polydda.scene.Scene`, a path, JSON text or a dict, and gives
the same numbers as its command (they share service.documents)."""

from __future__ import annotations

import json
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from polydda.scene import Scene

if TYPE_CHECKING:
    import pandas as pd

    from polydda.result import Result

__all__ = ["Sweep", "fos", "keyblocks", "le", "run", "sweep"]

SceneLike = Scene | str | Path | dict[str, Any]


def _scene(scene: SceneLike) -> Scene:
    return scene if isinstance(scene, Scene) else Scene.load(scene)


def _bar(total: float, label: str, unit: str, enabled: bool) -> Any:
    """A tqdm bar on stderr (in Jupyter: text that updates in place), or None."""
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=label, unit=unit, mininterval=0.2, leave=True,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]"
                           "{postfix}")


def run(scene: SceneLike, out: str | Path = "result.h5", *, progress: bool = True,
        checkpoints: str | Path | None = None) -> Result:
    """Simulate the scene (through its stages) into the HDF5 result `out`, as
    `polydda run` does, and return it opened (:class:`~polydda.result.Result`)."""
    from engine.results.writer import ResultWriter
    from engine.step.staged_run import run_scene
    from polydda.result import open_result
    from schemas.scene import SCHEMA_VERSION

    sc = _scene(scene)
    built = sc.build().build
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = ResultWriter(path, overwrite=True, schema_version=SCHEMA_VERSION,
                          record_contacts=built.model.controls.record_contacts)
    duration = built.stages[-1].end_time if built.stages else built.model.controls.duration
    bar = _bar(duration, f"run {sc.name}", "s", progress)

    def note(p: Any) -> None:
        bar.set_postfix_str(f"t = {p.time:.3f} s, step {p.step:,}", refresh=False)
        bar.update(min(p.time, duration) - bar.n)

    try:
        if checkpoints is None and built.stages:
            checkpoints = f"{path}.stages"
        run_scene(built.model, built.stages, recorder=writer,
                  progress=note if bar is not None else None, scene_json=sc.to_json(None),
                  checkpoints=checkpoints)
    finally:
        if bar is not None:
            bar.close()
    return open_result(path)


def le(scene: SceneLike) -> dict[str, Any]:
    """Limit equilibrium of the scene's one free block (planar block or two-plane wedge,
    the vector method): the document `polydda le --json` prints (factor_of_safety, mode,
    planes, forces); SceneError saying why where it does not apply."""
    from schemas.stage_checks import refuse_stages
    from service.documents import le_document, le_result

    built = _scene(scene).build().build
    refuse_stages(built, "limit equilibrium")
    return le_document(le_result(built), built)


def fos(scene: SceneLike, *, progress: bool = True) -> dict[str, Any]:
    """Factor of safety by strength reduction (bisection on tan φ / F): the document
    `polydda fos --json` prints (factor_of_safety, runs, critical friction angle)."""
    from engine.analyses.strength_reduction import QuasiStatic, factor_of_safety
    from schemas.errors import SceneError
    from schemas.stage_checks import refuse_stages
    from service.documents import fos_controls, fos_document

    sc = _scene(scene)
    built = sc.build().build
    refuse_stages(built, "the factor-of-safety search")
    controls = fos_controls(built)
    bar = _bar(controls.max_runs, f"fos {sc.name}", "trial", progress)

    def note(r: Any) -> None:
        bar.update(1)
        bar.set_postfix_str(f"F = {r.factor:.4g} {'fails' if r.failed else 'holds'}")

    try:
        result = factor_of_safety(built.model, controls,
                                  progress=note if bar is not None else None)
    except QuasiStatic as exc:
        raise SceneError([{"loc": "analysis.mode", "msg": str(exc)}]) from None
    finally:
        if bar is not None:
            bar.close()
    return fos_document(result, built)


def keyblocks(scene: SceneLike, result: str | Path | Result | None = None) -> pd.DataFrame:
    """The key-block table of the scene's excavations (`polydda keyblocks`): one row per
    exposed block (excavation, block, removable, mode, planes, factor_of_safety, weight;
    with a `result`, the DDA's displacement and verdict)."""
    import pandas as pd

    from engine.results.reader import Result as EngineResult
    from service.cli.keyblocks import keyblock_document

    built = _scene(scene).build().build
    opened = None
    if result is not None and not isinstance(result, EngineResult):
        from polydda.result import Result as Facade

        opened = result if isinstance(result, Facade) else None
        engine_result = opened.engine if opened is not None else EngineResult(result)
    else:
        engine_result = result
    try:
        doc = keyblock_document(built, engine_result)
    finally:
        if opened is None and engine_result is not None and engine_result is not result:
            engine_result.close()
    rows = [{"excavation": e["name"], **row} for e in doc["excavations"] for row in e["blocks"]]
    return pd.DataFrame(rows, columns=["excavation", "block", "removable", "mode", "planes",
                                       "factor_of_safety", "weight", "displacement", "dda"]
                        if result is not None else
                        ["excavation", "block", "removable", "mode", "planes",
                         "factor_of_safety", "weight"])


@dataclass
class Sweep:
    """A sweep's outcome: `summary` (the aggregate `polydda sweep --json` prints: per mode
    the probability of failure, histogram, CDF) and `realisations`, one row per
    realisation (its parameter values and factor of safety)."""

    summary: dict[str, Any]
    realisations: pd.DataFrame
    out: Path | None = None
    mode: str = "analytic"
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def probability_of_failure(self) -> float | None:
        agg = self.summary.get(self.mode) or {}
        return agg.get("probability_of_failure")

    def hist(self, ax: Any = None, bins: int | str = "auto") -> Any:
        """A histogram of the factors of safety (matplotlib axes), FS = 1 marked."""
        import matplotlib.pyplot as plt

        if ax is None:
            _, ax = plt.subplots(figsize=(6, 3.5))
        fs = self.realisations["factor_of_safety"].dropna()
        ax.hist(fs, bins=bins, color="#4b79a1", edgecolor="white")
        ax.axvline(1.0, color="#c0392b", lw=1.5, label="FS = 1")
        pof = self.probability_of_failure
        ax.set_title(f"{len(fs)} realisations" + ("" if pof is None else
                                                 f", probability of failure {100 * pof:.1f} %"))
        ax.set_xlabel("factor of safety")
        ax.set_ylabel("realisations")
        ax.legend()
        return ax


def sweep(scene: SceneLike, *, parameters: dict[str, Any] | None = None,
          n: int | None = None, seed: int | None = None, mode: str | None = None,
          out: str | Path | None = None, progress: bool = True) -> Sweep:
    """A sweep or Monte Carlo analysis (`polydda sweep`): `n` realisations of the scene's
    `sweep.parameters` (or `parameters`, as in the scene), each a factor of safety by
    limit equilibrium (`mode="analytic"`) or strength reduction (`"dda"`). Realisations
    are written under `out` (default: a temporary folder) as the command writes them."""
    import pandas as pd

    from schemas.errors import SceneError
    from schemas.stage_checks import refuse_stages
    from service.sweep import run_sweep, spec_of_scene

    sc = _scene(scene)
    built = sc.build().build
    refuse_stages(built, "a sweep")
    section = dict(sc.data.get("sweep") or {})
    if parameters is not None:
        section["parameters"] = parameters
        section.pop("friction_angle", None)
    for key, value in (("n", n), ("seed", seed), ("mode", mode)):
        if value is not None:
            section[key] = value
    if not section.get("parameters") and not section.get("friction_angle"):
        raise SceneError([{"loc": "sweep.parameters", "msg": "give the parameters to vary "
                           "(the scene's sweep.parameters, or parameters=)"}])
    data = dict(sc.data, sweep=section)
    spec = spec_of_scene(data)
    if spec.mode == "analytic":
        from service.documents import le_result

        le_result(built)  # SceneError where limit equilibrium does not apply
    folder = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="polydda-sweep-"))
    bar = _bar(spec.n, f"sweep {sc.name}", "realisation", progress)

    def note(done: int, total: int, now: int) -> None:
        bar.update(done - bar.n)

    try:
        doc = run_sweep(data, spec, folder, progress=note if bar is not None else None)
    finally:
        if bar is not None:
            bar.close()
    rows = []
    for rec in doc.get("realisations") or []:
        fs = rec.get("factor_of_safety")
        rows.append({"realisation": rec["index"], **(rec.get("parameters") or {}),
                     "factor_of_safety": fs if isinstance(fs, int | float)
                     and math.isfinite(fs) else None,
                     "status": rec.get("status")})
    frame = pd.DataFrame(rows)
    if len(frame):
        frame = frame.set_index("realisation").sort_index()
    summary = {k: v for k, v in doc.items() if k != "realisations"}
    return Sweep(summary, frame, folder, spec.mode, {"spec": json.loads(json.dumps(
        spec.scene_sweep()))})
