"""Horizontal shift from the height jumps of a 2.5-D height model (least-squares DSM matching).

Point-to-plane ICP on the stable surfaces of an airborne scan (ground, roofs) sees the shift only
along their normals. Those are nearly vertical: a flat floor, or gable roofs all running one way,
leave X and Y (or the along-ridge direction) undetermined (eq. 5.12a). The second source of
horizontal information in ALS is where the heights *jump*: building outlines and, in a forest,
crown shapes and tree tops. Both epochs see them from above, so they live in a height model.

The classical answer is least-squares matching of height models (Rosenholm and Torlegard 1988;
Gruen and Akca 2005 for the 3-D form; Karel et al. 2006 on ALS strips):

1. Rasterise each cloud to a surface model: the **highest point per cell** (the first surface seen
   from above: roofs, canopy; in a forest the crown envelope is what two flights share, single
   leaf returns are not), on cells of about the point spacing. Holes and the sampling noise of
   the maximum (a cell straddling an edge holds roof or ground by chance) are smoothed by the same
   normalised Gaussian in both epochs, so the edge stays where it is on average.
2. Observation per source cell x: dZ = Z_t(x + d) - Z_s(x) - dz, linearised with the height model's
   gradients (the mean of both epochs' gradients, which converges further than one of them):
   dZ ~ g . (dx, dy) - dz. Only the cells near a jump carry (dx, dy); flat cells carry dz.
   Gauss-Newton, coarse to fine (smoothing 3 cells, then 1 cell).
3. **Uncertainty from the data, not from a noise model**: the residuals of neighbouring cells share
   their cause (smoothing, one roof edge, one crown), and the maximum's sampling noise is far from
   Gaussian and concentrated at the edges. The covariance is the delete-a-block jackknife over
   square blocks of cells (as in maximum consensus, eq. 6.14): leaving block b out moves the
   estimate by d_b = (N - N_b)^-1 g_b, Sigma = (B - 1)/B sum d_b d_b^T; the larger of two block
   sizes counts, and the std is scaled for few blocks (t with B - 1 degrees of freedom).
4. X and Y are **determined** when both horizontal directions have a std below the precision limit
   ``max_std`` (0.1 m as ICP's default); otherwise both are inf (along a direction without height
   jumps the estimate wanders, and takes every axis with a share in it along).

Why a height model and not the crowns as planes: a crown is a new random sample of leaves in every
flight, so the normals fitted to it are random and point-to-plane residuals on it are biased
(the all-points ICP was 1.4-1.5 times overconfident on a conifer plot). The crown *envelope* (the
maximum per cell, smoothed over a few metres) is a property of the tree, and its bias from the
sampling is symmetric about every apex and edge: it does not move the horizontal shift.
Vertical growth of trees between real epochs goes into dz of this model, which is not used:
:func:`fill_held_axes` takes only the horizontal components, Z stays with ICP.

A part of the scene that changed between the epochs (a new building, felled trees) is an outlier
of the matching. With ``robust=True``, in every Gauss-Newton step the cells whose height difference
exceeds 5 robust sigmas (1.4826 MAD) of the cells with a similar gradient are left out (eq. 5.8,
:func:`robust_weights`); one scale for all cells would not do: the largest residuals sit at the
edges, which are the information. The jackknife is computed on the cells kept at the solution.
It is **off by default** (and in :func:`fill_held_axes`): where no common height jump fixes a
direction, the rejection follows the estimate and makes its own fit. On random halves of sample_c
(one gable roof, no jump across the ridge) it stated X and Y in 4 of 12 halves, 0.3-0.6 m off at
+-23-78 mm (up to 63 std); Tukey's biweight instead of the hard limit did the same (1.6 m off at
+-78 mm from a consensus start). Without it a change biases the shift, and the jackknife widens
the std only when the change is one of few blocks that carry a direction.

Measured (tests/registration/test_height_model.py; random halves of the real files shifted by
0.2-0.8 m, 12 halves each, the estimator alone started at zero):

- gable roofs with ridges along X (synthetic, 60 m x 60 m, 2.2 pts/m^2, 40 samplings): X, along the
  ridges, to +-44 mm; spread / stated 1.03, 0.88, 0.92 in X, Y, Z; mean error within 5 mm. With
  ``robust=True``: 1.04, 0.91, 0.93, 49 of 5,700 cells rejected (Tukey's biweight: 1.13-1.49 in X).
- the same with ``robust=True`` and 19 % of the area changed (a new hall 20 x 14 m, 8 m high, in one epoch; a stand of
  12 m trees cut in the other; 8 samplings): 7 of 8 determined, every component within 2.4 std
  (X, Y 16-99 mm off at +-42-85 mm; the edges of the change are not all rejected), about 900 of
  6,800 cells rejected; one sampling undetermined. Without the rejection the shift is 0.1-0.27 m off
  and the jackknife leaves X and Y undetermined.
- MixedConifer (height-normalised conifer plot, 2.3 pts/m^2 per half): X, Y to +-22 / +-26 mm;
  spread / stated 1.03 / 1.02, largest error 2.2 std; no bias over 24 halves (X +2 +- 4 mm). With
  ``robust=True``: 12 of 12 determined, 1.09 / 1.05, largest error 2.1 std, 1.2 % of the cells rejected.
- sample_c: one large gable roof clipped at its outline and a strip of ground: no height jump
  across the ridge inside the data; the along-ridge direction has std 0.42-0.81 m (or no shared
  information at all): X and Y undetermined in 12 of 12 halves (honest, not useful).
- warsaw_small (1,500 points per half over 33 m, a few trees): weak direction std 0.15-0.80 m,
  X and Y undetermined in 12 of 12 (with ``robust=True`` as well).

Equation numbers refer to notebook 05 (ICP) and 06 (maximum consensus).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from ..core.checks import as_points, positive
from ..core.errors import LabkitError
from ..core.frame import local_origin
from ..core.report import ReportMixin, fmt
from ..neighbours.sampling import median_spacing
from .closest_point.covariance import few_clusters_factor

__all__ = ["HeightModelShift", "fill_held_axes", "height_model_shift", "robust_weights"]

#: Classes left out of the height model (ASPRS low and high noise).
NOISE_CLASSES = (7, 18)
#: Smoothing of both height models (Gaussian sigma in cells): coarse start, then fine (twice: the source
#: rasterised again at the shift of the first fine pass).
SMOOTHING = (3.0, 1.0, 1.0)
#: Block edges of the jackknife in cells; the larger covariance counts.
BLOCK_CELLS = (6, 12)
#: Fewer blocks than this: no jackknife, every component undetermined.
MIN_BLOCKS = 8
#: Rejection limit (robust sigmas of the cells with a similar gradient) and the number of gradient classes.
REJECT_SIGMAS = 5.0
GRADIENT_BINS = 8


@dataclass(frozen=True, eq=False, repr=False)
class HeightModelShift(ReportMixin):
    """Shift (dx, dy, dz) of source onto target from least-squares matching of their height models.

    Attributes
    ----------
    translation : ndarray (3,)
        The shift in metres (source + translation ~ target).
    covariance : ndarray (3, 3)
        Delete-a-block jackknife covariance (m^2); inf on the diagonal of an undetermined component.
    determined : ndarray of bool (3,)
        Per axis: X and Y when both horizontal directions have a std below ``max_std``; Z with them.
    direction_std : ndarray (2,)
        Std (m) along the two horizontal eigen-directions of the jackknife covariance, ascending.
    cell : float
        Cell size of the height models (m).
    n_cells, n_blocks : int
        Observations (source cells compared) and jackknife blocks.
    n_rejected : int
        Cells rejected at the solution (a height difference far beyond the scale of the cells with a
        similar gradient: a change between the epochs, or a gross error).
    block_size : float
        Block edge (m) whose jackknife covariance was the larger.
    iterations : int
    converged : bool
    max_std : float
    message : str

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.height_model import height_model_shift
    >>> rng = np.random.default_rng(0)
    >>> def blocks(n):  # flat ground with 6 x 6 m boxes 5 m high on a 10 m grid
    ...     xy = rng.uniform(0, 50, (n, 2))
    ...     return np.column_stack([xy, 5.0 * (xy % 10 < 6).all(axis=1) + rng.normal(0, 0.02, n)])
    >>> hm = height_model_shift(blocks(6000) - [0.3, 0.2, 0.0], blocks(6000))
    >>> hm.determined.tolist(), bool(np.allclose(hm.translation, [0.3, 0.2, 0.0], atol=0.1))
    ([True, True, True], True)
    """

    translation: np.ndarray
    covariance: np.ndarray
    determined: np.ndarray
    direction_std: np.ndarray
    cell: float
    n_cells: int
    n_blocks: int
    block_size: float
    iterations: int
    converged: bool
    max_std: float
    message: str = ""
    n_rejected: int = 0

    @property
    def translation_std(self) -> np.ndarray:
        """Standard deviations of dx, dy, dz (m; inf where undetermined)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    def _report(self):
        rows = [(f"d{a}", (fmt(t, 4, "m") + f" +- {fmt(s, 4, 'm')}") if ok else "undetermined")
                for a, t, s, ok in zip("XYZ", self.translation, self.translation_std, self.determined)]
        rows += [("horizontal direction std", fmt(self.direction_std, 4, "m")),
                 ("cells / blocks", f"{self.n_cells} cells of {self.cell:.3g} m, {self.n_blocks} blocks of "
                                    f"{self.block_size:.3g} m (delete-a-block jackknife)"),
                 ("cells rejected", f"{self.n_rejected} (beyond {REJECT_SIGMAS:g} robust sigmas: changed between the epochs?)"),
                 ("converged", f"{self.converged} after {self.iterations} iterations")]
        if self.message:
            rows.append(("message", self.message))
        return "Height-model matching (source -> target)", [("", rows)]


def height_model_shift(source, target, *, initial=None, cell=None, max_std=0.1, max_iterations=30,
                       tol=1e-4, robust=False) -> HeightModelShift:
    """Shift of ``source`` onto ``target`` by least-squares matching of their height models.

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        Airborne clouds in one frame (UTM allowed); points of the noise classes (7, 18) are left out.
    initial : array_like (3,), optional
        Start shift (m), e.g. ICP's; default zero.
    cell : float, optional
        Cell size (m); default 1.5 times the larger median point spacing of the two clouds.
    max_std : float
        Precision limit (m): a component with a larger jackknife std is undetermined.
    max_iterations : int
        Gauss-Newton iterations per smoothing level.
    tol : float
        Convergence when the update is below ``tol`` metres.
    robust : bool
        Reject the cells whose height difference exceeds 5 robust sigmas (1.4826 MAD) of the cells with
        a similar gradient, anew in every step (:func:`robust_weights`): a part of the scene that
        changed between the epochs (a new building, felled trees) is left out instead of pulling the
        shift. Off by default: along a direction without common height jumps the rejection makes its
        own fit (see the module's measurements: sample_c). False: every cell counts.

    Returns
    -------
    HeightModelShift

    Raises
    ------
    LabkitError
        Too few points, or the two clouds share too few cells.

    References
    ----------
    .. [1] Notebook 05, section 6 (eq. 5.12a: determinability by precision) and notebook 06,
       eq. 6.14 (delete-a-block jackknife).
    .. [2] B. Rosenholm, K. Torlegard (1988): Three-dimensional absolute orientation of stereo
       models using digital elevation models. Photogrammetric Engineering and Remote Sensing 54(10),
       1385-1389.
    .. [3] A. Gruen, D. Akca (2005): Least squares 3D surface and curve matching. ISPRS Journal of
       Photogrammetry and Remote Sensing 59(3), 151-174, doi:10.1016/j.isprsjprs.2005.02.006.
    .. [4] G. Karel, M. Doneus, C. Briese, N. Pfeifer et al. (2006): Strip adjustment of ALS data by
       least-squares matching of height models; see also H.-G. Maas (2002): Methods for measuring
       height and planimetry discrepancies in airborne laserscanner data. PE&RS 68(9), 933-940.
    .. [5] B. Efron, C. Stein (1981): The jackknife estimate of variance. Annals of Statistics 9(3),
       586-596 (blocks: H. R. Kunsch 1989, Annals of Statistics 17(3), 1217-1241).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> def houses(n):  # flat ground, 8 x 4 m houses 4 m high on a 12 m grid: edges in X and Y
    ...     xy = rng.uniform(0, 60, (n, 2))
    ...     inside = (xy[:, 0] % 12 < 8) & (xy[:, 1] % 12 < 4)
    ...     return np.column_stack([xy, 4.0 * inside + rng.normal(0, 0.02, n)])
    >>> hm = height_model_shift(houses(8000) - [0.25, 0.0, 0.1], houses(8000))
    >>> err = hm.translation - [0.25, 0.0, 0.1]
    >>> bool(np.all(np.abs(err) < 3 * hm.translation_std)), bool(np.all(hm.translation_std < 0.1))
    (True, True)
    """
    src = _points(source, "source")
    tgt = _points(target, "target")
    max_std = positive(max_std, "max_std")
    origin = local_origin(tgt)
    src, tgt = src - origin, tgt - origin
    t0 = np.zeros(3) if initial is None else np.asarray(initial, dtype=np.float64).reshape(3)
    if cell is None:
        cell = 1.5 * max(median_spacing(src, distinct=True), median_spacing(tgt, distinct=True))
    cell = positive(cell, "cell")
    grid = _Grid.around(tgt, cell)
    raw_t, t, iterations = grid.raster(tgt), t0.copy(), 0
    for sigma in SMOOTHING:  # coarse to fine; the last level twice
        # the source is rasterised at the current shift: the target alone is interpolated (a low-pass),
        # and only by what this level still moves, so that both models stay equally smooth
        Zt, Zs = _smooth(raw_t, sigma), _smooth(grid.raster(src + t), sigma)
        x, n_it, converged, design = _match(grid, Zt, Zs, cell, max_iterations, tol, robust)
        t, iterations = t + x, iterations + n_it
    A, l, cells, epochs, w = design  # at the solution, with the weights there
    cov, n_blocks, block, single = _jackknife(A, l, cells, epochs, w)
    return _result(t, cov, n_blocks, block * cell, single, cell, len(l), iterations, converged, max_std,
                   int(np.sum(w == 0)))


def _match(grid, Zt, Zs, cell, max_iterations, tol, robust):
    """Gauss-Newton (cells rejected anew in each step when ``robust``) on one pair of smoothed height models:
    (shift, iterations, converged, last design with its weights)."""
    gt, gs = _gradient(Zt, cell), _gradient(Zs, cell)
    x, damping, previous, converged = np.zeros(3), 1.0, np.zeros(3), False
    for it in range(1, max_iterations + 1):
        A, l, cells, _ = _design(grid, Zt, Zs, gt, gs, x)
        if len(l) < 10:
            raise LabkitError(f"the height models share only {len(l)} cells of {cell:.3g} m: do the clouds "
                              "overlap? (height-model matching needs a common area)")
        w = robust_weights(l, A) if robust else np.ones(len(l))  # IRLS: the rejection follows the shift
        N = np.einsum("mi,m,mj->ij", A, w, A)  # einsum, not BLAS: the same sums on any number of threads
        s0 = float(np.sum(w * l**2)) / max(float(np.sum(w)) - 3, 1)  # variance of unit weight of this step
        # damped: a step of a cell is a 1-sigma prior
        dx = _solve(N + np.diag([s0, s0, 0.0]) / cell**2, np.einsum("mi,m,m->i", A, w, l))
        dx *= min(1.0, 0.5 * cell / max(np.hypot(dx[0], dx[1]), 1e-300))  # at most half a cell a step
        if dx @ previous < 0:  # a step that reverses the last one (the kinks of bilinear interpolation)
            damping = max(damping / 2, 1 / 64)
        previous = dx
        x = x + damping * dx
        formal = np.sqrt(s0 * np.clip(np.diag(np.linalg.pinv(N)), 0, None))
        converged = bool(np.all(np.abs(damping * dx) < np.maximum(tol, 0.05 * formal)))
        if converged:
            break
    A, l, cells, epochs = _design(grid, Zt, Zs, gt, gs, x)
    return x, it, converged, (A, l, cells, epochs, robust_weights(l, A) if robust else np.ones(len(l)))


def robust_weights(l, A, *, k=REJECT_SIGMAS, bins=GRADIENT_BINS):
    """Weight 0 for a cell whose height difference ``l`` lies beyond ``k`` robust sigmas of the cells with
    a similar gradient, else 1.

    The residuals of a height model are not alike: at a jump (roof edge, crown) the maximum per cell
    holds roof or ground by chance and the residuals are decimetres, on flat ground millimetres to
    centimetres. So the cells are put into ``bins`` classes of equal size by the length of their
    gradient (the first two columns of ``A``), and each residual is compared with its class's robust
    scale 1.4826 MAD about the class's median (notebook 05, eq. 5.8). A changed part of the scene (a
    new building: metres of height difference where both epochs are flat or one has an edge) lies far
    beyond the scale of its class; the edges that carry the shift stay. A hard limit, not a
    redescending weight (Tukey): the weights of Tukey's biweight on the sampling noise of the edges let
    the estimate settle, along a direction without height jumps, where a few cells happen to fit, with
    a jackknife std below the precision limit (a real gable roof: 1.6 m off at +-78 mm).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> A = np.column_stack([np.r_[np.zeros(900), np.full(100, 2.0)], np.zeros(1000), -np.ones(1000)])
    >>> l = np.r_[rng.normal(0, 0.02, 900), rng.normal(0, 0.3, 100)]  # flat cells, edge cells
    >>> l[:50] = 5.0  # a new building on flat ground
    >>> w = robust_weights(l, A)
    >>> bool(np.all(w[:50] == 0)), float(w[50:].mean())
    (True, 1.0)
    """
    g = np.hypot(A[:, 0], A[:, 1])
    rank = np.empty(len(g), dtype=np.int64)
    rank[np.argsort(g, kind="stable")] = np.arange(len(g))
    b = rank * max(1, min(bins, len(g) // 50)) // len(g)  # equal-sized classes of at least 50 cells
    u = np.empty(len(l))
    for c in np.unique(b):
        rows = b == c
        centred = l[rows] - np.median(l[rows])
        scale = 1.4826 * np.median(np.abs(centred))
        u[rows] = centred / max(scale, 1e-9 + 1e-6 * float(np.abs(l[rows]).max()))
    return (np.abs(u) < k).astype(np.float64)


def fill_held_axes(result, source, target, *, matched=None):
    """Fill the horizontal axes that point-to-plane left undetermined from height-model matching.

    ``result`` is an ICP result with ``dof='translation'`` on the selected points; ``source`` and
    ``target`` are the caller's whole clouds (roofs, crowns and ground make the height model). Where
    ICP holds X or Y (eq. 5.12a) and :func:`height_model_shift`, started at ICP's shift, determines
    them below the same precision limit, the held axes take its values and jackknife covariance. The
    axes ICP determined were solved with the held ones at their held value h0: with the precision
    matrix P of ICP's last adjustment (its degeneracy report, eq. 5.12b), they move by
    -B (h - h0), B = P_ff^-1 P_fh (eq. 5.15), and their covariance with h is -B Sigma_h. Their own
    covariance stays ICP's: it holds the prior of a held shift (the matching distance, eq. 5.15),
    which covers B Sigma_h B^T. Z therefore always comes from the point-to-plane observations;
    the height model's dz is not used (trees grow, its maximum per cell depends on the density).

    ``matched`` (optional) is a :class:`HeightModelShift` of the same clouds made at the start of
    ``result`` (``max_consensus`` fills its own held axes this way, and ICP started there holds them
    at those values): it is used instead of matching again when its verdict holds at this precision
    limit (X and Y determined at a limit no looser, or the same limit). Otherwise the match runs here.

    Returns
    -------
    (RegistrationResult, HeightModelShift or None)
        The result with the filled axes (its message and ``height_model`` say which came from where
        and why), or the result unchanged (with a note) when nothing could be filled.

    References
    ----------
    .. [1] Notebook 05, eqs. 5.12a-b and 5.15 (held parameters and their effect on the others).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration import icp
    >>> rng = np.random.default_rng(2)
    >>> def houses(n):  # flat ground, 8 x 4 m flat roofs 4 m high: point-to-plane sees only Z
    ...     xy = rng.uniform(0, 60, (n, 2))
    ...     inside = (xy[:, 0] % 12 < 8) & (xy[:, 1] % 12 < 4)
    ...     return np.column_stack([xy, 4.0 * inside + rng.normal(0, 0.02, n)])
    >>> res = icp(houses(8000) - [0.2, 0.1, 0.05], houses(8000))  # fill_held_axes runs inside
    >>> res.height_model is not None, bool(np.allclose(res.translation, [0.2, 0.1, 0.05], atol=0.1))
    (True, True)
    """
    deg = result.degeneracy
    if deg is None or tuple(result.parameter_names) != ("tx", "ty", "tz"):
        return result, None
    held = ~np.asarray(deg.axis_determined, dtype=bool)
    if not held[:2].any():
        return result, None
    max_std = deg.max_std if deg.max_std is not None else 0.1
    # determined below a limit is determined below any looser one; "undetermined" holds at the same limit only
    if isinstance(matched, HeightModelShift) and (matched.max_std == max_std or (
            matched.max_std <= max_std and bool(matched.determined[:2].all()))):
        hm, where = matched, " (matched once, at the start)"
    else:
        try:
            hm, where = height_model_shift(source, target, initial=result.translation, max_std=max_std), ""
        except LabkitError as exc:
            return replace(result, message=f"{result.message}; height model: not used ({exc})"), None
    fill = held & hm.determined & np.array([True, True, False])
    if not fill.any():
        note = (f"; the height model (all points, cells of {hm.cell:.3g} m{where}) does not fix X, Y either: "
                f"{hm.message or 'not determined'}")
        return replace(result, message=result.message + note, height_model=hm), hm
    free = ~held  # determined by ICP
    t = np.array(result.translation, dtype=np.float64)
    cov = np.array(result.covariance, dtype=np.float64)
    Ch = hm.covariance[np.ix_(fill, fill)]
    if free.any():  # the ICP-determined axes were solved at the held value h0 (eq. 5.15)
        B = deg.held_effect(free, fill)
        t[free] -= B @ (hm.translation[fill] - t[fill])
        cov[np.ix_(free, fill)] = -B @ Ch
        cov[np.ix_(fill, free)] = (-B @ Ch).T
        Cf = cov[np.ix_(free, free)]
        if np.linalg.eigvalsh(Cf - B @ Ch @ B.T)[0] < 0:  # ICP's prior did not cover it: add it
            cov[np.ix_(free, free)] = Cf + B @ Ch @ B.T
    t[fill] = hm.translation[fill]
    cov[np.ix_(fill, fill)] = Ch
    determined = free | fill
    deg = replace(deg, axis_determined=determined.copy(), parameter_determined=determined.copy())
    names = ", ".join(a for a, f in zip("XYZ", fill) if f)
    std = ", ".join(f"{1000 * np.sqrt(Ch[i, i]):.0f}" for i in range(len(Ch)))
    note = (f"; {names} FROM THE HEIGHT MODEL (+- {std} mm): point-to-plane on the selected surfaces left "
            f"{names} undetermined (normals nearly vertical), the height jumps of all points (roof edges, "
            f"crowns) fix {'them' if fill.sum() > 1 else 'it'}: least-squares matching of the highest point "
            f"per {hm.cell:.3g} m cell{where}, delete-a-block jackknife over {hm.n_blocks} blocks of "
            f"{hm.block_size:.3g} m; "
            f"{'Z' if free[2] else 'the other axes'} from point-to-plane, corrected to that position")
    rest = [a for a, h, f in zip("XYZ", held, fill) if h and not f]
    if rest:
        note += f"; {', '.join(rest)} undetermined by both"
    return replace(result, translation=t, covariance=cov, degeneracy=deg, message=result.message + note,
                   height_model=hm), hm


def _points(cloud, name):
    xyz = as_points(cloud, min_points=10, name=name)
    attrs = getattr(cloud, "attributes", None)
    if attrs is not None and "classification" in attrs:
        keep = ~np.isin(np.asarray(attrs["classification"]), NOISE_CLASSES)
        if keep.sum() >= 10:
            xyz = xyz[keep]
    return xyz


@dataclass(frozen=True)
class _Grid:
    """A raster over the local frame: lower-left corner, cell size, shape (ny, nx)."""

    corner: np.ndarray
    cell: float
    shape: tuple

    @classmethod
    def around(cls, xyz, cell):
        lo, hi = xyz[:, :2].min(axis=0) - 2 * cell, xyz[:, :2].max(axis=0) + 2 * cell
        n = np.ceil((hi - lo) / cell).astype(int) + 1
        if n.prod() > 4e7:
            raise LabkitError(f"a height model of {n[0]} x {n[1]} cells of {cell:.3g} m is too large: give a larger cell")
        return cls(lo, float(cell), (int(n[1]), int(n[0])))

    def raster(self, xyz):
        """Highest point per cell (NaN where empty); points outside the grid are dropped."""
        ij = np.floor((xyz[:, :2] - self.corner) / self.cell).astype(np.int64)
        inside = (ij >= 0).all(axis=1) & (ij[:, 0] < self.shape[1]) & (ij[:, 1] < self.shape[0])
        Z = np.full(self.shape[0] * self.shape[1], -np.inf)
        np.maximum.at(Z, ij[inside, 1] * self.shape[1] + ij[inside, 0], xyz[inside, 2])
        Z[~np.isfinite(Z)] = np.nan
        return Z.reshape(self.shape)

    def centres(self):
        iy, ix = np.indices(self.shape)
        return ix.ravel(), iy.ravel()


def _smooth(Z, sigma):
    """Normalised Gaussian smoothing; NaN where less than a quarter of the kernel's weight has data."""
    have = np.isfinite(Z)
    num = ndimage.gaussian_filter(np.where(have, Z, 0.0), sigma, mode="constant")
    den = ndimage.gaussian_filter(have.astype(float), sigma, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[den < 0.25] = np.nan
    return out


def _gradient(Z, cell):
    gy, gx = np.gradient(Z, cell)
    return gx, gy


def _bilinear(F, x, y):
    """F at fractional indices (x: column, y: row); NaN outside or next to a NaN."""
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 < F.shape[1] - 1) & (y0 < F.shape[0] - 1)
    out = np.full(len(x), np.nan)
    x0, y0, fx, fy = x0[ok], y0[ok], (x - np.floor(x))[ok], (y - np.floor(y))[ok]
    out[ok] = ((1 - fx) * (1 - fy) * F[y0, x0] + fx * (1 - fy) * F[y0, x0 + 1]
               + (1 - fx) * fy * F[y0 + 1, x0] + fx * fy * F[y0 + 1, x0 + 1])
    return out


def _design(grid, Zt, Zs, gt, gs, x):
    """Design rows, observations and cells of the cells both height models cover.

    Returns A with rows [g, -1] (g the mean of both epochs' gradients), l = -(Z_t(c + d) - Z_s(c) - dz),
    the (column, row) of each cell, and the gradient rows of each epoch alone ([g_s, -1], [g_t, -1]) for
    the information both epochs share. ``x`` = (dx, dy, dz), the shift beyond the start.
    """
    ix, iy = grid.centres()
    fx, fy = ix + x[0] / grid.cell, iy + x[1] / grid.cell
    f = _bilinear(Zt, fx, fy) - Zs.ravel() - x[2]  # misclosure at the current shift
    g_t = np.column_stack([_bilinear(gt[0], fx, fy), _bilinear(gt[1], fx, fy)])
    g_s = np.column_stack([gs[0].ravel(), gs[1].ravel()])
    ok = np.isfinite(f) & np.isfinite(g_t).all(axis=1) & np.isfinite(g_s).all(axis=1)
    one = -np.ones((ok.sum(), 1))
    A = np.hstack([0.5 * (g_s[ok] + g_t[ok]), one])  # f(x + dx) ~ f(x) + A dx
    return A, -f[ok], np.column_stack([ix[ok], iy[ok]]), (np.hstack([g_s[ok], one]), np.hstack([g_t[ok], one]))


def _jackknife(A, l, cells, epochs, w):
    """Delete-a-block jackknife covariance of the solution at its fixed point (eq. 6.14).

    The bread is the information both epochs share, J = sym(sum [g_s, -1]^T [g_t, -1]): the gradient
    of one epoch's noise is independent of the other's, so on a flat, noisy floor J ~ 0 in X and Y
    (and the deletions move the estimate by metres), whereas A^T A would count the noise's
    texture as information (as re-matching does for ICP, eq. 5.12b). The rejected cells (weight 0,
    :func:`robust_weights`) are left out of both. Leaving block b out moves the solution by
    d_b = -(J - J_b)^-1 A_b^T W_b l_b (at the solution A^T W l = 0); Sigma = (B - 1)/B sum
    d_b d_b^T over the block size (of :data:`BLOCK_CELLS`) with the larger trace, scaled by the t
    factor of few blocks. Returns (Sigma, B, block edge in cells, single): ``single`` is True when
    the shared information is not positive in some direction, or one block alone carries one.
    """
    Bs, Bt = epochs
    best = None
    for b in BLOCK_CELLS:
        _, block = np.unique(cells // b, axis=0, return_inverse=True)
        block = block.ravel()
        n_b = int(block.max()) + 1
        S = np.zeros((n_b, 3))
        np.add.at(S, block, A * (w * l)[:, None])
        Jb = np.zeros((n_b, 3, 3))
        np.add.at(Jb, block, w[:, None, None] * Bs[:, :, None] * Bt[:, None, :])
        Jb = 0.5 * (Jb + Jb.transpose(0, 2, 1))
        J = Jb.sum(axis=0)
        rest = J[None] - Jb
        floor = 1e-9 * float(np.einsum("mi,m,mi->", A, w, A))
        lam = np.linalg.eigvalsh(rest)
        single = bool((lam[:, 0] <= floor).any() or np.linalg.eigvalsh(J)[0] <= floor)
        if single:
            return np.full((3, 3), np.inf), n_b, b, True
        d = np.linalg.solve(rest, S[:, :, None])[:, :, 0]
        cov = np.einsum("bi,bj->ij", d, d) * (n_b - 1) / n_b * few_clusters_factor(n_b) ** 2
        if n_b < MIN_BLOCKS:
            cov = np.full((3, 3), np.inf)
        if best is None or np.trace(cov) > np.trace(best[0]) or not np.isfinite(np.trace(cov)):
            best = (cov, n_b, b, False)
            if not np.isfinite(np.trace(cov)):
                break
    return best


def _result(t, cov, n_blocks, block, single, cell, n_cells, iterations, converged, max_std, n_rejected=0):
    """The result: X and Y when both horizontal directions have a jackknife std below ``max_std``, else inf.

    A direction the height jumps do not fix is not just imprecise: the estimate wanders along it
    as far as the damping lets it (metres along the ridge of one long roof), and its jackknife,
    linearised at a point that is not a fixed point in that direction, says less than that. An axis
    with even a small share in it can then be decimetres off; so one weak horizontal direction
    leaves both axes undetermined (eq. 5.12a), and dz is stated only with dx and dy (it depends on
    where the surfaces are compared).
    """
    finite = bool(np.isfinite(cov).all()) and converged and not single
    dir_std = np.sqrt(np.clip(np.linalg.eigvalsh(cov[:2, :2]), 0, None)) if finite else np.full(2, np.inf)
    both = finite and bool(np.all(dir_std < max_std))
    determined = np.array([both, both, both and np.sqrt(cov[2, 2]) < max_std])
    cov = cov.copy() if finite else np.full((3, 3), np.inf)
    cov[~determined, :] = np.inf
    cov[:, ~determined] = np.inf
    why = []
    if single:
        why.append("the information both epochs share is not positive in some direction (no common height jumps), "
                   "or one block alone carries it: nothing stated")
    if n_blocks < MIN_BLOCKS:
        why.append(f"only {n_blocks} blocks (at least {MIN_BLOCKS} needed for the jackknife)")
    if not converged:
        why.append(f"not converged after {iterations} iterations: nothing stated")
    loose = [a for a, ok in zip("XYZ", determined) if not ok]
    if loose and finite:
        why.append(f"{', '.join(loose)} undetermined: horizontal direction std {np.array2string(dir_std, precision=3)} m "
                   f"against the limit {max_std:g} m (dz is stated only with dx and dy)")
    elif loose:
        why.append(f"{', '.join(loose)} undetermined")
    return HeightModelShift(t, cov, determined, dir_std, float(cell), int(n_cells), int(n_blocks),
                            float(block), int(iterations), bool(converged), float(max_std), "; ".join(why),
                            int(n_rejected))


def _solve(N, n):
    lam, V = np.linalg.eigh(0.5 * (N + N.T))
    ok = lam > 1e-10 * max(lam[-1], 1e-300)
    return V[:, ok] @ ((V[:, ok].T @ n) / lam[ok])
