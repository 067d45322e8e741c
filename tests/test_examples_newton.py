"""Every example's physics check (tests/test_examples.py) under Newton's method as the
contact solver: the examples' pinned numbers hold with it too (slow: the long runs)."""

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
    ex.test_terrain_slope_example_toe_blocks_slide, ex.test_tunnel_staged_example,
]


@pytest.mark.slow
@pytest.mark.parametrize("check", CHECKS, ids=lambda f: f.__name__.removeprefix("test_"))
def test_example_under_newton(check: Callable[[], None]) -> None:
    check()
