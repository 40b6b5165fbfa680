"""labkit.core.stats: the one chi-square test of a difference and the corrections for many tests."""

import numpy as np
import pytest
from scipy import stats

from labkit.core.stats import adjusted_p_values, chi2_test, quadratic_form


def test_chi2_test_equals_the_textbook_formula_for_one_and_a_stack():
    rng = np.random.default_rng(0)
    L = rng.normal(size=(20, 3, 3))
    C = np.einsum("nij,nkj->nik", L, L) + 0.1 * np.eye(3)
    e = rng.normal(size=(20, 3))
    T, p = chi2_test(e, C)
    want = np.array([ei @ np.linalg.inv(ci) @ ei for ei, ci in zip(e, C)])  # independent route: the inverse
    np.testing.assert_allclose(T, want, rtol=1e-10)
    np.testing.assert_allclose(p, stats.chi2.sf(want, 3), rtol=1e-10)
    T0, p0 = chi2_test(e[0], C[0])
    assert isinstance(T0, float) and T0 == pytest.approx(want[0]) and p0 == pytest.approx(p[0])


def test_no_test_is_nan_not_a_number_that_looks_like_one():
    C = np.array([np.eye(2), [[1.0, 1.0], [1.0, 1.0]], np.eye(2)])  # the second is singular
    e = np.array([[1.0, 0.0], [1.0, 0.0], [np.nan, 0.0]])
    T, p = chi2_test(e, C)
    assert T[0] == pytest.approx(1.0) and np.isnan(T[1:]).all() and np.isnan(p[1:]).all()
    assert np.isnan(quadratic_form(np.zeros(0), np.zeros((0, 0))))


@pytest.mark.parametrize("correction", ["holm", "fdr"])
def test_adjusted_p_values_reject_as_the_stepwise_procedures_do(correction):
    rng = np.random.default_rng(1)
    p = np.r_[rng.uniform(0, 0.02, 5), rng.uniform(0, 1, 15)]
    adj = adjusted_p_values(p, correction)
    m, alpha, order = len(p), 0.05, np.argsort(p)
    if correction == "holm":  # step down: reject while p_(k) <= alpha / (m - k + 1)
        k = next((i for i, q in enumerate(p[order]) if q > alpha / (m - i)), m)
    else:  # Benjamini-Hochberg step up: the largest k with p_(k) <= k alpha / m
        k = max((i + 1 for i, q in enumerate(p[order]) if q <= (i + 1) * alpha / m), default=0)
    want = np.zeros(m, bool)
    want[order[:k]] = True
    np.testing.assert_array_equal(adj <= alpha, want)
    assert (adj >= p).all() and (adj <= 1).all()


def test_holm_keeps_the_family_wise_error_under_the_null():
    rng = np.random.default_rng(2)
    any_false = [bool((adjusted_p_values(rng.uniform(size=30), "holm") <= 0.05).any()) for _ in range(2000)]
    assert np.mean(any_false) < 0.05 + 3 * np.sqrt(0.05 * 0.95 / 2000)
    none = adjusted_p_values([0.2, np.nan], "none")
    assert none[0] == 0.2 and np.isnan(none[1])
