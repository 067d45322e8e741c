"""Probability of failure from sampled strengths: realisations, the analytic wedge, aggregation.

Realisations are drawn from a seed with numpy's PCG64 (`numpy.random.default_rng`), so a
sweep is reproducible and realisation `k` is the same whether 10 or 200 are drawn. The
analytic factor of safety of a wedge on two planes (friction only) is the vector form of
the paper's eq. 51, `F = K tan φ / tan ψ_i` (docs/validation.md), with one φ per plane
allowed. :func:`aggregate` turns factors of safety into the probability of failure
(fraction with F < 1, with a 95 % Wilson interval), a histogram, the empirical CDF and the
sensitivity of F to each sampled parameter (Spearman rank correlation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.analyses.kinematics import normal

__all__ = ["WedgeGeometry", "aggregate", "truncated_normal", "wedge_factor_of_safety",
           "wedge_geometry", "wilson_interval"]


def truncated_normal(mean: float, sd: float, n: int, seed: int | Sequence[int],
                     lo: float = 0.0, hi: float = 90.0) -> np.ndarray:
    """`n` samples of Normal(mean, sd) truncated to [lo, hi) (friction angles stay valid),
    from `seed` (an int, or ints for numpy's SeedSequence); sample k does not depend on n."""
    rng = np.random.default_rng(seed)
    a, b = (lo - mean) / sd, (hi - mean) / sd
    u = rng.random(n)  # one uniform per realisation, then the inverse CDF
    from scipy import stats  # imported here: scipy.stats takes 0.3 s to import

    x = stats.truncnorm.ppf(u, a, b, loc=mean, scale=sd)
    return np.minimum(x, np.nextafter(hi, lo))


@dataclass(frozen=True)
class WedgeGeometry:
    """Normal reactions per unit weight on the two planes, and the intersection (degrees)."""

    n_a: float
    n_b: float
    plunge: float
    trend: float

    @property
    def wedge_factor(self) -> float:
        """K = sin β / sin(ξ/2) = (N_A + N_B) / (W cos ψ_i)."""
        return (self.n_a + self.n_b) / math.cos(math.radians(self.plunge))


def wedge_geometry(dip_a: float, dip_direction_a: float, dip_b: float,
                   dip_direction_b: float) -> WedgeGeometry:
    """Hoek & Bray vector method for a wedge sliding along the intersection of two planes:
    N_A n_A + N_B n_B balances the weight's part normal to the intersection."""
    na, nb = normal(dip_a, dip_direction_a), normal(dip_b, dip_direction_b)
    line = np.cross(na, nb)
    if np.linalg.norm(line) < 1e-9:
        raise ValueError("the two planes are parallel: no wedge")
    line /= np.linalg.norm(line)
    if line[2] > 0:
        line = -line
    w = np.array([0.0, 0.0, -1.0])
    across = -(w - (w @ line) * line)  # the reactions must carry this
    coef, *_ = np.linalg.lstsq(np.column_stack([na, nb]), across, rcond=None)
    plunge = math.degrees(math.asin(-line[2]))
    trend = math.degrees(math.atan2(line[0], line[1])) % 360.0
    return WedgeGeometry(float(coef[0]), float(coef[1]), plunge, trend)


def wedge_factor_of_safety(geometry: WedgeGeometry, phi_a_deg: Any,
                           phi_b_deg: Any | None = None) -> np.ndarray:
    """F = (N_A tan φ_A + N_B tan φ_B) / (W sin ψ_i); with φ_A = φ_B this is eq. 51."""
    ta = np.tan(np.radians(np.asarray(phi_a_deg, float)))
    tb = ta if phi_b_deg is None else np.tan(np.radians(np.asarray(phi_b_deg, float)))
    return (geometry.n_a * ta + geometry.n_b * tb) / math.sin(math.radians(geometry.plunge))


def wilson_interval(failures: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default)."""
    if n == 0:
        return 0.0, 1.0
    p = failures / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def aggregate(fs: Any, parameters: dict[str, Any] | None = None,
              bins: int = 20) -> dict[str, Any]:
    """Probability of failure (F < 1), statistics, histogram, CDF and Spearman sensitivity
    of F to each parameter, of the finite factors of safety `fs`."""
    f = np.asarray(fs, float)
    ok = np.isfinite(f)
    f_ok = f[ok]
    n = int(ok.sum())
    failures = int((f_ok < 1.0).sum())
    doc: dict[str, Any] = {
        "n": n, "failures": failures, "excluded": int((~ok).sum()),
        "probability_of_failure": failures / n if n else None,
        "pof_interval_95": list(wilson_interval(failures, n)),
    }
    if n == 0:
        return doc
    counts, edges = np.histogram(f_ok, bins=bins)
    order = np.sort(f_ok)
    doc.update({
        "mean": float(f_ok.mean()), "sd": float(f_ok.std(ddof=1)) if n > 1 else 0.0,
        "min": float(order[0]), "max": float(order[-1]),
        "percentiles": {str(q): float(np.percentile(f_ok, q)) for q in (5, 50, 95)},
        "histogram": {"edges": edges.tolist(), "counts": counts.tolist()},
        "cdf": {"fs": order.tolist(), "p": (np.arange(1, n + 1) / n).tolist()},
        "sensitivity": {},
    })
    for name, values in (parameters or {}).items():
        x = np.asarray(values, float)[ok]
        if n > 2 and np.ptp(x) > 0 and np.ptp(f_ok) > 0:
            from scipy import stats

            rho = stats.spearmanr(x, f_ok).statistic
            doc["sensitivity"][name] = float(rho)
    return doc
