"""Which cells make which block: cells glued across fictitious facets, then blocks too small
or too thin (slivers) merged into the neighbour they share the most facet area with."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from engine.geometry.cutting.facets import Facets

#: default smallest block, as a fraction of the median block volume of the cut
MIN_BLOCK_VOLUME_RATIO = 1e-3
#: default thinnest block, as a fraction of the median spacing of the joint sets (of the
#: median block width without sets): thinner blocks are slivers and merge
MIN_BLOCK_WIDTH_RATIO = 0.1


def _components(n: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """`(n,) int` connected component of each node of an undirected edge list."""
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def glued(
    fac: Facets, real: np.ndarray, n_cells: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells joined across fictitious facets (no real joint between them): `(c,) int`
    group per cell, and the cell pairs `(k,)`, `(k,)` that were joined."""
    glue = (fac.other > np.arange(len(fac.other))) & ~real
    rows, cols = fac.cell[glue], fac.cell[fac.other[glue]]
    return _components(n_cells, rows, cols), rows, cols


def cell_widths(fac: Facets, n_cells: int) -> np.ndarray:
    """`(c,)` m: each convex cell's smallest extent across its own face planes (its
    width, as :attr:`Polyhedron.width` of a convex block)."""
    width = np.full(n_cells, np.inf)
    cell_of = fac.cell
    order = np.argsort(cell_of, kind="stable")
    bounds = np.searchsorted(cell_of[order], np.arange(n_cells + 1))
    for c in range(n_cells):
        fs = order[bounds[c]:bounds[c + 1]]
        if not len(fs):
            continue
        ids = np.unique(np.concatenate([fac.ids[f] for f in fs.tolist()]))
        h = fac.coords[ids] @ fac.plane_normal[fac.label[fs]].T
        width[c] = float((h.max(axis=0) - h.min(axis=0)).min())
    return width


def groups(
    fac: Facets, glued: tuple[np.ndarray, np.ndarray, np.ndarray], sliver: float,
    merge_below: float, min_width: float, warnings: list[str],
) -> tuple[np.ndarray, np.ndarray]:
    """Blocks of the cells `glued` across fictitious facets (:func:`glued`); blocks
    smaller than `merge_below` (m³) or thinner than `min_width` (m: the widest of their
    cells, so a block glued from cells is as wide as its widest cell) join the neighbour
    block they share the most facet area with, repeated until none is left (a sliver
    merged into another sliver is merged again).

    Returns `(c,) int` group per cell and `(c,) bool` cells dropped (isolated slivers
    below `sliver` m³).
    """
    group, rows, cols = glued
    n_cells = len(group)
    cell_width = cell_widths(fac, n_cells) if min_width > 0 else np.full(n_cells, np.inf)
    dropped = np.zeros(n_cells, dtype=bool)
    n_small = n_thin = 0
    thinnest = np.inf
    for _ in range(8):
        n_g = int(group.max()) + 1 if n_cells else 0
        gvol = np.bincount(group, weights=fac.cell_volume, minlength=n_g)
        gwidth = np.full(n_g, -np.inf)
        np.maximum.at(gwidth, group, cell_width)
        small = gvol < max(sliver, merge_below)
        thin = ~small & (gwidth < min_width)
        if not (small | thin).any():
            break
        g_own = group[fac.cell]
        cand = np.flatnonzero((small | thin)[g_own] & (fac.other >= 0))
        g_nb = group[fac.cell[fac.other[cand]]]
        keep = g_nb != g_own[cand]
        cand, g_nb = cand[keep], g_nb[keep]
        if not len(cand):
            break
        # shared area per (block, neighbour block): merge across the largest
        pair_keys, inv = np.unique(np.stack([g_own[cand], g_nb], axis=1), axis=0,
                                   return_inverse=True)
        area = np.bincount(inv.reshape(-1), weights=fac.area[cand])
        order = np.lexsort((-area, pair_keys[:, 0]))
        _, first = np.unique(pair_keys[order, 0], return_index=True)
        best = order[first]
        src, dst = pair_keys[best, 0], pair_keys[best, 1]
        n_small += int(small[src].sum())
        n_thin += int(thin[src].sum())
        if thin[src].any():
            thinnest = min(thinnest, float(gwidth[src][thin[src]].min()))
        # one facet pair between each merged block and its neighbour joins them
        rep = np.zeros(n_g, dtype=np.int64)
        rep[group] = np.arange(n_cells)
        rows = np.concatenate([rows, rep[src]])
        cols = np.concatenate([cols, rep[dst]])
        group = _components(n_cells, rows, cols)
    n_g = int(group.max()) + 1 if n_cells else 0
    gvol = np.bincount(group, weights=fac.cell_volume, minlength=n_g)
    has_nb = np.zeros(n_g, dtype=bool)
    m = fac.other >= 0
    has_nb[group[fac.cell[m]][group[fac.cell[m]] != group[fac.cell[fac.other[m]]]]] = True
    dropped = ((gvol < sliver) & ~has_nb)[group]
    if n_small:
        warnings.append(f"{n_small} small block(s) below {max(sliver, merge_below):.3g} m³ "
                        "merged into a neighbour block")
    if n_thin:
        warnings.append(f"{n_thin} thin block(s) (sliver: narrower than {min_width:.3g} m, "
                        f"the thinnest {thinnest:.3g} m) merged into the neighbour they "
                        "share the largest face with")
    if dropped.any():
        warnings.append(f"{len(np.unique(group[dropped]))} isolated sliver block(s) dropped")
    return group, dropped
