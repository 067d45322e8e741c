"""Removability by the joint pyramid's extreme rays (engine.analyses.keyblocks.removable)
decides as the linear program of block theory does: on random plane sets, on the faces of
cut blocks, and on the cases a tolerance could get wrong (a wedge, a slot, a closed box)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linprog

from engine.analyses.keyblocks import Plane, removable


def _by_lp(normals: np.ndarray) -> bool:
    """The linear program the engine used before: the largest extent of the pyramid
    {d : N d <= 0} ∩ [-1, 1]³ along each axis direction."""
    best = -np.inf
    for sign in np.eye(3).tolist() + (-np.eye(3)).tolist():
        res = linprog(-np.asarray(sign), A_ub=normals, b_ub=np.zeros(len(normals)),
                      bounds=[(-1, 1)] * 3, method="highs")
        if res.status == 0:
            best = max(best, -float(res.fun))
    return best > 1e-9


def _planes(normals: np.ndarray) -> list[Plane]:
    return [Plane(np.asarray(n, float) / np.linalg.norm(n), 1.0, k, 0.5, 0.0)
            for k, n in enumerate(normals)]


def test_random_pyramids_agree_with_the_linear_program() -> None:
    rng = np.random.default_rng(42)
    seen = {True: 0, False: 0}
    for _ in range(150):
        k = int(rng.integers(1, 9))
        normals = rng.normal(size=(k, 3))
        expected = _by_lp(normals / np.linalg.norm(normals, axis=1, keepdims=True))
        assert removable(_planes(normals)) == expected, normals
        seen[expected] += 1
    assert min(seen.values()) > 20  # both verdicts are exercised


@pytest.mark.parametrize(("normals", "expected"), [
    ([[0, 0, -1]], True),                                        # one plane: lifts off
    ([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1]], True),   # a slot: up
    ([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], False),  # a box
    ([[1, 0, 0], [-1, 0, 0]], True),                             # two planes: a free line
    ([[0.6, 0, -0.8], [-0.6, 0, -0.8], [0, 1, 0], [0, -1, 0]], True),   # a wedge's roof
    ([[0.6, 0, 0.8], [-0.6, 0, 0.8], [0, 0.6, -0.8], [0, -0.6, -0.8]], False),  # tapered
])
def test_the_cases_a_tolerance_could_get_wrong(normals: list[list[float]],
                                               expected: bool) -> None:
    a = np.asarray(normals, float)
    assert _by_lp(a / np.linalg.norm(a, axis=1, keepdims=True)) == expected
    assert removable(_planes(a)) == expected
