"""Boxes, polygons and class codes: checking them and masking points with them.

Shared by the crops of :mod:`labkit.regions` and the read filter of
:mod:`labkit.io` (which applies them to every chunk of a large file). Masks take
coordinates as they are; the crops reduce them to a local origin first.
"""

from __future__ import annotations

import numpy as np

from .errors import LabkitError

#: Names of the ASPRS class codes (LAS 1.4 specification); codes 19-63 are reserved, 64-255 user defined.
ASPRS_NAMES = {
    0: "never classified", 1: "unclassified", 2: "ground", 3: "low vegetation", 4: "medium vegetation",
    5: "high vegetation", 6: "building", 7: "low point (noise)", 8: "model key point", 9: "water", 10: "rail",
    11: "road surface", 12: "overlap", 13: "wire guard", 14: "wire conductor", 15: "transmission tower",
    16: "wire connector", 17: "bridge deck", 18: "high noise",
}
#: The classes that stay put between epochs: ground, building, road surface (what ``icp-classes`` matches on).
STABLE_CLASSES = (2, 6, 11)


# ----------------------------------------------------------------------------- region checks
def as_bbox(bbox) -> np.ndarray:
    """Return a box as a (2, d) array [[min...], [max...]] with d = 2 (xy) or 3 (xyz).

    Accepted: ``(xmin, ymin, xmax, ymax)``, ``(xmin, ymin, zmin, xmax, ymax, zmax)``
    or a (2, 2) / (2, 3) array such as :attr:`PointCloud.bounds`.

    Examples
    --------
    >>> from labkit.core.masks import as_bbox
    >>> as_bbox((0, 0, 10, 5)).tolist()
    [[0.0, 0.0], [10.0, 5.0]]
    >>> as_bbox((0, 0, -1, 10, 5, 1)).tolist()
    [[0.0, 0.0, -1.0], [10.0, 5.0, 1.0]]
    """
    try:
        arr = np.asarray(bbox, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"bbox must be numbers (xmin, ymin, xmax, ymax), got {bbox!r}") from None
    if arr.shape in ((4,), (6,)):
        arr = arr.reshape(2, -1)
    if arr.shape not in ((2, 2), (2, 3)):
        raise LabkitError(
            "bbox must be (xmin, ymin, xmax, ymax), (xmin, ymin, zmin, xmax, ymax, zmax) "
            f"or a (2, 2)/(2, 3) [min, max] array; got shape {np.shape(bbox)}"
        )
    if not np.isfinite(arr).all() or (arr[0] > arr[1]).any():
        raise LabkitError(f"bbox needs finite values with min <= max in every axis, got {arr.ravel().tolist()}")
    return arr


def as_rings(polygon) -> list[np.ndarray]:
    """Return a polygon as a list of (m, 2) float64 rings (each with m >= 3 vertices).

    ``polygon`` is one ring ((m, 2) or (m, 3) array-like; z is ignored) or a list of
    rings (outer boundary and holes; the even-odd rule decides what is inside).
    A closing vertex equal to the first one may be given or omitted.

    Examples
    --------
    >>> from labkit.core.masks import as_rings
    >>> rings = as_rings([(0, 0), (4, 0), (4, 3)])
    >>> len(rings), rings[0].shape
    (1, (3, 2))
    """
    try:
        single = np.asarray(polygon, dtype=np.float64)
        rings = [single] if single.ndim == 2 else None
    except (TypeError, ValueError):
        rings = None
    if rings is None:
        try:
            rings = [np.asarray(r, dtype=np.float64) for r in polygon]
        except (TypeError, ValueError):
            raise LabkitError("polygon must be an (m, 2) array of vertices or a list of such rings") from None
    out = []
    for ring in rings:
        if ring.ndim != 2 or ring.shape[1] not in (2, 3) or len(ring) < 3:
            raise LabkitError(f"each polygon ring must be an (m, 2) vertex array with m >= 3, got shape {ring.shape}")
        if not np.isfinite(ring).all():
            raise LabkitError("polygon vertices must be finite numbers")
        out.append(ring[:, :2])
    return out


def as_classes(classes) -> np.ndarray:
    """Return class codes as a sorted int array (a single int is accepted); codes lie in 0..255 (LAS).

    Examples
    --------
    >>> from labkit.core.masks import as_classes
    >>> as_classes(2).tolist(), as_classes([6, 2, 2]).tolist()
    ([2], [2, 6])
    """
    if isinstance(classes, (str, bytes)):
        raise LabkitError(f"classes must be one or more integer class codes (ASPRS), got the string {classes!r}")
    arr = np.unique(np.atleast_1d(np.asarray(classes)))
    if arr.size == 0 or not np.issubdtype(arr.dtype, np.integer):
        raise LabkitError(f"classes must be one or more integer class codes (ASPRS), got {classes!r}")
    if arr.min() < 0 or arr.max() > 255:
        raise LabkitError(f"class codes lie in 0..255 (LAS classification), got {arr.tolist()}")
    return arr.astype(np.int64)


# ----------------------------------------------------------------------------- masks
def box_mask(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    """True for points inside the closed box ``box`` (from :func:`as_bbox`).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.core.masks import as_bbox, box_mask
    >>> xyz = np.array([[1.0, 1, 0], [5, 1, 0], [1, 9, 0]])
    >>> box_mask(xyz, as_bbox((0, 0, 2, 2))).tolist()
    [True, False, False]
    """
    d = box.shape[1]
    return np.all((xyz[:, :d] >= box[0]) & (xyz[:, :d] <= box[1]), axis=1)


def circle_mask(xyz: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """True for points whose horizontal distance to ``centre`` (x, y) is at most ``radius``.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.core.masks import circle_mask
    >>> xyz = np.array([[0.5, 0, 9.0], [2.0, 0, 0]])
    >>> circle_mask(xyz, np.array([0.0, 0.0]), 1.0).tolist()
    [True, False]
    """
    dx = xyz[:, 0] - centre[0]
    dy = xyz[:, 1] - centre[1]
    return dx * dx + dy * dy <= radius * radius


def polygon_mask(xyz: np.ndarray, rings: list[np.ndarray]) -> np.ndarray:
    """True for points inside the polygon by the even-odd rule (crossing number).

    A horizontal ray from each point towards +x crosses an edge (a, b) when the
    edge straddles the point's y (half-open: ``(a_y > y) != (b_y > y)``) and the
    crossing abscissa lies right of the point. The loop runs over edges, the
    test over all points at once. Coordinates are reduced to the polygon's first
    vertex so UTM values keep their precision.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.core.masks import as_rings, polygon_mask
    >>> xyz = np.array([[1.0, 1, 0], [3, 1, 0]])
    >>> polygon_mask(xyz, as_rings([(0, 0), (2, 0), (2, 2), (0, 2)])).tolist()
    [True, False]
    """
    origin = rings[0][0]
    lo = np.min([r.min(axis=0) for r in rings], axis=0)
    hi = np.max([r.max(axis=0) for r in rings], axis=0)
    inside = np.zeros(len(xyz), dtype=bool)
    near = np.flatnonzero(np.all((xyz[:, :2] >= lo) & (xyz[:, :2] <= hi), axis=1))
    if near.size == 0:
        return inside
    px = xyz[near, 0] - origin[0]
    py = xyz[near, 1] - origin[1]
    odd = np.zeros(near.size, dtype=bool)
    for ring in rings:
        a = ring - origin
        b = np.roll(a, -1, axis=0)
        for (ax, ay), (bx, by) in zip(a, b):
            if ay == by:
                continue  # horizontal edges never cross a horizontal ray
            straddle = (ay > py) != (by > py)
            x_cross = ax + (py - ay) * (bx - ax) / (by - ay)
            odd ^= straddle & (px < x_cross)
    inside[near] = odd
    return inside


def class_mask(classification: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """True for points whose class is one of ``classes``.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.core.masks import class_mask
    >>> class_mask(np.array([2, 5, 6, 2]), np.array([2, 6])).tolist()
    [True, False, True, True]
    """
    return np.isin(classification, classes)
