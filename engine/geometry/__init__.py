"""Geometry: polyhedra (convex and concave) and their mass properties, block shapes, the
displacement matrix T(x) and the rigid and affine transforms of block points, joint planes,
and the cutting of a rock mass by joints into blocks.

The lowest room of the engine: it may import only :mod:`engine.tolerances`.
"""
