"""PolyDDA from Python: the stable API of the project, in a namespace of its own.

    import polydda
    scene = polydda.Scene.load("examples/wedge.json")
    result = polydda.run(scene, out="wedge.h5")       # a progress bar while it runs
    result.history("B2")                               # pandas DataFrame
    polydda.le(scene)["factor_of_safety"]

Everything a user needs is a name of this package (docs/python.md lists them); the
packages `engine`, `schemas` and `service` are the inner layout, which may change. Names
are imported on first use: `import polydda` alone loads neither numpy's engine nor the
web service.
"""

from __future__ import annotations

import importlib
from typing import Any

from polydda._version import version as _version

__version__: str = _version()

_WHERE = {
    "Scene": "polydda.scene",
    "Blocks": "polydda.scene",
    "SceneError": "polydda.scene",
    "run": "polydda.analyses",
    "le": "polydda.analyses",
    "fos": "polydda.analyses",
    "keyblocks": "polydda.analyses",
    "sweep": "polydda.analyses",
    "Sweep": "polydda.analyses",
    "open_result": "polydda.result",
    "Result": "polydda.result",
}

__all__ = ["__version__", *sorted(_WHERE)]


def __getattr__(name: str) -> Any:
    """`polydda.<name>` from the module that defines it, imported now."""
    if name not in _WHERE:
        raise AttributeError(f"module 'polydda' has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
