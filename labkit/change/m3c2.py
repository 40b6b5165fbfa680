"""Change between two epochs: M3C2 distances with a level of detection (notebook 10).

M3C2 (Multiscale Model to Model Cloud Comparison, Lague, Brodu and Leroux 2013)
measures change at *core points* along a local surface normal, from the mean
positions of both epochs inside a short cylinder around that normal, and says
whether the change is larger than the two clouds can tell apart.

Notation (notebook 10):

- (eq. 1) normal        n_i = eigenvector of the smallest eigenvalue of the reference points
                        within ``normal_radius`` of core point c_i (several radii: the one of
                        lowest surface variation l3 / (l1 + l2 + l3)), oriented so n_i . o >= 0
- (eq. 2) cylinder      points p with |(p - c_i) . n_i| <= h and |p - c_i|^2 - ((p - c_i) . n_i)^2 <= r^2
- (eq. 3) distance      d_i = mean_k((p2_k - c_i) . n_i) - mean_k((p1_k - c_i) . n_i)
- (eq. 4) spread        s_j = standard deviation (ddof = 1) of the axial coordinates in epoch j
- (eq. 5) level of detection
                        LoD_i = q_i sqrt(s1^2 / n1 + s2^2 / n2 + n_i^T Sigma_t n_i)
                        q_i = t_(1 - alpha/2, k_i), Student t with the Welch-Satterthwaite degrees of freedom
                        k_i = (s1^2/n1 + s2^2/n2)^2 / ((s1^2/n1)^2/(n1-1) + (s2^2/n2)^2/(n2-1))
                        (``quantile='normal'``: q = z_(1 - alpha/2) as PDAL, CloudCompare, py4dgeo)
- (eq. 6) with a rigid registration (angles w, shift t about the origin o):
                        n_i^T Sigma_t n_i -> g_i^T Sigma_(w,t) g_i,  g_i = [(c_i - o) x n_i ; n_i]
- (eq. 7) significant   |d_i| > LoD_i

Eq. 5 without the registration term is the LoD of Lague et al. (2013, eq. 1); it
treats the two mean positions as independent with standard errors s/sqrt(n). The
spreads are estimated from a few dozen points per cylinder, so the ratio d / se follows
a Student t rather than a normal distribution: with z = 1.96 and a few dozen points per
cylinder more than alpha of the unchanged cores are flagged (tests/test_m3c2.py); the t
quantile with Welch's degrees of freedom keeps the false-alarm rate at alpha (it tends to
z for large counts).
The registration term, a stated covariance, does not reduce the degrees of freedom. A
registration error moves the whole compared epoch: its covariance Sigma_t adds
the variance of that displacement along the normal, so a poorly determined X
widens the LoD on steep faces (n along X) but not on flat ground (n along Z).
This is the propagation of M3C2-EP (Winiwarter, Anders, Hoefle 2021), here with
the covariance of the registration labkit has just estimated. CloudCompare, PDAL
and py4dgeo's plain M3C2 instead add a scalar registration error outside the
root (PDAL and py4dgeo: 1.96 (sqrt(...) + reg), CloudCompare 1.96 sqrt(...) + reg).

References
----------
Lague, D., Brodu, N., Leroux, J. (2013). Accurate 3D comparison of complex topography with
terrestrial laser scanner: application to the Rangitikei canyon (N-Z). ISPRS J. Photogramm.
Remote Sens. 82, 10-26. doi:10.1016/j.isprsjprs.2013.04.009
Winiwarter, L., Anders, K., Hoefle, B. (2021). M3C2-EP: Pushing the limits of 3D topographic
point cloud change detection by error propagation. ISPRS J. Photogramm. Remote Sens. 178,
240-258. doi:10.1016/j.isprsjprs.2021.06.011
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtri, stdtrit  # the quantiles of scipy.stats.norm / t, without importing scipy.stats

from . import search
from .registration import RegistrationCovariance, load_registration, registration_variance, save_registration
from ..core.checks import as_points, choice, positive, probability
from ..core.crs import check_same_crs, crs_of, crs_summary
from ..core.frame import local_origin, reduce
from ..core.lengths import length_text
from ..core.report import ReportMixin
from ..cloud import PointCloud
from ..neighbours.sampling import voxel_thin
from ..core.errors import LabkitError
from ..core.progress import progress_steps

__all__ = ["M3C2Result", "RegistrationCovariance", "load_registration", "m3c2", "registration_variance",
           "save_registration"]


@dataclass(frozen=True, eq=False, repr=False)
class M3C2Result(ReportMixin):
    """M3C2 change at core points (eq. 1-7 of notebook 10).

    Attributes
    ----------
    corepoints : ndarray (m, 3)
        Core points in the caller's frame.
    normals : ndarray (m, 3)
        Unit cylinder axes (eq. 1); NaN where the normal is undetermined.
    distance : ndarray (m,)
        M3C2 distance compared - reference along the normal (eq. 3), in the units of the
        input; NaN where a cylinder holds fewer than ``min_points`` points of either epoch.
    lod : ndarray (m,)
        Level of detection at the test level ``alpha`` (eq. 5); inf where the registration leaves the
        displacement along the normal undetermined.
    significant : ndarray of bool (m,)
        |distance| > lod (eq. 7); False where the distance is NaN.
    spread1, spread2 : ndarray (m,)
        Standard deviation (ddof = 1) of the axial coordinates in each cylinder (eq. 4).
    count1, count2 : ndarray of int (m,)
        Points of the reference / compared epoch in each cylinder.
    registration_variance : ndarray (m,)
        The registration term n^T Sigma_t n of eq. 5 (zero without a registration covariance).
    normal_radius : ndarray (m,)
        The normal radius chosen at each core point (NaN for given normals).
    z : ndarray (m,)
        The two-sided quantile 1 - ``alpha``/2 used at each core point (eq. 5): Student t with
        Welch's degrees of freedom, or the normal quantile for ``quantile='normal'``; NaN without a distance.
    cylinder_radius, max_depth, alpha, min_points, quantile :
        The parameters used.
    crs : str or None
        The inputs' CRS (``PointCloud.crs``); None when they state none (arrays, files without a CRS):
        the summary then says the coordinates are in an unknown frame.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.change.m3c2 import m3c2
    >>> g = np.arange(0.0, 4.0, 0.2)
    >>> plane = np.c_[np.repeat(g, len(g)), np.tile(g, len(g)), np.zeros(len(g) ** 2)]
    >>> result = m3c2(plane, plane + [0, 0, 0.1], [[2.0, 2.0, 0.0]], normal_radius=1.0, cylinder_radius=0.5,
    ...               max_depth=1.0)
    >>> type(result).__name__, result.distance.round(3).tolist()
    ('M3C2Result', [0.1])
    """

    corepoints: np.ndarray
    normals: np.ndarray
    distance: np.ndarray
    lod: np.ndarray
    significant: np.ndarray
    spread1: np.ndarray
    spread2: np.ndarray
    count1: np.ndarray
    count2: np.ndarray
    registration_variance: np.ndarray
    normal_radius: np.ndarray
    cylinder_radius: float
    max_depth: float
    alpha: float
    z: np.ndarray
    min_points: int
    quantile: str = "student"
    crs: str | None = None

    @property
    def valid(self) -> np.ndarray:
        """True where a distance was computed."""
        return np.isfinite(self.distance)

    @property
    def lod_without_registration(self) -> np.ndarray:
        """q sqrt(s1^2/n1 + s2^2/n2): eq. 5 without the registration term."""
        return self.z * np.sqrt(self.spread1**2 / self.count1 + self.spread2**2 / self.count2)

    def to_cloud(self):
        """The core points as a :class:`labkit.PointCloud` with ``distance``, ``lod``, ``significant`` (for LAS/CSV).

        Further attributes: ``m3c2_spread1/2``, ``m3c2_count1/2`` and ``normal_x/y/z``. Lengths in m.
        """
        attrs = {"distance": self.distance, "lod": self.lod, "significant": self.significant.astype(np.uint8),
                 "m3c2_spread1": self.spread1, "m3c2_spread2": self.spread2,
                 "m3c2_count1": self.count1.astype(np.int32), "m3c2_count2": self.count2.astype(np.int32),
                 "normal_x": self.normals[:, 0], "normal_y": self.normals[:, 1], "normal_z": self.normals[:, 2]}
        return PointCloud(self.corepoints, attrs, name="m3c2")

    def _report(self):
        ok = self.valid
        n, nv, ns = len(self.distance), int(ok.sum()), int(self.significant.sum())
        d = self.distance[ok]
        rows = [
            ("core points", f"{n} ({nv} with a distance, {n - nv} without)"),
            ("CRS", crs_summary(self.crs)),
            ("cylinder", f"radius {length_text(self.cylinder_radius)}, half length {length_text(self.max_depth)}"),
            ("normal radius", _radius_text(self.normal_radius)),
            ("test level", f"alpha = {self.alpha:.3f} ({_quantile_text(self)}), at least {self.min_points} points "
                           "per cylinder"),
        ]
        if nv:
            lod = self.lod[ok]
            rows += [
                ("distance median", length_text(np.median(d), sign=True)),
                ("distance 2.5 / 97.5 %", " / ".join(length_text(q, sign=True) for q in np.quantile(d, [0.025, 0.975]))),
                ("LoD median", length_text(np.median(lod[np.isfinite(lod)]) if np.isfinite(lod).any() else np.inf)),
                ("points per cylinder median", f"{np.median(self.count1[ok]):.0f} / {np.median(self.count2[ok]):.0f}"),
                ("significant change", f"{ns} of {nv} ({100 * ns / nv:.1f} %): "
                                       f"{int((self.significant & (self.distance > 0)).sum())} up, "
                                       f"{int((self.significant & (self.distance < 0)).sum())} down"),
            ]
        reg = self.registration_variance[ok]
        if np.any(reg != 0):
            finite = np.isfinite(reg)
            rows.append(("registration term median", length_text(np.sqrt(np.median(reg[finite])) if finite.any()
                                                                 else np.inf) + " (sqrt of n^T Sigma_t n)"))
            if not finite.all():
                rows.append(("LoD infinite", f"{int((~finite).sum())} cores: the registration does not determine "
                                             "the shift along their normal"))
        return f"M3C2 change: {ns} of {nv} core points significant", [("", rows)]


def m3c2(
    reference,
    compared,
    corepoints=None,
    *,
    normal_radius,
    cylinder_radius: float,
    max_depth: float,
    registration_covariance=None,
    normals=None,
    alpha: float = 0.05,
    progress: bool = False,
    orientation=(0.0, 0.0, 1.0),
    min_points: int = 2,
    held_std=None,
    quantile: str = "student",
) -> M3C2Result:
    """M3C2 distances from ``reference`` to ``compared`` with a level of detection (eq. 1-7).

    Parameters
    ----------
    reference, compared : array_like (n, 3) or PointCloud
        The two epochs in one frame (the compared epoch already registered onto the
        reference). UTM-sized coordinates are reduced to a local origin internally.
    corepoints : array_like (m, 3), float or None
        Where to measure. None: an even subsample of the reference, one point per cube of
        edge ``cylinder_radius``; a float: the same with that cube edge.
    normal_radius : float or sequence of float
        Radius of the PCA neighbourhood in the reference (eq. 1). Several radii: per core,
        the one of lowest surface variation (the most planar scale, Lague et al. 2013).
    cylinder_radius : float
        Radius r of the projection cylinder (eq. 2).
    max_depth : float
        Half length h of the cylinder along the normal (eq. 2): changes larger than this
        are not found.
    registration_covariance : (3, 3) array_like or RegistrationResult, optional
        Covariance of the compared epoch's registration shift (m^2), or the registration
        result itself (its translation, or angle and translation, covariance; eq. 6).
        An isotropic registration error sigma is ``sigma**2 * np.eye(3)``.
    normals : array_like (m, 3) or (3,), optional
        Given cylinder axes instead of PCA normals (normalised and oriented here).
    alpha : float
        Test level of the level of detection (two-sided false-alarm rate), default 0.05 (z = 1.96).
    progress : bool, str or callable
        Progress of the cylinder search (see :mod:`labkit.core.progress`); silent by default.
    orientation : array_like (3,)
        Normals are flipped to a positive component along it (default up, for ALS).
    min_points : int
        Fewer points of either epoch in a cylinder: no distance (NaN). At least 2, so that
        the spread is defined.
    held_std : dict, optional
        Prior standard deviations for registration parameters the data did not determine,
        e.g. ``{"rz": np.radians(0.02)}`` (see :func:`registration_variance`). Without it the
        LoD is infinite wherever such a parameter moves the surface along the normal.
    quantile : {"student", "normal"}
        The quantile of eq. 5: Student t with Welch's degrees of freedom (default; holds the
        false-alarm rate at ``alpha`` for small cylinders) or the normal quantile z
        (PDAL, CloudCompare and py4dgeo's convention).

    Returns
    -------
    M3C2Result

    Raises
    ------
    LabkitError
        Empty clouds, NaN coordinates, radii <= 0, a covariance that is not symmetric
        positive semi-definite, normals of the wrong shape, alpha outside (0, 1).

    Notes
    -----
    Distances are differences of means (PDAL, py4dgeo and CloudCompare's default);
    the spread uses ddof = 1, as py4dgeo, while PDAL divides by n. Cores with an
    undetermined normal (fewer than 3 reference points within the normal radius) get NaN.

    References
    ----------
    .. [1] Notebook 10, sections 2-3, eqs. 1-7.
    .. [2] D. Lague, N. Brodu, J. Leroux (2013): Accurate 3D comparison of complex topography with
       terrestrial laser scanner: application to the Rangitikei canyon (N-Z). ISPRS Journal of
       Photogrammetry and Remote Sensing 82, 10-26, doi:10.1016/j.isprsjprs.2013.04.009.
    .. [3] B. L. Welch (1947): The generalization of 'Student's' problem when several different
       population variances are involved. Biometrika 34(1-2), 28-35.
    .. [4] H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle (1992): Surface reconstruction
       from unorganized points. Computer Graphics (Proc. SIGGRAPH '92) 26(2), 71-78.

    Examples
    --------
    A noisy plane and the same plane 10 cm higher: the distance is significant at 1 cm noise.

    >>> import numpy as np
    >>> from labkit.change.m3c2 import m3c2
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 4, (2000, 2))
    >>> before = np.c_[xy, rng.normal(0, 0.01, 2000)]
    >>> after = np.c_[xy, 0.1 + rng.normal(0, 0.01, 2000)]
    >>> result = m3c2(before, after, [[2.0, 2.0, 0.0]], normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
    >>> round(float(result.distance[0]), 2), bool(result.significant[0]), bool(result.lod[0] < 0.01)
    (0.1, True, True)
    """
    # Check the arguments; reduce everything to one local origin
    check_same_crs(reference, compared, "m3c2", ("reference", "compared"))
    ref = as_points(reference, min_points=1, name="reference")
    cmp_ = as_points(compared, min_points=1, name="compared")
    radii = _check_radii(normal_radius) if normals is None else None
    r = positive(cylinder_radius, "cylinder_radius")
    h = positive(max_depth, "max_depth")
    alpha = probability(alpha, "alpha")
    choice(quantile, ("student", "normal"), "quantile")
    min_points = _check_min_points(min_points)
    up = _check_orientation(orientation)
    registration_variance(registration_covariance, np.zeros((1, 3)), up[None], held_std)  # fail before the work
    origin = local_origin(ref)
    ref_l, cmp_l = reduce(ref, origin), reduce(cmp_, origin)
    _check_cylinder_scale(ref_l, r)
    cores_world = _corepoints(corepoints, ref, ref_l, r)
    cores = reduce(cores_world, origin)
    # Normals (eq. 1): PCA in the reference, lowest surface variation over the radii, oriented
    if normals is None:
        nrm, chosen = _multiscale_normals(ref_l, cores, radii)
    else:
        nrm, chosen = _given_normals(normals, len(cores)), np.full(len(cores), np.nan)
    nrm = search.orient(nrm, up)
    # Cylinder statistics of both epochs (eq. 2-4)
    with progress_steps(progress, 2 * len(cores), "m3c2", "cylinders") as step:
        n1, mean1, s1 = search.cylinder_stats(ref_l, cores, nrm, r, h, step if step.enabled else None)
        n2, mean2, s2 = search.cylinder_stats(cmp_l, cores, nrm, r, h, step if step.enabled else None)
    enough = (n1 >= min_points) & (n2 >= min_points)
    distance = np.where(enough, mean2 - mean1, np.nan)  # (eq. 3)
    # Level of detection (eq. 5, 6) and significance (eq. 7)
    reg = registration_variance(registration_covariance, cores_world, nrm, held_std)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(enough, _quantile(alpha, s1, n1, s2, n2, quantile), np.nan)
        lod = np.where(enough, z * np.sqrt(s1**2 / n1 + s2**2 / n2 + reg), np.nan)  # (eq. 5)
    significant = np.abs(np.nan_to_num(distance)) > np.where(enough, lod, np.inf)  # (eq. 7)
    nan = np.nan
    return M3C2Result(
        cores_world, nrm, distance, lod, significant,
        np.where(enough, s1, nan), np.where(enough, s2, nan), n1, n2, reg, chosen, r, h, alpha, z, min_points, quantile,
        crs_of(reference) or crs_of(compared),
    )


# --------------------------------------------------------------------------- private steps
def _quantile(alpha, s1, n1, s2, n2, kind):
    """Two-sided quantile of eq. 5 per core: Student t with Welch-Satterthwaite degrees of freedom, or z."""
    z = float(ndtri(1 - alpha / 2))
    if kind == "normal":
        return np.full(np.shape(n1), z)
    a, b = s1**2 / n1, s2**2 / n2
    dof = (a + b) ** 2 / (a**2 / (n1 - 1) + b**2 / (n2 - 1))
    dof = np.where(np.isfinite(dof), dof, np.minimum(n1, n2) - 1.0)  # zero spreads: the smaller sample
    return np.where(dof > 0, stdtrit(np.maximum(dof, 1e-9), 1 - alpha / 2), np.nan)


def _quantile_text(result) -> str:
    q = result.z[np.isfinite(result.z)]
    if result.quantile == "normal" or not len(q):
        return f"z = {float(ndtri(1 - result.alpha / 2)):.3f}"
    return f"Student t, quantile median {np.median(q):.3f}, range {q.min():.3f}..{q.max():.3f}"


def _check_radii(normal_radius):
    values = np.atleast_1d(np.asarray(normal_radius, dtype=object))
    if values.ndim != 1 or len(values) == 0:
        raise LabkitError(f"normal_radius must be a number or a sequence of numbers, got {normal_radius!r}")
    return [positive(v, "normal_radius") for v in values]


def _check_cylinder_scale(ref_l, r) -> None:
    """Refuse a cylinder radius far below the reference's point spacing: its cylinders would hold no points."""
    sample = ref_l[:: max(1, len(ref_l) // 2000)]
    if len(sample) < 3:
        return
    d, _ = cKDTree(sample).query(sample, k=2, workers=-1)
    gap = d[:, 1][d[:, 1] > 0]  # duplicates say nothing about the spacing
    spacing = float(np.median(gap)) * (len(sample) / len(ref_l)) ** 0.5 if len(gap) else 0.0  # thinned: rescale
    if r < 0.01 * spacing:
        raise LabkitError(
            f"cylinder_radius {r:g} m is far below the point spacing of the reference (about {spacing:.3g} m): "
            "the cylinders would hold no points; choose a radius of a few point spacings"
        )


def _check_min_points(min_points) -> int:
    if isinstance(min_points, bool) or not isinstance(min_points, numbers.Integral) or min_points < 2:
        raise LabkitError(f"min_points must be an integer >= 2, got {min_points!r}")
    return int(min_points)


def _check_orientation(orientation) -> np.ndarray:
    o = np.asarray(orientation, dtype=np.float64)
    if o.shape != (3,) or not np.isfinite(o).all() or np.linalg.norm(o) == 0:
        raise LabkitError(f"orientation must be a non-zero vector of 3 numbers, got {orientation!r}")
    return o / np.linalg.norm(o)


def _corepoints(corepoints, ref, ref_l, r):
    """Core points in the caller's frame: given, or reference points of an even subsample (copies)."""
    if corepoints is None or (isinstance(corepoints, numbers.Real) and not isinstance(corepoints, bool)):
        spacing = r if corepoints is None else positive(corepoints, "corepoints (spacing)")
        return ref[voxel_thin(ref_l, spacing)]
    return np.array(as_points(corepoints, min_points=1, name="corepoints"), copy=True)


def _multiscale_normals(ref_l, cores, radii):
    """Per core the PCA normal at the radius of lowest surface variation (eq. 1)."""
    best_n, best_v = np.full((len(cores), 3), np.nan), np.full(len(cores), np.inf)
    chosen = np.full(len(cores), np.nan)
    for radius in radii:
        nrm, var = search.pca_normals(ref_l, cores, radius)
        better = np.isfinite(var) & (var < best_v)
        best_n[better], best_v[better], chosen[better] = nrm[better], var[better], radius
    return best_n, chosen


def _given_normals(normals, m):
    N = np.asarray(normals, dtype=np.float64)
    if N.shape == (3,):
        N = np.broadcast_to(N, (m, 3))
    if N.shape != (m, 3):
        raise LabkitError(f"normals must have shape (3,) or ({m}, 3) (one per core point), got {N.shape}")
    length = np.linalg.norm(N, axis=1)
    if not (np.isfinite(N).all() and (length > 0).all()):
        raise LabkitError("normals must be finite and non-zero")
    return N / length[:, None]


def _radius_text(chosen) -> str:
    vals = chosen[np.isfinite(chosen)]
    if not len(vals):
        return "none chosen (normals given, or too few points)"
    uniq, counts = np.unique(vals, return_counts=True)
    return ", ".join(f"{length_text(u)} ({c} cores)" for u, c in zip(uniq, counts))
