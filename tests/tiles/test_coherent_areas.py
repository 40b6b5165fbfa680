"""The neighbour test's control of many tests and the coherent areas (labkit.tiles.coherent, labkit.core.stats).

The fields here are simulated directly as ShiftFields: every tile's shift is drawn
from its own stated covariance around a known truth, so the false-alarm rate,
the power and the stated standard deviations can be checked over hundreds of
fields without a single registration.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from labkit import tiles
from labkit.core.stats import adjusted_p_values, chi2_test
from labkit.core.errors import LabkitError

NROW, NCOL = 8, 10
SHIFT = np.array([0.05, -0.03, 0.02])


def _covariances(rng, n=NROW * NCOL, flat=()):
    """Different covariance per tile (correlated axes, 1.5-4 mm); tiles in ``flat`` determine only Z."""
    A = rng.normal(0, 1, (n, 3, 3)) * 0.0015
    C = np.einsum("nij,nkj->nik", A, A) + np.diag([2e-6, 2e-6, 1e-6])
    det = np.ones((n, 3), bool)
    det[list(flat), :2] = False
    return C, det


def _field(truth, C, det, rng):
    """A ShiftField whose tile shifts are drawn from N(truth_i, C_i); undetermined axes held at 0, std inf."""
    grid = tiles.tile_grid((0, 0, NCOL * 100 - 1, NROW * 100 - 1), 100.0)
    t = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(len(grid), 3)))
    t = np.where(det, t, 0.0)
    Cs = np.where(det[:, :, None] & det[:, None, :], C, 0.0) + np.where(np.diag([1, 1, 1]) * ~det[:, :, None],
                                                                         np.inf, 0.0)
    shifts = tuple(tiles.TileShift(g, ti, Ci, d, 1000, 1000, 900, 1.0, True, 0.1, "ok")
                   for g, ti, Ci, d in zip(grid, t, Cs, det))
    return tiles.ShiftField(shifts, 100.0, "simulated")


def _columns():
    return np.tile(np.arange(NCOL), NROW)


def _false_alarm(test) -> bool:
    return bool((~test.agree).any() or test.n_areas > 1)


@pytest.mark.slow
def test_family_wise_false_alarms_at_most_alpha_over_200_fields():
    """Identical shifts everywhere: with Holm (and BH) at most alpha of the fields show any disagreement
    (a border or a split area); without correction nearly every field does."""
    rng = np.random.default_rng(14)
    C, det = _covariances(rng, flat=(11, 12, 47))
    truth = np.tile(SHIFT, (NROW * NCOL, 1))
    alpha, runs = 0.05, 200
    # binomial tolerance: more alarms than this have probability < 1 % if the rate is alpha
    limit = stats.binom.ppf(0.99, runs, alpha)
    alarms = {"holm": 0, "fdr": 0}
    area_shifts, tile_chi2 = [], []
    for _ in range(runs):
        field = _field(truth, C, det, rng)
        for correction in alarms:
            test = field.neighbour_test(alpha, correction=correction)
            alarms[correction] += _false_alarm(test)
            if correction == "holm" and test.n_areas == 1:
                area_shifts.append(test.area_shift[0])
                tile_chi2.append(test.tile_chi2 / test.tile_dof)
    assert alarms["holm"] <= limit and alarms["fdr"] <= limit, alarms
    none = [_false_alarm(_field(truth, C, det, rng).neighbour_test(alpha, correction="none")) for _ in range(10)]
    # about 140 pairs each at 5 %: a field without a false alarm has probability ~ 0.95^140 = 0.08 %
    assert sum(none) >= 9, sum(none)
    # the stated std of an area's common shift (eq. 5) against the spread over the simulated fields
    stated = np.sqrt(np.diag(field.neighbour_test(alpha).area_covariance[0]))
    spread = np.std(area_shifts, axis=0, ddof=1)
    np.testing.assert_allclose(spread / stated, 1.0, atol=0.2)
    np.testing.assert_allclose(np.mean(area_shifts, axis=0), SHIFT, atol=3 * stated.max() / np.sqrt(len(area_shifts)) * 3)
    # eq. 6: a tile against its own area's mean has covariance C_i - C_bar, so T / dof averages 1
    assert np.nanmean(tile_chi2) == pytest.approx(1.0, abs=0.05)


@pytest.mark.slow
def test_power_a_moved_block_is_found():
    """A 3 x 3 block moved by 2 cm in X (about 6 std of a pair difference) is its own area in most fields."""
    rng = np.random.default_rng(15)
    C, det = _covariances(rng)
    rows, cols = np.divmod(np.arange(NROW * NCOL), NCOL)
    block = (rows >= 2) & (rows < 5) & (cols >= 4) & (cols < 7)
    truth = np.tile(SHIFT, (NROW * NCOL, 1)) + np.outer(block, [0.02, 0.0, 0.0])
    found = {"holm": 0, "fdr": 0}
    for _ in range(30):
        field = _field(truth, C, det, rng)
        for correction in found:
            test = field.neighbour_test(0.05, correction=correction)
            own = len(set(test.areas[block])) == 1 and not np.isin(test.areas[~block], test.areas[block]).any()
            found[correction] += own and test.n_areas == 2
    assert found["holm"] >= 27 and found["fdr"] >= 24, found  # BH allows a share of false splits once it rejects


def test_a_chain_of_small_steps_is_not_one_area_but_a_step_splits_exactly():
    rng = np.random.default_rng(16)
    C, det = _covariances(rng)
    col = _columns()
    base = np.tile(SHIFT, (NROW * NCOL, 1))
    # drift: 4 mm more in X per column, 36 mm over the survey
    field = _field(base + np.outer(col * 0.004, [1, 0, 0]), C, det, rng)
    drift = field.neighbour_test(0.05)
    assert drift.agree.all() and drift.n_pair_areas == 1  # every neighbour agrees: one chain
    assert drift.n_areas >= 2
    assert not np.isin(drift.areas[col == 0], drift.areas[col == NCOL - 1]).any()  # the ends are apart
    # every tile fits its area's common shift (what the split guarantees), checked here from scratch
    for a in range(drift.n_areas):
        members = np.flatnonzero(drift.areas == a)
        if len(members) > 1:
            Cbar = drift.area_covariance[a]
            T, p = chi2_test(field.translations[members] - drift.area_shift[a], field.covariances[members] - Cbar)
            np.testing.assert_allclose(T, drift.tile_chi2[members], rtol=1e-9)
            adjusted = adjusted_p_values(np.r_[drift.p_value, drift.tile_p_value], "holm")
            assert (np.isnan(adjusted) | (adjusted > 0.05)).all()
    # step: half the survey 3 cm further in X; exactly two areas, split at the step
    step = _field(base + np.outer(col >= 5, [0.03, 0, 0]), C, det, rng).neighbour_test(0.05)
    assert step.n_areas == 2 and len(set(step.areas[col < 5])) == 1 and len(set(step.areas[col >= 5])) == 1
    np.testing.assert_allclose(step.area_shift[step.areas[col >= 5][0]] - step.area_shift[step.areas[0]],
                               [0.03, 0, 0], atol=0.002)
    # constant: one area
    flat = _field(base, C, det, np.random.default_rng(17)).neighbour_test(0.05)
    assert flat.n_areas == 1 and "coherent areas" in flat.summary() and "Holm" in flat.summary()


def test_adjusted_p_values_follow_their_definitions():
    rng = np.random.default_rng(3)
    alpha = 0.05
    for _ in range(50):
        p = np.r_[rng.uniform(0, 0.02, rng.integers(0, 6)), rng.uniform(0, 1, rng.integers(1, 30))]
        m = len(p)
        # Holm step-down: reject p_(1), p_(2), ... while p_(i) <= alpha / (m - i + 1)
        order = np.argsort(p)
        holm = np.zeros(m, bool)
        for i, o in enumerate(order):
            if p[o] > alpha / (m - i):
                break
            holm[o] = True
        np.testing.assert_array_equal(adjusted_p_values(p, "holm") <= alpha, holm)
        # Benjamini-Hochberg: scipy's implementation as the independent route
        np.testing.assert_allclose(adjusted_p_values(p, "fdr"), stats.false_discovery_control(p), rtol=1e-12)
        np.testing.assert_array_equal(adjusted_p_values(p, "none"), p)
    # NaN entries are not tests and do not count in m
    np.testing.assert_allclose(adjusted_p_values([0.01, np.nan, 0.02], "holm"), [0.02, np.nan, 0.02])
    with pytest.raises(LabkitError, match="correction must be one of"):
        adjusted_p_values([0.1], "bonferroni")


def test_chi2_test_single_and_stacked():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 3, 3))
    C = np.einsum("nij,nkj->nik", A, A) + 0.1 * np.eye(3)
    e = rng.normal(size=(6, 3))
    T, p = chi2_test(e, C)
    for k in range(6):
        want = e[k] @ np.linalg.solve(C[k], e[k])
        assert T[k] == pytest.approx(want, rel=1e-10) and p[k] == pytest.approx(stats.chi2.sf(want, 3), rel=1e-9)
        assert chi2_test(e[k], C[k]) == pytest.approx((T[k], p[k]), rel=1e-12)
    C[2] = np.diag([1.0, -1.0, 1.0])  # not positive definite
    C[4, 0, 0] = np.inf
    T, p = chi2_test(e, C)
    assert np.isnan(T[[2, 4]]).all() and np.isfinite(T[[0, 1, 3, 5]]).all()
    assert np.isnan(chi2_test(np.zeros(0), np.zeros((0, 0)))).all()


def test_correction_is_checked():
    rng = np.random.default_rng(5)
    C, det = _covariances(rng)
    field = _field(np.tile(SHIFT, (NROW * NCOL, 1)), C, det, rng)
    with pytest.raises(LabkitError, match="correction must be one of 'holm', 'fdr', 'none'"):
        field.neighbour_test(correction="bonferroni")


@pytest.mark.slow
def test_real_als_halves_one_area_with_extra_std_and_a_moved_tile_found(realdata):
    """Real flat ALS (IGN, 350 x 370 m, mostly ground): two random halves of the points as two epochs, one
    moved by a known shift, registered in 100 m tiles. Its tile shifts may scatter more than they state (most in X
    and Y on flat ground); with the extra std of eq. 4 estimated from the field, Holm gives one area, and a tile whose shift is raised by 15 cm is an area of its own."""
    import dataclasses
    import warnings

    from labkit.io import read_cloud

    cloud = read_cloud(realdata / "als" / "las_with_several_extra_byte_bloc.laz")
    half = np.random.default_rng(0).uniform(size=len(cloud)) < 0.5
    source = cloud.subset(half)
    source = source.with_xyz(source.xyz - SHIFT)
    field = tiles.register_tiles(source, cloud.subset(~half), "icp", size=100.0, scheduler="threads")
    ok = field.ok
    assert ok.sum() >= 10
    # the determined components recover the shift (flat ground: X, Y loosely, Z to millimetres)
    err = (field.determined_translations - SHIFT)[ok]
    assert np.nanmax(np.abs(err[:, 2])) < 0.005 and np.nanmax(np.abs(err[:, :2])) < 0.15
    # eq. 4 on the determined components: the scatter beyond the stated variances
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        std = np.where(field.determined, field.std, np.nan)[ok]
        excess = np.nanvar(field.determined_translations[ok], axis=0, ddof=1) - np.nanmean(std**2, axis=0)
    extra_std = float(np.sqrt(max(float(np.nanmax(excess)), 0.0)))
    plain = field.neighbour_test(0.05, correction="none")
    stable = field.neighbour_test(0.05, extra_std=extra_std)
    assert stable.n_areas == 1 and stable.agree.all()
    # the extra std only widens the covariances: it can merge areas, never split them
    assert plain.n_areas >= stable.n_areas and extra_std >= 0.0
    # a tile that moved 15 cm in Z (its covariance unchanged): found, and only it
    k = int(np.flatnonzero(ok & field.determined[:, 2])[len(np.flatnonzero(ok)) // 2])
    moved = tiles.ShiftField(tuple(dataclasses.replace(s, translation=s.translation + [0, 0, 0.15]) if n == k else s
                                   for n, s in enumerate(field.tiles)), field.size, field.method)
    test = moved.neighbour_test(0.05, extra_std=extra_std)
    assert test.n_areas == 2 and (test.areas == test.areas[k]).sum() == 1
