"""The ICP (iterative closest point): the loop (:mod:`.loop`), its robust
weights, adjustment, covariance, information, iteration records,
result and the coarse-to-fine pyramid. ``labkit.registration.icp``
is the function.
"""
