"""Earthquake loads: pseudo-static seismic coefficients (kh, kv) and a ground acceleration
history (Newmark's sliding block, in the ground's frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GroundMotion:
    """An acceleration time history of the ground (the fixed blocks): `times (k,)` s,
    non-decreasing (a repeated time is a jump), `acceleration (k, 3)` m/s², linear between
    samples and zero outside them. The run is in the ground's frame: every block that moves
    feels the inertial body force −m a(t) (its step mean), so displacements are relative to
    the ground (Newmark's sliding block)."""

    times: np.ndarray
    acceleration: np.ndarray

    def mean(self, t0: float, t1: float) -> np.ndarray:
        """Mean acceleration `(3,)` m/s² over `[t0, t1]` (exact for the piecewise-linear
        history)."""
        return (self._integral(t1) - self._integral(t0)) / (t1 - t0)

    def _integral(self, t: float) -> np.ndarray:
        """∫ a dt from the first sample to `t` `(3,)` m/s."""
        times, acc = np.asarray(self.times, float), np.asarray(self.acceleration, float)
        if len(times) == 0 or t <= times[0]:
            return np.zeros(3)
        seg = 0.5 * (acc[1:] + acc[:-1]) * np.diff(times)[:, None]
        cum = np.concatenate([np.zeros((1, 3)), np.cumsum(seg, axis=0)])
        if t >= times[-1]:
            return cum[-1]
        k = int(np.searchsorted(times, t, side="right")) - 1
        h = times[k + 1] - times[k]
        f = (t - times[k]) / h
        a_t = acc[k] + f * (acc[k + 1] - acc[k])
        return cum[k] + 0.5 * (acc[k] + a_t) * (t - times[k])


@dataclass(frozen=True)
class SeismicLoad:
    """Pseudo-static seismic coefficients: `kh` (horizontal, fraction of g) pointing to
    `azimuth_rad` (clockwise from North) and `kv` (vertical, fraction of g, positive up)."""

    kh: float = 0.0
    azimuth_rad: float = 0.0
    kv: float = 0.0

    def acceleration(self, g: float) -> np.ndarray:
        """The body force per unit mass (m/s², (3,)) for gravity of magnitude `g` m/s²."""
        return g * np.array([self.kh * np.sin(self.azimuth_rad),
                             self.kh * np.cos(self.azimuth_rad), self.kv])
