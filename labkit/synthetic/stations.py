"""Terrestrial laser scans of a hall with sphere targets from several stations, with known poses.

A hall (ground z = 0, four walls, a ceiling at 5 m) holds six sphere targets of
radius 0.1 m on thin poles, a decoy ball of another size on a pole, three
bare poles (one as thick as a target) and a crate. A panorama scanner stands
at ``n_stations`` set-ups near the middle; each set-up is levelled only
approximately (a small tilt) and turned about z at random.

Each scan is ring-free, as from a TLS: one shot per cell of a regular
zenith/azimuth grid with random jitter inside the cell, the first surface hit
along the ray, and the noise in the scanner's polar frame: range noise along
the ray plus angle noise of both angles. The points are given in each
scanner's own frame (the station at its origin); ``poses[i]`` maps scan i into
the hall's (world) frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from ..core.checks import as_rng, count, positive
from ..core.report import ReportMixin, fmt
from ..core.errors import LabkitError
from ._raycast import box_hits, ceiling_hits, cylinder_hits, first_hits, ground_hits, sphere_hits, wall_hits

LABEL_NAMES = ("ground", "wall", "target", "pole", "decoy", "crate", "ceiling")
GROUND, WALL, TARGET, POLE, DECOY, CRATE, CEILING = range(7)

_YARD = (12.0, 9.0, 5.0)  # half length x, half width y, height (m)
_POLE_R = 0.02  # radius of the poles that carry the targets and the decoy (m)
_ZENITH = (np.radians(30.0), np.radians(155.0))  # the scanner's field of view below its zenith
_CHUNK = 250_000  # rays cast at once


@dataclass(frozen=True, eq=False, repr=False)
class TargetStations(ReportMixin):
    """Scans of a hall with sphere targets from several stations (see :func:`target_stations`).

    Attributes
    ----------
    scans : tuple of ndarray (n_i, 3)
        Points of each scan in its scanner's own frame (station at the origin), m.
    poses : ndarray (k, 4, 4)
        True pose of each scan: world = poses[i] @ [scan point, 1].
    centers : ndarray (m, 3)
        True target centres in the world frame (m).
    radii : ndarray (m,)
        True target radii (m).
    hits : ndarray of int (k, m)
        Points of scan i on target j.
    visible : ndarray of bool (k, m)
        Target j is seen by scan i with at least ``min_hits`` points.
    labels : tuple of ndarray of int (n_i,)
        What each point hit: 0 ground, 1 wall, 2 target, 3 pole, 4 decoy, 5 crate, 6 ceiling.
    target : tuple of ndarray of int (n_i,)
        Index of the target a point lies on, -1 elsewhere.
    decoy : ndarray (4,)
        The decoy ball [x, y, z, r] in the world frame.
    range_noise, angle_noise : float
        Standard deviations of the range (m) and of both angles (rad).
    min_hits : int
        Points a target needs to count as visible.

    Examples
    --------
    >>> from labkit.synthetic import target_stations
    >>> yard = target_stations(n_stations=2, n_points=100_000, rng=0)
    >>> len(yard.scans), yard.poses.shape, yard.centers.shape, yard.radii.tolist()[:2]
    (2, (2, 4, 4), (6, 3), [0.1, 0.1])
    """

    scans: tuple
    poses: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    hits: np.ndarray
    visible: np.ndarray
    labels: tuple
    target: tuple
    decoy: np.ndarray
    range_noise: float
    angle_noise: float
    min_hits: int

    @property
    def n_stations(self) -> int:
        return len(self.scans)

    @property
    def stations(self) -> np.ndarray:
        """Station positions in the world frame, (k, 3)."""
        return self.poses[:, :3, 3].copy()

    def centers_in_scan(self, i: int) -> np.ndarray:
        """True target centres in the frame of scan i, (m, 3)."""
        R, t = self.poses[i, :3, :3], self.poses[i, :3, 3]
        return (self.centers - t) @ R

    def _report(self):
        rows = [
            ("stations", f"{self.n_stations}"),
            ("points per scan", ", ".join(f"{len(s)}" for s in self.scans)),
            ("targets", f"{len(self.radii)} of radius {fmt(self.radii.mean(), 3, 'm')}"),
            ("decoy ball radius", fmt(self.decoy[3], 3, "m")),
            ("targets visible per scan", ", ".join(f"{int(v.sum())}" for v in self.visible)),
            ("range noise", fmt(self.range_noise * 1e3, 1, "mm")),
            ("angle noise", fmt(self.angle_noise * 1e6, 0, "urad")),
        ]
        return "Synthetic TLS scans of sphere targets from several stations", [("", rows)]


def target_stations(
    n_stations: int = 4,
    n_points: int = 1_000_000,
    rng=None,
    *,
    target_radius: float = 0.1,
    decoy_radius: float = 0.15,
    range_noise: float = 0.002,
    angle_noise: float = 5e-5,
    max_tilt: float = 0.5,
    min_hits: int = 30,
) -> TargetStations:
    """Simulate TLS panoramas of six sphere targets in a hall from several stations.

    Parameters
    ----------
    n_stations : int
        Number of set-ups (1..12).
    n_points : int
        Shots per panorama (rays of the zenith/azimuth grid, 30-155 deg below
        the zenith); every shot hits a surface of the closed hall.
    rng : int or numpy.random.Generator, optional
        Seed of the layout, the poses, the grid jitter and the noise.
    target_radius : float
        Radius of the six targets (m).
    decoy_radius : float
        Radius of the decoy ball (m); must differ from ``target_radius`` by 20 %.
    range_noise : float
        Standard deviation of the range along each ray (m).
    angle_noise : float
        Standard deviation of the zenith and azimuth angles (rad).
    max_tilt : float
        Largest tilt of a set-up from the vertical (deg).
    min_hits : int
        Points a target needs to count as visible in a scan.

    Returns
    -------
    TargetStations

    Raises
    ------
    LabkitError
        A count or size out of range, a decoy as large as a target.

    Notes
    -----
    Pose of set-up i: ``world = R_z(yaw) R_tilt p + s`` with the station s
    about 1.5 m above the ground, 1-2.5 m from the middle of the hall; the
    targets stand 4-5.5 m from the middle at 1.0-1.8 m height, so they lie
    2-8 m from each station. A shot in direction (zenith theta, azimuth phi)
    of the scanner frame is cast in the world frame; its measured point is
    ``(rho + e_rho) u(theta + e_theta, phi + e_phi)`` in the scanner frame.

    References
    ----------
    .. [1] Seed 000, introduction: sphere targets scanned on tripods to register
       terrestrial laser scans.
    .. [2] T. Luhmann, S. Robson, S. Kyle, J. Boehm (2020): Close-Range
       Photogrammetry and 3D Imaging, 3rd edition, De Gruyter, section 4.4
       (terrestrial laser scanning: polar measurement and its errors).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import target_stations
    >>> yard = target_stations(n_stations=2, n_points=100_000, rng=0)
    >>> world = yard.scans[0] @ yard.poses[0, :3, :3].T + yard.poses[0, :3, 3]
    >>> on = yard.target[0] == 0
    >>> d = np.linalg.norm(world[on] - yard.centers[0], axis=1) - yard.radii[0]
    >>> bool(np.abs(d).max() < 0.02), yard.scans[0].shape[1]
    (True, 3)
    """
    gen = as_rng(rng)
    n_stations = count(n_stations, "n_stations", minimum=1)
    if n_stations > 12:
        raise LabkitError(f"n_stations must be at most 12, got {n_stations}")
    n_points = count(n_points, "n_points", minimum=1000)
    r_t = positive(target_radius, "target_radius")
    r_d = positive(decoy_radius, "decoy_radius")
    if abs(r_d - r_t) < 0.2 * r_t or not r_t <= 0.3 or not r_d <= 0.3:
        raise LabkitError(f"target_radius and decoy_radius must be <= 0.3 m and differ by 20 %, got {r_t}, {r_d}")
    range_noise = positive(range_noise, "range_noise")
    angle_noise = positive(angle_noise, "angle_noise")
    max_tilt = positive(max_tilt, "max_tilt")
    min_hits = count(min_hits, "min_hits", minimum=1)

    centers, decoy, poles, crate = _layout(gen, r_t, r_d)
    poses = np.array([_pose(gen, k, n_stations, max_tilt) for k in range(n_stations)])
    solids, kinds = _solids(centers, r_t, decoy, poles, crate)
    scans, labels, targets = [], [], []
    for pose in poses:
        points, which = _scan(gen, pose, solids, n_points, range_noise, angle_noise)
        scans.append(points)
        labels.append(kinds[which, 0])
        targets.append(kinds[which, 1])
    hits = np.array([np.bincount(t[t >= 0], minlength=len(centers)) for t in targets]).reshape(n_stations, -1)
    return TargetStations(
        scans=tuple(scans), poses=poses, centers=centers, radii=np.full(len(centers), r_t), hits=hits,
        visible=hits >= min_hits, labels=tuple(labels), target=tuple(targets), decoy=decoy,
        range_noise=range_noise, angle_noise=angle_noise, min_hits=min_hits,
    )


def _layout(gen, r_t, r_d):
    """Target centres (6, 3), decoy [x, y, z, r], bare poles [(x, y, r, height)], crate (centre, size, yaw)."""
    az = np.arange(6) * np.pi / 3 + gen.uniform(-0.2, 0.2, 6)
    dist = gen.uniform(4.0, 5.5, 6)
    centers = np.column_stack([dist * np.cos(az), dist * np.sin(az), gen.uniform(1.0, 1.8, 6)])
    a = az[0] + np.pi / 6  # the decoy between the first two targets
    decoy = np.array([4.8 * np.cos(a), 4.8 * np.sin(a), gen.uniform(1.1, 1.6), r_d])
    poles = []
    for j, r in enumerate((0.03, 0.06, r_t)):  # bare poles, one as thick as a target
        a = az[2 * j + 1] + np.pi / 6
        d = gen.uniform(3.5, 6.5)
        poles.append((d * np.cos(a), d * np.sin(a), r, 2.5))
    a = az[5] + np.pi / 6
    crate = (np.array([7.5 * np.cos(a), 7.5 * np.sin(a), 0.35]), np.array([1.2, 0.8, 0.7]), gen.uniform(0, np.pi))
    return centers, decoy, poles, crate


def _pose(gen, k, n_stations, max_tilt):
    """Scan -> world 4x4: yaw about z at random, a small tilt, the station near the middle of the hall."""
    a = 2 * np.pi * k / n_stations + gen.uniform(-0.3, 0.3)
    d = gen.uniform(1.0, 2.5)
    yaw = gen.uniform(0, 2 * np.pi)
    axis_az, tilt = gen.uniform(0, 2 * np.pi), np.radians(gen.uniform(0, max_tilt))
    axis = np.array([np.cos(axis_az), np.sin(axis_az), 0.0])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_tilt = np.eye(3) + np.sin(tilt) * K + (1 - np.cos(tilt)) * K @ K  # Rodrigues
    c, s = np.cos(yaw), np.sin(yaw)
    R_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R_z @ R_tilt
    T[:3, 3] = [d * np.cos(a), d * np.sin(a), gen.uniform(1.4, 1.7)]
    return T


def _solids(centers, r_t, decoy, poles, crate):
    """The ray-cast callables and, per solid, (label, target index)."""
    solids = [ground_hits, partial(wall_hits, half_x=_YARD[0], half_y=_YARD[1], height=_YARD[2]),
              partial(ceiling_hits, height=_YARD[2])]
    kinds = [(GROUND, -1), (WALL, -1), (CEILING, -1)]
    for j, c in enumerate(centers):
        solids += [partial(sphere_hits, c=c, r=r_t), partial(cylinder_hits, xy=c[:2], r=_POLE_R, z0=0.0, z1=c[2] - r_t)]
        kinds += [(TARGET, j), (POLE, -1)]
    solids += [partial(sphere_hits, c=decoy[:3], r=decoy[3]),
               partial(cylinder_hits, xy=decoy[:2], r=_POLE_R, z0=0.0, z1=decoy[2] - decoy[3])]
    kinds += [(DECOY, -1), (POLE, -1)]
    for x, y, r, h in poles:
        solids.append(partial(cylinder_hits, xy=np.array([x, y]), r=r, z0=0.0, z1=h))
        kinds.append((POLE, -1))
    solids.append(partial(box_hits, centre=crate[0], size=crate[1], yaw=crate[2]))
    kinds.append((CRATE, -1))
    return solids, np.array(kinds + [(-1, -1)])  # the last row: no hit (never returned)


def _scan(gen, pose, solids, n_points, range_noise, angle_noise):
    """One jittered zenith/azimuth panorama: measured points (scanner frame) and the solid each one hit."""
    z0, z1 = _ZENITH
    solid_angle = 2 * np.pi * (np.cos(z0) - np.cos(z1))
    step = np.sqrt(solid_angle / n_points)
    n_az = max(int(round(2 * np.pi / step)), 4)
    n_ze = max(int(round(n_points / n_az)), 2)
    ze = np.arccos(np.linspace(np.cos(z0), np.cos(z1), n_ze + 1))  # rows of equal solid angle
    zen = (ze[:-1] + ze[1:]) / 2
    theta = np.repeat(zen, n_az) + (gen.random(n_ze * n_az) - 0.5) * np.repeat(np.diff(ze), n_az) * 0.5
    phi = (np.tile(np.arange(n_az), n_ze) + 0.5 + (gen.random(n_ze * n_az) - 0.5) * 0.5) * (2 * np.pi / n_az)
    R, o = pose[:3, :3], pose[:3, 3]
    rho = np.empty(len(theta))
    which = np.empty(len(theta), dtype=np.int64)
    for lo in range(0, len(theta), _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        D = _directions(theta[sl], phi[sl]) @ R.T
        rho[sl], which[sl] = first_hits(o, D, solids)
    ok = which >= 0
    m = int(ok.sum())
    # noise in the polar frame of the scanner: range along the ray, zenith and azimuth angles
    rho_m = rho[ok] + range_noise * gen.standard_normal(m)
    U = _directions(theta[ok] + angle_noise * gen.standard_normal(m), phi[ok] + angle_noise * gen.standard_normal(m))
    return U * rho_m[:, None], which[ok]


def _directions(theta, phi):
    s = np.sin(theta)
    return np.column_stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)])
