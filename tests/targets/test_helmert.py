"""labkit.helmert: the 3D transformation in the Gauss-Helmert model against closed forms, a dense GHM, Monte Carlo."""

import numpy as np
import pytest

import labkit
from labkit.targets.helmert import helmert
from labkit.transforms import angles_from_rotation, apply_transform, make_transform, rotation_from_angles

ANGLES, SHIFT = (0.02, -0.015, 0.8), np.array([4.0, -3.0, 1.2])


def _truth():
    return make_transform(rotation_from_angles(*ANGLES), SHIFT)


def _kabsch(p, q):
    """Independent closed form (Arun et al. 1987) with numpy only."""
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    U, _, Vt = np.linalg.svd((p - mp).T @ (q - mq))
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mq - R @ mp


def _umeyama(p, q):
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    P, Q = p - mp, q - mq
    U, S, Vt = np.linalg.svd(Q.T @ P / len(p))
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (P**2).sum(axis=1).mean()
    return s, R, mq - s * R @ mp


def _random_cov(rng, n, lo=0.0005, hi=0.002):
    """A random full 3x3 covariance per point (random axes, standard deviations in [lo, hi])."""
    A = rng.normal(size=(n, 3, 3))
    Qm, _ = np.linalg.qr(A)
    s = rng.uniform(lo, hi, (n, 3))
    return np.einsum("nij,nj,nkj->nik", Qm, s**2, Qm)


def test_equal_isotropic_weights_give_the_closed_form_svd_solution():
    rng = np.random.default_rng(1)
    p = rng.uniform(-20, 20, (12, 3))
    q = apply_transform(_truth(), p) + rng.normal(0, 0.003, p.shape)
    R, t = _kabsch(p, q)
    for kw in ({}, {"source_cov": 0.002, "target_cov": 0.002}, {"target_cov": 0.01}):
        fit = helmert(p, q, **kw)
        assert fit.converged and fit.undetermined == ()
        assert np.abs(fit.rotation - R).max() < 1e-12
        assert np.abs(fit.translation - t).max() < 1e-10
    # a similarity with errors in the target only: Umeyama's closed form
    q7 = 1.0003 * apply_transform(_truth(), p) + rng.normal(0, 0.003, p.shape)
    s, R, t = _umeyama(p, q7)
    fit = helmert(p, q7, target_cov=0.003, scale=True)
    assert abs(fit.scale - s) < 1e-12 and np.abs(fit.rotation - R).max() < 1e-12
    assert np.abs(fit.translation - t).max() < 1e-10
    assert abs(fit.scale - 1.0003) < 5e-5


def _dense_ghm(p, q, Cp, Cq, x0, iterations=30):
    """The textbook Gauss-Helmert iteration with dense 3n x 6n B and 6n x 6n Sigma_ll (numerical derivatives)."""
    n = len(p)
    l = np.concatenate([p.ravel(), q.ravel()])
    S = np.zeros((6 * n, 6 * n))
    for i in range(n):
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] = Cp[i]
        S[3 * n + 3 * i:3 * n + 3 * i + 3, 3 * n + 3 * i:3 * n + 3 * i + 3] = Cq[i]

    def f(lv, x):
        pp, qq = lv[:3 * n].reshape(n, 3), lv[3 * n:].reshape(n, 3)
        return (pp @ rotation_from_angles(*x[:3]).T + x[3:6] - qq).ravel()

    def jac(fun, z, h=1e-7):
        return np.column_stack([(fun(z + h * e) - fun(z - h * e)) / (2 * h) for e in np.eye(len(z))])

    x, v = x0.copy(), np.zeros(6 * n)
    for _ in range(iterations):
        A = jac(lambda xx: f(l + v, xx), x)
        B = jac(lambda lv: f(lv, x), l + v)
        w = -B @ v + f(l + v, x)
        M = B @ S @ B.T
        N = A.T @ np.linalg.solve(M, A)
        dx = -np.linalg.solve(N, A.T @ np.linalg.solve(M, w))
        k = -np.linalg.solve(M, A @ dx + w)
        v = S @ B.T @ k
        x = x + dx
    return x, v.reshape(2, n, 3), np.linalg.inv(N)


def test_equals_a_dense_textbook_gauss_helmert_model_with_full_covariances():
    rng = np.random.default_rng(2)
    n = 5
    p = rng.uniform(-5, 5, (n, 3))
    q = apply_transform(_truth(), p) + rng.normal(0, 0.002, p.shape)
    Cp, Cq = _random_cov(rng, n), _random_cov(rng, n)
    fit = helmert(p, q, source_cov=Cp, target_cov=Cq)
    x0 = np.concatenate([np.array(ANGLES) + 0.001, SHIFT + 0.01])
    x, v, Qxx = _dense_ghm(p, q, Cp, Cq, x0)
    assert np.abs(fit.parameters - x).max() < 1e-9
    assert np.abs(fit.residuals_source - v[0]).max() < 1e-9
    assert np.abs(fit.residuals_target - v[1]).max() < 1e-9
    assert np.allclose(fit.covariance, Qxx, rtol=1e-5, atol=1e-14)  # a priori sigma0 = 1


@pytest.mark.parametrize("scale", [False, True])
def test_monte_carlo_spread_matches_the_stated_standard_deviations(scale):
    rng = np.random.default_rng(3)
    n, runs = 6, 500
    p_true = rng.uniform(-15, 15, (n, 3))
    s_true = 1.0002 if scale else 1.0
    q_true = s_true * apply_transform(_truth(), p_true)
    Cp, Cq = _random_cov(rng, n), _random_cov(rng, n)
    Lp, Lq = np.linalg.cholesky(Cp), np.linalg.cholesky(Cq)
    xs, stds, p_point, rejected = [], [], [], []
    for _ in range(runs):
        p = p_true + np.einsum("nij,nj->ni", Lp, rng.normal(size=(n, 3)))
        q = q_true + np.einsum("nij,nj->ni", Lq, rng.normal(size=(n, 3)))
        fit = helmert(p, q, source_cov=Cp, target_cov=Cq, scale=scale)
        xs.append(fit.parameters)
        stds.append(fit.std)
        p_point.append(fit.point_p)
        rejected.append(not fit.global_test.passed)
    xs, stated = np.array(xs), np.mean(stds, axis=0)
    ratio = xs.std(axis=0, ddof=1) / stated
    assert ((ratio > 0.8) & (ratio < 1.25)).all(), ratio
    # the tests keep their level under H0: 5 % of the point tests below p = 0.05, 5 % of the global tests rejected
    assert 0.035 < (np.array(p_point) < 0.05).mean() < 0.065
    assert 0.025 < np.mean(rejected) < 0.08
    truth = np.concatenate([ANGLES, s_true * SHIFT] + ([[s_true]] if scale else []))  # q = s (R p + t)
    assert (np.abs(xs.mean(axis=0) - truth) < 4 * stated / np.sqrt(runs)).all()


def test_point_test_without_a_priori_precision_keeps_its_level():
    """Unit weights of unknown scale: the test uses the estimated sigma0 (Beta distribution, Pope's tau in 3D)."""
    rng = np.random.default_rng(8)
    p0 = rng.uniform(-10, 10, (6, 3))
    q0 = apply_transform(_truth(), p0)
    p = np.array([helmert(p0 + rng.normal(0, 0.001, p0.shape), q0 + rng.normal(0, 0.001, p0.shape)).point_p
                  for _ in range(400)])
    assert 0.035 < (p < 0.05).mean() < 0.065


def test_global_test_and_point_test_find_a_moved_point():
    rng = np.random.default_rng(4)
    p = rng.uniform(-10, 10, (8, 3))
    q = apply_transform(_truth(), p) + rng.normal(0, 0.001, p.shape)
    clean = helmert(p, q, source_cov=0.001 / np.sqrt(2), target_cov=0.001 / np.sqrt(2))
    assert clean.global_test.passed and not clean.flagged.any()
    assert abs(clean.point_redundancy.sum() - clean.redundancy) < 1e-9 and clean.redundancy == 3 * 8 - 6
    q[5] += [0.03, 0.0, 0.0]
    moved = helmert(p, q, source_cov=0.001 / np.sqrt(2), target_cov=0.001 / np.sqrt(2))
    assert moved.global_test.passed is False
    assert int(np.nanargmax(moved.point_test)) == 5 and moved.flagged[5]
    # without a priori precision: no global test, the tau-like test still points at the moved point
    tau = helmert(p, q)
    assert tau.global_test.passed is None and int(np.nanargmax(tau.point_test)) == 5


def test_two_or_collinear_points_name_the_rotation_about_their_line():
    rng = np.random.default_rng(5)
    line = np.array([[0.0, 0, 0], [3, 1, 0.5], [6, 2, 1.0], [-3, -1, -0.5]])
    q = apply_transform(_truth(), line) + rng.normal(0, 0.001, line.shape)
    for p_, q_ in ((line[:2], q[:2]), (line, q)):
        fit = helmert(p_, q_, target_cov=0.001)
        assert len(fit.undetermined) == 1 and "rotation about the line" in fit.undetermined[0]
        assert np.isinf(fit.std[:3]).any() and not fit.ok
        # the points that were given are still matched
        assert np.abs(fit.apply(p_) - q_).max() < 0.005
    # a scale between two points is determined, the rotation about their line is not
    fit = helmert(line[:2], 2.0 * line[:2], target_cov=0.001, scale=True)
    assert abs(fit.scale - 2.0) < 1e-9 and np.isfinite(fit.std[6]) and fit.undetermined


def test_bad_input_raises_one_clear_error_and_inputs_stay_untouched():
    p = np.random.default_rng(6).uniform(-1, 1, (5, 3))
    q = p + 1.0
    p0, q0 = p.copy(), q.copy()
    helmert(p, q, source_cov=0.001, target_cov=0.001)
    assert np.array_equal(p, p0) and np.array_equal(q, q0)
    for kwargs in ({"target": q[:4]}, {"source": p[:1], "target": q[:1]},
                   {"target_cov": np.ones((5, 3, 3))}, {"source_cov": -1.0},
                   {"target": np.where(q > 1.5, np.nan, q)}):
        args = {"source": p, "target": q} | kwargs
        with pytest.raises(labkit.LabkitError):
            helmert(args.pop("source"), args.pop("target"), **args)
    with pytest.raises(labkit.DegenerateGeometryError):
        helmert(np.zeros((3, 3)), np.ones((3, 3)))


def test_summary_reads_in_degrees_and_millimetres():
    p = np.random.default_rng(7).uniform(-10, 10, (5, 3))
    fit = labkit.helmert(p, apply_transform(_truth(), p), target_cov=0.001)
    text = fit.summary()
    assert "deg" in text and "mm" in text and "Gauss-Helmert" in text
    assert np.allclose(angles_from_rotation(fit.rotation), ANGLES)
