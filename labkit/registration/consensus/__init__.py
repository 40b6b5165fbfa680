"""Maximum consensus: the consensus cube and search (:mod:`.cube`), its
inputs, compiled kernels, records (:mod:`.result`) and branch and
bound (:mod:`.bnb`).
"""
