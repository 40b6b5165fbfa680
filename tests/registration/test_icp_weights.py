"""Robust weights of ICP (labkit/registration/closest_point/weights.py): deletion limit, scale, IRLS factors."""

import numpy as np
import pytest

from labkit.registration.closest_point.weights import HUBER_C, TUKEY_C, deletion_limit, psi_prime, robust_weights


def test_deletion_limit_of_one_component_is_k_sigma_and_grows_with_components():
    assert deletion_limit(3.0, 1) == pytest.approx(3.0, abs=1e-9)
    assert deletion_limit(2.0, 1) == pytest.approx(2.0, abs=1e-9)
    # three components: the same two-sided probability on the chi distribution with 3 dof
    rng = np.random.default_rng(0)
    norms = np.linalg.norm(rng.normal(size=(400_000, 3)), axis=1)
    share = np.mean(norms > deletion_limit(3.0, 3))
    assert share == pytest.approx(0.0027, abs=0.0004)


def test_scale_from_the_residuals_and_gross_errors_deleted():
    rng = np.random.default_rng(1)
    l = rng.normal(0, 0.01, (4000, 1))
    l[:40] += 0.5  # gross errors
    keep, factor, scale, u, _ = robust_weights(l, np.ones(len(l)), 3.0, None)
    assert scale == pytest.approx(0.01, rel=0.05)
    assert not keep[:40].any() and keep[40:].mean() > 0.99
    np.testing.assert_array_equal(factor, keep.astype(float))  # no IRLS: weight 1 where kept
    keep_all, *_ = robust_weights(l, np.ones(len(l)), None, None)
    assert keep_all.all()


@pytest.mark.parametrize("robust", ["huber", "tukey"])
def test_factors_and_psi_prime_match_their_definitions(robust):
    u = np.linspace(0.05, 6.0, 400)
    l = u[:, None]  # centred at the median below: compare with the standardized sizes it returns
    _, factor, _, u_out, _ = robust_weights(l, np.ones(len(u)), None, robust)
    if robust == "huber":
        expected = np.minimum(1.0, HUBER_C / u_out)
    else:
        expected = np.where(u_out < TUKEY_C, (1 - (u_out / TUKEY_C) ** 2) ** 2, 0.0)
    np.testing.assert_allclose(factor, expected, rtol=0, atol=1e-12)
    # psi' by finite differences of psi(u) = u * factor(u), away from the kinks
    x = np.linspace(0.1, 6.0, 300)
    x = x[np.abs(x - (HUBER_C if robust == "huber" else TUKEY_C)) > 0.02]
    h = 1e-6
    psi = (lambda v: v * np.minimum(1.0, HUBER_C / v)) if robust == "huber" else (
        lambda v: v * np.where(v < TUKEY_C, (1 - (v / TUKEY_C) ** 2) ** 2, 0.0))
    numeric = (psi(x + h) - psi(x - h)) / (2 * h)
    np.testing.assert_allclose(psi_prime(x, robust), numeric, rtol=0, atol=1e-6)
