"""Maximum consensus: the consensus cube and search (:mod:`.cube`), its
inputs, compiled kernels, records (:mod:`.result`), branch and bound
(:mod:`.bnb`), the jackknife covariance of its refinement (:mod:`.jackknife`)
and the centre of the consensus hill along held directions (:mod:`.plateau`).
"""
