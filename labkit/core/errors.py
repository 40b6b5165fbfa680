"""Exceptions raised by labkit.

Every error that bad input can cause is a :class:`LabkitError`, which is a
``ValueError``: callers that already catch ``ValueError`` keep working, and the
message always says what was expected.

An iteration that does not converge is not an input error: the estimators
report it in their result (``converged=False`` and a ``reason``, e.g.
:class:`~labkit.sphere.ghm.SphereFit`), so a caller such as the RANSAC refit can
react to it.
"""

from __future__ import annotations


class LabkitError(ValueError):
    """Base class of every input or estimation error raised by labkit.

    Examples
    --------
    >>> from labkit.core.errors import LabkitError
    >>> issubclass(LabkitError, ValueError)  # callers catching ValueError keep working
    True
    >>> from labkit.tiles import tile_grid
    >>> try:
    ...     tile_grid((0, 0, 10, 10), size=-1)
    ... except LabkitError as exc:
    ...     print(exc)
    size must be a finite number > 0, got -1
    """


class DegenerateGeometryError(LabkitError):
    """The points cannot determine the model (coplanar, duplicate, singular N).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.sphere.ghm import gauss_helmert_model
    >>> from labkit.core.errors import DegenerateGeometryError
    >>> flat = np.c_[np.random.default_rng(0).uniform(-1, 1, (20, 2)), np.zeros(20)]  # a plane fixes no sphere
    >>> try:
    ...     gauss_helmert_model(flat)
    ... except DegenerateGeometryError:
    ...     print("degenerate")
    degenerate
    """


class EmptyRegionError(LabkitError):
    """A crop, filter or overlap left no (or too few) points.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.regions import crop_box
    >>> crop_box(np.zeros((3, 3)), (5, 5, 6, 6))  # nothing inside
    Traceback (most recent call last):
    labkit.core.errors.EmptyRegionError: ...
    """


class CloudFileError(LabkitError):
    """A point-cloud file is missing, unreadable, corrupt or of an unknown format.

    Examples
    --------
    >>> from labkit.io import read_cloud
    >>> read_cloud("no/such/file.laz")
    Traceback (most recent call last):
    labkit.core.errors.CloudFileError: ...
    """


class CrsMismatchError(LabkitError):
    """Two inputs of one computation state different coordinate reference systems.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.change.distances import cloud_to_cloud
    >>> a = PointCloud(np.zeros((3, 3)), crs="EPSG:25832")
    >>> cloud_to_cloud(a, PointCloud(np.zeros((3, 3)), crs="EPSG:25833"))
    Traceback (most recent call last):
    labkit.core.errors.CrsMismatchError: ...
    """


class CrsNote(UserWarning):
    """One input states a CRS and the other none: taken to be in the same frame (said, not refused)."""
