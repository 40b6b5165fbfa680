"""Eigenvalue features of a neighbourhood: linearity, planarity, scattering, ... (notebook 04, eqs. 6-8).

On the normalized eigenvalues e_i = l_i / (l1 + l2 + l3) (eq. 6) of a local PCA,
linearity, planarity and scattering (eq. 7) say whether a neighbourhood looks like
a line, a plane or a volume; omnivariance, anisotropy, eigenentropy and the change
of curvature (eq. 8) complete the usual set.

References
----------
Weinmann, Jutzi, Hinz, Mallet (2015): Semantic point cloud interpretation based on
optimal neighborhoods, relevant features and efficient classifiers. ISPRS J. 105, 286-304.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.report import ReportMixin, fmt
from ..core.errors import LabkitError


@dataclass(frozen=True, eq=False, repr=False)
class EigenFeatures(ReportMixin):
    """Eigenvalue features on normalized eigenvalues e_i = l_i / sum(l) (eq. 6-8).

    Linearity, planarity and scattering sum to 1; the largest says whether a
    neighbourhood looks like a line, a plane or a volume. Values are NaN where all
    eigenvalues are zero (all neighbours coincide).

    Examples
    --------
    >>> from labkit.features import eigen_features
    >>> f = eigen_features([4.0, 1.0, 0.0])  # a stretched plane
    >>> round(float(f.linearity), 3), round(float(f.planarity), 3), round(float(f.scattering), 3)
    (0.75, 0.25, 0.0)
    >>> f["planarity"] is f.planarity, len(f.keys())
    (True, 8)
    """

    linearity: np.ndarray  # (e1 - e2) / e1
    planarity: np.ndarray  # (e2 - e3) / e1
    scattering: np.ndarray  # e3 / e1 (sphericity)
    omnivariance: np.ndarray  # (e1 e2 e3)^(1/3)
    anisotropy: np.ndarray  # (e1 - e3) / e1
    eigenentropy: np.ndarray  # -sum e_i ln e_i
    change_of_curvature: np.ndarray  # e3 (surface variation)
    sum: np.ndarray  # l1 + l2 + l3, m^2

    NAMES = (
        "linearity", "planarity", "scattering", "omnivariance",
        "anisotropy", "eigenentropy", "change_of_curvature", "sum",
    )  # fmt: skip

    def __repr__(self) -> str:
        return f"EigenFeatures({np.shape(self.sum)}: {', '.join(self.NAMES)})"

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.NAMES:
            raise KeyError(f"no feature {name!r}; have {', '.join(self.NAMES)}")
        return getattr(self, name)

    def keys(self):
        return self.NAMES

    def items(self):
        return [(name, getattr(self, name)) for name in self.NAMES]

    def dominant(self) -> np.ndarray:
        """0 (line), 1 (plane) or 2 (volume): the largest of linearity, planarity, scattering."""
        return np.argmax(np.stack([self.linearity, self.planarity, self.scattering], axis=-1), axis=-1)

    def _report(self):
        rows = [(name, fmt(np.nanmedian(v), 4)) for name, v in self.items() if np.isfinite(v).any()]
        return "Eigenvalue features (medians)", [("", rows)]


def eigen_features(eigenvalues) -> EigenFeatures:
    """Dimensionality features of sorted eigenvalues (..., 3), l1 >= l2 >= l3 (eq. 6-8).

    References
    ----------
    .. [1] Notebook 04, section 7, eqs. 6-8.
    .. [2] M. Weinmann, B. Jutzi, S. Hinz, C. Mallet (2015): Semantic point cloud interpretation
       based on optimal neighborhoods, relevant features and efficient classifiers. ISPRS Journal of
       Photogrammetry and Remote Sensing 105, 286-304.
    .. [3] K. F. West, B. N. Webb, J. R. Lersch, S. Pothier, J. M. Triscari, A. E. Iverson (2004):
       Context-driven automated target detection in 3D data. Proc. SPIE 5426, 133-143.

    Examples
    --------
    >>> f = eigen_features([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])  # a line, a plane, a ball
    >>> f.linearity, f.planarity, f.scattering
    (array([1., 0., 0.]), array([0., 1., 0.]), array([0., 0., 1.]))
    >>> f.dominant()
    array([0, 1, 2])
    """
    lam = np.asarray(eigenvalues, dtype=np.float64)
    if lam.shape[-1:] != (3,):
        raise LabkitError(f"eigenvalues must have shape (..., 3), got {lam.shape}")
    if np.any(np.diff(lam, axis=-1) > 1e-12 * np.abs(lam[..., :1]) + 1e-300):
        raise LabkitError("eigenvalues must be sorted in descending order (l1 >= l2 >= l3)")
    total = lam.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.clip(lam, 0.0, None) / total[..., None]  # (eq. 6)
        e1, e2, e3 = e[..., 0], e[..., 1], e[..., 2]
        plogp = np.where(e > 0, e * np.log(np.where(e > 0, e, 1.0)), 0.0)
        return EigenFeatures(
            linearity=(e1 - e2) / e1,  # (eq. 7)
            planarity=(e2 - e3) / e1,
            scattering=e3 / e1,
            omnivariance=np.cbrt(e1 * e2 * e3),  # (eq. 8)
            anisotropy=(e1 - e3) / e1,
            eigenentropy=np.where(total > 0, -plogp.sum(axis=-1), np.nan),
            change_of_curvature=e3,
            sum=total,
        )

