"""Neighbourhoods: the k-d tree (:mod:`.kdtree` and its build and nearest-neighbour
kernels), the tree cache, neighbour search and local covariances
(:mod:`.search`), the 3x3 eigen-solver (:mod:`.eigh3`) and the one home of
point thinning and point spacing (:mod:`.sampling`).
"""
