"""Sphere adjustment in the Gauss-Helmert model (notebook 01, the exercise sheet, section 1).

Functional model (eq. 4): ``f_i(l + v, x) = |p_i + v_i - c| - r = 0`` with the
observations l = point coordinates and the parameters x = [xc, yc, zc, r].

Every condition involves one point only, so ``B Sigma_ll B^T`` is diagonal with
elements ``b_i^T Sigma_i b_i`` even for a full 3x3 covariance per point; the
normal matrix ``N = A^T (B Sigma_ll B^T)^-1 A`` is 4x4. Nothing of size n x n
or n x 3n is ever built: memory is O(n) and one iteration costs a few passes
over the points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import stdtrit  # scipy.stats.t.ppf without importing scipy.stats
from scipy.linalg.lapack import dpotrf, dpotrs

from ..core.checks import as_points, numeric_array, positive, probability
from ..core.frame import local_origin
from ..core.stats import GlobalTest, global_test, w_critical
from ..core.errors import DegenerateGeometryError, LabkitError
from .model import algebraic_sphere
from .fit import SphereFit
from .sweeps import compiled_sweeps, point_statistics

_EPS = np.finfo(np.float64).eps
_RCOND_MIN = 1e-12  # smallest reciprocal condition of the scaled N (the exercise sheet's det test)
_BLOCK = 32_768  # points per block in the sweeps of an iteration
_X0_SAMPLE = 20_000  # points used for the algebraic initial values
_FLAT_RATIO = 100.0  # radius above this many times the extent of the points: no curvature
_DIVERGED = "the iteration diverged (a point reached the centre or values became infinite)"


def gauss_helmert_model(
    points,
    x0=None,
    sigma=None,
    *,
    radius: float | None = None,
    tol: float = 1e-10,
    max_iterations: int = 50,
    alpha: float = 0.05,
    sigma0_apriori: float | None = None,
    alpha_w: float = 0.001,
) -> SphereFit:
    """Adjust a sphere to points in the Gauss-Helmert model (eqs. 1-24).

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        Observed coordinates l (m), n >= 4. Exactly 4 points give the circumsphere.
    x0 : array_like (4,), optional
        Initial values [xc, yc, zc, r] in the frame of ``points``; default: an
        algebraic sphere fit. With ``radius`` set, the centre (3,) is enough.
    sigma : None, float, array_like (n,), (n, 3) or (n, 3, 3), optional
        A priori precision of the coordinates: None (unit weights), one
        standard deviation for all, one per point, one per coordinate, or one
        3x3 covariance matrix per point (m, m^2).
    radius : float, optional
        Hold the radius fixed at this nominal value; only the centre is estimated.
    tol : float
        Convergence threshold on max|dx| (m); also the main-check tolerance.
    max_iterations : int
        Maximum number of iterations (the name ICP uses).
    alpha : float
        Significance level of the global test.
    sigma0_apriori : float, optional
        A priori standard deviation of unit weight (default 1 when ``sigma``
        is given). With neither ``sigma`` nor ``sigma0_apriori`` the scale of
        the weights is unknown: no global test is run (one against a made-up
        value would say nothing) and the residuals are tested with Pope's tau
        test on the estimated sigma0 instead of Baarda's w-test.
    alpha_w : float
        Significance level of each w- or tau-test (Baarda: 0.001, critical value 3.29).

    Returns
    -------
    SphereFit
        ``converged=False`` with a ``reason`` when the iteration fails.

    Raises
    ------
    LabkitError
        Bad shape, NaN/inf, fewer than 4 points, bad sigma or options.
    DegenerateGeometryError
        Coplanar, collinear, concyclic or duplicate points; singular N.

    Notes
    -----
    Rigorous iteration: linearize at l + v0 and x0 (eqs. 6-11) with the
    misclosures w = -B v0 + f(l + v0, x0) (eq. 8), solve
    dx = -N^-1 A^T (B Sigma B^T)^-1 w (eq. 21), k (eq. 19), v = Sigma B^T k
    (eq. 13), repeat until max|dx| < tol, then the main check (eq. 4).

    References
    ----------
    .. [1] Seed 000, section 1: functional model (eqs. 1-5), linearization and
       normal equations (eqs. 6-21), sigma0 and Sigma_xx (eqs. 22-24).
    .. [2] L. Lenzmann, E. Lenzmann (2004): Strenge Auswertung des nichtlinearen
       Gauss-Helmert-Modells. Allgemeine Vermessungs-Nachrichten 111(2), 68-73
       (the rigorous iteration: linearize at l + v0, misclosure w = -B v0 + f).
    .. [3] F. Neitzel (2010): Generalization of total least-squares on example of
       unweighted and weighted 2D similarity transformation. Journal of Geodesy
       84(12), 751-762, doi:10.1007/s00190-010-0408-0.
    .. [4] W. Baarda (1968): A testing procedure for use in geodetic networks.
       Netherlands Geodetic Commission, Publications on Geodesy 2(5) (w-test).
    .. [5] A. J. Pope (1976): The statistics of residuals and the detection of
       outliers. NOAA Technical Report NOS 65 NGS 1 (tau test without a priori sigma0).
    .. [6] Notebook 01, sections 2-9 (the same equations worked through, and the tests).
    .. [7] W. Niemeier (2008): Ausgleichungsrechnung. 2nd edition, de Gruyter, Berlin.
    .. [8] E. M. Mikhail, F. Ackermann (1976): Observations and Least Squares. IEP-Dun-Donnelley,
       New York.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.sphere.ghm import gauss_helmert_model
    >>> from labkit.synthetic import sphere_points
    >>> points = sphere_points(300, 1, center=[2.0, 1.0, 0.5], radius=0.15, noise=0.001)
    >>> fit = gauss_helmert_model(points, sigma=0.001)
    >>> fit.converged, fit.x.round(3).tolist()
    (True, [2.0, 1.0, 0.5, 0.15])
    >>> bool(np.all(fit.std < 2e-4)), fit.global_test.passed
    (True, True)
    """
    # Check input, once
    l_in = as_points(points, min_points=4)
    sigma = check_sigma(sigma, len(l_in))
    radius = None if radius is None else positive(radius, "radius")
    sigma0_apriori = None if sigma0_apriori is None else positive(sigma0_apriori, "sigma0_apriori")
    tol = positive(tol, "tol")
    alpha, alpha_w = probability(alpha, "alpha"), probability(alpha_w, "alpha_w")
    if int(max_iterations) != max_iterations or max_iterations < 1:
        raise LabkitError(f"max_iterations must be a whole number >= 1, got {max_iterations!r}")
    return adjust_sphere(l_in, x0, sigma, radius=radius, tol=tol, max_iterations=int(max_iterations), alpha=alpha,
                         sigma0_apriori=sigma0_apriori, alpha_w=alpha_w)


def adjust_sphere(
    points: np.ndarray,
    x0=None,
    sigma=None,
    *,
    radius: float | None = None,
    tol: float = 1e-10,
    max_iterations: int = 50,
    alpha: float = 0.05,
    sigma0_apriori: float | None = None,
    alpha_w: float = 0.001,
) -> SphereFit:
    """The adjustment of :func:`gauss_helmert_model` on inputs that are checked already.

    For a caller that adjusts many subsets of one checked cloud (the refit and snooping
    rounds of RANSAC): nothing is validated again, so every argument must be what
    :func:`gauss_helmert_model` would have passed on.

    Parameters
    ----------
    points : ndarray (n, 3) float64
        Finite coordinates (m), n >= 4, as returned by :func:`labkit.core.checks.as_points`.
    x0 : array_like (4,) or (3,), optional
        Initial values as in :func:`gauss_helmert_model` (their shape is still checked: it costs nothing).
    sigma : None, float or ndarray
        The value of :func:`check_sigma` for these points (rows of a checked array stay valid).
    radius, tol, max_iterations, alpha, sigma0_apriori, alpha_w
        Checked values of the options of :func:`gauss_helmert_model`.

    Returns
    -------
    SphereFit

    References
    ----------
    .. [1] Seed 000, section 1 (eqs. 1-24), as :func:`gauss_helmert_model`.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.core.checks import as_points
    >>> from labkit.sphere.ghm import adjust_sphere, check_sigma, gauss_helmert_model
    >>> from labkit.synthetic import sphere_points
    >>> points = as_points(sphere_points(300, 1, center=[2.0, 1.0, 0.5], radius=0.15, noise=0.001))
    >>> sigma = check_sigma(np.full(300, 0.001), 300)  # checked once ...
    >>> half = adjust_sphere(points[::2], sigma=sigma[::2])  # ... for every subset
    >>> bool(np.array_equal(half.x, gauss_helmert_model(points[::2], sigma=0.001).x))
    True
    """
    if len(points) < 4:
        raise LabkitError(f"points must hold at least 4 points, got {len(points)}")
    origin = local_origin(points)
    cov = _Stochastic(sigma)
    r_fix = radius
    sigma_known = sigma is not None or sigma0_apriori is not None
    sigma0_apriori = 1.0 if sigma0_apriori is None else sigma0_apriori
    x_start = _initial_values(points, x0, origin, r_fix)
    sweeps = compiled_sweeps() if cov.kind in ("scalar", "point") else None
    if sweeps is None:
        # Reduce to a local origin: one row per coordinate (contiguous, cache-friendly sweeps), in one pass
        L = np.empty((3, len(points)))
        np.subtract(points.T, origin[:, None], out=L)
        it = _iterate(L, x_start, cov, r_fix is not None, tol, int(max_iterations))  # (eqs. 6-22)
        per_point = lambda Qxx, scale: _per_point(L, it, Qxx, scale)  # noqa: E731
    else:  # equal or per-point precision: compiled sweeps over the points (n, 3), reduced on the fly
        pts = np.ascontiguousarray(points, dtype=np.float64)
        it = _iterate_compiled(pts, origin, x_start, cov, r_fix is not None, tol, int(max_iterations), sweeps)
        per_point = lambda Qxx, scale: point_statistics(pts, origin, it, Qxx, scale, sweeps[2])  # noqa: E731

    # Main check and statistics
    return _result(it, per_point, origin, r_fix is not None, tol, alpha, alpha_w, sigma0_apriori, sigma_known)


# --------------------------------------------------------------- stochastic model
class _Stochastic:
    """Sigma_ll of independent points: diag(B Sigma B^T) and v = Sigma B^T k, point by point.

    The rows b_i of B come as a (3, m) array for the points of the slice ``sl``.
    """

    def __init__(self, sigma):
        self.kind, self.C = _variances(sigma)

    def qbb(self, b, sl):
        """Diagonal of B Sigma_ll B^T: b_i^T Sigma_i b_i, shape (m,) (a scalar if all are equal)."""
        if self.kind == "scalar":  # |b_i| = 1: the same value for every point
            return self.C
        if self.kind == "point":
            return self.C[sl]
        if self.kind == "axis":
            return (b * b * self.C[:, sl]).sum(axis=0)
        return (b * self._Cb(b, sl)).sum(axis=0)

    def v(self, b, k, sl):
        """Residuals v = Sigma_ll B^T k (eq. 13), shape (3, m)."""
        if self.kind == "scalar":
            return b * (self.C * k)
        if self.kind == "point":
            return b * (self.C[sl] * k)
        if self.kind == "axis":
            return b * self.C[:, sl] * k
        return self._Cb(b, sl) * k

    def _Cb(self, b, sl):
        return np.einsum("nij,jn->in", self.C[sl], b)


def _variances(s):
    """(kind, variances) from a checked sigma (:func:`check_sigma`); kinds: scalar, point, axis, full."""
    if s is None:
        return "scalar", 1.0
    if np.ndim(s) == 0:
        return "scalar", float(s) ** 2
    if s.ndim < 3:
        return ("point" if s.ndim == 1 else "axis"), np.ascontiguousarray((s**2).T)
    return "full", s


def check_sigma(sigma, n: int):
    """The a priori sigma of ``n`` points checked: None, a float > 0, or a float64 array (n,), (n, 3) > 0 or (n, 3, 3).

    Covariance matrices (n, 3, 3) must be symmetric and positive definite; NaN/inf are refused.

    References
    ----------
    .. [1] Seed 000, section 1 (the stochastic model Sigma_ll of the Gauss-Helmert model).

    Examples
    --------
    >>> from labkit.sphere.ghm import check_sigma
    >>> check_sigma(0.002, 10), check_sigma([0.001] * 4, 4).shape
    (0.002, (4,))
    """
    if sigma is None:
        return None
    s = numeric_array(sigma, "sigma")
    if s.ndim == 0 or s.shape in ((n,), (n, 3)):
        if (s <= 0).any():
            raise LabkitError("sigma (standard deviations) must be > 0")
        return float(s) if s.ndim == 0 else s
    if s.shape == (n, 3, 3):
        scale = np.abs(s).max(axis=(1, 2))
        if (np.abs(s - s.transpose(0, 2, 1)).max(axis=(1, 2)) > 1e-9 * scale).any():
            raise LabkitError("sigma covariance matrices (n, 3, 3) must be symmetric")
        try:
            np.linalg.cholesky(s)
        except np.linalg.LinAlgError:
            raise LabkitError("sigma covariance matrices (n, 3, 3) must be positive definite") from None
        return s
    raise LabkitError(
        f"sigma must be None, a scalar, or of shape ({n},), ({n}, 3) or ({n}, 3, 3); got {s.shape}"
    )


# --------------------------------------------------------------- iteration
def _initial_values(points, x0, origin, r_fix):
    """x0 in the local frame: the caller's values or the algebraic sphere."""
    if x0 is None:  # a regular subsample of at most ~20 000 points is plenty for initial values
        x = algebraic_sphere(points[:: max(1, len(points) // _X0_SAMPLE)] - origin)
    else:
        x = np.asarray(x0, dtype=np.float64).ravel()
        if r_fix is not None and x.shape == (3,):  # a centre is enough when the radius is fixed
            x = np.append(x, r_fix)
        if x.shape != (4,) or not np.isfinite(x).all():
            raise LabkitError(f"x0 must be 4 finite numbers [xc, yc, zc, r], got {x0!r}")
        x = np.concatenate([x[:3] - origin, x[3:]])
    if r_fix is not None:
        x = np.concatenate([x[:3], [r_fix]])
    return x


@dataclass(frozen=True, eq=False)
class _Iteration:
    """State after the last iteration (local frame; b and v as (3, n), or (n, 3) from the compiled sweeps)."""

    x: np.ndarray
    v: np.ndarray
    k: np.ndarray
    b: np.ndarray
    qbb: np.ndarray
    N_chol: np.ndarray  # the upper Cholesky factor of N
    N: np.ndarray
    dx_history: np.ndarray
    omega_history: np.ndarray
    converged: bool
    reason: str
    amax: float  # max |l| (the scale of the rounding tolerances)
    extent: float  # largest extent of the points along an axis


def _blocks(n):
    """Slices of at most _BLOCK points: the temporaries of one block stay in the CPU cache."""
    return [slice(s, min(s + _BLOCK, n)) for s in range(0, n, _BLOCK)]


def _linearize(L, v0, x0):
    """Rows of B (eq. 10) and misclosures w (eq. 8) at l + v0, x0; L, v0 as (3, m)."""
    u = L + v0
    u -= x0[:3, None]
    ri = np.sqrt(np.einsum("ij,ij->j", u, u))  # (eq. 11)
    b = u
    b /= ri  # (eq. 10): b_i = (p_i + v0_i - c) / r_i
    # (eq. 8): w_i = [(l_i + v0_i - c) . (l_i - c)] / r_i - r  =  -b_i . v0_i + (r_i - r)
    w = ri - x0[3] - np.einsum("ij,ij->j", b, v0)
    return b, w, ri


def _normal_equations(b, q, w, fixed):
    """N = A^T P A and n = A^T P w (eq. 21) with A = [-b_i, -1] (eq. 9), never forming A.

    ``q`` is diag(B Sigma_ll B^T) for the block, P = 1/q; a scalar q (same
    precision for all points) scales the 4x4 sums instead of every row. The sums
    run in numpy's einsum loops, not BLAS: for 3 x m by m x 3 products BLAS gains
    nothing and its threads stall on a busy machine.
    """
    scalar = np.ndim(q) == 0
    P = 1.0 / q
    Pb, s = (b, P) if scalar else (b * P, 1.0)
    u = 3 if fixed else 4
    N, rhs = np.empty((u, u)), np.empty(u)
    N[:3, :3] = s * np.einsum("ij,kj->ik", Pb, b)
    rhs[:3] = -s * np.einsum("ij,j->i", Pb, w)
    if not fixed:
        N[:3, 3] = N[3, :3] = s * Pb.sum(axis=1)
        N[3, 3] = P * b.shape[1] if scalar else P.sum()
        rhs[3] = -(P * w.sum() if scalar else np.einsum("j,j->", P, w))
    return N, rhs


def _A_times(b, dx):
    """A dx with the rows a_i = [-b_i, -1] of eq. (9)."""
    Adx = dx[:3] @ b
    if len(dx) == 4:
        Adx += dx[3]
    return np.negative(Adx, out=Adx)


def _factor(N):
    """Cholesky factor of N after a conditioning check (the exercise sheet's det test)."""
    d = np.sqrt(np.diag(N))
    if not np.isfinite(N).all() or (d <= 0).any():
        raise DegenerateGeometryError("the normal matrix N is singular: the points do not determine a sphere")
    lam = np.linalg.eigvalsh(N / np.outer(d, d))
    if lam[0] < _RCOND_MIN * lam[-1]:
        raise DegenerateGeometryError(
            f"the normal matrix N is singular (reciprocal condition {lam[0] / lam[-1]:.1e}): "
            "the points lie on a plane, a circle or coincide"
        )
    c, info = dpotrf(N, lower=0, clean=0)  # the upper factor of cho_factor, without its wrappers (they cost more)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive definite")
    return c


def _iterate(L, x0, cov, fixed, tol, max_iter):
    """Rigorous Gauss-Helmert iteration (eqs. 6-22) until max|dx| < tol; L is (3, n).

    Each iteration makes two sweeps over blocks of points: (1) linearize and
    accumulate N and A^T P w, (2) after solving for dx, the correlates k and
    residuals v. Arrays of length n are written block by block.
    """
    n, u = L.shape[1], (3 if fixed else 4)
    blocks = _blocks(n)
    v0, x = np.zeros_like(L), x0.copy()
    b, w, qbb, k = np.empty_like(L), np.empty(n), np.empty(n), np.zeros(n)
    amax = float(np.abs(L).max())
    tol_eff = max(tol, 64 * _EPS * (amax + abs(x0[3])))
    dxs, omegas, converged, reason, N = [], [], False, "", None
    for _ in range(max_iter):
        # (1) linearize at l + v0, x0 (eqs. 8-11) and accumulate the normal equations (eq. 21)
        N_new, rhs, finite = np.zeros((u, u)), np.zeros(u), True
        for sl in blocks:
            b[:, sl], w[sl], ri = _linearize(L[:, sl], v0[:, sl], x)
            qbb[sl] = q = cov.qbb(b[:, sl], sl)  # diag(B Sigma_ll B^T)
            Nb, rb = _normal_equations(b[:, sl], q, w[sl], fixed)
            N_new += Nb
            rhs += rb
            finite &= bool(ri.min() > 0)
        if not (finite and np.isfinite(rhs).all()):
            reason = _DIVERGED
            break
        N = N_new
        N_chol, dx = _solve(N, rhs)
        # (2) correlates and residuals
        for sl in blocks:
            q = cov.C if cov.kind == "scalar" else qbb[sl]
            k[sl] = -(_A_times(b[:, sl], dx) + w[sl]) / q  # (eq. 19)
            v0[:, sl] = cov.v(b[:, sl], k[sl], sl)  # (eq. 13) v = Sigma_ll B^T k
        x = _advance(x, dx, dxs)
        omegas.append(float(np.einsum("i,i,i->", qbb, k, k)))  # v^T Sigma^-1 v = sum k_i^2 b_i^T Sigma_i b_i
        if np.abs(dx).max() < tol_eff:
            converged = True
            break
    reason = _outcome(N, converged, reason, max_iter, dxs)
    return _Iteration(x, v0, k, b, qbb, N_chol, N, np.array(dxs), np.array(omegas), converged, reason, amax,
                      float(np.ptp(L, axis=1).max()))


def _iterate_compiled(pts, origin, x0, cov, fixed, tol, max_iter, sweeps):
    """:func:`_iterate` in compiled sweeps (:mod:`~labkit.sphere.sweeps`) for equal or per-point precision."""
    linearize, correlates = sweeps[0], sweeps[1]
    n, u = len(pts), (3 if fixed else 4)
    q = np.atleast_1d(np.asarray(cov.C, dtype=np.float64))  # diag(B Sigma_ll B^T) = sigma_i^2 (|b_i| = 1)
    v0, x = np.empty((n, 3)), x0.copy()  # (v0 = 0 in the first sweep, which does not read it)
    b, w, k = np.empty((n, 3)), np.empty(n), np.zeros(n)
    dxs, omegas, converged, reason, N = [], [], False, "", None
    for it in range(max_iter):
        N_it, rhs, rmin, amax, extent = linearize(pts, origin, v0, x, q, u, b, w, it == 0)  # (eqs. 8-11, 21)
        if it == 0:
            tol_eff, scale = max(tol, 64 * _EPS * (amax + abs(x0[3]))), (amax, extent)
        if rmin <= 0 or not np.isfinite(rhs).all():
            reason = _DIVERGED
            break
        N_chol, dx = _solve(N_it, rhs)
        N = N_it
        omegas.append(correlates(b, w, dx, q, k, v0))  # (eqs. 19, 13), v^T Sigma^-1 v
        x = _advance(x, dx, dxs)
        converged = bool(np.abs(dx).max() < tol_eff)
        if converged:
            break
    reason = _outcome(N, converged, reason, max_iter, dxs)
    return _Iteration(x, v0, k, b, q, N_chol, N, np.array(dxs), np.array(omegas), converged, reason, *scale)


def _solve(N, rhs):
    """Cholesky factor of N and dx = -N^-1 A^T P w (eq. 21)."""
    return (N_chol := _factor(N)), -dpotrs(N_chol, rhs, lower=0)[0]


def _advance(x, dx, dxs):
    """x + dx (eq. 22); dx is kept in the history (0 for a held radius)."""
    x = x.copy()
    x[: len(dx)] += dx
    dxs.append(dx if len(dx) == 4 else np.append(dx, 0.0))
    return x


def _outcome(N, converged, reason, max_iter, dxs):
    """Why the iteration stopped unconverged ('' if it converged); raises if no linearization was valid."""
    if N is None:
        raise DegenerateGeometryError("the initial values give no valid linearization (a point at the sphere centre)")
    if converged or reason:
        return reason
    return f"no convergence after {max_iter} iterations (last max|dx| = {np.abs(dxs[-1]).max():.2e} m)"


def _per_point(L, it, Qxx, scale):
    """Main check (eq. 4), redundancy numbers, normal residuals, w-test values and v (n, 3): numpy route."""
    main_check = max(_max_misclosure(L[:, sl] + it.v[:, sl], it.x) for sl in _blocks(L.shape[1]))
    ri = np.clip(1.0 - (1.0 / it.qbb) * _leverage(it.b, Qxx), 0.0, 1.0)
    e = -it.qbb * it.k  # -b_i^T v_i: residual along the normal, positive outside
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ri > 1e-10, e / (scale * np.sqrt(it.qbb * ri)), np.nan)
    return main_check, ri, e, w, np.ascontiguousarray(it.v.T)


# --------------------------------------------------------------- statistics
def _result(it, per_point, origin, fixed, tol, alpha, alpha_w, sigma0_apriori, sigma_known=True):
    """Main check, sigma0, Sigma_xx, redundancy numbers, w-test; back to the caller's frame."""
    n, u = len(it.k), (3 if fixed else 4)
    dof = n - u
    # sigma0 (eq. 23) and Sigma_xx = sigma0^2 N^-1 (eq. 24 corrected)
    omega = float(it.omega_history[-1])  # v^T Sigma^-1 v of the last iteration
    sigma0 = float(np.sqrt(omega / dof)) if dof > 0 else np.nan
    Qxx = dpotrs(it.N_chol, np.eye(u), lower=0)[0]  # (cho_solve's routine)
    Sigma_xx = np.zeros((4, 4))
    Sigma_xx[:u, :u] = (sigma0 if dof > 0 else sigma0_apriori) ** 2 * Qxx
    undetermined = ""
    if dof == 0 and not sigma_known:  # no redundancy and no a priori precision: nothing states the scale
        Sigma_xx[:u, :u] = np.nan
        undetermined = (f"no redundancy ({n} points for {u} parameters): sigma0 and the standard deviations are "
                        "undetermined; give sigma (or more points) to state them")
    # Main check (Hauptprobe): eq. 4 with the adjusted l + v and x; redundancy numbers
    # r_i = 1 - p_i a_i^T N^-1 a_i; Baarda's w with the a priori sigma0, without one Pope's tau
    main_check, ri, e, w, v = per_point(Qxx, sigma0_apriori if sigma_known else sigma0)
    check_tol = max(tol, 1e3 * _EPS * (it.amax + abs(it.x[3])))
    if sigma_known:
        g_test, crit = global_test(omega, dof, sigma0_apriori, alpha), w_critical(alpha_w)
    else:
        g_test, crit = GlobalTest(np.nan, int(dof), np.nan, np.nan, alpha, None, np.nan), tau_critical(alpha_w, dof)
    reason = it.reason or _plausibility(it.extent, it.x, main_check, check_tol, it.converged) or undetermined
    return SphereFit(
        x=np.concatenate([it.x[:3] + origin, it.x[3:]]),
        Sigma_xx=Sigma_xx,
        sigma0=sigma0,
        v=v,
        converged=it.converged,
        iterations=len(it.dx_history),
        main_check=main_check,
        main_check_passed=main_check <= check_tol,
        redundancy=dof,
        dx_history=it.dx_history,
        omega_history=it.omega_history,
        redundancy_numbers=ri,
        w_test=w,
        normal_residuals=e,
        global_test=g_test,
        w_critical=crit,
        alpha_w=alpha_w,
        N=it.N,
        fixed_radius=fixed,
        sigma0_apriori=sigma0_apriori,
        reason=reason,
        sigma_known=sigma_known,
    )


def tau_critical(alpha_w: float, dof: int) -> float:
    """Two-sided critical value of Pope's tau test with ``dof`` = n - u degrees of freedom.

    tau = e_i / (sigma0_hat sqrt(q_i r_i)) uses the estimated sigma0, so it is
    not normal but tau-distributed: ``tau = sqrt(f) T / sqrt(f - 1 + T^2)``
    with T Student-t with f - 1 degrees of freedom (Pope 1976), |tau| <= sqrt(f).
    NaN for f < 2 (no test possible).

    References
    ----------
    .. [1] A. J. Pope (1976): The statistics of residuals and the detection of
       outliers. NOAA Technical Report NOS 65 NGS 1.

    Examples
    --------
    >>> from labkit.sphere.ghm import tau_critical
    >>> round(tau_critical(0.001, 10), 3), round(tau_critical(0.001, 10_000), 3)
    (2.679, 3.29)
    """
    alpha_w = probability(alpha_w, "alpha_w")
    if dof < 2:
        return float("nan")
    t = float(stdtrit(dof - 1, 1.0 - alpha_w / 2.0))
    return float(np.sqrt(dof) * t / np.sqrt(dof - 1 + t * t))


def _max_misclosure(lv, x):
    """max_i |f_i(l + v, x)| of eq. (4) for one block, lv = l + v as (3, m)."""
    q = lv - x[:3, None]
    return float(np.abs(np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]) - x[3]).max())


def _leverage(b, Qxx):
    """a_i^T N^-1 a_i for the rows a_i = [-b_i, -1] of A (eq. 9), b as (3, n)."""
    h = np.einsum("ij,in,jn->n", Qxx[:3, :3], b, b)
    if len(Qxx) == 4:
        h += 2.0 * np.einsum("i,in->n", Qxx[3, :3], b) + Qxx[3, 3]
    return h


def _plausibility(extent, x, main_check, check_tol, converged):
    """Reason why a converged result must not be trusted ('' if none)."""
    if not converged:
        return "no convergence"
    if main_check > check_tol:
        return f"main check failed: max|f(l+v, x)| = {main_check:.2e} m exceeds {check_tol:.1e} m"
    if x[3] <= 0:
        return f"the adjusted radius {x[3]:.4g} m is not positive"
    if x[3] > _FLAT_RATIO * extent:
        return (f"the points barely curve: radius {x[3]:.4g} m exceeds {_FLAT_RATIO:.0f}x their extent "
                f"({extent:.3g} m); a plane may fit as well")
    return ""
