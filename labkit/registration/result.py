"""One result type for every registration method (ICP, maximum consensus).

The transformation maps the *source* cloud onto the *target* cloud:
``target ~ R @ source + t`` in the caller's frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from .._report import ReportMixin, fmt
from ..transforms import angles_from_rotation, apply_transform, make_transform

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

    def _report(self):
        rows = []
        stds = [None] * len(self.eigenvalues) if self.direction_std is None else self.direction_std
        if self.max_std is not None:
            rows.append(("precision limit", f"a direction with std > {self.max_std:.4g} m is undetermined"))
        for lam, ok, vec, sd in zip(self.eigenvalues, self.constrained, self.eigenvectors.T, stds):
            direction = ", ".join(f"{n}:{c:+.2f}" for n, c in zip(self.names, vec) if abs(c) > 0.05)
            std = "" if sd is None else f" (std {sd:.3g} m)"
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

    def apply(self, points) -> np.ndarray:
        """Map source points (n, 3) into the target frame."""
        return apply_transform(self.matrix, points)

    def _report(self):
        std = self.translation_std
        rows = [
            (f"d{a}", f"{t:+.4f} m  +- {s:.4f} m") for a, t, s in zip(AXES, self.translation, std)
        ]
        if not np.allclose(self.rotation, np.eye(3)):
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
        if self.consistency is not None:
            sections += self.consistency._report()[1]
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


# ------------------------------------------------------------------ model test: do the groups agree?


@dataclass(frozen=True, eq=False, repr=False)
class Consistency(ReportMixin):
    """Test whether groups of correspondences (classes or spatial blocks) support one transformation.

    Every group's own least-squares estimate (in the directions that the group determines) is
    compared with the common estimate of all groups; the statistic is a generalized Cochran Q,
    T = sum_g (y_g - V_g^T x)^T C_g^-1 (y_g - V_g^T x) (eq. 5.16), chi-square with
    ``dof = sum_g r_g - rank`` degrees of freedom when one transformation fits every group.

    Attributes
    ----------
    grouping : str
        'class' (class of the target point) or 'block' (spatial quadrants).
    groups : tuple of str
        Names of the tested groups (groups that were too small are left out).
    n : ndarray of int
        Correspondences per group.
    statistic : float
        T of eq. (5.16).
    dof : int
        Degrees of freedom.
    p_value : float
        chi-square tail probability of T.
    alpha : float
        Level of the test.
    contribution : ndarray
        Each group's share of T (its own sum in eq. 5.16).
    offset : ndarray (g, 3)
        Each group's shift (dX, dY, dZ) relative to the result in metres (NaN where the
        group does not determine the axis).
    offset_std : ndarray (g, 3)
        Standard deviation of ``offset`` from the group's own covariance.
    between : ndarray (u, u)
        When the test rejects: a sandwich with the G groups as clusters,
        G / (G-1) N^-1 (sum_g s_g s_g^T) N^-1 with s_g = N_g (x_g - x) the pull of group g on the
        result x (eq. 5.17), in the tested parameters (ICP adds it to the result's covariance);
        zeros otherwise. N^-1 s_g is how far group g has moved the result from the other groups'
        estimate; the sum treats each group's disagreement as a random group effect.
    std_ratio : ndarray (3,)
        Standard deviation of dX, dY, dZ with ``between`` divided by the one without (1 when the
        groups agree; set by the registration method).
    """

    grouping: str
    groups: tuple
    n: np.ndarray
    statistic: float
    dof: int
    p_value: float
    alpha: float
    contribution: np.ndarray
    offset: np.ndarray
    offset_std: np.ndarray
    between: np.ndarray | None = None
    std_ratio: np.ndarray = field(default_factory=lambda: np.ones(3))

    #: The groups' spread counts as affecting the result when it widens a standard deviation by more.
    AFFECTS = 2.0

    @property
    def agree(self) -> bool:
        """The test's verdict: True unless the groups disagree at level ``alpha``."""
        return not (self.dof > 0 and self.p_value < self.alpha)

    @property
    def consistent(self) -> bool:
        """False when the groups disagree and their spread widens a shift component's standard deviation
        by more than a factor of 2 (the shift depends on which group one believes: changes suspected)."""
        return self.agree or bool(np.nanmax(self.std_ratio) <= self.AFFECTS)

    @property
    def worst(self) -> str:
        """The group with the largest share of the test statistic."""
        return self.groups[int(np.argmax(self.contribution))] if self.groups else ""

    def _report(self):
        if self.agree:
            verdict = "the groups agree"
        elif self.consistent:
            verdict = "the groups differ, but the shift hardly depends on it"
        else:
            verdict = "INCONSISTENT: the shift depends on the group, changes between the epochs suspected"
        rows = [
            ("groups by", self.grouping),
            ("T / dof", f"{self.statistic:.1f} / {self.dof}  (p = {self.p_value:.2g}, alpha = {self.alpha:g})"),
            ("verdict", verdict),
        ]
        for name, n, c, off, s in zip(self.groups, self.n, self.contribution, self.offset, self.offset_std):
            shift = ", ".join("-" if np.isnan(o) else f"{1000 * o:+.1f}+-{1000 * e:.1f}" for o, e in zip(off, s))
            rows.append((f"{name} (n={n})", f"T_g = {c:.1f}; dX, dY, dZ - result = {shift} mm"))
        if not self.agree:
            rows.append(("std widened by", fmt(self.std_ratio, 2) + " (spread between the groups, eq. 5.17)"))
        return "Consistency of the groups", [("", rows)]


def group_consistency(A, l, P, labels, names, cells, *, translation, rel_threshold=1e-2, alpha=1e-3,
                      grouping="class", min_n=30) -> Consistency | None:
    """Generalized Cochran Q test of one transformation for all groups (eq. 5.16).

    Parameters
    ----------
    A : ndarray (m, r, u)
        Design rows of the kept correspondences (u parameters, r components each).
    l : ndarray (m, r)
        Observations (residuals before the last step).
    P : ndarray (m,)
        Final weights.
    labels : ndarray of int (m,)
        Group of each row (index into ``names``; -1: no group).
    names : sequence of str
    cells : ndarray of int (m,)
        Spatial cell of each row; the groups' covariances are cluster-robust over these cells
        (eq. 5.13 without the robust-weight terms).
    translation : sequence of int
        Columns of tx, ty, tz in A (scaled to metres) for the reported offsets.
    rel_threshold : float
        A group determines the eigen-directions of its N_g above ``rel_threshold`` times its largest one.
    alpha : float
        Level of the test.
    min_n : int
        Smaller groups are not tested.

    Returns
    -------
    Consistency or None
        None when fewer than two groups are large enough.
    """
    u = A.shape[2]
    if u == 0:  # every parameter held: nothing to test
        return None
    N_all = np.einsum("mru,m,mrv->uv", A, P, A)
    x0 = np.linalg.lstsq(N_all, np.einsum("mru,m,mr->u", A, P, l), rcond=None)[0]  # the result's own step
    ys, Ws, Vs, used, ns, deltas, offs_std, scores = [], [], [], [], [], [], [], []
    for g, name in enumerate(names):
        rows = labels == g
        if rows.sum() < max(min_n, 2 * u):
            continue
        Ag, lg, Pg = A[rows], l[rows], P[rows]
        N = np.einsum("mru,m,mrv->uv", Ag, Pg, Ag)
        lam, V = np.linalg.eigh(0.5 * (N + N.T))
        keep = lam >= rel_threshold * max(lam[-1], 1e-300)
        lam, V = lam[keep], V[:, keep]
        y = (V.T @ np.einsum("mru,m,mr->u", Ag, Pg, lg)) / lam  # the group's own estimate of V^T x
        v = np.einsum("mru,u->mr", Ag, V @ y) - lg
        s = np.einsum("mru,m,mr->mu", Ag, Pg, v) @ V  # scores in the group's directions
        _, cell = np.unique(cells[rows], return_inverse=True)
        G = np.zeros((cell.max() + 1, len(lam)))
        np.add.at(G, cell.ravel(), s)
        m, nc, r = len(s), len(G), len(lam)
        if nc >= 2 * r + 1:  # cluster-robust (eq. 5.13)
            M = G.T @ G * nc / (nc - 1) * m / max(m - r, 1)
        else:  # too few cells: formal sigma0^2 N
            vPv = float(np.einsum("mr,m,mr->", v, Pg, v))
            M = np.diag(lam) * vPv / max(m * A.shape[1] - r, 1)
        C = M / np.outer(lam, lam)
        try:
            W = np.linalg.inv(0.5 * (C + C.T))
        except np.linalg.LinAlgError:
            continue
        ys.append(y), Ws.append(W), Vs.append(V), used.append(name), ns.append(int(rows.sum()))
        # the group's estimate relative to the result, on the parameters it determines
        determined = 1 - (V**2).sum(axis=1) < 0.05  # little share in the directions the group leaves free
        deltas.append(np.where(determined, V @ (y - V.T @ x0), 0.0))
        offs_std.append(np.where(determined, np.sqrt(np.clip(np.diag(V @ C @ V.T), 0, None)), np.nan))
        scores.append(V @ (lam * (y - V.T @ x0)))  # s_g = N_g (x_g - x): the group's pull on the result
    if len(used) < 2:
        return None
    H = sum(V @ W @ V.T for V, W in zip(Vs, Ws))
    b = sum(V @ W @ y for V, W, y in zip(Vs, Ws, ys))
    x = np.linalg.lstsq(H, b, rcond=None)[0]  # common estimate of all groups
    rank = np.linalg.matrix_rank(H, tol=rel_threshold * np.abs(H).max() * 1e-3)
    parts = np.array([float((y - V.T @ x) @ W @ (y - V.T @ x)) for V, W, y in zip(Vs, Ws, ys)])
    T = float(parts.sum())
    dof = int(sum(len(y) for y in ys) - rank)
    p = float(chi2.sf(T, dof)) if dof > 0 else 1.0
    delta, offset_std = np.array(deltas), np.array(offs_std)
    offset = np.where(np.isnan(offset_std), np.nan, delta)[:, translation]
    between = np.zeros((u, u))
    if dof > 0 and p < alpha:  # the groups as clusters of a sandwich (eq. 5.17)
        S = np.array(scores)
        k = len(S)
        Ni_S = np.linalg.lstsq(N_all, S.T, rcond=None)[0]  # N^-1 s_g: each group's influence on the result
        between = Ni_S @ Ni_S.T * k / (k - 1)
    return Consistency(grouping, tuple(used), np.array(ns), T, dof, p, float(alpha), parts, offset,
                       offset_std[:, translation], between)
