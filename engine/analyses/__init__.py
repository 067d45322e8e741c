"""Analyses built on runs or on the scene alone: strength reduction and the critical seismic
coefficient, toppling limit equilibrium, kinematic (Markland) screening and its stereonet,
joint statistics and reliability.

The top room: may import anything in the engine.
"""
