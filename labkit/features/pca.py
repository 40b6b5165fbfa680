"""Local PCA of every neighbourhood: normals, eigenvalues, centroids, local noise (notebook 04, eqs. 1-5).

For every point p_i the m points of its neighbourhood (k nearest neighbours, or
all points within a radius; :mod:`labkit.neighbours`) are reduced to their
centroid and summarised by their 3x3 covariance matrix:

- (eq. 1) centroid            p_bar = 1/m sum_j p_j
- (eq. 2) covariance          C = 1/m sum_j (p_j - p_bar)(p_j - p_bar)^T
- (eq. 3) eigen decomposition C = V diag(l1, l2, l3) V^T with l1 >= l2 >= l3 >= 0
- (eq. 4) normal              n = v3 (eigenvector of the smallest eigenvalue)
- (eq. 5) local noise         sigma_n = sqrt(m l3 / (m - 3)) (redundancy m - 3 of a fitted plane)

Exact duplicates are merged before the search (a copy is not a second
observation of the surface). Degenerate neighbourhoods (fewer than 3 distinct
points, or all on one line) do not determine a plane: their normal is NaN and
``LocalPCA.valid`` is False.

:func:`pca_at` gives the same normals and noise at chosen points of a kd-tree that a
caller already holds (the distances of :mod:`labkit.change.distances` reuse ICP's target tree).

References
----------
Hoppe, DeRose, Duchamp, McDonald, Stuetzle (1992): Surface reconstruction from
unorganized points. SIGGRAPH '92, 71-78.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.report import ReportMixin, fmt
from ..neighbours.search import CHUNK_SIZE, SearchPlan, check_chunk_size, check_scale, reduced, run_chunks
from ..neighbours.moments import covariances
from ..neighbours.search import run_moment_chunks, scale_text
from ..core.progress import progress_steps
from ._steps import check_at, check_duplicates, check_orientation, determined, mark_undetermined, orient_normals
from ._steps import plane_noise, sorted_eigh
from .eigen import EigenFeatures, eigen_features


@dataclass(frozen=True, eq=False, repr=False)
class LocalPCA(ReportMixin):
    """Result of :func:`local_pca`: per point eigenvalues, eigenvectors, normal and centroid.

    Attributes
    ----------
    eigenvalues : ndarray (n, 3)
        l1 >= l2 >= l3 >= 0 of the covariance (eq. 2-3), m^2.
    eigenvectors : ndarray (n, 3, 3)
        Column j belongs to ``eigenvalues[:, j]``; column 2 equals ``normals``.
    normals : ndarray (n, 3)
        Unit normals (eq. 4), oriented as requested.
    centroids : ndarray (n, 3)
        Neighbourhood centroids (eq. 1) in the input frame.
    counts : ndarray (n,)
        Number of neighbours m (including the point), distinct points when duplicates are merged.
    k, radius : search used.
    n_duplicates : int
        Input points that were exact copies of another point and were merged into it
        before the PCA (``duplicates='merge'``); they get the result of their kept copy.

    Examples
    --------
    >>> from labkit.features import local_pca
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # z = 0, 1 mm noise
    >>> pca = local_pca(floor, k=20)
    >>> pca.eigenvalues.shape, pca.eigenvectors.shape, int(pca.counts[0]), bool(pca.valid.all())
    ((200, 3), (200, 3, 3), 20, True)
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    normals: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray
    k: int | None
    radius: float | None
    n_duplicates: int = 0

    def __repr__(self) -> str:
        return f"LocalPCA({len(self.counts)} points, {scale_text(self.k, self.radius)})"

    @property
    def noise(self) -> np.ndarray:
        """Local noise sigma_n (eq. 5), metres; NaN where m <= 3 or the normal is undetermined."""
        return np.where(self.valid, plane_noise(self.eigenvalues[:, 2], self.counts), np.nan)

    @property
    def features(self) -> "EigenFeatures":
        """Eigenvalue features (eq. 6-8) of every neighbourhood."""
        return eigen_features(self.eigenvalues)

    @property
    def valid(self) -> np.ndarray:
        """True where the normal is determined: m >= 3 and the neighbourhood is not a line or a point.

        Where False the normal (and eigenvector column 2) is NaN.
        """
        return determined(self.eigenvalues, self.counts)

    @property
    def verticality(self) -> np.ndarray:
        """1 - |n_z|: 0 for horizontal surfaces, 1 for walls."""
        return 1.0 - np.abs(self.normals[:, 2])

    def _report(self):
        noise, f = self.noise, self.features
        rows = [
            ("points", str(len(self.counts))),
            ("search", scale_text(self.k, self.radius)),
            ("neighbours median", f"{np.median(self.counts):.0f}"),
            ("normal undetermined", str(int((~self.valid).sum()))),
            ("exact duplicates merged", str(self.n_duplicates)),
            ("local noise median", fmt(np.nanmedian(noise) if np.isfinite(noise).any() else np.nan, 4, "m")),
        ]
        rows += [(f"{name} median", fmt(np.nanmedian(v), 3)) for name, v in f.items() if np.isfinite(v).any()]
        return "Local PCA", [("", rows)]


def local_pca(
    points,
    k: int | None = 20,
    radius: float | None = None,
    *,
    orient: str = "up",
    viewpoint=None,
    at=None,
    duplicates: str = "merge",
    chunk_size: int = CHUNK_SIZE,
    progress=False,
) -> LocalPCA:
    """PCA of the neighbourhood of every point (eq. 1-4), vectorized and chunked.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        UTM-sized coordinates are fine: the algebra runs on a local origin.
    k : int, optional
        Nearest neighbours including the point (3 <= k <= n). Ignored if ``radius`` is given.
    radius : float, optional
        Ball radius in metres instead of kNN; points with fewer than 3 neighbours get NaN.
    orient : {'up', 'viewpoint', 'none'}
        'up': n_z >= 0 (ALS); 'viewpoint': toward ``viewpoint`` (3,) or per point (n, 3) (TLS
        scanner position, ALS trajectory); 'none': the sign eigh returns.
    at : array_like of int, optional
        Compute only at these points (neighbours still come from the whole cloud); the
        results then have ``len(at)`` rows and a per-point viewpoint has shape (len(at), 3).
    duplicates : {'merge', 'keep'}
        'merge' (default): exact duplicates (identical coordinates) count once, so that
        k means k distinct points; a duplicate is a second copy, not a second observation
        of the surface, and copies bias the plane toward themselves. The
        number merged is ``n_duplicates``. 'keep': every row counts.
    chunk_size : int
        Points per chunk; memory grows with chunk_size * k, not with n * k.
    progress : bool, "bar", "lines" or callable
        Report the chunks done (see :mod:`labkit.core.progress`); default silent.

    Returns
    -------
    LocalPCA
        Where the neighbourhood is degenerate (fewer than 3 distinct points, all on one
        line) the normal is NaN and ``valid`` is False.

    Raises
    ------
    LabkitError
        Bad points (NaN, wrong shape), k < 3 or k > n, radius <= 0, bad orientation.

    References
    ----------
    .. [1] Notebook 04, section 2, eqs. 1-4; the registration study, step 4 (kd-tree, centred covariance, PCA).
    .. [2] H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle (1992): Surface reconstruction
       from unorganized points. Computer Graphics (Proc. SIGGRAPH '92) 26(2), 71-78.
    .. [3] J. H. Friedman, J. L. Bentley, R. A. Finkel (1977): k-d tree search, doi:10.1145/355744.355745.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # z = 0, 1 mm noise
    >>> pca = local_pca(floor, k=20)
    >>> np.round(abs(pca.normals[0]), 2)  # the normal of the plane z = 0
    array([0., 0., 1.])
    >>> bool(np.median(pca.noise) < 0.002)  # about the 1 mm noise
    True
    """
    origin, here, view, plan, (k, radius), out = _pca(
        points, k, radius, orient, viewpoint, at, duplicates, chunk_size, progress, full=True
    )
    lam, vec, cen, counts = out
    # Orient the normals; results in the input frame
    normals = orient_normals(vec[:, :, 2], here, orient, view, origin)
    vec[:, :, 2] = normals
    return LocalPCA(lam, vec, normals, cen + origin, counts, k, radius, plan.n_duplicates)


def _pca(points, k, radius, orient, viewpoint, at, duplicates, chunk_size, progress, full):
    """The checks and the chunked PCA of :func:`local_pca`; with ``full=False`` only the normal of
    every point is kept (NaN where undetermined): :func:`normals` then writes and moves 3 numbers per
    point instead of 16 (eigenvalues, eigenvectors, centroid, count), the same normals."""
    # Reduce to a local origin and check the arguments
    local, origin = reduced(points)
    k, radius = check_scale(k, radius, len(local))
    at = check_at(at, len(local))
    here = local if at is None else local[at]  # the points that get a PCA
    view = check_orientation(orient, viewpoint, len(here))
    merge = check_duplicates(duplicates)
    # Exact duplicates merged into one point, kd-tree, output rows
    plan = SearchPlan(local, at, merge)
    # Per chunk (in leaf order): neighbours, centroid, covariance, sorted eigh
    n = plan.n_out
    if full:
        lam, vec = np.empty((n, 3)), np.empty((n, 3, 3))
        cen, counts = np.empty((n, 3)), np.empty(n, dtype=np.intp)
    else:
        nrm = np.empty((n, 3))
    pts = plan.points

    def moments(rows, seg_counts, c, C):
        l, V = sorted_eigh(C)
        if full:
            lam[rows], vec[rows] = l, V
            cen[rows], counts[rows] = c, seg_counts
        else:  # the normal, NaN where the neighbourhood is a point or a line (as mark_undetermined)
            nrm[rows] = np.where(determined(l, seg_counts)[:, None], V[:, :, 2], np.nan)

    def work(rows, per_scale, _):
        seg_counts, flat = per_scale[0]
        moments(rows, seg_counts, *covariances(pts, seg_counts, flat))  # ragged radius neighbourhoods

    with progress_steps(progress, plan.n_query, "normals", "pts") as step:
        if radius is None:  # kNN: the moments summed in the search kernel (no neighbour array)
            run_moment_chunks(plan, k, check_chunk_size(chunk_size), moments, step=step)
        else:
            run_chunks(plan, [(k, radius)], check_chunk_size(chunk_size), work, step=step)
    if not full:
        return origin, here, view, plan, (k, radius), plan.out(nrm)
    lam, vec, cen, counts = plan.out(lam), plan.out(vec), plan.out(cen), plan.out(counts)
    # Degenerate neighbourhoods (a point, a line) have no normal: NaN, valid=False
    mark_undetermined(lam, vec, counts)
    return origin, here, view, plan, (k, radius), (lam, vec, cen, counts)


def normals(
    points, k: int = 20, orient: str = "up", viewpoint=None, *, radius=None, at=None, duplicates="merge",
    chunk_size=CHUNK_SIZE, progress=False,
):
    """Unit normals (n, 3): eigenvector of the smallest eigenvalue of each neighbourhood (eq. 4).

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
    k : int
        Neighbours including the point itself (3 <= k <= n).
    orient : {'up', 'viewpoint', 'none'}
        'up' gives n_z >= 0 (ALS convention); 'viewpoint' points the normals toward
        ``viewpoint``; 'none' leaves eigh's arbitrary sign.
    viewpoint : array_like (3,) or (n, 3), optional
        Sensor position(s) in the frame of ``points``; only with orient='viewpoint'.
    radius : float, optional
        Radius neighbourhood instead of kNN.
    at : array_like of int, optional
        Only at these points (neighbours from the whole cloud); shape (len(at), 3).
    duplicates : {'merge', 'keep'}
        Exact duplicates count once (default), see :func:`local_pca`.
    progress : bool, "bar", "lines" or callable
        Report the chunks done (see :mod:`labkit.core.progress`); default silent.

    Returns
    -------
    ndarray (n, 3)
        NaN rows where the neighbourhood is degenerate (a point or a line).

    See Also
    --------
    local_pca : eigenvalues, centroids and counts as well.

    References
    ----------
    .. [1] Notebook 04, section 2, eqs. 1-4; the registration study, step 4 (normal = eigenvector of the smallest
       eigenvalue).
    .. [2] H. Hoppe et al. (1992): Surface reconstruction from unorganized points (SIGGRAPH '92).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # z = 0, 1 mm noise
    >>> n = normals(floor, k=20)  # orient='up': n_z >= 0
    >>> n.shape, np.round(abs(n[0]), 2), bool((n[:, 2] > 0).all())
    ((200, 3), array([0., 0., 1.]), True)
    """
    origin, here, view, _, _, nrm = _pca(
        points, k, radius, orient, viewpoint, at, duplicates, chunk_size, progress, full=False
    )  # as local_pca(...).normals, with less memory
    return orient_normals(nrm, here, orient, view, origin)


def local_noise(points, k: int = 20, radius: float | None = None, *, chunk_size: int = CHUNK_SIZE) -> np.ndarray:
    """Local noise sigma_n = sqrt(m l3 / (m - 3)) (eq. 5): spread of the neighbourhood along its normal, metres.

    l3 is the mean squared orthogonal residual of the best-fitting plane through the
    m neighbours; a plane has u = 3 parameters (two angles, one distance), so the
    redundancy is m - 3. ``points`` may also be a :class:`LocalPCA` (no new search).

    References
    ----------
    .. [1] Notebook 04, section 6, eq. 5; the registration study, step 4 ('lokales Rauschen' with PCA).
    .. [2] H. Hoppe et al. (1992): Surface reconstruction from unorganized points (SIGGRAPH '92).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0, noise=0.005)  # z = 0, 5 mm noise
    >>> sigma = local_noise(floor, k=20)
    >>> sigma.shape, round(float(np.median(sigma)), 3)
    ((200,), 0.005)
    """
    pca = points if isinstance(points, LocalPCA) else local_pca(points, k, radius, orient="none", chunk_size=chunk_size)
    return pca.noise


def pca_at(tree, at, k: int, *, chunk_size: int = CHUNK_SIZE, step=None, seen=None):
    """Normals (oriented up) and local noise of ``k`` neighbours at the points ``at`` of a kd-tree one already has.

    The numbers of ``local_pca(points, k=k, at=at)`` (eqs. 1-5: the normal, and the noise
    :attr:`LocalPCA.noise`) without building a second tree: for a step that holds the
    compiled kd-tree of a cloud (the distances of :mod:`labkit.change.distances` share the one ICP
    built) and needs the local planes only at some of its points. The queries run chunk by
    chunk in the tree's leaf order (the visited leaves stay in cache).

    Parameters
    ----------
    tree : labkit.neighbours.kdtree.KDTree
        Tree of the (reduced) cloud; with ``merge_duplicates=True`` exact copies count once,
        as ``local_pca``'s default ``duplicates='merge'``.
    at : array_like of int
        Rows of the cloud the tree was built from (negative counts from the end).
    k : int
        Neighbours including the point, 3 <= k <= number of points (fewer if merged copies leave fewer).
    chunk_size : int
        Query points per chunk (memory grows with chunk_size * k).
    step : callable, optional
        ``step(n)`` hears of every finished chunk of n points (a progress reporter).
    seen : callable, optional
        ``seen(rows, nb)`` receives each chunk's positions in ``at`` and their ``k`` neighbours as
        leaf positions of the tree, (len(rows), k), sorted by distance (-1: none): for a caller that
        needs more from the same search (e.g. the distance to a neighbour) without searching again.

    Returns
    -------
    normals : ndarray (len(at), 3)
        Unit normals with n_z >= 0; NaN where the neighbourhood is a point or a line.
    noise : ndarray (len(at),)
        sigma_n = sqrt(k l3 / (k - 3)) in the units of the cloud; NaN where the normal is, or for k = 3.

    References
    ----------
    .. [1] Notebook 04, section 2, eqs. 1-4.
    .. [2] H. Hoppe et al. (1992): Surface reconstruction from unorganized points (SIGGRAPH '92).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.neighbours.kdtree import KDTree
    >>> from labkit.features import local_pca, pca_at
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(500, 0)  # z = 0, 1 mm noise
    >>> tree = KDTree(floor, merge_duplicates=True)
    >>> n, sigma = pca_at(tree, [3, 7, 11], k=20)
    >>> n.shape, bool((n[:, 2] > 0.999).all()), bool(np.allclose(n, local_pca(floor, k=20, at=[3, 7, 11]).normals))
    ((3, 3), True, True)
    >>> bool(np.all(abs(sigma - 0.001) < 0.0005))  # about the 1 mm noise
    True
    """
    rep = tree.representative  # leaf position of the kept copy of every input row
    if rep is None:  # a tree without merging
        rep = np.empty(len(tree.indices), dtype=np.intp)
        rep[tree.indices] = np.arange(len(tree.indices))
    at = check_at(at, len(rep))
    k = min(check_scale(k, None, len(rep))[0], tree.n)
    chunk_size = check_chunk_size(chunk_size)
    pos = rep[at]
    order = np.argsort(pos, kind="stable")  # leaf order
    cols = np.ascontiguousarray(tree.data.T)
    nrm, noise = np.empty((len(at), 3)), np.empty(len(at))
    for a in range(0, len(at), chunk_size):
        rows = order[a : a + chunk_size]
        nb = tree.query_leaf_positions(pos[rows], k, workers=-1 if len(rows) > 2000 else 1)
        lam, V = sorted_eigh(covariances(tree.data, None, nb, cols)[1])  # (eqs. 1-3)
        ok = determined(lam, k)
        nrm[rows] = np.where(ok[:, None], V[:, :, 2], np.nan)  # (eq. 4)
        noise[rows] = np.where(ok, plane_noise(lam[:, 2], k), np.nan)  # (eq. 5)
        if seen is not None:
            seen(rows, nb)
        if step is not None:
            step(len(rows))
    return np.where(nrm[:, 2:3] < 0, -nrm, nrm), noise
