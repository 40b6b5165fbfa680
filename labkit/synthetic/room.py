"""A sphere target in a scanned room: the needle-in-a-haystack case for RANSAC.

One TLS station inside a furnished room sees walls, floor, ceiling, a table,
a cabinet, a crate, a thin stand and, on that stand, a sphere of about 30 cm
radius that makes up only a few per cent of the points. Uniform 4-point
sampling needs about ``(1/share)^4`` samples here; notebook 02 uses this scene
to motivate local sampling.

Simplifications (stated, not hidden): points are uniform per unit area on
every surface the station faces, occlusion is ignored, and the noise is
isotropic Gaussian. Frame: floor at z = 0, room corner at the origin; metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.checks import as_rng, positive
from ..core.report import fmt
from ..core.errors import LabkitError
from ._geometry import sphere_cap
from ._scene import SphereScanMixin

LABEL_NAMES = ("sphere", "walls", "floor", "ceiling", "furniture", "stand", "clutter")
SPHERE, WALLS, FLOOR, CEILING, FURNITURE, STAND, CLUTTER = range(7)

_ROOM = np.array([6.0, 4.5, 2.8])  # length, width, height (m)
_STATION = np.array([1.6, 1.3, 1.55])
_STAND_R = 0.025
_CLUTTER_SHARE = 0.01  # share of the non-sphere points scattered in the room volume
_MAX_INCIDENCE = np.radians(80.0)
# furniture boxes (lower corner, upper corner), metres
_TABLE_TOP = (np.array([0.9, 2.9, 0.72]), np.array([2.5, 3.8, 0.76]))
_TABLE_LEG = np.array([0.05, 0.05, 0.72])
_CABINET = (np.array([5.4, 0.3, 0.0]), np.array([6.0, 1.5, 2.0]))
_CRATE = (np.array([2.9, 0.3, 0.0]), np.array([3.5, 0.9, 0.5]))


@dataclass(frozen=True, eq=False, repr=False)
class RoomScene(SphereScanMixin):
    """A synthetic TLS scan of a room with one sphere target.

    Attributes
    ----------
    points : ndarray (n, 3)
        Scanned coordinates with noise, metres (shuffled).
    sphere : ndarray (4,)
        True sphere [xc, yc, zc, r].
    is_sphere : ndarray of bool (n,)
        True for points on the sphere surface.
    labels : ndarray of int (n,)
        0 sphere, 1 walls, 2 floor, 3 ceiling, 4 furniture, 5 stand, 6 clutter.
    label_names : tuple of str
    station : ndarray (3,)
        Scanner position.
    noise : float
        Standard deviation of the noise per coordinate (m).
    """

    points: np.ndarray
    sphere: np.ndarray
    is_sphere: np.ndarray
    labels: np.ndarray
    label_names: tuple
    station: np.ndarray
    noise: float

    def _report(self):
        counts = np.bincount(self.labels, minlength=len(self.label_names))
        return "Sphere in a room (synthetic TLS scan)", [
            ("", [
                ("points", f"{self.n:d}"),
                ("sphere share", f"{100 * self.is_sphere.mean():.2f} %"),
                ("true centre", fmt(self.sphere[:3], 4, "m")),
                ("true radius", fmt(self.sphere[3], 4, "m")),
                ("noise", f"{self.noise * 1e3:.2f} mm"),
            ]),
            ("Points per label", [(name, f"{c:d}") for name, c in zip(self.label_names, counts)]),
        ]


def room_scene(
    n_points: int = 20000,
    sphere_share: float = 0.02,
    radius: float = 0.3,
    noise: float = 0.002,
    rng=None,
) -> RoomScene:
    """Simulate one TLS station in a furnished room with a sphere on a stand.

    Parameters
    ----------
    n_points : int
        Total number of points (>= 100).
    sphere_share : float
        Share of the points on the sphere, in [0, 0.5]; 0 gives a room without
        a sphere (for testing that RANSAC reports "not found").
    radius : float
        Sphere radius in metres, at most 0.6 (so the sphere fits its place).
    noise : float
        Standard deviation of the Gaussian noise per coordinate (m).
    rng : int or numpy.random.Generator, optional
        Seed or generator; the sphere position and every point depend on it.

    Returns
    -------
    RoomScene

    Examples
    --------
    >>> from labkit.synthetic import room_scene
    >>> scene = room_scene(n_points=5000, rng=0)
    >>> scene.points.shape
    (5000, 3)
    """
    rng = as_rng(rng)
    n_sphere, n_clutter, n_surface = _counts(n_points, sphere_share)
    radius = positive(radius, "radius")
    if radius > 0.6:
        raise LabkitError(f"radius must be at most 0.6 m to fit the room, got {radius!r}")
    noise = float(noise)
    if not np.isfinite(noise) or noise < 0:
        raise LabkitError(f"noise must be a finite number >= 0, got {noise!r}")

    # The sphere on its stand, somewhere in the free corner of the room
    centre = np.array([rng.uniform(3.9, 4.7), rng.uniform(2.6, 3.4), rng.uniform(1.0, 1.5)])
    station = _STATION.copy()

    # Noise-free points: surfaces by area, the visible sphere cap, clutter
    rects, rect_labels = _rectangles(station, centre, radius)
    per_rect = _split(n_surface, [_area(r) for r in rects])
    parts = [_on_rectangle(rng, m, r) for m, r in zip(per_rect, rects)]
    parts += [sphere_cap(rng, n_sphere, centre, radius, station, _MAX_INCIDENCE), rng.uniform(0.0, _ROOM, size=(n_clutter, 3))]
    labels = np.concatenate([np.repeat(rect_labels, per_rect), np.full(n_sphere, SPHERE), np.full(n_clutter, CLUTTER)])
    clean = np.concatenate(parts, axis=0)

    # Noise and shuffle
    points = clean + rng.normal(0.0, noise, size=clean.shape)
    order = rng.permutation(len(points))
    return RoomScene(
        points=points[order],
        sphere=np.concatenate([centre, [radius]]),
        is_sphere=labels[order] == SPHERE,
        labels=labels[order],
        label_names=LABEL_NAMES,
        station=station,
        noise=noise,
    )


# ----------------------------------------------------------------- counts
def _counts(n_points, sphere_share):
    if isinstance(n_points, bool) or int(n_points) != n_points or n_points < 100:
        raise LabkitError(f"n_points must be a whole number >= 100, got {n_points!r}")
    share = float(sphere_share)
    if not (0.0 <= share <= 0.5):
        raise LabkitError(f"sphere_share must lie in [0, 0.5], got {sphere_share!r}")
    n_sphere = int(round(share * n_points))
    n_clutter = int(round(_CLUTTER_SHARE * (n_points - n_sphere)))
    return n_sphere, n_clutter, int(n_points) - n_sphere - n_clutter


def _split(n, weights):
    """Split n into integer parts proportional to ``weights`` (largest remainders)."""
    w = np.asarray(weights, dtype=np.float64) / np.sum(weights)
    parts = np.floor(n * w).astype(int)
    rest = n - parts.sum()
    parts[np.argsort(-(n * w - parts))[:rest]] += 1
    return parts


# ----------------------------------------------------------------- geometry
# A rectangle is (origin, edge a, edge b); points are origin + u a + v b.
def _area(rect):
    _, a, b = rect
    return float(np.linalg.norm(np.cross(a, b)))


def _on_rectangle(rng, n, rect):
    o, a, b = rect
    uv = rng.random((n, 2))
    return o + uv[:, :1] * a + uv[:, 1:] * b


def _box_faces(lo, hi, station):
    """The faces of an axis-aligned box that the station looks at (outward normal towards it)."""
    faces = []
    size = hi - lo
    for axis in range(3):
        i, j = [k for k in range(3) if k != axis]
        a, b = np.zeros(3), np.zeros(3)
        a[i], b[j] = size[i], size[j]
        for side, plane in ((-1.0, lo[axis]), (1.0, hi[axis])):
            if side * (station[axis] - plane) > 0 and size[i] > 0 and size[j] > 0:
                o = lo.copy()
                o[axis] = plane
                faces.append((o, a, b))
    return faces


def _rectangles(station, centre, radius):
    """All scanned flat surfaces with their labels, and the stand (a thin box)."""
    L, W, H = _ROOM
    rects = [
        (np.zeros(3), np.array([L, 0, 0]), np.array([0, 0, H])),  # wall y = 0
        (np.array([0, W, 0]), np.array([L, 0, 0]), np.array([0, 0, H])),  # wall y = W
        (np.zeros(3), np.array([0, W, 0]), np.array([0, 0, H])),  # wall x = 0
        (np.array([L, 0, 0]), np.array([0, W, 0]), np.array([0, 0, H])),  # wall x = L
        (np.zeros(3), np.array([L, 0, 0]), np.array([0, W, 0])),  # floor
        (np.array([0, 0, H]), np.array([L, 0, 0]), np.array([0, W, 0])),  # ceiling
    ]
    labels = [WALLS] * 4 + [FLOOR, CEILING]
    furniture = _box_faces(*_TABLE_TOP, station) + _box_faces(*_CABINET, station) + _box_faces(*_CRATE, station)
    lo_top = _TABLE_TOP[0]
    for dx, dy in ((0.05, 0.05), (1.5, 0.05), (0.05, 0.8), (1.5, 0.8)):
        leg_lo = np.array([lo_top[0] + dx, lo_top[1] + dy, 0.0])
        furniture += _box_faces(leg_lo, leg_lo + _TABLE_LEG, station)
    rects += furniture
    labels += [FURNITURE] * len(furniture)
    stand_lo = np.array([centre[0] - _STAND_R, centre[1] - _STAND_R, 0.0])
    stand_hi = np.array([centre[0] + _STAND_R, centre[1] + _STAND_R, centre[2] - radius])
    stand = _box_faces(stand_lo, stand_hi, station)
    return rects + stand, np.array(labels + [STAND] * len(stand))
