"""Results of a run: the HDF5 result file (its layout; the writer and its batching; the
reader and recovery), its summary and its plots.

May import :mod:`engine.step` (the frames a run records) and everything below it.
"""
