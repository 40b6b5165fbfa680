"""Which directions the data determine: eigen-analysis of the normal matrix of a registration.

Used by every registration method; the verdict names the parameters held at
their initial value (ICP gives up rotations first) and, with ``sigma0`` and
``max_std``, judges determinability by precision (eq. 5.12a).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.report import ReportMixin

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
        Per eigen-direction: determined. With ``max_std`` (ICP): the standard deviation along the
        direction, ``sigma0 / sqrt(eigenvalue)``, is at most ``max_std``; otherwise: eigenvalue /
        largest eigenvalue >= ``rel_threshold``.
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
    direction_std : ndarray (p,) or None
        Standard deviation along each eigen-direction, ``sigma0 / sqrt(eigenvalue)`` (m; rotations
        scaled to metres at the cloud's radius); inf where the eigenvalue is not positive.
    max_std : float or None
        The precision limit: a direction whose standard deviation exceeds it is undetermined.

    Examples
    --------
    >>> from labkit.registration import icp
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(1500, 1, size=6)  # a flat floor
    >>> res = icp(floor[::5] + [0.02, 0.0, 0.03], floor, dof="translation")
    >>> deg = res.degeneracy  # a floor fixes the height only
    >>> deg.well_posed, deg.undetermined_axes, round(float(res.translation[2]), 3)
    (False, ('X', 'Y'), -0.03)
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    constrained: np.ndarray
    axis_determined: np.ndarray
    rel_threshold: float
    names: tuple
    parameter_determined: np.ndarray | None = None
    share_threshold: float = 0.5
    direction_std: np.ndarray | None = None
    max_std: float | None = None

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

    def held_effect(self, free, held):
        """B = N_ff^-1 N_fh: how the free parameters, solved with the held ones at h0, follow a move of those.

        Moving the held parameters from h0 to h moves the free ones by -B (h - h0) (eq. 5.15). ``free`` and
        ``held`` are boolean masks over the parameters; N is rebuilt from the eigen decomposition.
        """
        N = (self.eigenvectors * self.eigenvalues) @ self.eigenvectors.T
        return np.linalg.lstsq(N[np.ix_(free, free)], N[np.ix_(free, held)], rcond=None)[0]

    def _report(self):
        rows = []
        stds = [None] * len(self.eigenvalues) if self.direction_std is None else self.direction_std
        if self.max_std is not None:
            rows.append(("precision limit", f"a direction with formal std > {self.max_std:.4g} m is undetermined "
                         "(formal: sigma0 / sqrt(lambda) of the last adjustment, eq. 5.12a; the +- of the shift "
                         "is the result's covariance, which adds correlated residuals and group spread)"))
        for lam, ok, vec, sd in zip(self.eigenvalues, self.constrained, self.eigenvectors.T, stds):
            direction = ", ".join(f"{n}:{c:+.2f}" for n, c in zip(self.names, vec) if abs(c) > 0.05)
            std = "" if sd is None else f" (formal std {sd:.3g} m)"
            rows.append((f"lambda = {lam:.4g}", f"{'constrained' if ok else 'UNDETERMINED'} along {direction}{std}"))
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
    *,
    sigma0: float | None = None,
    max_std: float | None = None,
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
    sigma0, max_std : float, optional
        Determinability from precision (eq. 5.12a): with both given, a direction is undetermined
        when its standard deviation ``sigma0 / sqrt(eigenvalue)`` exceeds ``max_std``, whatever
        its eigenvalue relative to the largest (on sloped terrain X and Y are often 5-50 times
        weaker than Z and still determined to centimetres). ``rel_threshold`` is then not used.

    References
    ----------
    .. [1] Notebook 05, section 6, eqs. 5.12a-5.12b.
    .. [2] J. Zhang, M. Kaess, S. Singh (2016): On degeneracy of optimization-based state estimation
       problems. IEEE International Conference on Robotics and Automation (ICRA).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.degeneracy import degeneracy_report
    >>> N = np.diag([1.0, 1.0, 1e4])  # a flat floor: only the height (tz) is well constrained
    >>> report = degeneracy_report(N, ["tx", "ty", "tz"])
    >>> report.undetermined_axes, report.undetermined_parameters, report.well_posed
    (('X', 'Y'), ('tx', 'ty'), False)
    """
    N = np.asarray(N, dtype=np.float64)
    lam, vecs = np.linalg.eigh(0.5 * (N + N.T))
    top = lam[-1] if lam[-1] > 0 else 1.0
    level = rel_threshold * top
    std = None
    if max_std is not None and sigma0 is not None:
        level = (float(sigma0) / float(max_std)) ** 2  # sigma0 / sqrt(lambda) <= max_std  (eq. 5.12a)
        with np.errstate(divide="ignore", invalid="ignore"):
            std = np.where(lam > 0, float(sigma0) / np.sqrt(np.clip(lam, 1e-300, None)), np.inf)
    constrained = lam >= max(level, 1e-300)
    determined = _weak_share(vecs, constrained) < share_threshold
    if hold_first and not constrained.all():
        determined = _hold_in_order(N, names, max(level, 1e-300), share_threshold, hold_first)
    axis_determined = determined[translation_slice].copy()
    return Degeneracy(
        lam, vecs, constrained, axis_determined, float(rel_threshold), tuple(names), determined,
        float(share_threshold), std, None if max_std is None or sigma0 is None else float(max_std),
    )  # fmt: skip


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
