"""A sphere target in a room scanned by a 16-beam multi-beam lidar (Velodyne VLP-16 type).

Unlike :func:`labkit.synthetic.room_scene` (points uniform per area), this
generator casts the scanner's rays: 16 beams at elevations -15..+15 deg every
2 deg, one point per beam every ``azimuth_step`` degrees, the first surface hit
along each ray, range noise along the ray. So every scan line is a ring, the
sphere is hit by only a few rings, nearer surfaces occlude farther ones, and
a k-nearest neighbourhood holds points of one or two rings - the structure of
real multi-beam scans that notebook 02 discusses.

Scene: a box room (walls, floor, ceiling) around the scanner, a table, a
person-sized cylinder and, on a thin stand, a sphere of radius 0.15-0.35 m at
1-8 m from the scanner. The distance is limited so that the sphere spans at
least ``min_rings`` scan lines (a sphere seen by one ring is a circle: not
determined). ``sphere=False`` gives the same room (same draws) without the
sphere and its stand. Frame: scanner-centred, the station at the origin, z up;
metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.checks import as_rng, positive
from ..core.report import fmt
from ..core.errors import LabkitError
from ._scene import SphereScanMixin

LABEL_NAMES = ("sphere", "walls", "floor", "ceiling", "table", "person", "stand")
SPHERE, WALLS, FLOOR, CEILING, TABLE, PERSON, STAND = range(7)

VLP16_ELEVATIONS = np.arange(-15.0, 15.5, 2.0)  # deg, the 16 beams of a VLP-16
_ROOM_HEIGHT = 3.0
_STAND_R = 0.02
_TABLE_SIZE = np.array([1.2, 0.8, 0.04])
_TABLE_HEIGHT = 0.75
_LEG = 0.05


@dataclass(frozen=True, eq=False, repr=False)
class MultibeamScene(SphereScanMixin):
    """A synthetic 16-beam scan of a room with (or without) a sphere target.

    Attributes
    ----------
    points : ndarray (n, 3)
        Scanned coordinates (m), scanner-centred (station at the origin).
    sphere : ndarray (4,)
        True sphere [xc, yc, zc, r] (also given when ``has_sphere`` is False:
        where it would have been).
    has_sphere : bool
    is_sphere : ndarray of bool (n,)
    labels : ndarray of int (n,)
        0 sphere, 1 walls, 2 floor, 3 ceiling, 4 table, 5 person, 6 stand.
    label_names : tuple of str
    ring : ndarray of int (n,)
        Beam index 0..15 (elevation -15 .. +15 deg).
    station : ndarray (3,)
        Scanner position (the origin).
    noise : float
        Standard deviation of the range noise (m).

    Examples
    --------
    >>> from labkit.synthetic import multibeam_room
    >>> scene = multibeam_room(rng=0)
    >>> type(scene).__name__, scene.points.shape[1], bool(scene.is_sphere.any())
    ('MultibeamScene', 3, True)
    """

    points: np.ndarray
    sphere: np.ndarray
    has_sphere: bool
    is_sphere: np.ndarray
    labels: np.ndarray
    label_names: tuple
    ring: np.ndarray
    station: np.ndarray
    noise: float

    @property
    def n_sphere_rings(self) -> int:
        """Number of scan lines that hit the sphere."""
        return int(np.unique(self.ring[self.is_sphere]).size)

    def _report(self):
        counts = np.bincount(self.labels, minlength=len(LABEL_NAMES))
        rows = [
            ("points", f"{self.n}"),
            ("sphere", (fmt(self.sphere, 3, "m") if self.has_sphere else "none (room only)")),
            ("distance", fmt(float(np.linalg.norm(self.sphere[:3] - self.station)), 2, "m")),
            ("rings on the sphere", f"{self.n_sphere_rings}"),
            ("range noise", fmt(self.noise * 1e3, 1, "mm")),
        ]
        rows += [(name, f"{c}") for name, c in zip(LABEL_NAMES, counts)]
        return "Synthetic 16-beam scan of a room", [("", rows)]


def multibeam_room(
    rng=None,
    *,
    sphere: bool = True,
    radius_range=(0.15, 0.35),
    distance_range=(1.0, 8.0),
    min_rings: int = 3,
    noise: float = 0.01,
    azimuth_step: float = 0.2,
) -> MultibeamScene:
    """Simulate one 16-beam lidar scan of a furnished room with a sphere target.

    Parameters
    ----------
    rng : int or numpy.random.Generator, optional
        Seed; the same seed gives the same room with and without the sphere.
    sphere : bool
        Place the sphere (and its stand) in the room.
    radius_range : (float, float)
        Radius of the sphere (m), drawn uniformly.
    distance_range : (float, float)
        Distance of the sphere centre from the scanner (m), drawn uniformly
        and capped so that the sphere spans at least ``min_rings`` scan lines.
    min_rings : int
        Scan lines the sphere must span (2 deg apart).
    noise : float
        Standard deviation of the range noise along each ray (m).
    azimuth_step : float
        Horizontal angle between two shots of one beam (deg); 0.2 is a VLP-16 at 10 Hz.

    Returns
    -------
    MultibeamScene

    Examples
    --------
    >>> from labkit.synthetic import multibeam_room
    >>> scene = multibeam_room(rng=0)
    >>> scene.points.shape[1], scene.has_sphere, scene.n_sphere_rings >= 3
    (3, True, True)
    """
    gen = as_rng(rng)
    r_lo, r_hi = _pair(radius_range, "radius_range")
    d_lo, d_hi = _pair(distance_range, "distance_range")
    noise = positive(noise, "noise")
    step = positive(azimuth_step, "azimuth_step")
    if step > 5:
        raise LabkitError(f"azimuth_step must be at most 5 deg, got {azimuth_step!r}")
    if isinstance(min_rings, bool) or int(min_rings) != min_rings or not 1 <= min_rings <= 8:
        raise LabkitError(f"min_rings must be a whole number in 1..8, got {min_rings!r}")

    # Sphere: radius, distance (so that it spans min_rings lines), direction; the scanner height
    radius = gen.uniform(r_lo, r_hi)
    d_cap = radius / np.sin(np.radians(min_rings * 1.0 + 0.5))
    distance = gen.uniform(d_lo, max(d_lo, min(d_hi, d_cap)))
    half = np.degrees(np.arcsin(min(radius / distance, 0.99)))
    scanner_h = gen.uniform(0.8, 1.6)  # above the floor
    lo_el = np.degrees(np.arcsin(np.clip((-scanner_h + radius + 0.15) / distance, -1, 1)))
    el = gen.uniform(max(-10.0 + half / 2, lo_el), max(10.0 - half / 2, lo_el + 0.1))
    az = gen.uniform(0, 2 * np.pi)
    e, a = np.radians(el), az
    centre = distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    # Room around scanner and sphere; table and person away from the line of sight
    lo = np.minimum(-gen.uniform(2.0, 6.0, 2), centre[:2] - radius - gen.uniform(0.5, 2.0, 2))
    hi = np.maximum(gen.uniform(2.0, 6.0, 2), centre[:2] + radius + gen.uniform(0.5, 2.0, 2))
    room = (np.array([lo[0], lo[1], -scanner_h]), np.array([hi[0], hi[1], _ROOM_HEIGHT - scanner_h]))
    table_xy = _free_spot(gen, lo, hi, az, 0.8)
    person_xy = _free_spot(gen, lo, hi, az, 0.4)
    person_r = gen.uniform(0.18, 0.25)

    # Rays of the 16 beams and the first hit of each
    azimuths = np.radians(np.arange(0.0, 360.0, step) + gen.uniform(0, step))
    elev = np.radians(VLP16_ELEVATIONS)
    E, A = np.meshgrid(elev, azimuths, indexing="ij")
    U = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    ring = np.repeat(np.arange(len(elev)), len(azimuths))
    t, label = _room_hits(U, room)
    floor_z = -scanner_h
    table_lo = np.array([table_xy[0] - _TABLE_SIZE[0] / 2, table_xy[1] - _TABLE_SIZE[1] / 2,
                         floor_z + _TABLE_HEIGHT - _TABLE_SIZE[2]])
    boxes = [(table_lo, table_lo + _TABLE_SIZE, TABLE)]
    for dx in (0.05, _TABLE_SIZE[0] - 0.1):
        for dy in (0.05, _TABLE_SIZE[1] - 0.1):
            leg_lo = np.array([table_lo[0] + dx, table_lo[1] + dy, floor_z])
            boxes.append((leg_lo, leg_lo + np.array([_LEG, _LEG, _TABLE_HEIGHT - _TABLE_SIZE[2]]), TABLE))
    for b_lo, b_hi, lab in boxes:
        t, label = _closer(t, label, _box_hits(U, b_lo, b_hi), lab)
    t, label = _closer(t, label, _cylinder_hits(U, person_xy, person_r, floor_z, floor_z + 1.75), PERSON)
    if sphere:
        t, label = _closer(t, label, _sphere_hits(U, centre, radius), SPHERE)
        t, label = _closer(t, label, _cylinder_hits(U, centre[:2], _STAND_R, floor_z, centre[2] - radius), STAND)

    # Points with range noise along the ray
    ok = np.isfinite(t)
    t = t[ok] + noise * gen.standard_normal(int(ok.sum()))
    points = U[ok] * t[:, None]
    label, ring = label[ok], ring[ok]
    return MultibeamScene(
        points=points, sphere=np.append(centre, radius), has_sphere=bool(sphere), is_sphere=label == SPHERE,
        labels=label, label_names=LABEL_NAMES, ring=ring, station=np.zeros(3), noise=noise,
    )


def _pair(value, name):
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be a pair (low, high), got {value!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
        raise LabkitError(f"{name} must satisfy 0 < low <= high, got {value!r}")
    return lo, hi


def _free_spot(gen, lo, hi, sphere_az, clearance):
    """A floor position inside the room, at least 30 deg in azimuth from the sphere and 1 m from the scanner."""
    for _ in range(200):
        xy = gen.uniform(lo + clearance + 0.2, hi - clearance - 0.2)
        diff = np.angle(np.exp(1j * (np.arctan2(xy[1], xy[0]) - sphere_az)))
        if abs(diff) > np.radians(30) and np.linalg.norm(xy) > 1.0:
            return xy
    return 0.5 * (lo + hi) + 0.0  # pragma: no cover - rooms are always large enough


def _closer(t, label, t_new, lab):
    nearer = t_new < t
    return np.where(nearer, t_new, t), np.where(nearer, lab, label)


def _room_hits(U, room):
    """Range to the room's inner faces from the origin, and which face (walls, floor, ceiling)."""
    lo, hi = room
    with np.errstate(divide="ignore", invalid="ignore"):
        T = np.where(U > 0, hi / U, np.where(U < 0, lo / U, np.inf))
    axis = np.argmin(T, axis=1)
    t = T[np.arange(len(U)), axis]
    label = np.where(axis < 2, WALLS, np.where(U[:, 2] < 0, FLOOR, CEILING))
    return t, label


def _box_hits(U, lo, hi):
    """Range to an axis-parallel box seen from outside (slab method); inf where missed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = lo / U, hi / U
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((near <= far) & (near > 0), near, np.inf)


def _cylinder_hits(U, xy, r, z0, z1):
    """Range to a vertical cylinder (side and top) from the origin; inf where missed."""
    a = U[:, 0] ** 2 + U[:, 1] ** 2
    b = -2.0 * (U[:, :2] @ xy)
    c = xy @ xy - r * r
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    z = t * U[:, 2]
    side = np.where((disc > 0) & (t > 0) & (z >= z0) & (z <= z1), t, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = z1 / U[:, 2]
    p = U[:, :2] * tt[:, None] - xy
    top = np.where((tt > 0) & (np.einsum("ij,ij->i", p, p) <= r * r), tt, np.inf)
    return np.minimum(side, top)


def _sphere_hits(U, c, r):
    """Range to the near side of a sphere from the origin; inf where missed."""
    uc = U @ c
    disc = uc * uc - (c @ c - r * r)
    t = uc - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc > 0) & (t > 0), t, np.inf)
