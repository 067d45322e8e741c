"""PolyDDA's engine: 3-D DDA of polyhedral blocks (no JSON, no service; plain arrays in)."""

from __future__ import annotations

import os
from pathlib import Path


def kernels_cached() -> bool:
    """Whether numba's on-disk cache already holds the engine's compiled kernels; if not,
    the first step of the first run on a machine compiles them (about a minute)."""
    here = Path(__file__).resolve().parent
    places = [here / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        places.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    return any(any(p.rglob("_detection_kernels.narrow_phase-*.nbi")) for p in places
               if p.is_dir())
