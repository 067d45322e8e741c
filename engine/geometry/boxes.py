"""Overlapping axis-aligned boxes in plain numpy: the broad phase of checks made once (a
scene's explicit blocks overlapping), where compiling or loading the contact room's kernel
(:func:`engine.contact.detection.aabb_pairs`) would cost more than the search itself."""

from __future__ import annotations

import numpy as np

#: candidate pairs examined at once (bounds the memory of a dense sweep)
_CHUNK = 1 << 20


def box_pairs(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """All pairs `(k, 2)` (a < b, sorted) of closed boxes `lower, upper (n, 3)` that overlap.

    Sort and sweep along the axis where the box centres spread most (the same pairs, in the
    same order, as the compiled `aabb_pairs`): O(n log n + candidates along that axis).
    """
    lower = np.asarray(lower, dtype=float).reshape(-1, 3)
    upper = np.asarray(upper, dtype=float).reshape(-1, 3)
    n = len(lower)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    axis = int(np.argmax(np.var(0.5 * (lower + upper), axis=0)))
    order = np.argsort(lower[:, axis], kind="stable")
    lo_sorted = lower[order, axis]
    # box s (in sorted order) meets along the axis exactly the boxes s+1 .. end[s]-1
    end = np.searchsorted(lo_sorted, upper[order, axis], side="right")
    count = np.maximum(end - np.arange(1, n + 1), 0)
    found = []
    first = 0
    while first < n:  # chunks of boxes whose candidates fit in _CHUNK
        total = np.cumsum(count[first:])
        last = first + max(1, int(np.searchsorted(total, _CHUNK, side="right")))
        c = count[first:last]
        s = np.repeat(np.arange(first, last), c)
        t = s + 1 + np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
        a, b = order[s], order[t]
        meet = np.all((lower[a] <= upper[b]) & (lower[b] <= upper[a]), axis=1)
        found.append(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)[meet])
        first = last
    pairs = np.concatenate(found).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
