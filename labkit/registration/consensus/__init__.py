"""Maximum consensus: the consensus cube and search (:mod:`.cube`), its
inputs, compiled kernels, records (:mod:`.result`), branch and bound
(:mod:`.bnb`) and the jackknife covariance of its refinement (:mod:`.jackknife`).
"""
