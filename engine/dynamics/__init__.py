"""Shi's block system of one step, without the contacts' rules: the constants of a run
(:mod:`.system`, MuJoCo's model) and everything that changes (:mod:`.state`, its data), the
block terms (inertia, elasticity, body forces, loads), the block-sparse global assembly,
the linear solve, and where the blocks' points are (:mod:`.motion`).

May import :mod:`engine.model`, :mod:`engine.loads`, :mod:`engine.geometry` and the
foundation modules; never :mod:`engine.contact` or above.
"""
