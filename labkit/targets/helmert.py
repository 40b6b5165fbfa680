"""3D rigid or similarity transformation between corresponding points in the Gauss-Helmert model (notebook 11).

Functional model (notebook 11, eq. 1): for every pair of corresponding points
``f_i(l + v, x) = s R (p_i + v_p,i) + t - (q_i + v_q,i) = 0`` (three conditions per pair), with the
observations l = both point sets, the parameters x = [rx, ry, rz, tx, ty, tz, (s)] and R = Rz Ry Rx.

Every condition involves one pair only, so ``B Sigma_ll B^T`` is block diagonal with the 3x3 blocks
``M_i = s^2 R Sigma_p,i R^T + Sigma_q,i`` (eq. 10); the normal matrix is 6x6 (7x7) and every step runs
on stacks of 3x3 blocks. Nothing of size 3n x 3n is ever built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import pose as _pose
from ..core.checks import as_points, count, positive, probability
from ..core.report import ReportMixin, fmt
from ..core.stats import GlobalTest, global_test, w_critical
from ..core.errors import DegenerateGeometryError, LabkitError

__all__ = ["helmert", "HelmertFit"]

NAMES = ("rx", "ry", "rz", "tx", "ty", "tz", "scale")
_COLLINEAR = 1e-6  # second singular value of the centred points below this times the first: on a line


def helmert(source, target, *, source_cov=None, target_cov=None, scale: bool = False, alpha: float = 0.05,
            alpha_w: float = 0.001, tol: float = 1e-11, max_iterations: int = 50) -> HelmertFit:
    """Adjust the transformation source -> target of corresponding points in the Gauss-Helmert model.

    Parameters
    ----------
    source, target : array_like (n, 3)
        Corresponding points p_i and q_i (m), n >= 2, in the same order.
    source_cov, target_cov : None, float, array_like (n,), (n, 3) or (n, 3, 3), optional
        A priori precision of each point: one standard deviation for all, one per point, one per
        coordinate, or a 3x3 covariance matrix per point (m, m^2). When only one set has a covariance, the
        other is taken as error-free. When neither has one, both get unit weights of unknown scale: no
        global test, and the point tests use the estimated sigma0 (Pope's tau instead of Baarda's test).
    scale : bool
        Estimate a scale factor (7-parameter similarity transformation) instead of a rigid one.
    alpha : float
        Significance level of the global test.
    alpha_w : float
        Significance level of the test of each point (critical value 3.29 for the default 0.001).
    tol : float
        Convergence threshold on max|dx| (rad, m).
    max_iterations : int
        Maximum number of iterations.

    Returns
    -------
    HelmertFit
        ``matrix`` (4x4, source -> target), ``covariance`` of [rx, ry, rz, tx, ty, tz, (s)] with
        R = Rz(rz) Ry(ry) Rx(rx), residuals, global test, test per point and ``undetermined``, the named
        directions the points do not fix (two points or collinear points: the rotation about their line),
        whose parameters carry an infinite variance.

    Raises
    ------
    LabkitError
        Bad shapes, NaN/inf, fewer than two points, covariances that are not positive (semi-)definite.
    DegenerateGeometryError
        All points coincide (nothing but the translation is determined).

    Notes
    -----
    Rigorous iteration (notebook 11, eqs. 6-9): linearize at l + v0 and x0, misclosures
    w_i = s R p_i + t - q_i (the conditions are linear in v), N = sum A_i^T M_i^-1 A_i,
    dx = -N^-1 sum A_i^T M_i^-1 w_i, k_i = -M_i^-1 (A_i dx + w_i), v_p,i = s Sigma_p,i R^T k_i,
    v_q,i = -Sigma_q,i k_i. Coordinates are reduced to the centroids first; translation and covariance
    are returned in the caller's frames. With a known a priori precision Sigma_xx = sigma0^2 N^-1 with the
    a priori sigma0 (the global test checks it); otherwise with the estimated one. The translation refers to
    the origin of the caller's frames: far from it (UTM coordinates) its standard deviation contains the
    rotation's uncertainty times that lever arm. Equal isotropic
    precision of both sets gives exactly the closed-form SVD solution (Kabsch) for a rigid transformation.

    References
    ----------
    .. [1] Notebook 11, sections 3-6: functional model (eqs. 1-2), linearization (eqs. 3-8), the 3x3 blocks
       of B Sigma_ll B^T (eq. 6), normal equations and iteration (eq. 9), statistics (eqs. 10-12).
    .. [2] Seed 000, section 1 (the Gauss-Helmert model of the sphere: the same steps, eqs. 6-24).
    .. [3] F. Neitzel (2010): Generalization of total least-squares on example of unweighted and weighted 2D
       similarity transformation. Journal of Geodesy 84(12), 751-762, doi:10.1007/s00190-010-0408-0.
    .. [4] S. Umeyama (1991): Least-squares estimation of transformation parameters between two point
       patterns. IEEE TPAMI 13(4), 376-380, doi:10.1109/34.88573.
    .. [5] W. Baarda (1968): A testing procedure for use in geodetic networks. Netherlands Geodetic
       Commission, Publications on Geodesy 2(5).

    Examples
    --------
    >>> import numpy as np
    >>> import labkit
    >>> from labkit.transforms import make_transform, rotation_from_angles, apply_transform
    >>> rng = np.random.default_rng(0)
    >>> p = rng.uniform(-10, 10, (6, 3))
    >>> T = make_transform(rotation_from_angles(0.01, -0.02, 0.5), [3.0, -2.0, 0.5])
    >>> q = apply_transform(T, p) + rng.normal(0, 0.001, (6, 3))
    >>> fit = labkit.helmert(p, q, target_cov=0.001)  # the noise is in the target only
    >>> bool(np.allclose(fit.matrix, T, atol=5e-3)), fit.global_test.passed, fit.undetermined
    (True, True, ())
    >>> two = labkit.helmert(p[:2], q[:2], target_cov=0.001)
    >>> two.undetermined[0].startswith("rotation about the line"), bool(np.isinf(two.std[:3]).any())
    (True, True)
    """
    p_in = as_points(source, min_points=2, name="source")
    q_in = as_points(target, min_points=2, name="target")
    if p_in.shape != q_in.shape:
        raise LabkitError(f"source and target must hold the same number of points, got {len(p_in)} and {len(q_in)}")
    n = len(p_in)
    Cp, Cq = _pose.as_covariances(source_cov, n, "source_cov"), _pose.as_covariances(target_cov, n, "target_cov")
    sigma_known = Cp is not None or Cq is not None
    if not sigma_known:
        Cp = Cq = np.broadcast_to(np.eye(3), (n, 3, 3))
    alpha, alpha_w = probability(alpha, "alpha"), probability(alpha_w, "alpha_w")
    tol, max_iterations = positive(tol, "tol"), count(max_iterations, "max_iterations")

    # Reduce both sets to their centroids (rounded: exact for mm-resolution coordinates)
    op, oq = np.round(p_in.mean(axis=0), 3), np.round(q_in.mean(axis=0), 3)
    p, q = p_in - op, q_in - oq
    if np.abs(p).max() == 0 or np.abs(q).max() == 0:
        raise DegenerateGeometryError("all points coincide: only the translation would be determined")

    # Initial values: weighted closed form; iterate (eqs. 6-9)
    w0 = 1.0 / np.maximum(np.trace(_sum_cov(Cp, Cq), axis1=1, axis2=2), 1e-300)
    R0, t0, s0 = _pose.closed_form(p, q, w0, scale)
    it = _iterate(p, q, Cp, Cq, _pose.angles_of(R0), t0, s0, scale, tol, max_iterations)

    # Statistics and the caller's frame
    return _result(p, it, op, oq, scale, sigma_known, alpha, alpha_w)


def _sum_cov(Cp, Cq):
    return (0 if Cp is None else Cp) + (0 if Cq is None else Cq)


@dataclass(frozen=True, eq=False)
class _State:
    angles: np.ndarray
    t: np.ndarray
    s: float
    A: np.ndarray  # (n, 3, u)
    M: np.ndarray  # (n, 3, 3) blocks of B Sigma_ll B^T
    k: np.ndarray  # (n, 3) correlates
    vp: np.ndarray
    vq: np.ndarray
    Q: np.ndarray  # N^+
    null: np.ndarray  # (u, k) directions N does not fix
    iterations: int
    converged: bool
    reason: str


def blocks_M(R, s, Cp, Cq):
    """The 3x3 blocks M_i = s^2 R Sigma_p,i R^T + Sigma_q,i of B Sigma_ll B^T (notebook 11, eq. 6)."""
    M = np.zeros((len(Cp if Cp is not None else Cq), 3, 3))
    if Cp is not None:
        M += s * s * np.einsum("ij,njk,lk->nil", R, Cp, R)
    if Cq is not None:
        M += Cq
    return M


def _iterate(p, q, Cp, Cq, angles, t, s, scale, tol, max_iterations):
    """Rigorous Gauss-Helmert iteration (notebook 11, eqs. 6-9) on stacks of 3x3 blocks."""
    vp, vq = np.zeros_like(p), np.zeros_like(q)
    converged, reason = False, ""
    for i in range(1, max_iterations + 1):
        R = _pose.rotation_from_angles(*angles)
        A = _pose.pose_jacobian(angles, s, p + vp, scale)  # (eq. 7) A_i = d f_i / d x at l + v0
        M = blocks_M(R, s, Cp, Cq)  # (eq. 6)
        try:
            P = np.linalg.inv(M)  # 3x3 blocks only
        except np.linalg.LinAlgError:
            raise LabkitError("a block s^2 R Sigma_p R^T + Sigma_q is singular: give at least one "
                              "positive-definite covariance per point pair") from None
        w = s * p @ R.T + t - q  # (eq. 8) w = -B v0 + f(l + v0, x0), linear in v
        PA = P @ A
        N = np.einsum("nji,njk->ik", A, PA)
        rhs = np.einsum("nji,nj->i", PA, w)
        dx, Q, null = _pose.solve_normal(N, rhs)  # (eq. 9)
        k = -np.einsum("nij,nj->ni", P, np.einsum("nij,j->ni", A, dx) + w)  # (eq. 9) correlates
        vp = s * np.einsum("nij,kj,nk->ni", Cp, R, k) if Cp is not None else np.zeros_like(p)  # v_p = s Sigma_p R^T k
        vq = -np.einsum("nij,nj->ni", Cq, k) if Cq is not None else np.zeros_like(q)  # v_q = -Sigma_q k
        angles, t = angles + dx[:3], t + dx[3:6]
        if scale:
            s = s + dx[6]
        if np.abs(dx).max() < tol:
            converged = True
            break
    else:
        reason = f"no convergence after {max_iterations} iterations (last max|dx| = {np.abs(dx).max():.2e})"
    return _State(angles, t, s, A, M, k, vp, vq, Q, null, i, converged, reason)


def _result(p, st, op, oq, scale, sigma_known, alpha, alpha_w):
    """sigma0, Sigma_xx, tests and naming of undetermined directions; back to the caller's frames."""
    n, u = len(p), (7 if scale else 6)
    rank = u - st.null.shape[1]
    dof = 3 * n - rank
    omega = float(np.einsum("ni,nij,nj->", st.k, st.M, st.k))  # (eq. 10) v^T Sigma^-1 v = sum k^T M k
    sigma0 = float(np.sqrt(omega / dof)) if dof > 0 else np.nan
    factor = 1.0 if sigma_known or dof <= 0 else sigma0**2
    x, J = _pose.to_caller_frame(st.angles, st.t, st.s, op, oq, scale)
    cov, bad = _pose.propagate(factor * st.Q, J, st.null, NAMES[:u])
    # test of each point: e_i = -M_i k_i with cofactor M_i - A_i N^+ A_i^T (eq. 12)
    e = -np.einsum("nij,nj->ni", st.M, st.k)
    Qee = st.M - np.einsum("nij,jk,nlk->nil", st.A, st.Q, st.A)
    T, r, pval, z = _pose.point_tests(e, Qee, 1.0, sigma_known, dof, omega)
    share = np.einsum("nii->n", np.linalg.solve(st.M, Qee))
    g = global_test(omega, dof, 1.0, alpha) if sigma_known else GlobalTest(
        np.nan, int(dof), np.nan, np.nan, alpha, None, np.nan)
    R = _pose.rotation_from_angles(*st.angles)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = st.s * R, x[3:6]
    return HelmertFit(
        matrix=matrix, parameters=x, covariance=cov, sigma0=sigma0, sigma_known=sigma_known, redundancy=int(dof),
        residuals_source=st.vp, residuals_target=st.vq, point_statistic=T, point_dof=r, point_p=pval,
        point_test=z, point_redundancy=share, global_test=g, alpha_w=alpha_w, w_critical=w_critical(alpha_w),
        undetermined=_name_null(p, st.null, bad, scale), undetermined_parameters=bad,
        converged=st.converged, iterations=st.iterations, reason=st.reason, scaled=scale,
    )


def _name_null(p, null, bad, scale):
    """Plain words for the directions N does not fix (empty tuple when all are fixed)."""
    if not null.shape[1]:
        return ()
    sv, Vt = np.linalg.svd(p - p.mean(axis=0), full_matrices=False)[1:]
    params = ", ".join(np.array(NAMES)[np.flatnonzero(bad)])
    if len(p) == 2 or sv[1] < _COLLINEAR * sv[0]:
        what = "two points" if len(p) == 2 else "collinear points"
        return (f"rotation about the line through the points, direction {fmt(Vt[0], 4)} in the source frame "
                f"({what}; affects {params})",)
    return (f"{null.shape[1]} direction(s) of the parameters ({params}) are not determined by the points",)


@dataclass(frozen=True, eq=False, repr=False)
class HelmertFit(ReportMixin):
    """Adjusted 3D transformation (source -> target) with the statistics of the Gauss-Helmert model.

    Attributes
    ----------
    matrix : ndarray (4, 4)
        s R and t in homogeneous form: target = matrix @ source (caller's frames).
    parameters : ndarray (6,) or (7,)
        [rx, ry, rz (rad), tx, ty, tz (m), (scale)] with R = Rz(rz) Ry(ry) Rx(rx).
    covariance : ndarray (6, 6) or (7, 7)
        Covariance of ``parameters``; rows/columns of undetermined parameters NaN, their variance inf.
    sigma0 : float
        A posteriori standard deviation of unit weight (NaN without redundancy).
    sigma_known : bool
        A priori covariances were given: global test and Baarda's test; else the estimated sigma0 is used.
    redundancy : int
        3n - u (u = number of determined parameters).
    residuals_source, residuals_target : ndarray (n, 3)
        Residuals of the points (m).
    point_statistic, point_dof, point_p : ndarray (n,)
        T_i = e_i^T Q_ee,i^+ e_i / sigma0^2 of each point pair, its degrees of freedom and p-value.
    point_test : ndarray (n,)
        The normal quantile with the same two-sided p-value (comparable with Baarda's w; NaN if untestable).
    point_redundancy : ndarray (n,)
        Share of each point pair in the redundancy (sums to ``redundancy``).
    global_test : GlobalTest
    alpha_w, w_critical : float
        Level and critical value of the point test.
    undetermined : tuple of str
        Named directions the points do not fix; empty when the transformation is fully determined.
    undetermined_parameters : ndarray of bool
    converged : bool
    iterations : int
    reason : str
    scaled : bool
        A scale factor was estimated.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.targets.helmert import helmert
    >>> p = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [0, 0, 3]])
    >>> fit = helmert(p, p + [1.0, 2.0, 3.0], target_cov=0.001)
    >>> fit.translation.round(6).tolist(), fit.std.shape
    ([1.0, 2.0, 3.0], (6,))
    """

    matrix: np.ndarray
    parameters: np.ndarray
    covariance: np.ndarray
    sigma0: float
    sigma_known: bool
    redundancy: int
    residuals_source: np.ndarray
    residuals_target: np.ndarray
    point_statistic: np.ndarray
    point_dof: np.ndarray
    point_p: np.ndarray
    point_test: np.ndarray
    point_redundancy: np.ndarray
    global_test: GlobalTest
    alpha_w: float
    w_critical: float
    undetermined: tuple
    undetermined_parameters: np.ndarray
    converged: bool
    iterations: int
    reason: str
    scaled: bool

    @property
    def scale(self) -> float:
        return float(self.parameters[6]) if self.scaled else 1.0

    @property
    def rotation(self) -> np.ndarray:
        """R (3, 3), without the scale."""
        return self.matrix[:3, :3] / self.scale

    @property
    def translation(self) -> np.ndarray:
        return self.matrix[:3, 3].copy()

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of ``parameters`` (rad, m, -); inf where undetermined."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def names(self) -> tuple:
        return NAMES[: len(self.parameters)]

    @property
    def flagged(self) -> np.ndarray:
        """Point pairs whose test exceeds the critical value (candidate gross errors or moved points)."""
        return np.nan_to_num(self.point_test) > self.w_critical

    @property
    def ok(self) -> bool:
        return self.converged and not self.reason and not self.undetermined

    def apply(self, points) -> np.ndarray:
        """Map source-frame points (n, 3) into the target frame."""
        xyz = as_points(points)
        return xyz @ self.matrix[:3, :3].T + self.matrix[:3, 3]

    def _report(self):
        std = self.std
        rows = []
        for i, name in enumerate(self.names):
            if i < 3:
                rows.append((name, f"{np.degrees(self.parameters[i]):+.6f} deg  +- "
                                   f"{np.degrees(std[i]) * 3600:.2f} arcsec"))
            elif i < 6:
                rows.append((name, f"{self.parameters[i]:+.4f} m  +- {std[i] * 1e3:.2f} mm"))
            else:
                rows.append((name, f"{self.parameters[i]:.8f}  +- {std[i] * 1e6:.2f} ppm"))
        g = self.global_test
        glob = ("not run: no a priori covariance given" if not self.sigma_known else
                f"T = {g.statistic:.2f}, accepted [{g.lower:.2f}, {g.upper:.2f}]: "
                + {True: "passed", False: "REJECTED", None: "not testable"}[g.passed])
        j = int(np.nanargmax(self.point_test)) if np.isfinite(self.point_test).any() else -1
        worst = "no redundancy" if j < 0 else (f"{self.point_test[j]:.2f} at point {j} (critical "
                                               f"{self.w_critical:.2f}): "
                                               + ("SUSPECT" if self.flagged[j] else "no gross error"))
        sections = [("Parameters (source -> target)", rows), ("Adjustment", [
            ("points", f"{len(self.point_test):d}"), ("redundancy", f"{self.redundancy:d}"),
            ("iterations", f"{self.iterations:d} ({'converged' if self.converged else 'NOT converged'})"),
            ("sigma0", fmt(self.sigma0, 4)), ("global test", glob), ("largest point test", worst)])]
        if self.undetermined:
            sections.insert(0, ("UNDETERMINED", [("", u) for u in self.undetermined]))
        if self.reason:
            sections.insert(0, ("WARNING", [("reason", self.reason)]))
        kind = "similarity" if self.scaled else "rigid"
        return f"3D {kind} transformation (Gauss-Helmert model)", sections
