"""Steps shared by the local-PCA functions of :mod:`labkit.features` (private; notebook 04, eqs. 3-5).

The sorted eigen decomposition (eq. 3), the test whether a neighbourhood determines
a plane, the local noise (eq. 5), the orientation of the normals and the argument
checks that :func:`~labkit.features.local_pca`, :func:`~labkit.features.multiscale_features`
and :func:`~labkit.features.robust_normals` share.
"""

from __future__ import annotations

import numpy as np

from ..core.checks import choice
from ..neighbours.eigh3 import eigh3_analytic
from ..core.errors import LabkitError

DUPLICATES = ("merge", "keep")
ORIENTATIONS = ("up", "viewpoint", "none")
def check_at(at, n):
    """None, or a 1-D integer index array into the n points."""
    if at is None:
        return None
    idx = np.asarray(at)
    if idx.ndim == 1 and len(idx) == 0:
        raise LabkitError("at is empty: give at least one point index")
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise LabkitError(f"at must be a 1-D array of point indices, got shape {idx.shape} and dtype {idx.dtype}")
    if len(idx) == 0:
        raise LabkitError("at is empty: give at least one point index")
    if idx.min() < -n or idx.max() >= n:
        raise LabkitError(f"at contains indices outside 0..{n - 1}")
    return np.where(idx < 0, idx + n, idx).astype(np.intp)


def check_duplicates(duplicates) -> bool:
    return choice(duplicates, DUPLICATES, "duplicates") == "merge"


def determined(lam, counts) -> np.ndarray:
    """True where a plane is determined: m >= 3 and l2 > 1e-12 l1 (not a point, not a line).

    ``lam`` descending (n, 3). A line has l2 = 0 up to rounding, which is about
    eps^2 of l1 on reduced coordinates; 1e-12 means a width below 1e-6 of the length.
    """
    l1, l2 = lam[:, 0], lam[:, 1]
    with np.errstate(invalid="ignore"):
        return (counts >= 3) & (l2 > 1e-12 * l1) & np.isfinite(l1)


def mark_undetermined(lam, vec, counts) -> None:
    """NaN normals (eigenvector column 2) where :func:`determined` is False (in place)."""
    bad = ~determined(lam, counts)
    if bad.any():
        vec[bad, :, 2] = np.nan




def check_orientation(orient, viewpoint, n):
    choice(orient, ORIENTATIONS, "orient")
    if orient != "viewpoint":
        if viewpoint is not None:
            raise LabkitError("viewpoint is only used with orient='viewpoint'")
        return None
    if viewpoint is None:
        raise LabkitError("orient='viewpoint' needs viewpoint: shape (3,) or (n, 3)")
    v = np.asarray(viewpoint, dtype=np.float64)
    if v.shape not in ((3,), (n, 3)) or not np.isfinite(v).all():
        raise LabkitError(f"viewpoint must be finite with shape (3,) or ({n}, 3), got {v.shape}")
    return v




def sorted_eigh(C):
    """Eigenvalues (c, 3) descending and eigenvectors (c, 3, 3) in the same column order (eq. 3).

    ``np.linalg.eigh`` returns ascending eigenvalues of a symmetric matrix; we reverse
    once. (``np.linalg.eig`` would return them in no particular order: the pitfall the registration study warns of.)
    :func:`labkit.neighbours.eigh3.eigh3_analytic` is the same decomposition in closed form for
    stacks of 3x3 matrices, as accurate and about 10x faster than ``np.linalg.eigh``;
    matrices with NaN (too few neighbours) give NaN rows.
    """
    lam, V = eigh3_analytic(np.reshape(C, (-1, 3, 3)))  # ascending, like np.linalg.eigh
    return np.clip(lam[:, ::-1], 0.0, None), V[:, :, ::-1]


def plane_noise(l3, m):
    """sigma_n = sqrt(m l3 / (m - 3)) (eq. 5); NaN for m <= 3."""
    m = np.asarray(m, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(m > 3, np.sqrt(m * l3 / (m - 3)), np.nan)


def orient_normals(nrm, local, orient, view, origin):
    """Flip normals to n_z >= 0 ('up') or to n . (viewpoint - p) >= 0 ('viewpoint')."""
    if orient == "none":
        return np.ascontiguousarray(nrm)
    if orient == "up":
        flip = nrm[:, 2] < 0
    else:
        flip = np.einsum("nd,nd->n", nrm, (view - origin) - local) < 0
    return np.where(flip[:, None], -nrm, nrm)
