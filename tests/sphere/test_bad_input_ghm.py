"""Precision without redundancy (labkit.sphere.ghm): a Gauss-Helmert sphere through exactly as many points as
parameters and without an a priori sigma states its standard deviations as undetermined (NaN and a reason), never
as numbers; with sigma given they are the a priori ones, checked against a Monte Carlo spread."""

import numpy as np
import pytest

from labkit.sphere.ghm import gauss_helmert_model


def _on_sphere(n, seed, centre=(1.0, 2.0, 0.5), radius=0.8):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return np.asarray(centre) + radius * u / np.linalg.norm(u, axis=1, keepdims=True)


@pytest.mark.parametrize("seed", range(6))
def test_four_points_without_sigma_have_undetermined_precision(seed):
    fit = gauss_helmert_model(_on_sphere(4, seed))
    assert fit.redundancy == 0 and np.isnan(fit.sigma0)
    assert np.isnan(fit.std).all()
    assert "undetermined" in fit.reason and "give sigma" in fit.reason
    assert not fit.ok
    np.testing.assert_allclose(fit.center, [1.0, 2.0, 0.5], atol=1e-8)  # the estimate itself is exact


@pytest.mark.parametrize("radius", [None, 0.8])
def test_three_points_are_refused(radius):
    from labkit.core.errors import LabkitError

    with pytest.raises(LabkitError, match="at least 4 points"):
        gauss_helmert_model(_on_sphere(3, 0), radius=radius)


def test_four_points_with_the_radius_held_keep_one_redundancy():
    fit = gauss_helmert_model(_on_sphere(4, 0) + np.random.default_rng(1).normal(0, 1e-3, (4, 3)), radius=0.8)
    assert fit.redundancy == 1 and np.isfinite(fit.std[:3]).all() and "undetermined" not in fit.reason


@pytest.mark.parametrize("n", [5, 8, 30])
def test_with_redundancy_the_precision_is_estimated(n):
    pts = _on_sphere(n, 1) + np.random.default_rng(2).normal(0, 1e-3, (n, 3))
    fit = gauss_helmert_model(pts)
    assert fit.redundancy == n - 4 and np.isfinite(fit.sigma0) and np.isfinite(fit.std).all()
    assert "undetermined" not in fit.reason


@pytest.mark.parametrize("seed", [3, 4])
def test_four_points_with_sigma_state_the_a_priori_precision(seed):
    """Independent check: the spread of the fitted centre over noisy repeats matches the stated std."""
    sigma = 2e-4
    truth = _on_sphere(4, seed)
    stated = gauss_helmert_model(truth, sigma=sigma).std
    assert np.isfinite(stated).all()
    rng = np.random.default_rng(10 + seed)
    x = np.array([gauss_helmert_model(truth + rng.normal(0, sigma, truth.shape), sigma=sigma).x for _ in range(800)])
    ratio = x.std(axis=0, ddof=1) / stated
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
