"""Every sphere of a given size in a scan: ``find_spheres`` (multi-instance RANSAC)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..core.checks import as_points, count, positive
from ..core.frame import local_origin, reduce
from ..core.errors import LabkitError
from .config import Config, S
from .detect import _check_station, _radius_limits, _seed_and_generator, ransac_sphere
from .proposals import sphere_proposals
from .verify import Verifier

SEQUENTIAL_MAX = 200_000  # 'auto': up to this many points, detect -> remove -> repeat on the whole scan
CROP = 1.5  # a proposal is searched within CROP r_max + 3 t of its centre
MAX_PROPOSALS = 300  # proposals searched at most (ordered by votes)
MAX_ROUNDS = 50  # detections of the sequential scheme at most
MIN_INLIERS = 10


def find_spheres(points, radius_range, *, threshold=None, station=None, max_spheres=None, rng=None,
                 proposals="auto"):
    """Find every sphere with a radius in ``radius_range`` in a scan.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        The scan (any frame; UTM coordinates are reduced internally).
    radius_range : (r_min, r_max)
        Admissible radii (m), e.g. the nominal radius of the targets +- 10 %.
        Balls of another size are not reported.
    threshold : float, optional
        Inlier threshold t (m) of the RANSAC searches (eqs. 25-26). Default:
        5 % of the mid radius (5 mm for 0.1 m targets). As in
        :func:`ransac_sphere`, the final inliers and the precision come from
        a robust band around each refitted sphere, not from t.
    station : array_like (3,), optional
        Scanner position in the frame of ``points`` (the origin for a file in
        the scanner's own frame). Turns the normals of the proposals towards
        the scanner and enables the visibility checks; give it when known.
    max_spheres : int, optional
        Report at most this many spheres (the best ones).
    rng : int or numpy.random.Generator, optional
        Seed of the searches.
    proposals : {'auto', 'sequential', 'votes'}
        How the spheres are searched. 'sequential': RANSAC on the whole scan,
        remove the inliers (and the ball they enclose), repeat until nothing
        is found; suits multi-beam scans, whose neighbourhoods hold one scan
        line. 'votes': candidate centres from surface normals (each point
        votes for p - r n; flat parts of the scan are dropped first; see
        :mod:`labkit.ransac.proposals`), then RANSAC in each candidate's
        neighbourhood; suits dense TLS scans of millions of points. 'auto':
        'sequential' up to 200,000 points, else 'votes'.

    Returns
    -------
    tuple of RansacResult
        One found sphere each (``center``, ``radius``, ``covariance``,
        ``inliers`` over all input points), ordered by quality: the smallest
        standard deviation of the centre first. Empty when there is none.

    Raises
    ------
    LabkitError
        Fewer than 4 points, NaN/inf, an invalid radius range, threshold,
        station, max_spheres or option.

    Notes
    -----
    Every reported sphere passed the verification of :func:`ransac_sphere`
    (no points inside, a shell standing out from its surroundings, not pieces
    of one or two planes, a cap rather than a ring; with ``station`` facing
    the scanner and no points behind it), for the 'votes' scheme once more on
    the whole scan. Two detections closer than r_max are one sphere: the
    better is kept.

    References
    ----------
    .. [1] Seed 000, section 2: RANSAC for a sphere (eqs. 25-27) and the
       Gauss-Helmert refit of its inliers; notebook 02.
    .. [2] R. Schnabel, R. Wahl, R. Klein (2007): Efficient RANSAC for
       point-cloud shape detection. Computer Graphics Forum 26(2), 214-226,
       doi:10.1111/j.1467-8659.2007.01016.x (detect, remove, repeat).
    .. [3] T. Rabbani, F. van den Heuvel (2005): Efficient Hough transform for
       automatic detection of cylinders in point clouds. ISPRS Archives
       XXXVI-3/W19, 60-65 (votes of surface points for a centre along the normal).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit import find_spheres
    >>> from labkit.synthetic import target_stations
    >>> yard = target_stations(n_stations=1, n_points=300_000, rng=0)
    >>> spheres = find_spheres(yard.scans[0], (0.09, 0.11), station=np.zeros(3), rng=0)
    >>> found, truth = np.array([s.center for s in spheres]), yard.centers_in_scan(0)
    >>> err = np.linalg.norm(found[:, None] - truth[None], axis=2)  # (found, true) in metres
    >>> bool(err.min(axis=1).max() < 0.005)  # every sphere found is a target
    True
    >>> bool(err.min(axis=0)[yard.visible[0]].max() < 0.005)  # every visible target is found
    True
    """
    # Check the input
    xyz = as_points(points, min_points=S)
    if radius_range is None:
        raise LabkitError("radius_range (r_min, r_max) in metres is needed: find_spheres looks for one size")
    r_min, r_max, _ = _radius_limits(radius_range, None, False)
    if r_min <= 0:
        raise LabkitError(f"radius_range must satisfy 0 < r_min < r_max, got {radius_range!r}")
    t = 0.05 * 0.5 * (r_min + r_max) if threshold is None else positive(threshold, "threshold")
    station = _check_station(station)
    if max_spheres is not None:
        max_spheres = count(max_spheres, "max_spheres", minimum=1)
    if proposals not in ("auto", "sequential", "votes"):
        raise LabkitError(f"proposals must be 'auto', 'sequential' or 'votes', got {proposals!r}")
    if proposals == "auto":
        proposals = "sequential" if len(xyz) <= SEQUENTIAL_MAX else "votes"
    _, gen = _seed_and_generator(rng)
    search = dict(threshold=t, radius_range=(r_min, r_max), station=station, min_inliers=MIN_INLIERS)

    # Detect, then order by quality (the precision of the centre)
    if proposals == "sequential":
        found = _sequential(xyz, search, gen, max_spheres)
    else:
        found = _from_proposals(xyz, search, gen)
    found.sort(key=_centre_std)
    return tuple(found if max_spheres is None else found[:max_spheres])


def _sequential(xyz, search, gen, max_spheres):
    """Detect on the remaining points, remove the sphere's shell and interior, repeat."""
    remaining = np.arange(len(xyz))
    found = []
    for _ in range(MAX_ROUNDS):
        if len(remaining) < MIN_INLIERS or (max_spheres is not None and len(found) >= max_spheres):
            break
        result = ransac_sphere(xyz[remaining], rng=gen, **search)
        if not result.found:
            break
        found.append(_on_all_points(result, remaining, len(xyz)))
        d = np.linalg.norm(xyz[remaining] - result.center, axis=1) - result.radius
        remaining = remaining[d >= result.band]
    return found


def _from_proposals(xyz, search, gen):
    """RANSAC around each proposed centre; each found sphere verified again on the whole scan."""
    origin = local_origin(xyz)
    X = reduce(xyz, origin)
    t, (r_min, r_max), station = search["threshold"], search["radius_range"], search["station"]
    s = None if station is None else station - origin
    prop = sphere_proposals(X, r_min, r_max, t, s)
    cfg = Config(t, 0.99, r_min, r_max, True, "ransac", "closed_form", "auto", 100_000, True, MIN_INLIERS, True,
                 None, 0.001, None, s)
    whole = Verifier(X, s, cfg)
    found = []
    for c in prop.centers[:MAX_PROPOSALS]:
        if any(np.linalg.norm(c - (f.center - origin)) < r_max for f in found):
            continue  # (a sphere found already)
        local = whole.ball(c, CROP * r_max + 3.0 * t)
        if len(local) < MIN_INLIERS:
            continue
        result = ransac_sphere(xyz[local], rng=gen, **search)
        if not result.found or whole.final_check(result.fit.x - np.append(origin, 0.0), result.band):
            continue
        twin = [k for k, f in enumerate(found) if np.linalg.norm(f.center - result.center) < r_max]
        result = _on_all_points(result, local, len(xyz))
        if not twin:
            found.append(result)
        elif _centre_std(result) < _centre_std(found[twin[0]]):
            found[twin[0]] = result
    return found


def _on_all_points(result, idx, n):
    """The result with its inliers over all n input points (it was found on the points idx)."""
    inliers = np.zeros(n, dtype=bool)
    inliers[idx[result.inliers]] = True
    return replace(result, inliers=inliers, outlier_ratio=1.0 - inliers.mean())


def _centre_std(result):
    return float(np.sqrt(np.trace(result.fit.Sigma_xx[:3, :3])))
