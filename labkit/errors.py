"""Exceptions raised by labkit.

Every error that bad input can cause is a :class:`LabkitError`, which is a
``ValueError``: callers that already catch ``ValueError`` keep working, and the
message always says what was expected.

An iteration that does not converge is not an input error: the estimators
report it in their result (``converged=False`` and a ``reason``, e.g.
:class:`~labkit.adjustment.SphereFit`), so a caller such as the RANSAC refit can
react to it. ``ConvergenceError`` was exported but never raised; it is
deprecated (accessing it warns) and will be removed.
"""

from __future__ import annotations

import warnings


class LabkitError(ValueError):
    """Base class of every input or estimation error raised by labkit."""


class DegenerateGeometryError(LabkitError):
    """The points cannot determine the model (coplanar, duplicate, singular N)."""


class _ConvergenceError(LabkitError):
    """Deprecated, never raised: non-convergence is reported in the result (``converged``, ``reason``)."""


class EmptyRegionError(LabkitError):
    """A crop, filter or overlap left no (or too few) points."""


class CloudFileError(LabkitError):
    """A point-cloud file is missing, unreadable, corrupt or of an unknown format."""


def _deprecated_convergence_error(stacklevel: int = 3):
    """The deprecated class, with a DeprecationWarning pointing at the caller's line."""
    warnings.warn("ConvergenceError is deprecated and will be removed: labkit never raises it; an iteration "
                  "that does not converge is reported in its result (converged=False and a reason)",
                  DeprecationWarning, stacklevel=stacklevel)
    return _ConvergenceError


def __getattr__(name: str):
    if name == "ConvergenceError":
        return _deprecated_convergence_error()
    raise AttributeError(f"module 'labkit.errors' has no attribute {name!r}")
