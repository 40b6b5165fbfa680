"""One result type for every registration method (ICP, maximum consensus).

The transformation maps the *source* cloud onto the *target* cloud:
``target ~ R @ source + t`` in the caller's frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.crs import crs_summary
from ..core.lengths import length_text
from ..core.report import ReportMixin, fmt
from ..transforms import angles_from_rotation, apply_transform, make_transform
from .consistency import Consistency, group_consistency  # noqa: F401  (re-exported: their former home)
from .degeneracy import AXES, Degeneracy, degeneracy_report  # noqa: F401  (re-exported)


@dataclass(frozen=True, eq=False, repr=False)
class RegistrationResult(ReportMixin):
    """Outcome of a registration of ``source`` onto ``target``.

    Attributes
    ----------
    translation : ndarray (3,)
        Shift (dX, dY, dZ) in metres, in the caller's frame.
    rotation : ndarray (3, 3)
        Rotation (identity for ``dof="translation"``), about ``origin``.
    origin : ndarray (3,)
        Local origin the rotation refers to: ``p' = R (p - origin) + origin + t``.
    covariance : ndarray (p, p)
        Covariance of the estimated parameters from the last adjustment (sigma0^2 N^-1 or,
        for ICP by default, a cluster-robust sandwich; inf for undetermined parameters).
    parameter_names : tuple of str
        Names of the estimated parameters, e.g. ('tx', 'ty', 'tz') or
        ('rx', 'ry', 'rz', 'tx', 'ty', 'tz') (angles in radians).
    sigma0 : float
        A posteriori standard deviation of unit weight.
    n_used : int
        Number of correspondences (or consensus points) in the final adjustment.
    share_used : float
        n_used divided by the number of source points considered.
    converged : bool
        Whether the method met its convergence criterion.
    iterations : int
        Iterations (ICP) or branch-and-bound steps (consensus) performed.
    degeneracy : Degeneracy or None
        Constrained and undetermined directions.
    method : str
        'icp', 'max_consensus', ...
    history : tuple
        Method-specific per-iteration records (frozen dataclasses).
    runtime_s : float
        Wall-clock time of the estimation in seconds.
    message : str
        Why the method stopped, and any warning.
    correspondences : object, optional
        The correspondences of the final adjustment (ICP: ``Correspondences``).
    consistency : Consistency, optional
        Test whether the groups of correspondences (classes or spatial blocks) agree on one
        transformation (ICP); when they do not, the covariance includes their disagreement.
    selection : Selection, optional
        Which points took part and why (stable classes, surface points or all points;
        :func:`labkit.registration.selection.select_points`).
    class_checks : tuple of ClassCheck
        The classes left out of a 'stable classes' selection, each tested against the result (which class
        agrees, which moved; :func:`labkit.registration.selection.check_other_classes`). Empty otherwise.
    height_model : HeightModelShift, optional
        The height-model matching that filled horizontal axes point-to-plane left undetermined
        (:func:`labkit.registration.height_model.fill_held_axes`), or that was tried and did not.
    crs : str or None
        The inputs' CRS (``PointCloud.crs``; ICP); None when they state none (arrays, files without one).
        :func:`labkit.save_registration` writes it to the registration file.

    Examples
    --------
    >>> from labkit.registration import icp
    >>> from labkit.synthetic import wavy_pair
    >>> res = icp(*wavy_pair(300, noise=0.001, shift=[-0.02, 0.01, -0.03]), dof="translation")  # two samplings
    >>> res.method.split()[0], res.parameter_names, res.converged
    ('icp', ('tx', 'ty', 'tz'), True)
    >>> res.translation.round(2)  # the shift back
    array([-0.02,  0.01, -0.03])
    """

    translation: np.ndarray
    rotation: np.ndarray
    origin: np.ndarray
    covariance: np.ndarray
    parameter_names: tuple
    sigma0: float
    n_used: int
    share_used: float
    converged: bool
    iterations: int
    degeneracy: Degeneracy | None = None
    method: str = ""
    history: tuple = field(default_factory=tuple)
    runtime_s: float = float("nan")
    message: str = ""
    correspondences: object = None  # method-specific final correspondences (ICP: Correspondences)
    consistency: Consistency | None = None
    selection: object = None
    class_checks: tuple = ()
    height_model: object = None
    crs: str | None = None

    @property
    def consistent(self) -> bool:
        """False when the consistency test found groups of the data that disagree (changes suspected)."""
        return self.consistency is None or self.consistency.consistent

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 matrix in the caller's frame: p' = R p + (t + origin - R origin)."""
        R = np.asarray(self.rotation)
        t_world = self.translation + self.origin - R @ self.origin
        return make_transform(R, t_world)

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the estimated parameters (sqrt of the covariance diagonal)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    @property
    def translation_std(self) -> np.ndarray:
        """Standard deviations of tx, ty, tz."""
        idx = [self.parameter_names.index(n) for n in ("tx", "ty", "tz")]
        return self.std[idx]

    @property
    def translation_cov(self) -> np.ndarray:
        """Covariance (3, 3) of tx, ty, tz (inf on the diagonal of an undetermined component)."""
        idx = [self.parameter_names.index(n) for n in ("tx", "ty", "tz")]
        return np.asarray(self.covariance)[np.ix_(idx, idx)]

    def apply(self, points) -> np.ndarray:
        """Map source points (n, 3) into the target frame.

        Examples
        --------
        >>> import numpy as np
        >>> res = RegistrationResult(translation=np.array([0.1, 0.0, -0.2]), rotation=np.eye(3),
        ...                          origin=np.array([500000.0, 5400000.0, 0.0]), covariance=np.zeros((3, 3)),
        ...                          parameter_names=("tx", "ty", "tz"), sigma0=1.0, n_used=10, share_used=1.0,
        ...                          converged=True, iterations=3)
        >>> np.round(res.apply(np.array([[500010.0, 5400020.0, 30.0]])), 3).tolist()
        [[500010.1, 5400020.0, 29.8]]
        """
        return apply_transform(self.matrix, points)

    def _report(self):
        std = self.translation_std
        rows = [
            (f"d{a}", length_text(t, s, sign=True)) for a, t, s in zip(AXES, self.translation, std)
        ]
        if not np.allclose(self.rotation, np.eye(3)):
            ang = np.degrees(angles_from_rotation(self.rotation)) * 3600
            rows.append(("rotation rx, ry, rz", fmt(ang, 2, "arcsec")))
        rows += [
            ("sigma0", fmt(self.sigma0, 4)),
            ("correspondences used", f"{self.n_used} ({100 * self.share_used:.1f} %)"),
            ("converged", f"{self.converged} after {self.iterations} iterations"),
            ("runtime", fmt(self.runtime_s, 3, "s")),
            ("CRS", crs_summary(self.crs)),
        ]
        if self.selection is not None:
            rows.append(("points used", str(self.selection)))
        if self.message:
            rows.append(("message", self.message))
        sections = [("Transformation (source -> target)", rows)]
        if self.class_checks:
            sections.append(("Other classes against the shift (left out of the estimate)",
                             [(f"class {c.code}", str(c).split(", ", 1)[1]) for c in self.class_checks]))
        if self.height_model is not None:
            sections.append(("Height model (horizontal axes point-to-plane left undetermined)",
                             self.height_model._report()[1][0][1]))
        if self.consistency is not None:
            sections += self.consistency._report()[1]
        if self.degeneracy is not None:
            sections += self.degeneracy._report()[1]
        return f"Registration result ({self.method or 'unknown method'})", sections
