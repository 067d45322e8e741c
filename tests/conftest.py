"""Shared fixtures: small scene builders."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import pytest

from schemas.convert import BOX_FACES, box_vertices


def _box_block(name: str | None, lo: list[float], hi: list[float], **kw: Any) -> dict[str, Any]:
    """An explicit box block as scene JSON."""
    out: dict[str, Any] = {"vertices": box_vertices(lo, hi).tolist(),
                           "faces": copy.deepcopy(BOX_FACES), **kw}
    if name is not None:
        out["name"] = name
    return out


@pytest.fixture
def box_block() -> Callable[..., dict[str, Any]]:
    """`box_block(name, lo, hi, **fields)`: an explicit box block as scene JSON."""
    return _box_block


@pytest.fixture
def cube_on_base() -> dict[str, Any]:
    """A 1 m cube resting on a fixed base block: the smallest useful scene."""
    return {
        "blocks": [
            _box_block("cube", [0, 0, 0], [1, 1, 1]),
            _box_block("base", [-1, -1, -1], [2, 2, 0], fixed=True),
        ]
    }
