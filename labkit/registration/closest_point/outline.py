"""The direction point-to-plane ICP leaves weak, moved to where the clouds' outlines agree (plan view).

Point-to-plane residuals see a shift only along the surface normals. Gable roofs whose ridges all run
one way, on ALS with nearly vertical normals, leave one horizontal direction ``u`` (along the ridges)
undetermined (eq. 5.12a); when ``u`` is oblique to the axes, ICP holds both X and Y at their start and
the well-determined horizontal direction across the ridges is not solved either. Along ``u`` the only
information is where the surfaces *end*: gable ends, eaves, the outline of a building, which the
point-to-plane residuals ignore.

:func:`refine_weak_direction` uses it in two steps:

1. **Hold the weak direction, not the axes.** ICP runs again in a frame turned about the vertical so
   that ``u`` is its first axis: there only that axis is held, and the direction across the ridges
   and Z are solved by point-to-plane as usual.
2. **Point-to-line matching of the outlines along u.** In plan view, a point whose ``k`` nearest
   neighbours lie mostly on one side is on an outline (the offset of their centroid exceeds
   ``OUTLINE_SHARE`` of their mean distance; its direction gives the outward normal of the outline).
   Source outline points are paired with the nearest target outline point of a similar normal, and
   the shift ``s`` along ``u`` minimises the Huber-weighted residuals along the target's normal,
   n . (q - p - s u): outlines across ``u`` (gable ends) carry ``s``, outlines along ``u`` carry
   nothing. Re-matched until the step is below 0.1 mm (or to the middle of a 2-cycle between two
   sets of pairs). The other axes are corrected to the new position with the precision matrix of
   step 1 (eq. 5.15), as :func:`~labkit.registration.height_model.fill_held_axes` does.

Why outlines and not a consensus count scanned along ``u``: on sample_c a count of source points with
a target point within r, scanned over +-1 m, had either a plateau as wide as 2 r (r twice the point
spacing: the centre 0-190 mm off) or, with r of one spacing, peaks where the scan lines of the two
halves coincide (0.6-0.8 m off). The outline fit does not depend on the start: the same estimate from
all four start shifts of the benchmark.

**The precision is not claimed.** Measured (2026-12-02): on random halves of sample_c (six splits,
four shifts each) the along-ridge error is -9, +75, +84, -3, +2, -12 mm (the same for the four shifts
of a split; every component within 80 mm in all 24 rows; held, the error was the whole shift along the
ridges, 0.05-0.70 m); the internal std of ``s`` (cluster-robust over 2 m cells of the outline pairs,
eq. 5.13) said 16-21 mm. On independent samplings of one gable roof 40 x 30 m (3.3 points per m^2 a
cloud, 30 samplings) the rms error was 56 mm against an internal 20 mm (errors up to 6 of it); at 6.7
points per m^2 38 mm against 13 mm. Neighbouring outline points share most of their 30 neighbours, so
the errors of one outline are correlated over several metres, and the along-ridge information comes
from two gable ends: a std from them cannot be checked. So the held axes are *moved* to the outline
estimate but stay undetermined (std inf); the message gives the move. A second reason: where two
epochs were clipped to the same tile, the clip edge is an outline at the same coordinates in both and
pulls ``s`` to zero (tests/registration/test_outline.py); a component that is not stated may be
anywhere, so that does no harm to a stated precision. Sparse clouds (point spacing beyond half the
matching distance, ``SPACING_SHARE``) are left held.

What the turned run states is Z; the direction across the ridges is solved there (to millimetres) but
not stated, since X and Y both share ``u``. With X and Y held off the truth, Z on sloped roofs had
13-23 mm and the quadrants disagreed; solved across the ridges, sample_c's Z has 1.6-4 mm with errors of
0-2 mm over the 24 halves, and the group test of the turned run replaces the stale one.

Runs only where the outcome cannot hurt a stated component: ``dof='translation'``, point-to-plane,
X and Y both held with exactly one undetermined direction (nearly horizontal), no rotation in the start.
Equation numbers refer to notebook 05.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ...core.errors import LabkitError
from ...neighbours.sampling import even_subset, median_spacing
from .result import disagreement_text

#: Plan-view neighbours of the outline test, and the centroid offset (share of their mean distance) beyond
#: which a point is on an outline. At a straight edge the offset is about 0.6 of the mean distance,
#: inside a surface a few hundredths; scan lines (denser along than across) stay below 0.5 with 30 neighbours
#: (with 12 and 0.3, a third of the sample_c roof was "outline").
OUTLINE_K = 30
OUTLINE_SHARE = 0.5
#: Points per cloud the outline test looks at (an even subset in space beyond): on a roof of 200,000 points
#: it cost 1.4 s CPU a cloud, and 50,000 leave about 40 points per m^2 there, far more than the fit needs.
OUTLINE_POINTS = 50_000
#: Largest point spacing, as a share of the matching distance, at which the outlines are used. The outline
#: band of 30 neighbours is 3-4 spacings wide; beyond half the gate, pairs within the gate sample the band's
#: random structure: on warsaw_small (0.62 m spacing of the selected points, gate 1 m) the outline
#: estimate was 0.28 m off at an internal std of 39 mm (sample_c: 0.36 m; the synthetic roofs of the tests 0.2-0.28 m).
SPACING_SHARE = 0.5
#: Outline pairs need normals within about 45 degrees (cosine).
NORMAL_AGREE = 0.7
#: Huber constant (robust sigmas) and deletion limit of the outline residuals (eq. 5.8-5.9).
HUBER, DELETE = 1.5, 4.5
#: Fewest outline pairs across u (sum of squared direction cosines) and fewest cells for a fit.
MIN_INFORMATION, MIN_CELLS = 10.0, 4
ITERATIONS = 30
#: Convergence: a step below this (m), or two iterates back within it (a 2-cycle of the pairs).
STEP = 1e-4


@dataclass(frozen=True, eq=False)
class OutlineShift:
    """Shift along one horizontal direction from point-to-line matching of the plan-view outlines.

    Attributes
    ----------
    shift : float
        Shift (m) along ``direction`` added to the start.
    std : float
        Cluster-robust std of ``shift`` over square cells of the pairs (eq. 5.13); an internal
        figure, not a stated precision: the errors were 2-3 times larger (module docstring).
    n_pairs, n_cells : int
        Outline pairs used at the solution, and the cells they fall in.
    information : float
        Sum of the weights times squared cosines between the outline normals and ``direction``:
        about the number of pairs across it.
    converged : bool
    """

    shift: float
    std: float
    n_pairs: int
    n_cells: int
    information: float
    converged: bool


def outline_points(xy, k=OUTLINE_K, share=OUTLINE_SHARE):
    """Rows of ``xy`` (plan view) on an outline of the point set, and their outward unit normals.

    A point is on an outline when the centroid of its ``k`` nearest neighbours lies more than ``share``
    of their mean distance away from it; the outward normal points away from that centroid.

    Examples
    --------
    >>> import numpy as np
    >>> g = np.arange(20.0)
    >>> xy = np.column_stack([np.repeat(g, 20), np.tile(g, 20)])  # a 20 x 20 grid
    >>> rows, normals = outline_points(xy)
    >>> edge = np.minimum(xy[rows], 19 - xy[rows]).min(axis=1)  # cells to the nearest edge
    >>> bool(np.all(edge <= 1)), len(rows) > 60
    (True, True)
    """
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) <= k:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    d, nb = cKDTree(xy).query(xy, k=k + 1, workers=-1)
    offset = xy[nb[:, 1:]].mean(axis=1) - xy
    size = np.linalg.norm(offset, axis=1)
    rows = np.flatnonzero(size > share * d[:, 1:].mean(axis=1))
    return rows, -offset[rows] / size[rows, None]


def outline_shift(source_xy, target_xy, direction, *, gate=1.0, block_size=2.0):
    """Shift of ``source_xy`` along the unit 2-vector ``direction`` that aligns the outlines (plan view).

    Point-to-line residuals n . (q - p - s u) of source outline points p against the nearest target
    outline point q within ``gate`` whose normal n agrees; Huber weights, deletion beyond
    ``DELETE`` robust sigmas, re-matched each step. Symmetric: the same fit of the target onto the
    source gives -s as well, and the two are averaged (each half's outline is the other's reference
    once; on sample_c this took the rms error over six splits from 66 to 47 mm, on a synthetic roof
    from 61 to 55 mm). None when the outlines carry too little across ``direction`` (fewer than
    ``MIN_INFORMATION`` pairs across it or ``MIN_CELLS`` cells) in either fit.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> roof = lambda n: rng.uniform([0, 0], [30, 12], (n, 2))  # a 30 x 12 m rectangle
    >>> est = outline_shift(roof(4000) - [0.3, 0.0], roof(4000), np.array([1.0, 0.0]))
    >>> bool(abs(est.shift - 0.3) < 0.1)
    True
    """
    u = np.asarray(direction, dtype=np.float64)
    source_xy, target_xy = np.asarray(source_xy, dtype=np.float64), np.asarray(target_xy, dtype=np.float64)
    rs, ns = outline_points(source_xy)
    rt, nt = outline_points(target_xy)
    if len(rs) < MIN_CELLS or len(rt) < MIN_CELLS:
        return None
    forward = _one_way(source_xy[rs], ns, target_xy[rt], nt, u, gate, block_size)
    backward = _one_way(target_xy[rt], nt, source_xy[rs], ns, u, gate, block_size)
    if forward is None or backward is None:
        return None
    return OutlineShift(
        shift=0.5 * (forward.shift - backward.shift), std=0.5 * float(np.hypot(forward.std, backward.std)),
        n_pairs=forward.n_pairs + backward.n_pairs, n_cells=max(forward.n_cells, backward.n_cells),
        information=forward.information + backward.information, converged=forward.converged and backward.converged,
    )  # fmt: skip


def _one_way(p, ns, q, nt, u, gate, block_size):
    """The shift s of the outline points p (normals ns) onto q (normals nt) along u: OutlineShift or None."""
    tree = cKDTree(q)
    s, converged, path = 0.0, False, []
    for _ in range(ITERATIONS):
        pairs = _pairs(tree, p + s * u, ns, nt, gate)
        if pairs is None:
            return None
        i, j = pairs
        n = nt[j]
        a = n @ u  # design: d(residual)/ds
        e = np.einsum("ij,ij->i", n, q[j] - p[i] - s * u)  # point-to-line residual (eq. 5.2 in the plane)
        w = _huber(e)
        info = float(np.sum(w * a * a))
        if info < MIN_INFORMATION:
            return None
        ds = float(np.sum(w * a * e)) / info
        s += ds
        path.append(s)
        if abs(ds) < STEP:
            converged = True
            break
        if len(path) > 2 and abs(s - path[-3]) < STEP:  # alternating between two sets of pairs: their middle
            ds = 0.5 * (s - path[-2])  # residuals below: at the middle, from those at path[-2]
            s, converged = path[-2] + ds, True
            break
    v = e - a * ds  # residuals at the solution
    cells = np.floor(p[i] / block_size).astype(np.int64)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    g = np.bincount(cell.ravel(), w * a * v)  # score of each cell (eq. 5.13)
    G = len(g)
    if G < MIN_CELLS:
        return None
    std = float(np.sqrt(np.sum(g**2) * G / (G - 1)) / info)
    return OutlineShift(shift=s, std=std, n_pairs=int((w > 0).sum()), n_cells=G, information=info,
                        converged=converged)


def _pairs(tree, p, ns, nt, gate):
    """Rows (i, j) of source and target outline points paired: nearest within the gate, normals agreeing."""
    d, j = tree.query(p, k=1, distance_upper_bound=gate, workers=-1)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", ns, nt[j]) > NORMAL_AGREE
    if ok.sum() < MIN_CELLS:
        return None
    return np.flatnonzero(ok), j[ok]


def _huber(e):
    """Huber weights on the residuals with the robust scale 1.4826 MAD; 0 beyond DELETE sigmas (eq. 5.8-5.9)."""
    scale = max(1.4826 * float(np.median(np.abs(e))), 1e-6)
    z = np.abs(e) / scale
    w = np.minimum(1.0, HUBER / np.maximum(z, 1e-12))
    return np.where(z > DELETE, 0.0, w)


def weak_direction(result):
    """The one undetermined direction of a translation-only result (unit 3-vector), or None.

    None unless ``dof='translation'``, both X and Y are held, exactly one eigen-direction is
    undetermined and it is nearly horizontal (vertical share below 5 %).
    """
    deg = result.degeneracy
    if deg is None or tuple(result.parameter_names) != ("tx", "ty", "tz"):
        return None
    if np.asarray(deg.axis_determined)[:2].any() or not np.allclose(result.rotation, np.eye(3)):
        return None
    weak = np.asarray(deg.eigenvectors)[:, ~np.asarray(deg.constrained, dtype=bool)]
    if weak.shape[1] != 1 or weak[2, 0] ** 2 > 0.05:
        return None
    u = weak[:, 0] * np.array([1.0, 1.0, 0.0])
    return u / np.linalg.norm(u)


def refine_weak_direction(result, source, target, settings, icp_function):
    """Solve all but the weak direction by point-to-plane, and move that one to the outlines' estimate.

    Parameters
    ----------
    result : RegistrationResult
        ICP on the selected points (``source``, ``target``) with X and Y held.
    source, target : array_like (n, 3) or PointCloud
        The points ``result`` was computed from.
    settings : dict
        The keywords of that ICP run (``select='all'``), with ``options``.
    icp_function : callable
        :func:`labkit.registration.icp` (passed in: this module is imported by it).

    Returns
    -------
    RegistrationResult
        ``result`` with its translation moved (Z re-solved with its covariance from the turned run, X and Y
        still undetermined) and a note in the message, or ``result`` unchanged with the reason.
    """
    u = weak_direction(result)
    if u is None:
        return result
    src, tgt = _points(source), _points(target)
    gate = settings["options"].max_distance if np.isfinite(settings["options"].max_distance) else 1.0
    spacing = max(median_spacing(src), median_spacing(tgt))
    if not spacing <= SPACING_SHARE * gate:
        return replace(result, message=f"{result.message}; outlines: not used (point spacing {spacing:.2g} m, "
                                       f"more than {SPACING_SHARE:g} of the matching distance)")
    # 1. ICP in a frame whose first axis is u: only that axis is held (x' = Q (x - c) + c)
    Q = _turn(u)
    c = tgt.mean(axis=0)
    start = np.eye(4)
    start[:3, 3] = Q @ result.translation
    turned = dict(settings, initial=start, height_model=False, progress=False, coarse_to_fine=False)
    try:
        res = icp_function(_moved(source, (src - c) @ Q.T + c), _moved(target, (tgt - c) @ Q.T + c),
                           select="all", **turned)
    except LabkitError as exc:
        return replace(result, message=f"{result.message}; outlines: not used ({exc})")
    held = ~np.asarray(res.degeneracy.axis_determined, dtype=bool)
    if not (held[0] and not held[1:].any()):
        return replace(result, message=f"{result.message}; outlines: not used (turned to the weak direction, "
                                       f"ICP held {', '.join(res.degeneracy.undetermined_axes) or 'nothing'})")
    # 2. point-to-line matching of the plan-view outlines along u (the turned frame's x axis)
    t = np.array(res.translation, dtype=np.float64)
    src, tgt = src[even_subset(src, OUTLINE_POINTS)], tgt[even_subset(tgt, OUTLINE_POINTS)]  # dense clouds
    est = outline_shift(((src - c) @ Q.T)[:, :2] + t[:2], ((tgt - c) @ Q.T)[:, :2], np.array([1.0, 0.0]),
                        gate=gate, block_size=settings["block_size"])
    cov = np.array(res.covariance, dtype=np.float64)
    if est is None or not est.converged or abs(est.shift) > gate:
        why = "too little outline across the weak direction" if est is None else (
            "not converged" if not est.converged else "beyond the matching distance")
        note = f"; outlines: not used ({why}), X and Y held, Z re-solved with the weak direction alone held"
    else:
        t = _moved_along_first(t, est.shift, res.degeneracy)
        note = (f"; X, Y MOVED ALONG THE WEAK DIRECTION ({u[0]:+.2f}, {u[1]:+.2f}) by {1000 * est.shift:+.0f} mm "
                f"to where the outlines agree ({est.n_pairs} outline pairs, point-to-line), and across it by "
                "point-to-plane; still undetermined: the outline estimate's precision is not checked")
    cov = Q.T @ np.where(np.isfinite(cov), cov, 0.0) @ Q
    cov[:2, :] = cov[:, :2] = np.inf  # X and Y share the undetermined direction
    test, message = _consistency(result, res, settings["options"].classes)
    return replace(result, translation=Q.T @ t, covariance=cov, message=message + note, consistency=test,
                   runtime_s=result.runtime_s + res.runtime_s)


def _consistency(result, turned, classes):
    """The group test of the turned run in place of the first run's (test and message).

    With X and Y held off the truth, the groups of the first run disagree in Z on sloped roofs (the
    held offset across the ridges): that test, its text and its spread are stale once the direction
    across the ridges is solved. The turned run's offsets are reported in Z only (X and Y are undetermined).
    """
    message, test = result.message, turned.consistency
    if result.consistency is not None and not result.consistency.agree:
        message = message.replace("; " + disagreement_text(result.consistency, classes), "")
    if test is None:
        return None, message
    offset, offset_std = np.array(test.offset, dtype=np.float64), np.array(test.offset_std, dtype=np.float64)
    offset[:, :2] = offset_std[:, :2] = np.nan
    test = replace(test, offset=offset, offset_std=offset_std)
    if not test.agree:
        message += "; " + disagreement_text(test, classes)
    return test, message


def _moved_along_first(t, shift, deg):
    """t with its first component moved by ``shift`` and the others corrected by -B shift (eq. 5.15)."""
    out = t.copy()
    B = deg.held_effect(np.array([False, True, True]), np.array([True, False, False]))
    out[1:] -= B[:, 0] * shift
    out[0] += shift
    return out


def _turn(u):
    """Rotation about the vertical taking the horizontal unit vector ``u`` to the x axis."""
    cos, sin = u[0], u[1]
    return np.array([[cos, sin, 0.0], [-sin, cos, 0.0], [0.0, 0.0, 1.0]])


def _points(cloud):
    return np.asarray(getattr(cloud, "xyz", cloud), dtype=np.float64)


def _moved(cloud, xyz):
    return cloud.with_xyz(xyz) if hasattr(cloud, "with_xyz") else xyz
