"""Correspondences between two clouds: the matching (:mod:`.match`), the
matcher, the correspondence records and the local surface fits.
"""
