"""The sphere: its model (:mod:`.model`), the Gauss-Helmert adjustment of a sphere
(:mod:`.ghm`) and the fitted sphere with its precision (:mod:`.fit`).
"""
