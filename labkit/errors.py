"""Exceptions raised by labkit.

Every error that bad input can cause is a :class:`LabkitError`, which is a
``ValueError``: callers that already catch ``ValueError`` keep working, and the
message always says what was expected.
"""

from __future__ import annotations


class LabkitError(ValueError):
    """Base class of every input or estimation error raised by labkit."""


class DegenerateGeometryError(LabkitError):
    """The points cannot determine the model (coplanar, duplicate, singular N)."""


class ConvergenceError(LabkitError):
    """An iteration did not converge and the caller asked for an exception."""


class EmptyRegionError(LabkitError):
    """A crop, filter or overlap left no (or too few) points."""


class CloudFileError(LabkitError):
    """A point-cloud file is missing, unreadable, corrupt or of an unknown format."""
