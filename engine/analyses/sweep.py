"""Sweeps and Monte Carlo analyses of a scene's parameters, as numbers: what each parameter
may be (its quantity's range), its draws from a seed (each parameter its own random stream,
so realisation k is the same whatever N), the spec of N realisations, the shares of a sweep
fanned out over jobs, and the aggregate document (probability of failure, FS histogram and
CDF, Spearman sensitivity) of the realisations' records.

Writing a realisation's values into a scene and running it is the scene's business
(:mod:`service.sweep`); the engine sees only numbers here.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from engine.jsonable import finite

#: what a sweep may vary: (lowest, highest, unit) of each quantity; a normal or lognormal
#: draw is truncated to these bounds (friction angle: [0°, 90°), the highest excluded)
SWEEP_QUANTITIES: dict[str, tuple[float, float, str]] = {
    "friction_angle": (0.0, 90.0, "degrees"),
    "cohesion": (0.0, math.inf, "Pa"),
    "joint_orientation": (0.0, math.inf, "degrees"),
    "water_level": (-math.inf, math.inf, "m"),
    "kh": (0.0, 5.0, ""),
    "bolt_pretension": (0.0, math.inf, "N"),
    "bolt_capacity": (0.0, math.inf, "N"),
    "penalty": (0.0, math.inf, "N/m"),
    "time_step": (0.0, math.inf, "s"),
}


def sweep_truncation(quantity: str, low: float | None = None,
                     high: float | None = None) -> tuple[float, float]:
    """The range a normal or lognormal draw of `quantity` is truncated to: the quantity's
    range, narrowed by `low` / `high` when given."""
    lo, hi, _ = SWEEP_QUANTITIES[quantity]
    return (lo if low is None else max(lo, low), hi if high is None else min(hi, high))

#: the quantities limit equilibrium (sweep mode `analytic`) takes into account: all but the
#: DDA's numerical settings
ANALYTIC_QUANTITIES = ("friction_angle", "cohesion", "joint_orientation", "water_level", "kh",
                       "bolt_pretension", "bolt_capacity")
MODES = ("dda", "analytic")
#: the parameter drawn from the seed itself (the friction-only sweeps' stream)
LEGACY_NAME = "friction_angle"


@dataclass(frozen=True)
class Parameter:
    """One varied parameter of a sweep (validated as
    :class:`schemas.scene.SweepParameterSpec`): its name, quantity, distribution and
    what it applies to."""

    name: str
    quantity: str
    distribution: str
    mean: float | None = None
    sd: float | None = None
    low: float | None = None
    high: float | None = None
    values: tuple[float, ...] | None = None
    kappa: float | None = None
    joint_material: str | None = None
    joint: str | None = None
    bolt: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """The fields given (numbers as floats, so 40 and 40.0 are alike)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if f.name == "values":
                v = [float(x) for x in v]
            elif isinstance(v, int | float):
                v = float(v)
            out[f.name] = v
        return out

    def entropy(self, seed: int) -> int | list[int]:
        """The seed of this parameter's own random stream: (seed, CRC-32 of its name);
        `friction_angle` draws from the seed itself."""
        if self.name == LEGACY_NAME:
            return int(seed)
        return [int(seed), zlib.crc32(self.name.encode())]

    def draw(self, n: int, seed: int) -> np.ndarray:
        """Realisations 0 .. n-1 of a random parameter, `(n,)`, or `(n, 2)` angles θ, ψ
        (radians) from the joint's mean normal for `fisher`; row k does not depend on n."""
        # scipy.stats behind these costs half a second to import: only a sweep needs it
        # (the scene schema imports this module for the quantities' ranges)
        from engine.analyses.jointstats import Distribution, fisher_angles_of
        from engine.analyses.reliability import truncated_normal

        if self.distribution == "normal":
            lo, hi = sweep_truncation(self.quantity, self.low, self.high)
            return truncated_normal(self.mean, self.sd, n, self.entropy(seed), lo, hi)
        rng = np.random.default_rng(self.entropy(seed))
        if self.distribution == "fisher":
            u = rng.random((n, 2))  # row k: one pair per realisation
            return np.column_stack([fisher_angles_of(self.kappa, u[:, 0]),
                                    2.0 * math.pi * u[:, 1]])
        u = rng.random(n)
        if self.distribution == "uniform":
            return self.low + u * (self.high - self.low)
        if self.distribution == "lognormal":
            lo, hi = sweep_truncation(self.quantity)
            dist = Distribution("lognormal", self.mean, self.sd).frozen()
            a, b = dist.cdf(lo), dist.cdf(hi)
            return np.minimum(dist.ppf(a + u * (b - a)), np.nextafter(hi, lo))
        raise ValueError(f"{self.name}: '{self.distribution}' is not drawn at random")

    def describe(self) -> dict[str, Any]:
        """The parameter for the sweep document: its spec, and the range a normal or
        lognormal draw is truncated to."""
        out = {k: v for k, v in self.as_dict().items() if k != "name"}
        if self.distribution in ("normal", "lognormal"):
            lo, hi = sweep_truncation(self.quantity, self.low, self.high)
            out["truncated_to"] = [finite_or_none(lo), finite_or_none(hi)]
        return out


def finite_or_none(x: float) -> float | None:
    """`x`, or None for an infinite bound (JSON has no infinity)."""
    return float(x) if math.isfinite(x) else None


@dataclass(frozen=True)
class SweepSpec:
    """N realisations from `seed` of the `parameters`; `friction_mean` and `friction_sd`
    (degrees) are the short form of φ ~ Normal on every weakened joint material."""

    n: int
    seed: int
    friction_mean: float | None = None
    friction_sd: float | None = None
    mode: str = "dda"
    #: the realisations this sweep evaluates (a share of the N; None: all)
    only: tuple[int, ...] | None = None
    parameters: tuple[Parameter, ...] = ()

    def __post_init__(self) -> None:
        if self.n < 1:
            raise ValueError(f"n must be at least 1, got {self.n}")
        if (self.friction_mean is None) != (self.friction_sd is None):
            raise ValueError("give both the friction mean and sd, or neither")
        if self.friction_sd is not None and not self.friction_sd > 0:
            raise ValueError(f"friction sd must be positive, got {self.friction_sd:g}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got '{self.mode}'")
        names = [p.name for p in self.all_parameters()]
        if not names:
            raise ValueError("a sweep needs a parameter (or the friction mean and sd)")
        if len(set(names)) != len(names):
            raise ValueError(f"a parameter is given twice: {', '.join(names)}")
        if self.mode == "analytic":
            bad = [p.name for p in self.parameters if p.quantity not in ANALYTIC_QUANTITIES]
            if bad:
                raise ValueError(f"limit equilibrium (mode 'analytic') has no "
                                 f"{', '.join(bad)}: those are settings of the DDA; use "
                                 "mode 'dda'")

    def all_parameters(self) -> tuple[Parameter, ...]:
        """The short-form friction angle (if given) and then the parameters, in order."""
        short = () if self.friction_mean is None else (Parameter(
            LEGACY_NAME, "friction_angle", "normal", self.friction_mean, self.friction_sd),)
        return short + tuple(self.parameters)

    def draws(self) -> dict[str, np.ndarray]:
        """Every parameter's value per realisation (rows; see :meth:`Parameter.draw`); the
        `values` parameters form a grid, the first listed varying fastest, cycling."""
        out: dict[str, np.ndarray] = {}
        k = np.arange(self.n)
        stride = 1
        for p in self.all_parameters():
            if p.distribution == "values":
                out[p.name] = np.asarray(p.values, float)[(k // stride) % len(p.values)]
                stride *= len(p.values)
            else:
                out[p.name] = p.draw(self.n, self.seed)
        return out

    def friction_angles(self) -> np.ndarray:
        """φ of each realisation (degrees) of the parameter `friction_angle`."""
        return self.draws()[LEGACY_NAME]

    def analytic_applies(self) -> bool:
        """Whether limit equilibrium takes every parameter into account."""
        return all(p.quantity in ANALYTIC_QUANTITIES for p in self.all_parameters())

    def indices(self) -> list[int]:
        """The realisations to evaluate, in order."""
        return list(range(self.n)) if self.only is None else sorted(self.only)

    def population(self) -> dict[str, Any]:
        """What makes realisation k what it is (every field but `only`; 40 and 40.0
        alike); a friction-only sweep's is what it was before parameters existed, so its
        realisation files are found again."""
        out: dict[str, Any] = {"n": int(self.n), "seed": int(self.seed)}
        if self.friction_mean is not None:
            out |= {"friction_mean": float(self.friction_mean),
                    "friction_sd": float(self.friction_sd)}
        out["mode"] = self.mode
        if self.parameters:
            out["parameters"] = [p.as_dict() for p in self.parameters]
        return out

    def as_dict(self) -> dict[str, Any]:
        """The spec for the sweep document (:meth:`from_dict` reads it back)."""
        return {"n": self.n, "seed": self.seed, "friction_mean": self.friction_mean,
                "friction_sd": self.friction_sd, "mode": self.mode,
                "only": None if self.only is None else list(self.only),
                "parameters": [p.as_dict() for p in self.parameters]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SweepSpec:
        """The spec of :meth:`as_dict` or :meth:`population` (or of a document written
        before parameters existed)."""
        only = d.get("only")
        return cls(int(d["n"]), int(d["seed"]), d.get("friction_mean"), d.get("friction_sd"),
                   d.get("mode", "dda"), None if only is None else tuple(only),
                   tuple(_parameter(p) for p in d.get("parameters") or ()))

    def scene_sweep(self) -> dict[str, Any]:
        """The scene's `sweep` section of this spec (without the share)."""
        out: dict[str, Any] = {"n": self.n, "seed": self.seed, "mode": self.mode}
        if self.friction_mean is not None:
            out["friction_angle"] = {"mean": self.friction_mean, "sd": self.friction_sd}
        if self.parameters:
            out["parameters"] = {p.name: {k: v for k, v in p.as_dict().items() if k != "name"}
                                 for p in self.parameters}
        return out


def _parameter(d: Mapping[str, Any]) -> Parameter:
    """A parameter of a sweep document (:meth:`Parameter.as_dict`)."""
    d = dict(d)
    if d.get("values") is not None:
        d["values"] = tuple(float(v) for v in d["values"])
    return Parameter(**d)


def share_parts(indices: Sequence[int], shares: int) -> list[list[int]]:
    """The realisations of each of `shares` jobs (every `shares`-th index, so the shares
    take alike long); empty shares (more shares than indices) are left out."""
    k = max(1, shares)
    return [p for p in (list(indices[i::k]) for i in range(k)) if p]


def merge_documents(docs: list[dict[str, Any]]) -> dict[str, Any]:
    """One sweep document from those of jobs that each evaluated a share of the same sweep
    (same population; a realisation in several shares counts once)."""
    specs = [SweepSpec.from_dict(d["spec"]) for d in docs]
    if not specs or any(s.population() != specs[0].population() for s in specs):
        raise ValueError("the documents are not shares of one sweep (n, seed, parameters "
                         "or mode differ)")
    records = {r["index"]: r for d in docs for r in d["realisations"]}
    whole = SweepSpec.from_dict(specs[0].population())
    return sweep_document(whole, [records[k] for k in sorted(records)])


def _recorded(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A record's parameter values (a friction-only record written before parameters
    existed has only `friction_angle`)."""
    return rec.get("parameters") or {LEGACY_NAME: rec["friction_angle"]}


def sensitivity_inputs(records: Sequence[Mapping[str, Any]]) -> dict[str, list[float]]:
    """Each parameter's values over the records as numbers for the sensitivity: an
    orientation as `NAME.dip` and `NAME.dip_direction` (unwrapped about the circular mean,
    so 359° and 1° are 2° apart)."""
    out: dict[str, list[float]] = {}
    for name in (_recorded(records[0]) if records else {}):
        vals = [_recorded(r)[name] for r in records]
        if not isinstance(vals[0], dict):
            out[name] = [float(v) for v in vals]
            continue
        out[f"{name}.dip"] = [float(v["dip"]) for v in vals]
        dd = np.radians([float(v["dip_direction"]) for v in vals])
        mean = math.atan2(float(np.sin(dd).sum()), float(np.cos(dd).sum()))
        out[f"{name}.dip_direction"] = np.degrees(
            mean + (dd - mean + math.pi) % (2 * math.pi) - math.pi).tolist()
    return out


def sweep_document(spec: SweepSpec, records: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate of the realisations done: by `spec.mode`, and by limit equilibrium over
    the same realisations when it applies to every one (`analytic_note` says why not);
    their PoF difference. The sensitivity is Spearman's ρ of FS and each parameter."""
    from engine.analyses.reliability import aggregate

    inputs = sensitivity_inputs(records)
    fs = [r["factor_of_safety"] if r.get("status") == "completed" else None for r in records]
    fs_arr = np.array([np.nan if f is None else f for f in fs], float)
    doc: dict[str, Any] = {
        "spec": spec.as_dict(),
        "parameters": {p.name: p.describe() for p in spec.all_parameters()},
        "done": len(records),
        spec.mode: aggregate(fs_arr, inputs),
    }
    ana = [r.get("analytic_fs") for r in records]
    if spec.mode != "analytic" and records and all(a is not None for a in ana):
        doc["analytic"] = aggregate(np.array(ana, float), inputs)
        p, q = doc[spec.mode]["probability_of_failure"], doc["analytic"]["probability_of_failure"]
        doc["pof_difference"] = None if p is None or q is None else p - q
        rel = fs_arr / np.array(ana, float) - 1.0
        ok = np.isfinite(rel)
        doc["fs_relative_difference"] = {
            "mean": float(rel[ok].mean()) if ok.any() else None,
            "max_abs": float(np.abs(rel[ok]).max()) if ok.any() else None}
    notes = sorted({r["analytic_note"] for r in records if r.get("analytic_note")})
    if notes:
        doc["analytic_note"] = ("limit equilibrium did not apply to every realisation: "
                                + "; ".join(notes[:3]))
    doc["realisations"] = records
    return finite(doc)
