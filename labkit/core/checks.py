"""Input validation shared by every public function.

The helpers never modify their input: they return a new float64 array when a
conversion is needed, so callers may write into the result freely only after an
explicit ``copy`` (``as_points(..., copy=True)``).

Numbers are checked here once, for the whole package: ``positive``,
``non_negative``, ``finite``, ``numeric_array``, ``probability``, ``count`` (a whole number, never a
silently truncated 20.5), ``as_seed`` and ``as_rng``. A string or a bool where a
number is expected is refused (``buffer='1'`` is a bug at the caller, not a 1).

Precision guard
---------------
Coordinates stored in a low-precision float type (float32, float16) are
rounded to steps of the type's spacing at their magnitude: a float32 easting of
5.4e6 m is a multiple of 0.5 m. :func:`as_points` refuses such input when half
a step exceeds the tolerance (default :data:`PRECISION_TOLERANCE` = 0.1 mm), and
accepts it otherwise (float32 room or local coordinates up to about 2 km). A
caller who knows the coarser steps are fine passes ``tolerance=`` or wraps the
work in ``with precision_tolerance(0.5): ...``; converting to float64 does not
bring the lost digits back, it only silences the guard.
"""

from __future__ import annotations

import contextlib
import contextvars
import numbers
import operator

import numpy as np

from .errors import LabkitError

#: Largest accepted rounding of low-precision coordinates (m): half a step of the float type.
PRECISION_TOLERANCE = 1e-4

_tolerance = contextvars.ContextVar("labkit_precision_tolerance", default=PRECISION_TOLERANCE)


@contextlib.contextmanager
def precision_tolerance(tolerance: float):
    """Within the block, accept low-precision coordinates rounded by up to ``tolerance`` metres.

    ``with precision_tolerance(0.5): icp(a32, b32)`` accepts float32 coordinates at
    UTM size (rounded to 0.25 m); ``precision_tolerance(np.inf)`` switches the guard off.

    References
    ----------
    .. [1] Notebook 03, section 2 ('Why float64': the spacing of float32 coordinates at UTM size).
    .. [2] D. Goldberg (1991): What every computer scientist should know about floating-point
       arithmetic. ACM Computing Surveys 23(1), 5-48, doi:10.1145/103162.103163.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit import precision_tolerance
    >>> from labkit.core.checks import as_points
    >>> utm32 = np.array([[612_345.25, 5_701_234.5, 80.0]], dtype=np.float32)  # float32 rounds to 0.25-0.5 m here
    >>> with precision_tolerance(0.5):
    ...     as_points(utm32).dtype
    dtype('float64')
    """
    tol = _number(tolerance, "the precision tolerance", "a number > 0 (m)")
    if not tol > 0:
        raise LabkitError(f"the precision tolerance must be a number > 0 (m), got {tolerance!r}")
    token = _tolerance.set(tol)
    try:
        yield tol
    finally:
        _tolerance.reset(token)


def as_points(points, *, min_points: int = 1, name: str = "points", copy: bool = False,
              tolerance: float | None = None) -> np.ndarray:
    """Return ``points`` as a finite float64 array of shape (n, 3).

    Low-precision float input (float32, float16) is refused when its rounding at
    the largest coordinate exceeds ``tolerance`` (m; default the current
    :func:`precision_tolerance`, normally :data:`PRECISION_TOLERANCE` = 1e-4 m),
    see :func:`check_precision`.

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
    require_real(xyz, name)
    try:
        arr = np.array(xyz, dtype=np.float64, copy=copy) if copy else np.asarray(xyz, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        if isinstance(xyz, (str, bytes)):
            raise LabkitError(f"{name} must be numeric with shape (n, 3), got a string (read files with "
                              "read_cloud)") from None
        raise LabkitError(f"{name} must be numeric with shape (n, 3): {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise LabkitError(f"{name} must have shape (n, 3), got {arr.shape}")
    if arr.shape[0] < min_points:
        raise LabkitError(f"{name} needs at least {min_points} points, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise LabkitError(f"{name} contains {bad} point(s) with NaN or infinite coordinates")
    check_precision(xyz, name, tolerance, _values=arr)
    return arr


def require_real(values, name: str) -> None:
    """Refuse complex numbers (numpy would silently drop their imaginary parts)."""
    try:
        complex_values = np.iscomplexobj(values)
    except (TypeError, ValueError):
        return  # ragged or not numbers: the conversion that follows says so
    if complex_values:
        raise LabkitError(f"{name} must hold real numbers, got complex values")


def check_precision(values, name: str = "points", tolerance: float | None = None, *, _values=None) -> None:
    """Refuse low-precision float coordinates whose rounding at their magnitude exceeds ``tolerance``.

    ``values`` keeps its own dtype (e.g. a float32 array read from a file); float64
    and integer input always pass. Readers that convert to float64 themselves
    call this on the raw array first. See the module notes (precision guard).
    """
    dtype = getattr(values, "dtype", None)
    if dtype is None or not np.issubdtype(dtype, np.floating) or np.finfo(dtype).bits >= 64:
        return
    arr = values if _values is None else _values
    if arr.size == 0:
        return
    tol = _tolerance.get() if tolerance is None else _number(tolerance, "tolerance", "a number > 0 (m)")
    if not tol > 0:  # NaN too; inf switches the guard off
        raise LabkitError(f"tolerance must be a number > 0 (m), got {tolerance!r}")
    with np.errstate(invalid="ignore"):
        big = float(np.nanmax(np.abs(np.asarray(arr))))
    if not np.isfinite(big):
        return  # NaN / inf are refused elsewhere
    step = float(np.spacing(dtype.type(big)))  # distance to the next representable value at the largest |x|
    if step / 2 > tol:
        raise LabkitError(
            f"{name}: {dtype.name} coordinates up to {big:.3g} m are rounded by up to {step / 2:.3g} m "
            f"({dtype.name} has steps of {step:.3g} m there), more than the tolerance of {tol:.3g} m; keep the "
            f"coordinates in float64 (or reduce them to a local origin before converting), or accept the loss "
            f"with labkit.precision_tolerance({step / 2:.3g})"
        )


# --------------------------------------------------------------------------- numbers
def numeric_array(value, name: str, *, finite: bool = True) -> np.ndarray:
    """``value`` as a float64 array; a non-numeric value, and NaN or inf unless ``finite=False``, is refused.

    Examples
    --------
    >>> from labkit.core.checks import numeric_array
    >>> numeric_array([1, 2], "sigma").tolist()
    [1.0, 2.0]
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be numeric, got {type(value).__name__}") from None
    if finite and not np.isfinite(arr).all():
        raise LabkitError(f"{name} contains NaN or infinite values")
    return arr


def _number(value, name: str, what: str) -> float:
    """``value`` as float; strings, bools and non-numbers are refused with ``what`` in the message."""
    if isinstance(value, (str, bytes, bool, np.bool_)) or not isinstance(value, (numbers.Real, np.ndarray)) \
            or np.iscomplexobj(value):
        raise LabkitError(f"{name} must be {what}, got {value!r} ({type(value).__name__})")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be {what}, got {value!r}") from None


def finite(value, name: str) -> float:
    """Return ``value`` as float, raising if it is not a finite number (NaN and inf refused)."""
    val = _number(value, name, "a finite number")
    if not np.isfinite(val):
        raise LabkitError(f"{name} must be a finite number, got {value!r}")
    return val


def positive(value, name: str) -> float:
    """Return ``value`` as float, raising if it is not a finite number > 0."""
    val = _number(value, name, "a number > 0")
    if not np.isfinite(val) or val <= 0:
        raise LabkitError(f"{name} must be a finite number > 0, got {value!r}")
    return val


def non_negative(value, name: str) -> float:
    """Return ``value`` as float, raising if it is not a finite number >= 0."""
    val = _number(value, name, "a number >= 0")
    if not np.isfinite(val) or val < 0:
        raise LabkitError(f"{name} must be a finite number >= 0, got {value!r}")
    return val


def probability(value, name: str) -> float:
    """Return ``value`` as float, raising unless 0 < value < 1."""
    val = _number(value, name, "a number in (0, 1)")
    if not (0.0 < val < 1.0):
        raise LabkitError(f"{name} must lie strictly between 0 and 1, got {value!r}")
    return val


def count(value, name: str, *, minimum: int = 1, maximum: int | None = None) -> int:
    """Return ``value`` as int, raising unless it is a whole number in [minimum, maximum].

    Integral floats (``20.0``) are accepted; ``20.5``, ``'20'``, ``True`` and NaN are
    refused instead of being truncated or coerced.
    """
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise LabkitError(f"{name} must be a whole number >= {minimum}, got {value!r} ({type(value).__name__})")
    try:
        val = operator.index(value)  # int, numpy integer
    except TypeError:
        if not isinstance(value, numbers.Real) or not np.isfinite(value) or float(value) != int(value):
            raise LabkitError(f"{name} must be a whole number >= {minimum}, got {value!r}") from None
        val = int(value)
    if val < minimum or (maximum is not None and val > maximum):
        upper = "" if maximum is None else f" and <= {maximum}"
        raise LabkitError(f"{name} must be a whole number >= {minimum}{upper}, got {value!r}")
    return int(val)


def flag(value, name: str) -> bool:
    """Return ``value`` as bool; only True/False (or 0/1) are accepted, not any truthy object like ``'no'``."""
    if isinstance(value, (bool, np.bool_)) or (isinstance(value, numbers.Integral) and value in (0, 1)):
        return bool(value)
    raise LabkitError(f"{name} must be True or False, got {value!r}")


def as_seed(seed, name: str = "seed") -> int | None:
    """A random seed: None or a whole number >= 0 (numpy refuses negative seeds)."""
    return None if seed is None else count(seed, name, minimum=0)


def as_rng(rng) -> np.random.Generator:
    """Return a ``numpy.random.Generator`` from an int seed (>= 0), a Generator or None."""
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, np.random.SeedSequence):
        return np.random.default_rng(rng)
    if rng is None or (isinstance(rng, numbers.Integral) and not isinstance(rng, (bool, np.bool_))):
        return np.random.default_rng(as_seed(rng, "rng"))
    raise LabkitError(f"rng must be an int >= 0, a numpy.random.Generator or None, got {type(rng).__name__}")


def output_folder(path, name: str = "folder"):
    """``path`` as a Path for a folder to write into: a path-like that is not an existing file."""
    import os
    from pathlib import Path

    if not isinstance(path, (str, os.PathLike)) or not str(path).strip():
        raise LabkitError(f"{name} must be a folder path (str or Path), got {path!r}")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise LabkitError(f"{name} {path} is a file, not a folder: give a folder path")
    return path


def choice(value, allowed, name: str):
    """Return ``value`` if it is one of ``allowed``; otherwise raise naming the options."""
    try:
        ok = value in allowed
    except TypeError:  # e.g. an unhashable value against a set
        ok = False
    if not ok or isinstance(value, (bool, np.bool_)) and not any(isinstance(a, (bool, np.bool_)) for a in allowed):
        options = ", ".join(repr(a) for a in allowed)
        raise LabkitError(f"{name} must be one of {options}; got {value!r}")
    return value
