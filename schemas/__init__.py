"""Scene schema (pydantic), validation errors and conversion of a scene to engine inputs.

The names below are imported on first use: `import schemas.scene` (the format) or
`schemas.errors` must not pull the engine's conversion (cutting, contact detection) in.
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "BuildResult": "schemas.convert",
    "build_model": "schemas.convert",
    "SceneError": "schemas.errors",
    "SCHEMA_VERSION": "schemas.scene",
    "Limits": "schemas.scene",
    "Scene": "schemas.scene",
    "load_scene": "schemas.scene",
    "scene_json_schema": "schemas.scene",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """`schemas.<name>` from the module that defines it, imported now."""
    if name not in _WHERE:
        raise AttributeError(f"module 'schemas' has no attribute {name!r}")
    return getattr(importlib.import_module(_WHERE[name]), name)
