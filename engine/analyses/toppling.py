"""Limit equilibrium of block toppling on a stepped base (Goodman & Bray 1976).

Rectangular columns of width Δx (along the base) stand on treads that dip ψ_p toward the
toe; each tread is `b` above the next one toe-ward. Column n = 1 is at the toe. Every
column carries its weight W_n, the thrust P_n of its up-slope neighbour at height M_n, the
thrust P_{n-1} of its toe-side neighbour at height L_n (both with interface friction
tan φ_d) and a base reaction R_n, S_n at K_n from its toe corner. Starting from the crest
side with P = 0, the recursion gives the force P_{n-1} that column n needs from below to
neither topple (P_{n-1,t}) nor slide (P_{n-1,s}); the slope is at limiting equilibrium
when the toe needs none (P_0 = 0). Forces are per metre along strike; angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["STABLE", "TOPPLE", "SLIDE", "ToppleResult", "column_heights", "lever_arms",
           "overturning_moment", "toppling_thrust",
           "sliding_thrust", "base_reactions", "base_reaction_arm",
           "goodman_bray", "critical_friction_angle"]

STABLE, TOPPLE, SLIDE = "stable", "topple", "slide"


def column_heights(n_columns: int, crest: int, a1: float, a2: float, b: float) -> np.ndarray:
    """Heights y_n (m) of columns 1..N: y_n = n (a1 − b) up to the crest column, then each
    one a2 + b lower (the slope face rises a1, the upper slope falls a2 per column)."""
    y = np.empty(n_columns)
    for k in range(n_columns):
        n = k + 1
        y[k] = n * (a1 - b) if n <= crest else y[k - 1] - a2 - b
    return y


def lever_arms(y: np.ndarray, crest: int, a1: float, a2: float) -> tuple[np.ndarray, np.ndarray]:
    """Heights above each column's base where its neighbours push: M_n (up-slope thrust
    P_n, at the top of the shorter of n, n+1) and L_n (toe-side thrust P_{n-1})."""
    n = np.arange(1, len(y) + 1)
    m = np.where(n < crest, y, y - a2)
    ell = np.where(n <= crest, y - a1, y)
    return m, ell


def overturning_moment(p_n: float, w: float, y: float, m: float, dx: float, psi_p: float,
                       phi_d: float) -> float:
    """Moment (N·m/m) about column n's toe corner of its weight and its up-slope
    neighbour's thrust and friction, positive when it turns the column toward the toe."""
    return float(p_n * (m - dx * np.tan(phi_d))
                 + 0.5 * w * (y * np.sin(psi_p) - dx * np.cos(psi_p)))


def toppling_thrust(p_n: float, w: float, y: float, m: float, ell: float, dx: float,
                    psi_p: float, phi_d: float) -> float:
    """P_{n-1,t}: the toe-side thrust that just stops column n rotating about its toe (at
    L_n ≤ 0, below the base, no thrust can: ±inf as the column does or does not topple)."""
    moment = overturning_moment(p_n, w, y, m, dx, psi_p, phi_d)
    if ell <= 0.0:
        return float(np.inf if moment > 0.0 else -np.inf)
    return moment / ell


def sliding_thrust(p_n: float, w: float, psi_p: float, phi_p: float, phi_d: float) -> float:
    """P_{n-1,s}: the toe-side thrust that just stops column n sliding on its base."""
    resisting = w * (np.tan(phi_p) * np.cos(psi_p) - np.sin(psi_p))
    return float(p_n - resisting / (1.0 - np.tan(phi_p) * np.tan(phi_d)))


def base_reactions(p_n: float, p_nm1: float, w: float, psi_p: float,
                   phi_d: float) -> tuple[float, float]:
    """Normal R_n and shear S_n (up-dip) the base must give column n (force balance)."""
    r = w * np.cos(psi_p) + np.tan(phi_d) * (p_n - p_nm1)
    s = w * np.sin(psi_p) + p_n - p_nm1
    return float(r), float(s)


def base_reaction_arm(p_n: float, p_nm1: float, w: float, y: float, m: float, ell: float,
                      dx: float, psi_p: float, phi_d: float) -> float:
    """K_n: where R_n acts, measured up-dip from the toe corner (moment balance); 0 for a
    toppling column, and a column that does not topple needs 0 ≤ K_n ≤ Δx."""
    r, _ = base_reactions(p_n, p_nm1, w, psi_p, phi_d)
    return (p_nm1 * ell - overturning_moment(p_n, w, y, m, dx, psi_p, phi_d)) / r


@dataclass
class ToppleResult:
    """The recursion's answer for columns 1..N (toe first).

    `thrust[k]` is P_{n-1} of column n = k + 1 as required (negative: none needed; P_0 is
    `thrust[0]`), `toppling[k]`/`sliding[k]` its two candidates, `mode[k]` the column's mode,
    `normal`/`shear` the base reactions R_n, S_n and `arm` K_n (N/m, m).
    """

    thrust: np.ndarray
    toppling: np.ndarray
    sliding: np.ndarray
    mode: list[str]
    normal: np.ndarray
    shear: np.ndarray
    arm: np.ndarray

    @property
    def toe_thrust(self) -> float:
        """P_0 (N/m): the support the toe column needs; ≤ 0 means the slope stands."""
        return float(self.thrust[0])


def goodman_bray(y: np.ndarray, m: np.ndarray, ell: np.ndarray, dx: float, psi_p: float,
                 phi_p: float, phi_d: float, unit_weight: float = 1.0) -> ToppleResult:
    """Toe-ward recursion from the last column (P_N = 0): each column passes down the larger
    of P_{n-1,t} and P_{n-1,s}, or nothing when it needs no support (stable)."""
    n = len(y)
    w = unit_weight * dx * np.asarray(y, float)
    out = {k: np.zeros(n) for k in ("thrust", "toppling", "sliding", "normal", "shear", "arm")}
    mode = [STABLE] * n
    p_n = 0.0
    for k in range(n - 1, -1, -1):
        p_t = toppling_thrust(p_n, w[k], y[k], m[k], ell[k], dx, psi_p, phi_d)
        p_s = sliding_thrust(p_n, w[k], psi_p, phi_p, phi_d)
        p = max(p_t, p_s)
        if p > 0.0:
            mode[k] = TOPPLE if p_t > p_s else SLIDE
        p_nm1 = max(p, 0.0)
        out["thrust"][k], out["toppling"][k], out["sliding"][k] = p, p_t, p_s
        if np.isfinite(p_nm1):
            out["normal"][k], out["shear"][k] = base_reactions(p_n, p_nm1, w[k], psi_p, phi_d)
            out["arm"][k] = base_reaction_arm(p_n, p_nm1, w[k], y[k], m[k], ell[k], dx,
                                              psi_p, phi_d)
        else:  # nothing toe-side can hold it
            out["normal"][k] = out["shear"][k] = out["arm"][k] = np.nan
        p_n = p_nm1
    return ToppleResult(mode=mode, **out)


def critical_friction_angle(y: np.ndarray, m: np.ndarray, ell: np.ndarray, dx: float,
                            psi_p: float, tol: float = 1e-10,
                            interface_ratio: float = 1.0) -> float:
    """φ (rad) on bases and interfaces at which the toe needs no support (P_0 = 0), by
    bisection; `interface_ratio` = tan φ_d / tan φ_p (1: the same friction everywhere)."""

    def toe(phi: float) -> float:
        phi_d = np.arctan(interface_ratio * np.tan(phi))
        return goodman_bray(y, m, ell, dx, psi_p, phi, phi_d).toe_thrust

    # P_0 falls as φ grows; the sliding term needs tan φ_p tan φ_d < 1
    lo = 1e-6
    hi = (np.arctan(1.0 / np.sqrt(interface_ratio)) if interface_ratio > 0 else 0.5 * np.pi) - 1e-9
    if toe(lo) <= 0.0:
        return lo
    if toe(hi) > 0.0:
        raise ValueError("the columns need toe support at any friction angle")
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if toe(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
