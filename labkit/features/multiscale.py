"""Local PCA at several neighbourhood sizes, the scale of least eigenentropy per point (notebook 04, eq. 8).

A small neighbourhood sees only noise, a large one mixes surfaces; per point the
scale whose eigenvalues are most "decided" (least eigenentropy) is kept.

References
----------
Weinmann et al. (2015), cited in full in :mod:`labkit.features.eigen`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.checks import choice
from ..core.report import ReportMixin
from ..core.errors import LabkitError
from ..neighbours.search import CHUNK_SIZE, SearchPlan, check_chunk_size, check_scale, reduced, run_chunks
from ..neighbours.moments import covariances
from ._steps import check_duplicates, check_orientation, mark_undetermined, orient_normals, sorted_eigh
from .eigen import EigenFeatures, eigen_features
from .pca import LocalPCA


@dataclass(frozen=True, eq=False, repr=False)
class MultiScaleFeatures(ReportMixin):
    """Local PCA at several scales and, per point, the scale of least eigenentropy.

    Attributes
    ----------
    scales : tuple
        The k values (by='k') or radii (by='radius').
    eigenvalues : ndarray (n, s, 3)
        Sorted eigenvalues at every scale.
    best : ndarray (n,)
        Index into ``scales`` with minimal eigenentropy (Weinmann et al. 2015).
    pca : LocalPCA
        The PCA of every point at its chosen scale (``k``/``radius`` fields are None).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.features import multiscale_features
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)
    >>> ms = multiscale_features(floor, scales=(10, 20))
    >>> ms.scales, ms.best.shape, ms.entropy.shape
    ((10, 20), (200,), (200, 2))
    >>> bool(np.median(ms.features.planarity) > 0.3)  # a plane, not a line or a volume
    True
    """

    scales: tuple
    by: str
    eigenvalues: np.ndarray
    best: np.ndarray
    pca: LocalPCA

    def __repr__(self) -> str:
        return f"MultiScaleFeatures({len(self.best)} points, {self.by} = {self.scales})"

    @property
    def entropy(self) -> np.ndarray:
        """Eigenentropy (n, s) at every scale."""
        return eigen_features(self.eigenvalues).eigenentropy

    @property
    def features(self) -> EigenFeatures:
        """Eigenvalue features at each point's chosen scale."""
        return self.pca.features

    def _report(self):
        share = np.bincount(self.best, minlength=len(self.scales)) / max(len(self.best), 1)
        rows = [(f"{self.by} = {s}", f"chosen for {100 * p:.1f} % of the points") for s, p in zip(self.scales, share)]
        return "Multi-scale local PCA (least eigenentropy)", [("", rows)]


def multiscale_features(
    points, scales=(10, 20, 40), *, by: str = "k", orient: str = "up", viewpoint=None, duplicates: str = "merge",
    chunk_size: int = CHUNK_SIZE,
) -> MultiScaleFeatures:
    """Local PCA at several neighbourhood sizes; per point keep the scale of least eigenentropy.

    A small scale sees only noise, a large one mixes surfaces; the scale whose
    eigenvalues are most "decided" (least eigenentropy, eq. 8) is kept per point.
    For ``by='k'`` a single search with the largest k serves all scales (kNN
    neighbourhoods are nested).

    Parameters
    ----------
    scales : sequence of int (by='k') or float (by='radius')
    by : {'k', 'radius'}
    duplicates : {'merge', 'keep'}
        Exact duplicates count once (default), see :func:`local_pca`.

    References
    ----------
    .. [1] Notebook 04, section 9, eqs. 6-8; the registration study, step 4 (repeat with several radii / k).
    .. [2] M. Weinmann et al. (2015): eigenentropy, ISPRS J. 105, 286-304.
    .. [3] K. F. West, B. N. Webb, J. R. Lersch, S. Pothier, J. M. Triscari, A. E. Iverson (2004):
       Context-driven automated target detection in 3D data. Proc. SPIE 5426, 133-143.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # z = 0, 1 mm noise
    >>> ms = multiscale_features(floor, scales=(10, 20, 40))
    >>> ms.eigenvalues.shape, sorted(set(ms.best.tolist()))  # (n, scales, 3); chosen scale per point
    ((200, 3, 3), [0, 1, 2])
    >>> np.round(abs(ms.pca.normals[0]), 2)
    array([0., 0., 1.])
    """
    local, origin = reduced(points)
    choice(by, ("k", "radius"), "by")
    scales = tuple(sorted(scales))
    if not scales:
        raise LabkitError("scales must contain at least one k or radius")
    checked = [check_scale(s, None, len(local)) if by == "k" else check_scale(None, s, len(local)) for s in scales]
    view = check_orientation(orient, viewpoint, len(local))
    plan = SearchPlan(local, None, check_duplicates(duplicates))  # exact duplicates merged
    n, s = plan.n_out, len(scales)
    lam_all = np.empty((n, s, 3))
    vec, cen, counts = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty(n, dtype=np.intp)
    best = np.empty(n, dtype=np.intp)
    pts = plan.points
    cols = pts.T.copy()

    def work(rows, per_scale, _):
        # per scale: eigenvalues; keep the eigenvectors of the least-entropy scale
        results = [(covariances(pts, c, f, cols), c) for c, f in per_scale]
        eig = [sorted_eigh(C) for (_, C), _ in results]
        lam_all[rows] = np.stack([lam for lam, _ in eig], axis=1)
        h = eigen_features(lam_all[rows]).eigenentropy
        b = np.argmin(np.where(np.isfinite(h), h, np.inf), axis=1)
        pick = np.arange(len(rows))
        best[rows] = b
        vec[rows] = np.stack([v for _, v in eig], axis=1)[pick, b]
        cen[rows] = np.stack([c for (c, _), _ in results], axis=1)[pick, b]
        counts[rows] = np.stack([m for _, m in results], axis=1)[pick, b]

    run_chunks(plan, checked, check_chunk_size(chunk_size), work)
    lam_all, best, vec, cen, counts = (plan.out(a) for a in (lam_all, best, vec, cen, counts))
    lam = lam_all[np.arange(len(local)), best]
    mark_undetermined(lam, vec, counts)
    normals = orient_normals(vec[:, :, 2], local, orient, view, origin)
    vec[:, :, 2] = normals
    pca = LocalPCA(lam, vec, normals, cen + origin, counts, None, None, plan.n_duplicates)
    return MultiScaleFeatures(scales, by, lam_all, best, pca)

