"""Input validation shared by every public function.

The helpers never modify their input: they return a new float64 array when a
conversion is needed, so callers may write into the result freely only after an
explicit ``copy`` (``as_points(..., copy=True)``).
"""

from __future__ import annotations

import numbers

import numpy as np

from .errors import LabkitError


def as_points(points, *, min_points: int = 1, name: str = "points", copy: bool = False) -> np.ndarray:
    """Return ``points`` as a finite float64 array of shape (n, 3).

    Raises
    ------
    LabkitError
        If the shape is not (n, 3), fewer than ``min_points`` rows are given,
        any coordinate is NaN or infinite, or a PointCloud is known to be in
        degrees or feet (:meth:`labkit.cloud.PointCloud.require_metric`).
    """
    xyz = getattr(points, "xyz", points)  # PointCloud or array-like
    if callable(getattr(points, "require_metric", None)):  # a PointCloud in degrees or feet is refused
        points.require_metric(f"a metric step (on {name})")
    try:
        arr = np.array(xyz, dtype=np.float64, copy=copy) if copy else np.asarray(xyz, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LabkitError(f"{name} must be numeric with shape (n, 3): {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise LabkitError(f"{name} must have shape (n, 3), got {arr.shape}")
    if arr.shape[0] < min_points:
        raise LabkitError(f"{name} needs at least {min_points} points, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise LabkitError(f"{name} contains {bad} point(s) with NaN or infinite coordinates")
    return arr


def as_rng(rng) -> np.random.Generator:
    """Return a ``numpy.random.Generator`` from an int seed, a Generator or None."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, (numbers.Integral, np.random.SeedSequence)):
        return np.random.default_rng(rng)
    raise LabkitError(f"rng must be an int, a numpy.random.Generator or None, got {type(rng).__name__}")


def positive(value, name: str) -> float:
    """Return ``value`` as float, raising if it is not a finite number > 0."""
    try:
        val = float(value)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be a number > 0, got {value!r}") from None
    if not np.isfinite(val) or val <= 0:
        raise LabkitError(f"{name} must be a finite number > 0, got {value!r}")
    return val


def probability(value, name: str) -> float:
    """Return ``value`` as float, raising unless 0 < value < 1."""
    try:
        val = float(value)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be a number in (0, 1), got {value!r}") from None
    if not (0.0 < val < 1.0):
        raise LabkitError(f"{name} must lie strictly between 0 and 1, got {value!r}")
    return val


def choice(value, allowed, name: str):
    """Return ``value`` if it is one of ``allowed``; otherwise raise naming the options."""
    if value not in allowed:
        options = ", ".join(repr(a) for a in allowed)
        raise LabkitError(f"{name} must be one of {options}; got {value!r}")
    return value
