"""Change between epochs: M3C2 (:mod:`.m3c2`) with its grid, search and
registration steps and defaults, and cloud-to-cloud distances (:mod:`.distances`).
"""
