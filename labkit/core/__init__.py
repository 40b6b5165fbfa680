"""Infrastructure shared by every package: errors, input checks, atomic files and
outputs, progress, coordinate frames, units and lengths, CRS, statistics,
reports, masks, the numba cache and lazy imports. Imports nothing of labkit above it.
"""
