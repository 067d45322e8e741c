"""JSON-ready values: the documents the engine's analyses return are written as strict JSON,
which has no NaN or infinity."""

from __future__ import annotations

from typing import Any


def finite(value: Any) -> Any:
    """`value` with NaN and infinities replaced by None (strict JSON)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value
