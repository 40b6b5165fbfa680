"""Matching refuses what it cannot use: targets or sources without a normal, and bad arguments, with one clear error."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.registration.matching.match import RULES, match


def plane(rng, n=400, size=5.0, sigma=0.002):
    """Tilted plane z = 0.1 x + 0.05 y with noise; the unit upward normal."""
    xy = rng.uniform(0, size, (n, 2))
    z = 0.1 * xy[:, 0] + 0.05 * xy[:, 1] + rng.normal(0, sigma, n)
    nrm = np.array([-0.1, -0.05, 1.0])
    return np.column_stack([xy, z]), nrm / np.linalg.norm(nrm)



# ----------------------------------------------------------------------------- consumers drop them


def test_matching_rejects_targets_without_a_normal():
    rng = np.random.default_rng(7)
    tgt, _ = plane(rng, n=600)
    line = np.outer(np.linspace(0, 2, 40), [1.0, 0.0, 0.0]) + [20.0, 20.0, 5.0]
    target = np.vstack([tgt, line])
    source = target + [0.0, 0.0, 0.01]
    corr = match(source, target, max_distance=0.5, max_angle_deg=None, noise_weighting=False)
    on_line = corr.target_index >= len(tgt)
    assert on_line.sum() > 0
    assert (corr.rule[on_line] == RULES.index("degenerate")).all()
    assert (corr.weight[on_line] == 0).all()
    assert np.isfinite(corr.plane_distance[corr.accepted]).all()
    assert corr.accepted[~on_line].mean() > 0.9


def test_matching_rejects_sources_without_a_normal():
    rng = np.random.default_rng(8)
    tgt, _ = plane(rng, n=600)
    half = tgt[tgt[:, 0] < 2.5]  # source plane points on one half, a line (a scan line) on the other
    x = np.linspace(3.5, 5.0, 40)
    line = np.column_stack([x, np.full(40, 4.0), 0.1 * x + 0.2 + 0.01])
    source = np.vstack([half + [0, 0, 0.01], line])
    corr = match(source, tgt, max_distance=1.0, max_angle_deg=30.0)
    on_line = corr.source_index >= len(half)
    assert on_line.sum() == 40
    assert (corr.rule[on_line] == RULES.index("degenerate")).all()
    assert corr.accepted[~on_line].mean() > 0.9


# ----------------------------------------------------------------------------- argument catalogue

_PTS = np.random.default_rng(9).normal(size=(60, 3))


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: match(_PTS, _PTS, k=100), "k must lie between 3"),
        (lambda: match(_PTS, _PTS, surface="cubic"), "surface must be one of"),
        (lambda: match(_PTS, _PTS, surface="quadric", k=8), "k must be at least 10"),
        (lambda: match(_PTS, _PTS, max_distance=-1.0), "max_distance"),
        (lambda: match(_PTS, _PTS, target_normals=np.zeros((60, 3))), "zero-length normals"),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_bad_arguments_give_one_clear_error(call, message):
    with pytest.raises(LabkitError, match=message):
        call()
