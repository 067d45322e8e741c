"""Loads on blocks beyond gravity: water pressure in the joints, rock bolts and cables,
pseudo-static seismic coefficients and ground acceleration histories.

Each load's input data type lives with its physics (the :class:`engine.model.Model` holds
them). May import :mod:`engine.geometry` and the foundation modules only.
"""
