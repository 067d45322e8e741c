"""Every example's physics check (tests/test_examples.py) under Newton's method as the
contact solver: the examples' pinned numbers hold with it too (slow: the long runs); and
the staged tunnel's key block, which Newton's method lets fall where the open-close
iteration holds it (docs/contact-solvers.md)."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from tests import test_examples as ex
from tests.test_newton import newton  # noqa: F401 (the fixture: models run under Newton)

CHECKS: list[Callable[[], None]] = [
    ex.test_incline_example, ex.test_free_fall_example, ex.test_pushed_block_example,
    ex.test_stack_example, ex.test_toppling_example,
    ex.test_toppling_columns_gain_no_energy_from_their_contacts,
    ex.test_block_system_example, ex.test_benched_slope_example_holds,
]


@pytest.mark.slow
def test_terrain_slope_toe_blocks_slide_under_newton() -> None:
    """examples/terrain_slope.json under Newton: the toe blocks slide on the bedding 40/180
    at φ 38° with limit equilibrium's acceleration a = g (sin 40° − cos 40° tan 38°), having
    started within two steps (Δt 2 ms): ½ a (t − 2Δt)² ≤ d(0.5 s) ≤ 1.01 · ½ a t². Their
    pull exceeds friction by 4.4 % of g, so the first step's springs and dashpots taking up
    their weight (Coulomb's cap follows the whole normal force) show as a start 2.6 ms late
    (the open-close iteration, whose dashpots act after the step, is within 1 % of ½ a t²);
    the rest of the hill holds (0.1 mm)."""
    sliding, rest = ex.terrain_toe_displacements()
    a, t, dt = ex.TERRAIN_TOE_ACCELERATION, 0.5, 0.002
    assert len(sliding) == 2
    assert all(0.5 * a * (t - 2 * dt) ** 2 <= x <= 1.01 * 0.5 * a * t**2 for x in sliding)
    assert all(x < 1e-4 for x in rest)


@pytest.mark.slow
@pytest.mark.parametrize("check", CHECKS, ids=lambda f: f.__name__.removeprefix("test_"))
def test_example_under_newton(check: Callable[[], None]) -> None:
    check()


@pytest.mark.slow
def test_tunnel_key_block_falls_under_newton() -> None:
    """examples/tunnel_staged.json: the key block B54 (removable, sliding on J2 at FS 0.327
    by key-block analysis) slides out once the tunnel is dug, at g (sin 65° − cos 65°
    tan 35°) = 5.988 m/s² within 2 % (the complementarity solve agrees; the open-close
    iteration holds it, clamped by its settle stage's locked-in contact forces); the run
    creates no energy."""
    import numpy as np

    from engine.step.staged_run import run_stages
    from schemas.convert import build_model

    built = build_model(ex.EXAMPLES / "tunnel_staged.json")
    k = built.block_names.index("B54")
    c0 = built.model.blocks[k].polyhedron.centroid
    track: list[tuple[float, float]] = []

    class Track:
        def begin(self, *a: object) -> None: ...
        def end(self, *a: object) -> None: ...

        def record(self, frame: object) -> None:
            track.append((frame.time, float(np.linalg.norm(frame.centroids[k] - c0))))

    res = run_stages(built.model, built.stages, recorder=Track())
    assert res.status == "completed", res.message
    t, d = np.array(track).T
    late = t >= 0.25
    accel = 2.0 * np.polyfit(t[late], d[late], 2)[0]
    g = 9.81
    expected = g * (np.sin(np.radians(65)) - np.cos(np.radians(65)) * np.tan(np.radians(35)))
    assert accel == pytest.approx(expected, rel=0.02)
    assert res.summary["energy"]["created_ratio"] < 1e-3

