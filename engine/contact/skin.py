"""Contact detection with a skin, as Verlet lists are: a full detection also keeps, for a
margin μ, every piece pair and candidate feature (vertex, edge) that any later step may
need while no block has moved more than μ since; until one has, the following steps search
only those, and find exactly what a full detection would.

Why nothing is missed (every step, every pair and feature, exactly):

- A block's motion since the full detection is affine, so no point of it moved further than
  its farthest vertex, δ (:func:`block_drift`); every box coordinate of a piece moved by at
  most δ.
- The full detection keeps the piece pairs whose boxes overlap when each is grown by
  R + snap_hi + μ (R each block's reach at the full detection plus μ, snap_hi the feature
  snap of the scene grown by 2μ), and for each pair the surface vertices inside, and the
  real edges meeting, the other piece's box grown by R_i + R_j + snap_hi + 2μ.
- A later step grows the boxes by its reach + snap and looks only at the pairs whose grown
  boxes overlap (its broad phase), and in a pair only at vertices inside, and edges
  meeting, the other's box grown by the pair's search radius r = reach_i + reach_j + snap
  (the narrow phase's first tests). While every δ ≤ μ, every reach ≤ R and the snap ≤
  snap_hi, each of those is a box test that held at the full detection with the larger
  growth: the kept pairs and features contain all of them. The kept pairs are tested again
  with the step's own growth (:func:`engine.contact._detection_kernels._kept_pair`), and
  the kept features go through all the narrow phase's tests, so a step finds exactly the
  contacts, gaps and planes of a full detection (tests/test_skin.py compares them step by
  step).
- A block that moved more than μ, a reach beyond R, a block awake that was not, or another
  scene: the next search is a full detection that keeps new lists. Lists that served fewer
  than SKIN_MIN_SERVED searches did not pay for themselves (blocks that move a margin a
  step, as a falling pile's): the next 1, 2, 4 ... SKIN_MAX_BACKOFF searches are full
  detections without lists, then lists are tried again.

The margin μ is SKIN_SIZE of the thinnest free block, and at most SKIN_REACH times the
largest reach of a free block at the full detection: a skin of about one step's reach lasts
as many steps as the blocks take to move that far. What it saves is the broad phase, the
geometry of pieces no pair needs, and the narrow phase's look at features no contact can
come from; the narrow phase itself (the planes of the contacts found) is done every step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.contact import _detection_kernels as kern
from engine.contact._skin_kernels import block_drift, candidate_features
from engine.contact.constraints import ContactSet
from engine.contact.detection import Search, broad_phase, narrow, start_search
from engine.geometry.polyhedron import Polyhedron
from engine.tolerances import DEFAULT_TOLERANCES, Tolerances

#: the skin's margin is at most this fraction of the thinnest free block ...
SKIN_SIZE = 0.05
#: ... and at most this many times the largest reach of a free block
SKIN_REACH = 1.0
#: a skin that served fewer searches than this did not pay for its lists (blocks moving
#: a margin a step, as a falling pile's): the next ones are made after 1, 2, 4 ... 64 full
#: detections without lists
SKIN_MIN_SERVED = 2
SKIN_MAX_BACKOFF = 64


@dataclass
class Skin:
    """What a full detection keeps for the following steps (see the module docstring):
    the scene it was made for, the margin `margin` m, each block's reach `reach (n,)` m and
    the snap `snap` m the lists cover, the blocks awake then `active (n,)`, the vertices
    then `x0 (V, 3)`, the kept piece pairs `pa`, `pb` and their candidate features `lists`;
    and how many full detections and searches on the lists it made."""

    scene: object
    margin: float
    reach: np.ndarray
    snap: float
    active: np.ndarray
    x0: np.ndarray
    pa: np.ndarray
    pb: np.ndarray
    lists: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    refreshes: int = 0
    reuses: int = 0
    #: searches these lists served after their full detection; whether they still serve
    served: int = 0
    live: bool = True
    #: full detections to make without lists before the next ones, and the last back-off
    #: (lists that served fewer than SKIN_MIN_SERVED searches did not pay)
    idle: int = 0
    backoff: int = 0

    def covers(self, search: Search, active: np.ndarray, vertex_block: np.ndarray) -> bool:
        """Whether the lists hold every pair and feature of `search` with `active` blocks."""
        return (search.scene is self.scene and len(active) == len(self.active)
                and not np.any(active & ~self.active)
                and bool(np.all(search.reach <= self.reach)) and search.snap <= self.snap
                and float(block_drift(search.x, self.x0, vertex_block,
                                      len(self.active)).max(initial=0.0)) <= self.margin)


def skin_margin(search: Search, thickness: np.ndarray, free: np.ndarray) -> float:
    """The margin μ (m) of a skin made at `search`: SKIN_SIZE of the thinnest free block,
    at most SKIN_REACH times the largest reach of a free block (`thickness`, `free (n,)`)."""
    if not np.any(free):
        return 0.0
    return float(min(SKIN_SIZE * thickness[free].min(),
                     SKIN_REACH * search.reach[free].max(initial=0.0)))


def detect_with_skin(blocks: Sequence[Polyhedron], reach: np.ndarray, active: np.ndarray,
                     vertices: np.ndarray, vertex_block: np.ndarray, thickness: np.ndarray,
                     workspace: dict, tol: Tolerances = DEFAULT_TOLERANCES) -> ContactSet:
    """The contacts :func:`engine.contact.detection.detect_contacts` finds for `blocks` at
    `vertices` within each block's `reach (n,)` (pairs with an `active` block), searched on
    the lists of the skin in `workspace["skin"]` while it covers the step, else on the
    lists of a new skin made there (a full detection: its broad phase with the skin's
    growth, which holds the step's own pairs). `vertex_block (V,)`: each vertex's block;
    `thickness (n,)`: each block's thickness (the margin's scale)."""
    active = np.asarray(active, dtype=bool)
    search = start_search(blocks, reach, tol, vertices)
    skin = workspace.get("skin")
    if skin is not None and skin.live:
        if skin.covers(search, active, vertex_block):
            skin.reuses += 1
            skin.served += 1
            return _search_lists(search, skin, active)
        if skin.served < SKIN_MIN_SERVED:  # the lists did not pay: none for a while
            skin.backoff = min(max(2 * skin.backoff, 1), SKIN_MAX_BACKOFF)
            skin.idle, skin.live = skin.backoff, False
            skin.pa = skin.pb = np.zeros(0, dtype=np.int64)
        else:
            skin.backoff = 0
    if skin is not None and not skin.live and skin.idle > 0:
        skin.idle -= 1
        return narrow(search, *broad_phase(search, search.reach + search.snap, active))
    skin = workspace["skin"] = _new_skin(search, active, vertex_block, thickness, skin)
    return _search_lists(search, skin, active)


def _search_lists(search: Search, skin: Skin, active: np.ndarray) -> ContactSet:
    """The contacts of `search` from the skin's pairs and candidate features."""
    keep = kern.SkinLists(*skin.lists, search.reach + search.snap, active)
    return narrow(search, skin.pa, skin.pb, keep)


def _new_skin(search: Search, active: np.ndarray, vertex_block: np.ndarray,
              thickness: np.ndarray, old: Skin | None) -> Skin:
    """The skin of a full detection at `search` (counting on from the `old` one's)."""
    margin = skin_margin(search, thickness, active)
    reach = search.reach + margin
    snap = search.tol.lengths(search.extent + 2.0 * margin).feature_snap
    slack = 1e-3 * snap  # far above the round-off of a box test at the scene's size
    grow_pairs = reach + snap + margin + slack
    pa, pb = broad_phase(search, grow_pairs, active)
    s = search.scene
    lists = candidate_features(pa, pb, search.x, s.piece_block, s.pv_start, s.pv_count,
                               s.pv_vtx, s.pv_surface, s.e_start, s.e_count, s.e_vtx,
                               s.e_real, search.p_lo, search.p_hi,
                               reach + 0.5 * snap + margin + slack)
    counts = (0, 0, 0) if old is None else (old.refreshes, old.reuses, old.backoff)
    return Skin(s, margin, reach, snap, active.copy(), search.x.copy(), pa, pb, lists,
                counts[0] + 1, counts[1], backoff=counts[2])
