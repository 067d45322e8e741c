"""Joint-set statistics for realisations: Fisher dispersion of orientation, spacing and size.

Orientation: the pole of a set scatters about its mean by Fisher's distribution (density
∝ exp(κ cos θ) on the sphere). Its angle θ from the mean has the closed-form inverse CDF
cos θ = 1 + ln(u + (1 − u) e^{−2κ}) / κ (u uniform; Fisher, Lewis & Embleton 1987), the
azimuth about the mean is uniform; κ is estimated by maximum likelihood from the mean
resultant length R̄: coth κ − 1/κ = R̄. Spacing and size (persistence) follow scipy.stats
distributions (exponential spacing: a set whose planes are a Poisson process along its
normal, Priest & Hudson 1976; lognormal trace lengths or disc radii), so the planes of a set
need not be parallel nor evenly spaced.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.analyses.kinematics import normal, trend_plunge

__all__ = ["Distribution", "fisher_angles", "fisher_angles_of", "fisher_fit",
           "fisher_orientations", "fisher_stats", "plane_positions", "scatter_about"]


def fisher_angles(kappa: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` angles (radians) from the mean direction of a Fisher distribution of `kappa`."""
    return fisher_angles_of(kappa, rng.random(n))


def fisher_angles_of(kappa: float, u: Any) -> np.ndarray:
    """The angles (radians) from the mean direction of a Fisher distribution of `kappa`
    whose CDF is the uniforms `u` (the inverse CDF, so a caller may choose its draws)."""
    u = np.asarray(u, float)
    if kappa <= 0:
        return np.arccos(1.0 - 2.0 * u)  # uniform on the sphere
    cos_t = 1.0 + np.log(u + (1.0 - u) * math.exp(-2.0 * kappa)) / kappa
    return np.arccos(np.clip(cos_t, -1.0, 1.0))


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing `n` to an orthonormal basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def scatter_about(dip: float, dip_direction: float, theta: Any,
                  psi: Any) -> tuple[np.ndarray, np.ndarray]:
    """(dips, dip directions) in degrees of the planes whose normals lie `theta` radians
    from the plane's normal, at azimuths `psi` radians about it."""
    theta, psi = np.atleast_1d(np.asarray(theta, float)), np.atleast_1d(np.asarray(psi, float))
    mean = normal(dip, dip_direction)
    e1, e2 = _basis(mean)
    v = (np.cos(theta)[:, None] * mean + np.sin(theta)[:, None]
         * (np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2))
    v[v[:, 2] < 0] *= -1.0  # upward normals: a plane, whichever side
    dips = np.degrees(np.arccos(np.clip(v[:, 2], -1.0, 1.0)))
    dds = np.degrees(np.arctan2(v[:, 0], v[:, 1])) % 360.0
    return dips, dds


def fisher_orientations(dip: float, dip_direction: float, kappa: float, n: int,
                        seed: int | np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`n` (dips, dip directions) in degrees whose normals scatter about the set's mean
    normal by Fisher(κ); reproducible from `seed`."""
    rng = np.random.default_rng(seed)
    theta = fisher_angles(kappa, n, rng)
    psi = rng.random(n) * 2.0 * math.pi
    return scatter_about(dip, dip_direction, theta, psi)


def fisher_fit(dips: Any, dip_directions: Any) -> dict[str, float]:
    """Mean orientation, mean resultant length R̄ and maximum-likelihood κ of a sample of
    planes (normals taken on the side of their mean)."""
    v = np.array([normal(d, a) for d, a in zip(np.ravel(dips), np.ravel(dip_directions),
                                                 strict=True)])
    first = v.sum(axis=0)
    v[v @ first < 0] *= -1.0
    return fisher_stats(v)


def fisher_stats(v: np.ndarray) -> dict[str, float]:
    """Mean plane (dip, dip direction in degrees), mean resultant length R̄ and maximum-
    likelihood κ of unit normals `v (n, 3)` already turned to one side."""
    resultant = v.sum(axis=0)
    r_bar = float(np.linalg.norm(resultant) / len(v))
    if r_bar >= 1.0 - 1e-12:
        kappa = math.inf
    elif r_bar < 1e-9:
        kappa = 0.0
    else:  # A(κ) = coth κ − 1/κ is increasing from 0 to 1
        def a(k: float) -> float:
            return 1.0 / math.tanh(k) - 1.0 / k - r_bar

        from scipy import optimize  # imported here: scipy.optimize takes 0.3 s to import

        kappa = float(optimize.brentq(a, 1e-9, 1e7, xtol=1e-12, rtol=1e-12))
    trend, plunge = trend_plunge(resultant)  # the mean normal as a line: its pole
    return {"dip": 90.0 - plunge, "dip_direction": (trend + 180.0) % 360.0,
            "mean_resultant_length": r_bar, "kappa": kappa}


@dataclass(frozen=True)
class Distribution:
    """A positive quantity (spacing, trace length, disc radius in m): `fixed`,
    `exponential` (mean) or `lognormal` (mean and standard deviation)."""

    kind: str
    mean: float
    sd: float | None = None

    def frozen(self) -> Any:
        """The scipy.stats distribution with this mean (and sd)."""
        from scipy import stats  # imported here: scipy.stats takes 0.3 s to import

        if self.kind == "fixed":
            return stats.rv_discrete(values=([self.mean], [1.0]))
        if self.kind == "exponential":
            return stats.expon(scale=self.mean)
        if self.kind == "lognormal":
            if self.sd is None or self.sd <= 0:
                raise ValueError("a lognormal distribution needs a positive sd")
            s2 = math.log(1.0 + (self.sd / self.mean) ** 2)
            return stats.lognorm(s=math.sqrt(s2), scale=self.mean / math.exp(s2 / 2))
        raise ValueError(f"unknown distribution '{self.kind}' (fixed, exponential, lognormal)")

    def sample(self, n: int, seed: int | np.random.Generator) -> np.ndarray:
        """`n` values, reproducible from `seed`."""
        if self.kind == "fixed":
            return np.full(n, float(self.mean))
        return np.asarray(self.frozen().rvs(size=n, random_state=np.random.default_rng(seed)),
                          float)


def plane_positions(spacing: Distribution, length: float,
                    seed: int | np.random.Generator) -> np.ndarray:
    """Offsets (m) along the set's normal of its planes across `length`: spacings drawn
    one after another from a random start within the first spacing."""
    rng = np.random.default_rng(seed)
    start = spacing.sample(1, rng)[0] * rng.random()
    batch = int(2 * length / spacing.mean) + 16
    gaps = np.empty(0)
    while start + gaps.sum() <= length:  # rarely more than one batch
        gaps = np.concatenate([gaps, spacing.sample(batch, rng)])
    pos = start + np.concatenate([[0.0], np.cumsum(gaps)])
    return pos[pos <= length]
