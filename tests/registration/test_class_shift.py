"""The check of the classes a registration left out: matchings and translation steps from the result."""

from __future__ import annotations

import numpy as np
import pytest

from labkit import PointCloud
from labkit.registration import icp
from labkit.registration.selection import check_other_classes


def _pair(seed, lift=0.0, n=4000):
    """Two samplings of hills: ground (2) in the west, a class left out (5) in the east; the source moved by
    (0.05, -0.03, 0.02) and its class 5 lifted by ``lift`` besides."""
    rng = np.random.default_rng(seed)

    def cloud():
        xy = rng.uniform(0, 30, (n, 2))
        z = 0.5 * np.sin(xy[:, 0] / 3) + 0.4 * np.cos(xy[:, 1] / 4) + rng.normal(0, 0.01, n)
        return PointCloud(np.column_stack([xy, z]), {"classification": np.where(xy[:, 0] < 18, 2, 5)})

    src, tgt = cloud(), cloud()
    cls = src.attributes["classification"]
    return src.with_xyz(src.xyz - [0.05, -0.03, 0.02] + np.where(cls[:, None] == 5, [0.0, 0.0, lift], 0.0)), tgt


@pytest.mark.parametrize("lift", [0.0, 0.06])
def test_class_check_agrees_with_icp_run_on_the_class(lift):
    """Independent route: ICP run to convergence on the class from the result (the same test on its shift)."""
    src, tgt = _pair(1, lift)
    res = icp(src, tgt, rng=0)
    assert res.selection.classes == (2,)
    (fast,) = res.class_checks
    (slow,) = check_other_classes(src, tgt, res, res.selection, icp, coarse_to_fine=False, consistency_alpha=None,
                                  rng=0)
    assert fast.code == slow.code == 5 and fast.agree == slow.agree == (lift == 0.0)
    assert np.isfinite(fast.offset_std).all() and np.isfinite(slow.offset_std).all()
    assert np.all(np.abs(fast.offset - slow.offset) <= 0.5 * slow.offset_std), (fast.offset, slow.offset)
    assert np.allclose(fast.offset_std, slow.offset_std, rtol=0.2)
    assert abs(fast.offset[2] + lift) < 3 * fast.offset_std[2], str(fast)
    assert ("5 moved" in res.message) == (lift > 0)


def test_stated_std_of_a_class_that_did_not_move_matches_its_spread():
    """Monte Carlo over samplings: the class's offset / its stated std has an rms of about 1 on every axis."""
    z = []
    for seed in range(24):
        (check,) = icp(*_pair(10 + seed, n=2500), rng=0).class_checks
        z.append(check.offset / check.offset_std)
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.75) & (rms < 1.3)), rms  # measured 1.08, 1.06, 0.97
