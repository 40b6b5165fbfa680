"""Tests of labkit.registration.consistency: the group test's false-alarm rate under H0 (Monte Carlo through
ICP on wavy pairs), its reference distribution against an independent simulation, and its power."""

import numpy as np
import pytest

from labkit.core.distributions import chi2_sf
from labkit.registration import icp
from labkit.registration.consistency import family_level, group_consistency, welch_james
from labkit.synthetic import wavy_surface

SHIFT = np.array([0.05, 0.02, 0.03])


def _wavy_pair(seed, lift=0.0):
    """Two samplings of the wavy surface (6 m square); the source's NE quadrant lifted by ``lift``."""
    rng = np.random.default_rng(seed)
    target, source = wavy_surface(1500, rng), wavy_surface(300, rng)
    source[(source[:, 0] > 3) & (source[:, 1] > 3), 2] += lift
    return source - SHIFT, target


@pytest.mark.slow
def test_false_alarm_rate_of_icp_on_agreeing_groups_is_alpha():
    # 200 pairs of one surface, nothing changed: the groupings (local-noise terciles, quadrants) tested
    # together at alpha = 5 % must reject in about 5 % of the pairs. A chi-square reference with the
    # groups' cluster-robust covariances rejected 27-29 % per grouping here; at alpha 0.001 over 1000
    # pairs 13.6 % before, 0.4 % with the jackknife covariances, the Welch-James F and Bonferroni
    alarms = [not icp(*_wavy_pair(seed), consistency_alpha=0.05).consistency.agree for seed in range(200)]
    rate, mc = np.mean(alarms), np.sqrt(0.05 * 0.95 / len(alarms))
    assert abs(rate - 0.05) < 3 * mc, rate


def test_welch_james_reference_against_simulated_few_cell_groups():
    # an independent route: three groups of 12 cells each, a random effect per cell (correlated rows);
    # T / scale must follow F(dof, nu), where the chi-square on T is far off
    rng = np.random.default_rng(5)
    m, cells = 360, np.repeat(np.arange(36), 10)
    A = rng.normal(size=(m, 1, 3))
    labels = cells // 12
    p_f, p_chi2 = [], []
    for _ in range(300):
        l = rng.normal(size=(m, 1)) + rng.normal(size=36)[cells][:, None]
        c = group_consistency(A, l, np.ones(m), labels, ["a", "b", "c"], cells, translation=[0, 1, 2])
        p_f.append(c.p_value)
        p_chi2.append(float(chi2_sf(c.statistic, c.dof)))
    p_f, p_chi2 = np.array(p_f), np.array(p_chi2)
    mc = np.sqrt(0.05 * 0.95 / len(p_f))
    assert abs(np.mean(p_f < 0.05) - 0.05) < 3 * mc, np.mean(p_f < 0.05)
    assert np.mean(p_chi2 < 0.05) > 0.05 + 4 * mc  # the chi-square reference rejects too often


def test_welch_james_is_chi_square_with_known_covariances():
    V, W = np.eye(3), np.eye(3)
    H = 2 * W
    assert welch_james(H, [V, V], [W, W], [np.inf, np.inf], 3) == (3.0, np.inf)
    scale, nu = welch_james(H, [V, V], [W, W], [10.0, 10.0], 3)
    assert scale > 3 and np.isfinite(nu)


def test_power_on_a_lifted_quadrant():
    # the source's NE quadrant lifted 3 cm (15 times the noise): the quadrants disagree and NE differs most;
    # unlifted, the same pairs agree
    lifted = [icp(*_wavy_pair(9000 + seed, lift=0.03)).consistency for seed in range(20)]
    found = [not c.agree and c.grouping == "block" and c.worst == "block NE" for c in lifted]
    assert np.mean(found) >= 0.5, np.mean(found)
    assert all(icp(*_wavy_pair(9000 + seed)).consistency.agree for seed in range(20))


def test_family_level_shares_alpha_between_the_groupings():
    # two groupings tested together at 1 %: each at 0.5 %; a p of 0.8 % no longer rejects and loses its spread
    rng = np.random.default_rng(2)
    m = 400
    A = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    labels, cells = np.repeat([0, 1], m // 2), np.arange(m) % 40
    tests = []
    for offset in (0.0035, 0.05):  # p = 0.0072 and far below
        l = rng.normal(0.0, 0.01, (m, 3))
        l[labels == 1, 2] += offset
        tests.append(group_consistency(A, l, np.ones(m), labels, ["a", "b"], cells, translation=[0, 1, 2], alpha=0.01))
    together = family_level(tests, 0.01)
    assert [t.alpha for t in together] == [0.005, 0.005] and all(t.family == 2 for t in together)
    for alone, joint in zip(tests, together):
        assert joint.agree == (alone.p_value >= 0.005)
        assert np.any(joint.between) == (not joint.agree)
    assert not tests[0].agree and together[0].agree  # rejected alone at 1 %, not at its share
    assert not together[1].agree and "0.01 / 2 groupings" in together[1].summary()
