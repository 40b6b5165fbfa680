"""One result type for every registration method (ICP, maximum consensus).

The transformation maps the *source* cloud onto the *target* cloud:
``target ~ R @ source + t`` in the caller's frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._report import ReportMixin, fmt
from ..transforms import make_transform

AXES = ("X", "Y", "Z")


@dataclass(frozen=True, eq=False, repr=False)
class Degeneracy(ReportMixin):
    """Which directions the data constrain, from the eigen decomposition of N.

    Attributes
    ----------
    eigenvalues : ndarray (p,)
        Eigenvalues of the normal matrix N, ascending (``numpy.linalg.eigh``).
    eigenvectors : ndarray (p, p)
        Matching unit eigenvectors in the columns.
    constrained : ndarray of bool (p,)
        Per eigen-direction: eigenvalue / largest eigenvalue >= ``rel_threshold``.
    axis_determined : ndarray of bool (3,)
        Per translation axis X, Y, Z: the entry of ``parameter_determined`` for tx, ty, tz.
    rel_threshold : float
        The relative eigenvalue threshold used.
    names : tuple of str
        Parameter names in the order of N.
    parameter_determined : ndarray of bool (p,)
        Per parameter: False when its squared share summed over the unconstrained
        eigen-directions reaches ``share_threshold``, or, with ``hold_first``, after the
        rounds described in :func:`degeneracy_report` (ICP holds exactly these parameters
        fixed and reports their standard deviation as inf).
    share_threshold : float
        The share used for ``parameter_determined``.
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    constrained: np.ndarray
    axis_determined: np.ndarray
    rel_threshold: float
    names: tuple
    parameter_determined: np.ndarray | None = None
    share_threshold: float = 0.5

    @property
    def well_posed(self) -> bool:
        """True when every direction is constrained."""
        return bool(self.constrained.all())

    @property
    def undetermined_axes(self) -> tuple:
        """Names of the translation axes the data do not determine, e.g. ('Y',)."""
        return tuple(a for a, ok in zip(AXES, self.axis_determined) if not ok)

    @property
    def undetermined_parameters(self) -> tuple:
        """Names of all parameters the data do not determine, e.g. ('rz', 'tx', 'ty')."""
        if self.parameter_determined is None:
            return ()
        return tuple(n for n, ok in zip(self.names, self.parameter_determined) if not ok)

    def _report(self):
        rows = []
        for lam, ok, vec in zip(self.eigenvalues, self.constrained, self.eigenvectors.T):
            direction = ", ".join(f"{n}:{c:+.2f}" for n, c in zip(self.names, vec) if abs(c) > 0.05)
            rows.append((f"lambda = {lam:.4g}", f"{'constrained' if ok else 'UNDETERMINED'} along {direction}"))
        rows.append(("undetermined axes", ", ".join(self.undetermined_axes) or "none"))
        rotations = [n for n in self.undetermined_parameters if n.startswith("r")]
        if rotations:
            rows.append(("undetermined rotations", ", ".join(rotations)))
        return "Degeneracy report", [("", rows)]


def degeneracy_report(
    N,
    names,
    rel_threshold: float = 1e-2,
    translation_slice=slice(None),
    share_threshold: float = 0.5,
    hold_first=(),
) -> Degeneracy:
    """Eigen-analysis of a normal matrix N (p x p, symmetric).

    Parameters
    ----------
    N : ndarray (p, p)
        Normal matrix of the last adjustment (A^T P A).
    names : sequence of str
        Parameter names in the order of N.
    rel_threshold : float
        A direction with eigenvalue below ``rel_threshold * max eigenvalue`` is
        called undetermined.
    translation_slice : slice
        Which parameters are the translation (tx, ty, tz) for the per-axis verdict.
    share_threshold : float
        A parameter whose squared components in the unconstrained eigen-directions
        sum to at least this is undetermined. ICP uses 0.05, the share above which
        it holds a parameter fixed, so that the report names every held parameter
        (two weak directions mixing rz with X and Y make both X and Y undetermined,
        even if neither has half of its weight in them).
    hold_first : sequence of str
        Parameters to give up first when a weak direction involves them (ICP: the rotations).
        Empty (the default): every parameter with a share in a weak direction is undetermined.
        Otherwise, in rounds: the ``hold_first`` parameters with a share in the weak directions
        are held, the normal matrix of the remaining parameters is tested again (eigenvalues
        against the same level ``rel_threshold * max eigenvalue of N``), and only parameters
        that are still weak in it are held as well. A weak direction mixing rz with X and Y
        then costs rz, not the two translations: the rotation's initial value (none, or the
        given one) is the plausible prior for epochs, a shift of zero is not.
    """
    N = np.asarray(N, dtype=np.float64)
    lam, vecs = np.linalg.eigh(0.5 * (N + N.T))
    top = lam[-1] if lam[-1] > 0 else 1.0
    constrained = lam >= rel_threshold * top
    determined = _weak_share(vecs, constrained) < share_threshold
    if hold_first and not constrained.all():
        determined = _hold_in_order(N, names, rel_threshold * top, share_threshold, hold_first)
    axis_determined = determined[translation_slice].copy()
    return Degeneracy(
        lam, vecs, constrained, axis_determined, float(rel_threshold), tuple(names), determined, float(share_threshold)
    )


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

    def apply(self, points) -> np.ndarray:
        """Map source points (n, 3) into the target frame."""
        from ..transforms import apply_transform

        return apply_transform(self.matrix, points)

    def _report(self):
        std = self.translation_std
        rows = [
            (f"d{a}", f"{t:+.4f} m  +- {s:.4f} m") for a, t, s in zip(AXES, self.translation, std)
        ]
        if not np.allclose(self.rotation, np.eye(3)):
            from ..transforms import angles_from_rotation

            ang = np.degrees(angles_from_rotation(self.rotation)) * 3600
            rows.append(("rotation rx, ry, rz", fmt(ang, 2, "arcsec")))
        rows += [
            ("sigma0", fmt(self.sigma0, 4)),
            ("correspondences used", f"{self.n_used} ({100 * self.share_used:.1f} %)"),
            ("converged", f"{self.converged} after {self.iterations} iterations"),
            ("runtime", fmt(self.runtime_s, 3, "s")),
        ]
        if self.message:
            rows.append(("message", self.message))
        sections = [("Transformation (source -> target)", rows)]
        if self.degeneracy is not None:
            sections += self.degeneracy._report()[1]
        return f"Registration result ({self.method or 'unknown method'})", sections


def _weak_share(vecs, constrained):
    """Per parameter: squared components summed over the unconstrained eigen-directions."""
    loose = vecs[:, ~constrained]  # weak directions in the columns
    return (loose**2).sum(axis=1) if loose.size else np.zeros(len(vecs))


def _hold_in_order(N, names, level, share_threshold, hold_first):
    """Which parameters are determined when the ``hold_first`` ones are given up first (rounds)."""
    first = np.isin(np.asarray(names), list(hold_first))
    free = np.ones(len(N), dtype=bool)
    while free.any():
        lam, vecs = np.linalg.eigh(0.5 * (N + N.T)[np.ix_(free, free)])
        weak = lam < level
        if not weak.any():
            break
        share = np.zeros(len(N))
        share[free] = _weak_share(vecs, ~weak)
        candidates = free & (share >= share_threshold)
        if not candidates.any():  # spread thinly: give up the parameter with the largest share
            candidates = free & (share == share[free].max())
        preferred = candidates & first
        free &= ~(preferred if preferred.any() else candidates)
    return free
