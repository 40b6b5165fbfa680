"""labkit.registration.references: references from targets, pairs and repeats, against a stacked least-squares solution."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.registration.references import (
    average_references, load_references, manual_reference, reference_from_pairs, reference_from_targets, save_references, truth_reference,
)
from labkit.transforms import make_transform, rotation_from_angles


def _stacked_lsq(d, C):
    """The weighted mean as one Gauss-Markov model: l = stacked d_i, A = stacked I, P = blockdiag(C_i^-1)."""
    n = len(d)
    A = np.tile(np.eye(3), (n, 1))
    P = np.zeros((3 * n, 3 * n))
    for i, c in enumerate(C):
        P[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(c)
    N = A.T @ P @ A
    x = np.linalg.solve(N, A.T @ P @ d.ravel())
    v = A @ x - d.ravel()
    s0 = np.sqrt(v @ P @ v / (3 * n - 3))
    return x, np.linalg.inv(N), s0


def test_targets_give_the_weighted_least_squares_shift_and_its_variance_factor():
    rng = np.random.default_rng(0)
    centres = rng.uniform(-20, 20, (6, 3))
    L = rng.normal(size=(6, 3, 3)) * 2e-3
    cov_s = np.einsum("nij,nkj->nik", L, L) + np.eye(3) * 1e-6  # correlated, different per target
    cov_t = np.eye(3) * 4e-6
    shift = np.array([0.05, -0.02, 0.01])
    target = centres + shift + rng.normal(0, 3e-3, centres.shape)  # scatter beyond the stated covariances
    ref = reference_from_targets(centres, cov_s, target, cov_t)
    x, Qxx, s0 = _stacked_lsq(target - centres, cov_s + cov_t)
    np.testing.assert_allclose(ref.translation, x, rtol=0, atol=1e-12)
    assert ref.sigma0 == pytest.approx(s0, rel=1e-10) and ref.n == 6
    np.testing.assert_allclose(ref.covariance, Qxx * max(1.0, s0**2), rtol=1e-9)  # scaled when s0 > 1
    assert np.all(np.abs(ref.translation - shift) < 4 * ref.std)


def test_pairs_are_targets_with_the_picking_precision_on_both_epochs():
    picks = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 1], [5, 5, 1]])
    ref = reference_from_pairs(picks, picks + [0.1, 0, 0], std=0.02)
    same = reference_from_targets(picks, np.eye(3) * 4e-4, picks + [0.1, 0, 0], np.eye(3) * 4e-4, kind="pairs")
    np.testing.assert_allclose(ref.translation, same.translation)
    np.testing.assert_allclose(ref.covariance, same.covariance)
    np.testing.assert_allclose(ref.std, np.sqrt(2 * 0.02**2 / 4))  # two picks per pair, four pairs


def test_repeats_that_scatter_more_than_stated_widen_the_covariance():
    stated = [manual_reference([t, 0, 0], std=0.001) for t in (0.10, 0.13, 0.07)]  # 3 cm apart, +-1 mm each
    mean = average_references(stated)
    assert mean.translation[0] == pytest.approx(0.10) and mean.sigma0 > 1
    assert mean.std[0] > 0.001 / np.sqrt(3) * 5  # external accuracy wins over the internal one
    plain = average_references([manual_reference([t, 0, 0]) for t in (0.10, 0.13, 0.07)])  # no stated std
    assert plain.std[0] == pytest.approx(np.std([0.10, 0.13, 0.07], ddof=1) / np.sqrt(3))


def test_a_file_round_trip_keeps_rotation_and_covariance(tmp_path):
    T = make_transform(rotation_from_angles(0.0, 0.0, 0.01), [1.0, 2.0, 3.0])
    refs = [truth_reference(T, region="a", case="x"),
            manual_reference([0.1, 0.2, 0.3], covariance=np.diag([1e-4, 2e-4, 3e-4]), region="b", case="x")]
    back = load_references(save_references(refs, tmp_path / "r.json"))
    assert list(back) == [("a", "x"), ("b", "x")]
    np.testing.assert_allclose(back[("a", "x")].matrix, T, atol=1e-15)
    np.testing.assert_allclose(back[("b", "x")].covariance, np.diag([1e-4, 2e-4, 3e-4]))


def test_bad_references_are_refused_with_a_reason(tmp_path):
    with pytest.raises(LabkitError, match="either as std or as covariance"):
        manual_reference([0, 0, 0], std=0.01, covariance=np.eye(3))
    with pytest.raises(LabkitError, match="at least one"):
        average_references([])
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(LabkitError, match="not a labkit reference file"):
        load_references(tmp_path / "bad.json")
