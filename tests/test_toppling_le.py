"""Goodman & Bray (1976) limit equilibrium of block toppling (engine/toppling.py).

The slope of examples/toppling_goodman_bray.json: 12 columns 5 m wide on treads dipping 28°
toward the toe, a1 = a2 = 2.5 m, b = 0.5 m, crest at column 8, the same friction on bases
and interfaces. At the critical friction angle 33.93° columns 1–3 slide, 4–10 topple and
11–12 stand. The single-column checks are the textbook chart (Hoek & Bray): a block on a
plane dipping ψ slides iff φ < ψ and topples iff Δx / y < tan ψ.
"""

from __future__ import annotations

import numpy as np
import pytest

from engine.analyses.toppling import (
    SLIDE,
    STABLE,
    TOPPLE,
    column_heights,
    critical_friction_angle,
    goodman_bray,
    lever_arms,
)

PSI = np.radians(28.0)
DX, A1, A2, B, CREST = 5.0, 2.5, 2.5, 0.5, 8
MODES = [SLIDE] * 3 + [TOPPLE] * 7 + [STABLE] * 2


def _slope() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    y = column_heights(12, CREST, A1, A2, B)
    return (y, *lever_arms(y, CREST, A1, A2))


def test_column_geometry() -> None:
    y, m, ell = _slope()
    assert y.tolist() == [2, 4, 6, 8, 10, 12, 14, 16, 13, 10, 7, 4]
    # below the crest a column is pushed at its own top and pushes its toe-side neighbour
    # at that one's top, b lower than a1 below its own; above the crest the other way round
    assert m.tolist() == [2, 4, 6, 8, 10, 12, 14, 13.5, 10.5, 7.5, 4.5, 1.5]
    assert ell.tolist() == [-0.5, 1.5, 3.5, 5.5, 7.5, 9.5, 11.5, 13.5, 13, 10, 7, 4]


def test_critical_friction_angle_and_modes() -> None:
    y, m, ell = _slope()
    phi = critical_friction_angle(y, m, ell, DX, PSI)
    assert np.degrees(phi) == pytest.approx(33.93, abs=0.01)
    res = goodman_bray(y, m, ell, DX, PSI, phi, phi)
    assert res.toe_thrust == pytest.approx(0.0, abs=1e-8)
    assert res.mode == MODES
    # just stronger: the toe needs no support; just weaker: it does
    for d, sign in ((0.05, -1), (-0.05, 1)):
        p0 = goodman_bray(y, m, ell, DX, PSI, phi + np.radians(d), phi + np.radians(d))
        assert np.sign(p0.toe_thrust) == sign


def test_every_column_is_in_equilibrium_at_the_critical_angle() -> None:
    """Statics, independently of the recursion: weight, both neighbours' thrusts with
    friction and the base reaction at K_n sum to zero force and moment for every column;
    toppling columns pivot on their toe (K = 0) within friction, sliding ones are at the
    friction limit with K inside the base, and no contact pulls."""
    y, m, ell = _slope()
    phi = critical_friction_angle(y, m, ell, DX, PSI)
    res = goodman_bray(y, m, ell, DX, PSI, phi, phi, unit_weight=2600 * 9.81)
    p = np.append(np.maximum(res.thrust, 0.0), 0.0)  # p[k] = P_{n-1} of column k + 1
    mu = np.tan(phi)
    for k in range(12):
        w = 2600 * 9.81 * DX * y[k]
        # (point, force) in the column's frame: x up-dip along the tread, y along the column
        loads = [((DX / 2, y[k] / 2), (-w * np.sin(PSI), -w * np.cos(PSI))),
                 ((DX, m[k]), (-p[k + 1], -mu * p[k + 1])),
                 ((0.0, ell[k]), (p[k], mu * p[k])),
                 ((res.arm[k], 0.0), (res.shear[k], res.normal[k]))]
        force = np.sum([f for _, f in loads], axis=0)
        moment = sum((x - 1.3) * f[1] - (z - 0.7) * f[0] for (x, z), f in loads)
        assert np.abs(force).max() < 1e-9 * w and abs(moment) < 1e-9 * w * y[k], k
        assert res.normal[k] > 0
        if res.mode[k] == TOPPLE:
            assert res.arm[k] == pytest.approx(0.0, abs=1e-9)
            assert res.shear[k] <= mu * res.normal[k] * (1 + 1e-12)
        elif res.mode[k] == SLIDE:
            assert res.shear[k] == pytest.approx(mu * res.normal[k], rel=1e-9)
            assert 0.0 <= res.arm[k] <= DX
        else:
            assert 0.0 <= res.arm[k] <= DX and abs(res.shear[k]) <= mu * res.normal[k]


@pytest.mark.parametrize(("height", "phi_deg", "mode"), [
    (4.0, 35.0, STABLE),   # Δx/y = 1.25 > tan 28°, φ > ψ
    (10.0, 35.0, TOPPLE),  # Δx/y = 0.5 < tan 28° = 0.532
    (9.0, 35.0, STABLE),   # Δx/y = 0.556, just above tan 28°
    (4.0, 25.0, SLIDE),    # φ < ψ
])
def test_single_column_follows_the_textbook_chart(height: float, phi_deg: float,
                                                  mode: str) -> None:
    y = np.array([height])
    res = goodman_bray(y, y, y, DX, PSI, np.radians(phi_deg), np.radians(phi_deg))
    assert res.mode == [mode]


def test_single_column_limits() -> None:
    """A squat column is critical at φ = ψ; a column topples exactly when Δx/y = tan ψ."""
    y = np.array([4.0])
    assert np.degrees(critical_friction_angle(y, y, y, DX, PSI)) == pytest.approx(28.0,
                                                                                 abs=1e-6)
    h = DX / np.tan(PSI)
    for f, mode in ((0.999, STABLE), (1.001, TOPPLE)):
        y = np.array([h * f])
        assert goodman_bray(y, y, y, DX, PSI, 0.7, 0.7).mode == [mode]


def test_weaker_interfaces_need_more_base_friction() -> None:
    """Interface friction holds the toppling columns back: halving tan φ_d raises the
    critical base friction angle (the DDA comparison depends on it)."""
    y, m, ell = _slope()
    same = critical_friction_angle(y, m, ell, DX, PSI)
    weak = critical_friction_angle(y, m, ell, DX, PSI, interface_ratio=0.5)
    assert np.degrees(weak) > np.degrees(same) + 5
