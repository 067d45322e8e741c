"""Shared machinery of the benchmark suite: running a model, energies, Pareto fronts, output.

Every section (accuracy, peers, stability, scaling, savings) stores its raw numbers as
`results/<section>.json` plus CSVs and PNGs; `benchmarks.__main__` turns the JSON files into
REPORT.md, so a section can be re-run alone (`--only`) without losing the others.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import resource
import subprocess
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from engine.model import Model
from engine.step.frame import DISSIPATIONS, ENERGY_NAMES, STORED_ENERGIES, WORKS, Frame
from engine.step.simulation import RunResult, run

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"

#: energy keys of a frame that the engine fills
ENERGY_KEYS = ENERGY_NAMES


class FrameLog:
    """A recorder that keeps the frames it is given (light copies, no contacts)."""

    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self.status: str | None = None
        self.message = ""

    def begin(self, model: Model, scene_json: str | None = None) -> None:
        """Nothing to prepare."""

    def record(self, frame: Frame) -> None:
        """Keep the frame without its contact arrays (memory)."""
        frame.contacts = None
        frame.normal_force = None
        frame.shear_force = None
        self.frames.append(frame)

    def end(self, status: str, message: str = "", summary: dict[str, Any] | None = None) -> None:
        """Remember how the run ended."""
        self.status, self.message = status, message

    def times(self) -> np.ndarray:
        """Recorded times `(k,)` s."""
        return np.array([f.time for f in self.frames])

    def series(self, block: int, attr: str = "centroids") -> np.ndarray:
        """`attr` of block `block` at every recorded frame `(k, ...)`."""
        return np.array([getattr(f, attr)[block] for f in self.frames])

    def energy(self, key: str) -> np.ndarray:
        """One energy `(k,)` J over the recorded frames."""
        return np.array([f.energies.get(key, 0.0) for f in self.frames])


@dataclass
class Outcome:
    """How one engine run went: status, wall times, steps and (optionally) its frames."""

    status: str
    message: str
    wall: float
    steps: int
    simulated: float
    timings: dict[str, float]
    result: RunResult
    log: FrameLog | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def compute_wall(self) -> float:
        """Wall time without recording (the `output` phase), s."""
        return self.wall - self.timings.get("output", 0.0)


def run_model(model: Model, record: bool = False, max_wall: float | None = None) -> Outcome:
    """Run `model` to its duration; with `record`, keep the frames (energies, histories).

    `max_wall` s: cancel a run that takes longer (status `cancelled`)."""
    log = FrameLog() if record else None
    t0 = time.perf_counter()

    def too_long() -> bool:
        return max_wall is not None and time.perf_counter() - t0 > max_wall

    res = run(model, recorder=log, should_stop=too_long)
    wall = time.perf_counter() - t0
    return Outcome(res.status, res.message, wall, res.steps, res.state.time,
                   dict(res.summary.get("timings", {})), res, log)


def energy_check(log: FrameLog, reference: float) -> dict[str, float]:
    """Energy growth and balance residual of a recorded run, relative to `reference` J.

    Mechanical energy E = kinetic + elastic + contact − work of gravity and loads; it may
    only fall (friction and integrator dissipation). `growth` is max E(t) − E(0) over
    the run; `residual` the largest |work − (stored − stored₀ + dissipated)| (bookkeeping).
    """
    if not log.frames:
        return {"growth": float("nan"), "residual": float("nan")}
    stored = sum(log.energy(n) for n in STORED_ENERGIES)
    work = sum(log.energy(n) for n in WORKS)
    lost = sum(log.energy(n) for n in DISSIPATIONS)
    mech = stored - work
    ok = np.isfinite(mech)
    growth = float(np.max(mech[ok] - mech[0])) if ok.any() else float("inf")
    resid = (float(np.max(np.abs(work - (stored - stored[0]) - lost)[ok])) if ok.any()
             else float("inf"))
    ref = max(reference, 1e-30)
    return {"growth": growth / ref, "residual": resid / ref}


def pareto_front(cost: Sequence[float], error: Sequence[float]) -> np.ndarray:
    """Indices of the points not dominated in (cost, error), ordered by cost."""
    c = np.asarray(cost, float)
    e = np.asarray(error, float)
    order = np.lexsort((e, c))
    best = np.inf
    keep = []
    for i in order:
        if np.isfinite(e[i]) and e[i] < best:
            keep.append(int(i))
            best = e[i]
    return np.array(keep, dtype=int)


def growth_exponent(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log y against log x (NaN with fewer than two positive points)."""
    xa, ya = np.asarray(x, float), np.asarray(y, float)
    ok = (xa > 0) & (ya > 0) & np.isfinite(ya)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(xa[ok]), np.log(ya[ok]), 1)[0])


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_csv(path: Path, rows: Iterable[dict[str, Any]]) -> None:
    """Write dict rows as CSV (union of keys, first-seen order)."""
    rows = list(rows)
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt(r.get(k)) for k in keys})


def _fmt(v: Any) -> Any:
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def save_json(out: Path, section: str, data: dict[str, Any]) -> None:
    """Store a section's numbers as `out/<section>.json`."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{section}.json").write_text(json.dumps(data, indent=1, default=_jsonable))


def load_json(out: Path, section: str) -> dict[str, Any] | None:
    """A section's stored numbers, or None when it has not been run into `out`."""
    p = out / f"{section}.json"
    return json.loads(p.read_text()) if p.exists() else None


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v))


def machine_info() -> dict[str, Any]:
    """Cores, CPU model, load, memory and software versions of this machine."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import scipy

    try:
        from importlib.metadata import version

        engine_version = version("polydda")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        engine_version = "unknown"
    try:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return {
        "nproc": os.cpu_count(),
        "cpu": cpu,
        "load": list(os.getloadavg()),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "engine": engine_version,
        "commit": commit,
        "platform": platform.platform(),
    }


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """`(fn(), wall seconds)`."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0
