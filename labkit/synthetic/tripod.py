"""A terrestrial laser scan of a sphere target on a tripod, with known truth.

The scene mimics what a TLS station sees of a reference sphere: only the cap
facing the scanner, three tripod legs (their visible halves), the tripod head
with tribrach and adapter, a patch of ground and random clutter. Everything is
generated in one vectorized pass, so 10^6 points take a fraction of a second.

Frame: ground at z = 0, the tripod axis is the z axis; metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.checks import as_rng, count, non_negative, positive
from ..core.report import fmt
from ..core.errors import LabkitError
from ._geometry import sphere_cap, unit
from ._scene import SphereScanMixin

LABEL_NAMES = ("sphere", "tripod legs", "base plate", "ground", "clutter")
SPHERE, LEGS, BASE, GROUND, CLUTTER = range(5)

UTM_OFFSET = np.array([600_000.0, 5_400_000.0, 300.0])

# Geometry of the target (metres)
_HEAD_Z = 1.30  # top of the tripod head plate
_HEAD_R = 0.085  # radius of the head plate
_PLATE_T = 0.02  # plate thickness
_TRIBRACH_R, _TRIBRACH_H = 0.06, 0.05
_STEM_R, _STEM_H = 0.012, 0.03
_LEG_R, _LEG_TOP_R, _LEG_FOOT_R = 0.018, 0.07, 0.60
_GROUND_HALF = 1.5
_STATION = np.array([7.0, -4.0, 1.65])  # scanner position relative to the tripod
_MAX_INCIDENCE = np.radians(80.0)  # points beyond this incidence are not returned
# share of the non-sphere points when none is set explicitly
_STRUCTURE_SHARE = {LEGS: 1.2, BASE: 0.5, GROUND: 1.5}


@dataclass(frozen=True, eq=False, repr=False)
class TripodScene(SphereScanMixin):
    """A synthetic TLS scan of a sphere target on a tripod.

    Attributes
    ----------
    points : ndarray (n, 3)
        Scanned coordinates with noise, metres (shuffled).
    sphere : ndarray (4,)
        True sphere [xc, yc, zc, r] in the frame of ``points``.
    is_sphere : ndarray of bool (n,)
        True for points scanned on the sphere surface.
    labels : ndarray of int (n,)
        0 sphere, 1 tripod legs, 2 base plate, 3 ground, 4 clutter.
    label_names : tuple of str
        Names of the labels, indexed by label.
    station : ndarray (3,)
        Scanner position in the frame of ``points``.
    noise : float
        Standard deviation of the noise across the beam (m).
    range_noise : float
        Standard deviation of the noise along the beam (m); equals ``noise``
        for isotropic noise.
    offset : ndarray (3,)
        Shift added to the local scene (zero unless UTM coordinates were asked for).

    Examples
    --------
    >>> from labkit.synthetic import sphere_on_tripod
    >>> scene = sphere_on_tripod(n_sphere=200, rng=0)
    >>> type(scene).__name__, int(scene.is_sphere.sum()), scene.points.shape[1]
    ('TripodScene', 200, 3)
    """

    points: np.ndarray
    sphere: np.ndarray
    is_sphere: np.ndarray
    labels: np.ndarray
    label_names: tuple
    station: np.ndarray
    noise: float
    range_noise: float
    offset: np.ndarray

    def __repr__(self) -> str:
        return (f"TripodScene(n={self.n}, sphere={fmt(self.sphere, 4)}, "
                f"outlier_ratio={self.outlier_ratio:.3f}, noise={self.noise:g}, range_noise={self.range_noise:g})")

    def covariances(self, mask=None) -> np.ndarray:
        """The noise covariance of each point, (n, 3, 3) (or of ``points[mask]``).

        Across the beam the variance is ``noise**2``, along the beam
        ``range_noise**2``: ``Sigma_i = noise^2 I + (range_noise^2 - noise^2) u u^T``.
        """
        pts = self.points if mask is None else self.points[mask]
        u = unit(pts - self.station)
        extra = self.range_noise**2 - self.noise**2
        return self.noise**2 * np.eye(3) + extra * u[:, :, None] * u[:, None, :]

    def _report(self):
        counts = np.bincount(self.labels, minlength=len(self.label_names))
        rows = [(name, f"{c:d}") for name, c in zip(self.label_names, counts)]
        return "Sphere on a tripod (synthetic TLS scan)", [
            ("", [
                ("points", f"{self.n:d}"),
                ("outlier ratio", fmt(self.outlier_ratio, 3)),
                ("true centre", fmt(self.sphere[:3], 4, "m")),
                ("true radius", fmt(self.sphere[3], 4, "m")),
                ("station", fmt(self.station, 3, "m")),
                ("noise (across / range)", f"{self.noise * 1e3:.2f} / {self.range_noise * 1e3:.2f} mm"),
            ]),
            ("Points per label", rows),
        ]


def sphere_on_tripod(
    n_sphere: int = 2000,
    n_clutter: int | None = None,
    outlier_ratio: float | None = None,
    radius: float = 0.0725,
    noise: float = 0.001,
    utm=False,
    rng=None,
    *,
    range_noise: float | None = None,
) -> TripodScene:
    """Simulate one TLS station scanning a sphere target on a tripod.

    Parameters
    ----------
    n_sphere : int
        Number of points on the visible cap of the sphere.
    n_clutter : int, optional
        Number of random clutter points in the box around the target. Default:
        10 % of the non-sphere points.
    outlier_ratio : float, optional
        Share of non-sphere points in [0, 1). The scene then holds
        ``round(n_sphere * outlier_ratio / (1 - outlier_ratio))`` non-sphere
        points (exact when that is an integer, e.g. 0.5 and 0.8), split among
        legs, base plate, ground and clutter. Default: a typical scene with
        about 3.5 non-sphere points per sphere point.
    radius : float
        Sphere radius in metres (72.5 mm is a common TLS target).
    noise : float
        Standard deviation of the Gaussian noise per coordinate (m); with
        ``range_noise`` set, the standard deviation across the beam.
    utm : bool or array_like (3,)
        True shifts the scene by (600000, 5400000, 300) m; an array gives the shift.
    rng : int or numpy.random.Generator, optional
        Seed or generator; the same seed gives the same scene.
    range_noise : float, optional
        Standard deviation along the beam from the station (anisotropic
        scanner noise). Default: equal to ``noise`` (isotropic).

    Returns
    -------
    TripodScene

    Examples
    --------
    >>> from labkit.synthetic import sphere_on_tripod
    >>> scene = sphere_on_tripod(n_sphere=500, rng=0)
    >>> scene.points.shape[1], int(scene.is_sphere.sum()), scene.sphere.tolist()
    (3, 500, [0.0, 0.0, 1.4525000000000001, 0.0725])
    """
    rng = as_rng(rng)
    counts = _counts(n_sphere, n_clutter, outlier_ratio)
    radius = positive(radius, "radius")
    noise = non_negative(noise, "noise")
    range_noise = noise if range_noise is None else non_negative(range_noise, "range_noise")
    offset = _offset(utm)

    # True geometry, local frame
    centre = np.array([0.0, 0.0, _HEAD_Z + _TRIBRACH_H + _STEM_H + radius])
    station = _STATION.copy()

    # Noise-free samples per part
    parts = [
        sphere_cap(rng, counts[SPHERE], centre, radius, station, _MAX_INCIDENCE),
        _legs(rng, counts[LEGS], station),
        _base(rng, counts[BASE], station),
        _ground(rng, counts[GROUND]),
        _clutter(rng, counts[CLUTTER], centre),
    ]
    labels = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    clean = np.concatenate(parts, axis=0)

    # Scanner noise, shuffle, shift
    points = clean + _scanner_noise(rng, clean, station, noise, range_noise)
    order = rng.permutation(len(points))
    points, labels = points[order], labels[order]
    return TripodScene(
        points=points + offset,
        sphere=np.concatenate([centre + offset, [radius]]),
        is_sphere=labels == SPHERE,
        labels=labels,
        label_names=LABEL_NAMES,
        station=station + offset,
        noise=noise,
        range_noise=range_noise,
        offset=offset,
    )


# ----------------------------------------------------------------- arguments
def _offset(utm):
    if utm is True:
        return UTM_OFFSET.copy()
    if utm is False or utm is None:
        return np.zeros(3)
    off = np.asarray(utm, dtype=np.float64)
    if off.shape != (3,) or not np.isfinite(off).all():
        raise LabkitError(f"utm must be True/False or a finite shift of shape (3,), got {utm!r}")
    return off


def _counts(n_sphere, n_clutter, outlier_ratio):
    """Number of points per label: [sphere, legs, base, ground, clutter]."""
    n_sphere = count(n_sphere, "n_sphere", minimum=0)
    if outlier_ratio is None:
        n_structure = {k: int(round(s * n_sphere)) for k, s in _STRUCTURE_SHARE.items()}
        n_out = sum(n_structure.values())
        n_clutter = int(round(0.1 * n_out / 0.9)) if n_clutter is None else count(n_clutter, "n_clutter", minimum=0)
        return [n_sphere, n_structure[LEGS], n_structure[BASE], n_structure[GROUND], n_clutter]
    ratio = non_negative(outlier_ratio, "outlier_ratio")
    if not (0.0 <= ratio < 1.0):
        raise LabkitError(f"outlier_ratio must lie in [0, 1), got {outlier_ratio!r}")
    n_out = int(round(n_sphere * ratio / (1.0 - ratio)))
    n_clutter = int(round(0.1 * n_out)) if n_clutter is None else count(n_clutter, "n_clutter", minimum=0)
    if n_clutter > n_out:
        raise LabkitError(
            f"n_clutter={n_clutter} exceeds the {n_out} non-sphere points that outlier_ratio={ratio} allows"
        )
    total = sum(_STRUCTURE_SHARE.values())
    legs = int(round((n_out - n_clutter) * _STRUCTURE_SHARE[LEGS] / total))
    base = int(round((n_out - n_clutter) * _STRUCTURE_SHARE[BASE] / total))
    ground = n_out - n_clutter - legs - base
    return [n_sphere, legs, base, ground, n_clutter]


# ----------------------------------------------------------------- geometry
def _cylinder_side(rng, n, bottom, top, r, station):
    """Points on the half of a cylinder's mantle that faces the station."""
    if n == 0:
        return np.empty((0, 3))
    axis = top - bottom
    a = unit(axis)
    look = station - 0.5 * (bottom + top)
    look = unit(look - (look @ a) * a)  # the visible half is centred on this direction
    side = np.cross(a, look)
    t = rng.random(n)
    phi = rng.uniform(-0.5 * np.pi, 0.5 * np.pi, n)
    radial = np.cos(phi)[:, None] * look + np.sin(phi)[:, None] * side
    return bottom + t[:, None] * axis + r * radial


def _split(n, weights):
    """Split n into integer parts proportional to weights (summing to n)."""
    w = np.asarray(weights, dtype=np.float64)
    parts = np.floor(n * w / w.sum()).astype(int)
    parts[0] += n - parts.sum()
    return parts


def _legs(rng, n, station):
    """Three tripod legs (cylinders) from the head to the feet on the ground."""
    az = np.radians([90.0, 210.0, 330.0])
    dirs = np.column_stack([np.cos(az), np.sin(az), np.zeros(3)])
    top = dirs * _LEG_TOP_R + [0.0, 0.0, _HEAD_Z - _PLATE_T]
    foot = dirs * _LEG_FOOT_R
    return np.concatenate(
        [_cylinder_side(rng, m, foot[j], top[j], _LEG_R, station) for j, m in enumerate(_split(n, [1, 1, 1]))]
    )


def _base(rng, n, station):
    """Tripod head plate (top annulus and rim), tribrach and sphere adapter stem."""
    n_top, n_rim, n_tri, n_stem = _split(n, [0.4, 0.15, 0.35, 0.10])
    # top face of the head plate, outside the tribrach footprint
    rr = np.sqrt(rng.uniform(_TRIBRACH_R**2, _HEAD_R**2, n_top))
    phi = rng.uniform(0, 2 * np.pi, n_top)
    top = np.column_stack([rr * np.cos(phi), rr * np.sin(phi), np.full(n_top, _HEAD_Z)])
    z = np.array([0.0, 0.0, 1.0])
    rim = _cylinder_side(rng, n_rim, z * (_HEAD_Z - _PLATE_T), z * _HEAD_Z, _HEAD_R, station)
    tri = _cylinder_side(rng, n_tri, z * _HEAD_Z, z * (_HEAD_Z + _TRIBRACH_H), _TRIBRACH_R, station)
    stem_z0 = _HEAD_Z + _TRIBRACH_H
    stem = _cylinder_side(rng, n_stem, z * stem_z0, z * (stem_z0 + _STEM_H), _STEM_R, station)
    return np.concatenate([top, rim, tri, stem])


def _ground(rng, n):
    """A slightly rough, gently tilted ground patch around the tripod."""
    xy = rng.uniform(-_GROUND_HALF, _GROUND_HALF, size=(n, 2))
    z = 0.01 * xy[:, 0] - 0.005 * xy[:, 1] + rng.normal(0.0, 0.004, n)
    return np.column_stack([xy, z])


def _clutter(rng, n, centre):
    """Random points: vegetation, passers-by, mixed pixels; a quarter near the sphere."""
    n_near = n // 4
    box = rng.uniform([-_GROUND_HALF, -_GROUND_HALF, 0.0], [_GROUND_HALF, _GROUND_HALF, 2.2], size=(n - n_near, 3))
    near = centre + rng.uniform(-0.3, 0.3, size=(n_near, 3))
    return np.concatenate([box, near])


def _scanner_noise(rng, clean, station, noise, range_noise):
    """Gaussian noise: ``noise`` across the beam, ``range_noise`` along it."""
    eps = rng.normal(0.0, noise, size=clean.shape)
    if range_noise != noise:
        u = unit(clean - station)
        along = np.einsum("ij,ij->i", eps, u)
        eps += ((range_noise / noise - 1.0) * along if noise > 0 else rng.normal(0.0, range_noise, len(u)))[:, None] * u
    return eps
