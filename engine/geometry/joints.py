"""Joint planes as the cutting sees them: a plane, its tag, and the polygon that bounds a
non-persistent joint."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class JointPlane:
    """One joint plane for block cutting.

    `normal (3,)` unit normal, `point (3,)` a point on the plane, `tag` the joint id
    the faces it makes will carry, `extent (k, 3)` a convex polygon in the plane that
    bounds a non-persistent joint (None: persistent, cuts everything it crosses).
    """

    normal: np.ndarray
    point: np.ndarray
    tag: int = 0
    extent: np.ndarray | None = None
