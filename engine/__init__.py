"""PolyDDA's engine: 3-D DDA of polyhedral blocks (no JSON, no service; plain arrays in).

The compiled (numba) kernels are cached on disk in a folder named after a digest of their
sources: numba's own cache notices a change of a kernel's module but not of a kernel it calls
from another module (the motion kernels, the contact constants), and would run stale code.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import warnings
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent


def kernel_cache_dir() -> Path:
    """Where numba caches the engine's kernels: NUMBA_CACHE_DIR when the user sets it, else
    `engine/__pycache__/kernels-<digest of the kernel sources>`."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(here.rglob("_*_kernels.py")) + [here / "contact" / "constraints.py"]:
        if path.exists():
            digest.update(path.read_bytes())
    return here / "__pycache__" / f"kernels-{digest.hexdigest()[:16]}"


if not os.environ.get("NUMBA_CACHE_DIR"):
    if "numba" in sys.modules:  # numba read its settings already: set its cache directly
        sys.modules["numba"].config.CACHE_DIR = str(kernel_cache_dir())
    else:  # numba reads this when a kernel module imports it (importing it here costs 0.2 s)
        os.environ["NUMBA_CACHE_DIR"] = str(kernel_cache_dir())


def kernels_cached() -> bool:
    """Whether numba's on-disk cache already holds the engine's compiled kernels; if not,
    the first step of the first run on a machine compiles them (about a minute)."""
    place = kernel_cache_dir()
    return place.is_dir() and any(place.rglob("_detection_kernels.narrow_phase-*.nbi"))


#: top-level packages whose calls are PolyDDA's own (the CLI, the service, the facade, the
#: tests and benchmarks): they may use the inner layout without a deprecation warning
_OWN_PACKAGES = frozenset({"engine", "schemas", "service", "polydda", "tests", "benchmarks"})
_warned: set[str] = set()


def user_entry(replacement: str) -> Any:
    """Decorate a function users called directly before the `polydda` package existed:
    called from outside PolyDDA's own packages it works as before and warns once per
    process (DeprecationWarning) that `replacement` is the stable name."""

    def wrap(fn: Any) -> Any:
        name = f"{fn.__module__}.{fn.__qualname__}"

        @functools.wraps(fn)
        def call(*args: Any, **kwargs: Any) -> Any:
            where = sys._getframe(1).f_globals
            spec = where.get("__spec__")  # a module run with -m is __main__ by its __name__
            caller = str(getattr(spec, "name", None) or where.get("__name__", ""))
            if caller.split(".")[0] not in _OWN_PACKAGES and name not in _warned:
                _warned.add(name)
                warnings.warn(f"{name} belongs to PolyDDA's inner layout, which may change: "
                              f"use {replacement} (the stable Python API, docs/python.md)",
                              DeprecationWarning, stacklevel=2)
            return fn(*args, **kwargs)

        return call

    return wrap
