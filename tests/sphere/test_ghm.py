"""Gauss-Helmert sphere adjustment against independent routes.

- scipy.optimize.least_squares on the orthogonal distances (unit weights, fixed radius),
- a dense textbook Gauss-Helmert model built here (B as n x 3n, Sigma_ll as 3n x 3n),
- Monte Carlo replicates for Sigma_xx, sigma0 and the confidence ellipsoid,
- the closed-form circumsphere of 4 points.
"""

import numpy as np
import pytest
from scipy.optimize import least_squares

from labkit.sphere.ghm import SphereFit, gauss_helmert_model
from labkit.core.errors import DegenerateGeometryError, LabkitError
from labkit.sphere.model import circumspheres
from labkit.synthetic import sphere_on_tripod

SHIFT = np.array([600_000.0, 5_400_000.0, 300.0])


def _cap(n, rng, noise=0.001, **kw):
    """Sphere points of a tripod scene (the visible cap only), with the truth."""
    scene = sphere_on_tripod(n_sphere=n, outlier_ratio=0.0, noise=noise, rng=rng, **kw)
    return scene


def _odr_scipy(points, x0, radius=None):
    """Orthogonal-distance sphere fit with scipy (analytic Jacobian)."""
    def fun(x):
        r = radius if radius is not None else x[3]
        return np.linalg.norm(points - x[:3], axis=1) - r

    def jac(x):
        d = points - x[:3]
        J = -d / np.linalg.norm(d, axis=1, keepdims=True)
        return J if radius is not None else np.column_stack([J, -np.ones(len(points))])

    start = x0[:3] if radius is not None else x0
    sol = least_squares(fun, start, jac=jac, xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm")
    return sol.x


def _dense_ghm(l, Sigma_ll, x0, iters=30):
    """Textbook Gauss-Helmert model with dense matrices, v ordered as in eq. (5)."""
    n = len(l)
    lx = l.T.ravel()  # [x1..xn, y1..yn, z1..zn]
    v = np.zeros(3 * n)
    x = x0.astype(float).copy()
    for _ in range(iters):
        p = (lx + v).reshape(3, n).T  # l + v0 as (n, 3)
        d = p - x[:3]
        ri = np.linalg.norm(d, axis=1)  # (eq. 11)
        A = np.column_stack([-d / ri[:, None], -np.ones(n)])  # (eq. 9)
        B = np.zeros((n, 3 * n))  # (eq. 10)
        for j in range(3):
            B[np.arange(n), j * n + np.arange(n)] = d[:, j] / ri
        w = -B @ v + (ri - x[3])  # (eq. 8)
        M = B @ Sigma_ll @ B.T
        Minv = np.linalg.inv(M)
        N = A.T @ Minv @ A  # (eq. 21)
        dx = -np.linalg.solve(N, A.T @ Minv @ w)
        k = -Minv @ (A @ dx + w)  # (eq. 19)
        v = Sigma_ll @ B.T @ k  # (eq. 13)
        x = x + dx
        if np.abs(dx).max() < 1e-13:
            break
    omega = v @ np.linalg.solve(Sigma_ll, v)
    sigma0 = np.sqrt(omega / (n - 4))
    Ninv = np.linalg.inv(N)
    Qkk = Minv - Minv @ A @ Ninv @ A.T @ Minv
    Qvv = Sigma_ll @ B.T @ Qkk @ B @ Sigma_ll
    R = Qvv @ np.linalg.inv(Sigma_ll)
    r_point = np.diag(R).reshape(3, n).sum(axis=0)
    e = np.einsum("ij,ij->i", B.reshape(n, 3, n).transpose(0, 2, 1)[np.arange(n), np.arange(n)], v.reshape(3, n).T)
    var_e = np.einsum("ij,ij->i", B @ Qvv, B)
    w_test = -e / np.sqrt(var_e)
    return dict(x=x, v=v.reshape(3, n).T, sigma0=sigma0, Sigma_xx=sigma0**2 * Ninv, r=r_point, w=w_test)


def _block_diag(covs):
    """Dense 3n x 3n Sigma_ll (order of eq. 5) from per-point 3x3 covariances."""
    n = len(covs)
    S = np.zeros((3 * n, 3 * n))
    for a in range(3):
        for b in range(3):
            S[a * n + np.arange(n), b * n + np.arange(n)] = covs[:, a, b]
    return S


# ------------------------------------------------------------------ correctness
def test_unit_weights_equal_scipy_orthogonal_distance_fit():
    scene = _cap(800, rng=1)
    pts = scene.sphere_points
    fit = gauss_helmert_model(pts)
    ref = _odr_scipy(pts, scene.sphere + 0.003)
    assert fit.ok and fit.converged and fit.main_check_passed
    np.testing.assert_allclose(fit.x, ref, atol=1e-9, rtol=0)
    # the residuals move every point onto the adjusted sphere, along the normal
    on = np.linalg.norm(pts + fit.v - fit.center, axis=1)
    np.testing.assert_allclose(on, fit.radius, atol=1e-12)
    d = np.linalg.norm(pts - fit.center, axis=1) - fit.radius
    np.testing.assert_allclose(fit.normal_residuals, d, atol=1e-12)


def test_fixed_radius_equals_scipy_with_radius_held():
    scene = _cap(500, rng=2)
    pts = scene.sphere_points
    nominal = 0.0725
    fit = gauss_helmert_model(pts, radius=nominal, sigma=0.001)
    ref = _odr_scipy(pts, scene.sphere + 0.002, radius=nominal)
    np.testing.assert_allclose(fit.center, ref, atol=1e-9, rtol=0)
    assert fit.radius == nominal and fit.fixed_radius
    assert fit.redundancy == len(pts) - 3
    assert fit.std[3] == 0 and (fit.std[:3] > 0).all()
    assert fit.redundancy_numbers.sum() == pytest.approx(len(pts) - 3, rel=1e-9)
    # a centre alone is enough as initial values when the radius is fixed
    fit3 = gauss_helmert_model(pts, x0=scene.sphere[:3] + 0.002, radius=nominal, sigma=0.001)
    np.testing.assert_allclose(fit3.center, ref, atol=1e-9, rtol=0)


@pytest.mark.parametrize("anisotropic", [False, True])
def test_matches_dense_textbook_gauss_helmert(anisotropic):
    scene = _cap(30, rng=3, noise=0.0005, range_noise=0.003 if anisotropic else None)
    pts = scene.sphere_points
    covs = scene.covariances()
    fit = gauss_helmert_model(pts, sigma=covs)
    ref = _dense_ghm(pts - pts.mean(axis=0), _block_diag(covs), fit.x - np.r_[pts.mean(axis=0), 0])
    np.testing.assert_allclose(fit.x - np.r_[pts.mean(axis=0), 0], ref["x"], atol=1e-12)
    np.testing.assert_allclose(fit.v, ref["v"], atol=1e-12)
    assert fit.sigma0 == pytest.approx(ref["sigma0"], rel=1e-8)
    np.testing.assert_allclose(fit.Sigma_xx, ref["Sigma_xx"], rtol=1e-7, atol=1e-20)
    np.testing.assert_allclose(fit.redundancy_numbers, ref["r"], atol=1e-9)
    np.testing.assert_allclose(fit.w_test, ref["w"], rtol=1e-7)
    # with range noise the residuals are not along the normal any more
    if anisotropic:
        b = (pts + fit.v - fit.center) / fit.radius
        cross = np.linalg.norm(np.cross(b, fit.v), axis=1)
        assert np.median(cross / np.linalg.norm(fit.v, axis=1)) > 0.05  # sin of the angle to the normal


def test_dense_reference_converges_from_poor_start_to_the_same_solution():
    scene = _cap(12, rng=4)
    pts = scene.sphere_points
    fit = gauss_helmert_model(pts, x0=scene.sphere + [0.01, -0.01, 0.01, 0.005])
    ref = _dense_ghm(pts, np.eye(3 * len(pts)), scene.sphere + [0.01, -0.01, 0.01, 0.005])
    np.testing.assert_allclose(fit.x, ref["x"], atol=1e-11)


def test_redundancy_numbers_sum_to_redundancy_and_lie_in_unit_interval():
    fit = gauss_helmert_model(_cap(300, rng=5).sphere_points, sigma=0.001)
    r = fit.redundancy_numbers
    assert r.sum() == pytest.approx(fit.redundancy, rel=1e-9)
    assert (r > 0).all() and (r < 1).all()


@pytest.mark.parametrize("kind", ["scalar", "point", "axis", "full"])
def test_all_sigma_forms_of_the_same_precision_agree(kind):
    pts = _cap(200, rng=6).sphere_points
    n, s = len(pts), 0.002
    sigma = {"scalar": s, "point": np.full(n, s), "axis": np.full((n, 3), s),
             "full": np.broadcast_to(s**2 * np.eye(3), (n, 3, 3))}[kind]
    fit = gauss_helmert_model(pts, sigma=sigma)
    ref = gauss_helmert_model(pts, sigma=s)
    np.testing.assert_allclose(fit.x, ref.x, atol=1e-13)
    np.testing.assert_allclose(fit.Sigma_xx, ref.Sigma_xx, rtol=1e-9)
    assert fit.sigma0 == pytest.approx(ref.sigma0, rel=1e-10)


# ------------------------------------------------------------------ Monte Carlo
def _monte_carlo(anisotropic, reps=300, n=150):
    scene = _cap(n, rng=7, noise=0.0, range_noise=0.0)
    truth, clean = scene.sphere, scene.sphere_points
    gen = sphere_on_tripod(n_sphere=n, outlier_ratio=0.0, noise=0.001,
                           range_noise=0.004 if anisotropic else None, rng=7)
    covs = _cov_at(clean, gen)  # the scanner's covariance model at the noise-free points
    L = np.linalg.cholesky(covs)
    rng = np.random.default_rng(70)
    xs, s0, inside, pred = [], [], [], []
    for _ in range(reps):
        pts = clean + np.einsum("nij,nj->ni", L, rng.normal(size=(n, 3)))
        fit = gauss_helmert_model(pts, sigma=covs)
        xs.append(fit.x)
        s0.append(fit.sigma0)
        inside.append(fit.confidence_ellipsoid(0.95).contains(truth[:3]))
        pred.append(fit.Sigma_xx / fit.sigma0**2)  # sigma0 a priori = 1
    return truth, np.array(xs), np.array(s0), np.mean(inside), np.mean(pred, axis=0)


def _cov_at(points, scene):
    u = points - scene.station
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return scene.noise**2 * np.eye(3) + (scene.range_noise**2 - scene.noise**2) * u[:, :, None] * u[:, None, :]


@pytest.mark.slow
@pytest.mark.parametrize("anisotropic", [False, True])
def test_monte_carlo_spread_matches_Sigma_xx(anisotropic):
    truth, xs, s0, coverage, Q = _monte_carlo(anisotropic)
    emp_std = xs.std(axis=0, ddof=1)
    pred_std = np.sqrt(np.diag(Q))
    np.testing.assert_allclose(emp_std, pred_std, rtol=0.15)
    # the estimates scatter around the truth (bias well below the spread)
    assert (np.abs(xs.mean(axis=0) - truth) < 4 * pred_std / np.sqrt(len(xs)) + 0.1 * pred_std).all()
    assert s0.mean() == pytest.approx(1.0, abs=0.03)
    assert 0.91 <= coverage <= 0.99


def test_sigma0_reveals_a_wrong_a_priori_sigma():
    pts = _cap(500, rng=8, noise=0.002).sphere_points
    fit = gauss_helmert_model(pts, sigma=0.001)
    assert fit.sigma0 == pytest.approx(2.0, rel=0.1)
    assert fit.global_test.passed is False
    assert gauss_helmert_model(pts, sigma=0.002).global_test.passed is True


# ------------------------------------------------------------------ 4 points, frames
def test_four_points_give_the_exact_circumsphere():
    rng = np.random.default_rng(9)
    for _ in range(20):
        c, r = rng.uniform(-3, 3, 3), rng.uniform(0.05, 2.0)
        u = rng.normal(size=(4, 3))
        pts = c + r * u / np.linalg.norm(u, axis=1, keepdims=True)
        cc, rr, valid = circumspheres(pts[None])
        if not valid[0]:
            continue
        fit = gauss_helmert_model(pts)
        assert fit.converged and fit.main_check_passed and fit.redundancy == 0
        np.testing.assert_allclose(fit.center, cc[0], atol=1e-9)
        assert fit.radius == pytest.approx(rr[0], abs=1e-9)
        np.testing.assert_allclose(fit.v, 0.0, atol=1e-12)
        assert np.isnan(fit.sigma0) and fit.global_test.passed is None
        # no redundancy, no a priori sigma: the precision is undetermined and said so, never a made-up number
        assert np.isnan(fit.std).all() and not fit.ok and "undetermined" in fit.reason
        assert fit.largest_w == -1


def test_utm_shift_gives_the_same_result():
    scene = _cap(400, rng=10)
    pts = scene.sphere_points
    a = gauss_helmert_model(pts, sigma=0.001)
    b = gauss_helmert_model(pts + SHIFT, sigma=0.001)
    np.testing.assert_allclose(b.center - SHIFT, a.center, atol=1e-9, rtol=0)
    assert b.radius == pytest.approx(a.radius, abs=1e-9)
    np.testing.assert_allclose(b.v, a.v, atol=1e-9)
    np.testing.assert_allclose(b.Sigma_xx, a.Sigma_xx, rtol=1e-6)
    c = gauss_helmert_model(pts + SHIFT, x0=a.x + np.r_[SHIFT, 0], sigma=0.001)
    np.testing.assert_allclose(c.center - SHIFT, a.center, atol=1e-9, rtol=0)


# ------------------------------------------------------------------ tests of the statistics
def test_gross_error_is_flagged_by_global_and_w_test():
    scene = _cap(300, rng=11)
    pts = scene.sphere_points.copy()
    clean = gauss_helmert_model(pts, sigma=0.001)
    assert clean.global_test.passed
    j = 17
    normal = (pts[j] - scene.sphere[:3]) / scene.sphere[3]
    pts[j] += 0.015 * normal  # 15 mm outward
    fit = gauss_helmert_model(pts, sigma=0.001)
    assert fit.global_test.passed is False
    assert fit.largest_w == j
    assert fit.w_test[j] > fit.w_critical  # outside: positive w
    assert fit.flagged[j]
    assert "GROSS ERROR" in fit.summary()


def test_w_test_is_standard_normal_without_gross_errors():
    fit = gauss_helmert_model(_cap(3000, rng=12).sphere_points, sigma=0.001)
    assert np.nanmean(fit.w_test) == pytest.approx(0.0, abs=0.06)
    assert np.nanstd(fit.w_test) == pytest.approx(1.0, abs=0.05)
    np.testing.assert_allclose(fit.standardized_residuals * fit.sigma0, fit.w_test, rtol=1e-12)


def test_confidence_ellipsoid_axes_from_Sigma_xx():
    fit = gauss_helmert_model(_cap(300, rng=13).sphere_points, sigma=0.001)
    ell = fit.confidence_ellipsoid(0.9)
    C = fit.Sigma_xx[:3, :3]
    for a, d in zip(ell.semi_axes, ell.axes.T):
        np.testing.assert_allclose(C @ d, (a**2 / ell.quantile) * d, rtol=1e-8, atol=1e-18)
    assert ell.semi_axes[0] >= ell.semi_axes[1] >= ell.semi_axes[2] > 0
    assert ell.contains(fit.center)
    assert not ell.contains(fit.center + 2 * ell.semi_axes[0] * ell.axes[:, 0])


def test_report_and_history():
    fit = gauss_helmert_model(_cap(200, rng=14).sphere_points, sigma=0.001)
    assert isinstance(fit, SphereFit)
    assert fit.dx_history.shape == (fit.iterations, 4)
    assert fit.omega_history.shape == (fit.iterations,)
    assert np.abs(fit.dx_history[-1]).max() < 1e-10
    text = fit.summary()
    assert "Gauss-Helmert" in text and "main check" in text and "passed" in text
    assert "<table>" in fit._repr_html_()


# ------------------------------------------------------------------ bad input
def _plane(n=20):
    g = np.random.default_rng(0).uniform(-1, 1, (n, 2))
    return np.column_stack([g, np.full(n, 2.0)])


def _circle(n=20):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([np.cos(t), np.sin(t), np.zeros(n)]) + [5.0, 1.0, 0.3]


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((3, 3)) + np.arange(3)[:, None],  # n < 4
        np.ones((10, 2)),  # wrong shape
        np.ones(12),  # 1-D
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 1.0]]),
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.inf, 0, 1.0]]),
        "points",
    ],
)
def test_bad_points_raise_labkit_error(points):
    with pytest.raises(LabkitError):
        gauss_helmert_model(points)


@pytest.mark.parametrize(
    "points",
    [
        _plane(),
        _circle(),
        np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 1.0]]),  # duplicate among 4
        np.repeat(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), 5, axis=0),  # 3 distinct points
        np.zeros((10, 3)),
    ],
    ids=["plane", "circle", "duplicate4", "three-distinct", "all-equal"],
)
def test_degenerate_geometry_raises(points):
    with pytest.raises(DegenerateGeometryError):
        gauss_helmert_model(points)


@pytest.mark.parametrize("points", [_plane(), _circle()], ids=["plane", "circle"])
def test_singular_N_raises_with_given_initial_values(points):
    x0 = np.r_[points.mean(axis=0) + [0.0, 0.0, 0.5], 1.2]
    with pytest.raises(DegenerateGeometryError, match="singular"):
        gauss_helmert_model(points, x0=x0)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"sigma": -1.0},
        {"sigma": np.ones(7)},
        {"sigma": np.ones((20, 2))},
        {"sigma": np.full((20, 3, 3), -1.0)},
        {"sigma": np.tile([[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], (20, 1, 1))},
        {"sigma": [np.nan] * 20},
        {"x0": [0.0, 0.0, 0.0]},
        {"x0": [0.0, 0.0, np.nan, 1.0]},
        {"radius": -0.1},
        {"tol": 0.0},
        {"max_iterations": 0},
        {"max_iterations": 2.5},
        {"alpha": 1.5},
    ],
)
def test_bad_options_raise_labkit_error(kwargs):
    pts = _cap(20, rng=15).sphere_points
    with pytest.raises(LabkitError):
        gauss_helmert_model(pts, **kwargs)


def test_non_convergence_is_reported_not_raised():
    pts = _cap(100, rng=16).sphere_points
    fit = gauss_helmert_model(pts, x0=np.r_[pts.mean(axis=0), 0.5], max_iterations=2)
    assert not fit.converged and not fit.ok
    assert "no convergence" in fit.reason
    assert "WARNING" in fit.summary()


def test_nearly_flat_points_are_flagged():
    pts = _plane(200) + np.random.default_rng(1).normal(0, 1e-4, (200, 3))
    try:
        fit = gauss_helmert_model(pts)
    except DegenerateGeometryError:
        return
    assert not fit.ok and "barely curve" in fit.reason


def test_inputs_are_not_modified():
    scene = _cap(100, rng=17, range_noise=0.003)
    pts = scene.sphere_points.copy()
    covs = scene.covariances()
    x0 = scene.sphere + 0.001
    before = (pts.copy(), covs.copy(), x0.copy())
    gauss_helmert_model(pts, x0=x0, sigma=covs)
    pts.flags.writeable = False
    covs.flags.writeable = False
    x0.flags.writeable = False
    gauss_helmert_model(pts, x0=x0, sigma=covs)  # read-only input works
    for a, b in zip((pts, covs, x0), before):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("kind", ["none", "scalar", "point", "fixed"])
def test_compiled_sweeps_equal_the_numpy_route(seed, kind, monkeypatch):
    """Equal or per-point precision runs in compiled sweeps over (n, 3); the numpy route over (3, n)
    blocks gives the same adjustment, statistics and tests to rounding."""
    from labkit.sphere import ghm
    from labkit.synthetic import sphere_points

    points = sphere_points(3000, seed, center=[2.0, 1.0, 0.5], radius=0.15, noise=0.001)
    kw = {"none": {}, "scalar": {"sigma": 0.001}, "point": {"sigma": np.full(3000, 0.001)},
          "fixed": {"sigma": 0.001, "radius": 0.15}}[kind]
    fast = gauss_helmert_model(points, **kw)
    monkeypatch.setattr(ghm, "compiled_sweeps", lambda: None)
    slow = gauss_helmert_model(points, **kw)
    assert fast.converged and fast.iterations == slow.iterations and fast.reason == slow.reason
    np.testing.assert_allclose(fast.x, slow.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.Sigma_xx, slow.Sigma_xx, rtol=1e-9, atol=1e-24)
    for name in ("v", "w_test", "redundancy_numbers", "normal_residuals"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=1e-9, atol=1e-12)
    assert fast.main_check == pytest.approx(slow.main_check, abs=1e-15)
    assert fast.sigma0 == pytest.approx(slow.sigma0, rel=1e-9)


def test_flagged_treats_undefined_and_infinite_w_as_the_numpy_route():
    """flagged: |w| beyond the critical value; an undefined w (NaN: redundancy number 0) is never flagged, an
    infinite one always (as |nan_to_num(w)| > w_crit), and with an undefined critical value nothing is."""
    from dataclasses import replace

    from labkit.synthetic import sphere_points

    fit = gauss_helmert_model(sphere_points(40, 3, radius=0.2, noise=0.001), sigma=0.001)
    w = fit.w_test.copy()
    w[:4] = [np.nan, np.inf, -np.inf, 100.0]
    for crit in (fit.w_critical, np.inf, np.nan):
        odd = replace(fit, w_test=w, w_critical=crit)
        np.testing.assert_array_equal(odd.flagged, np.abs(np.nan_to_num(w)) > crit)
    assert replace(fit, w_test=w).flagged[:4].tolist() == [False, True, True, True]
