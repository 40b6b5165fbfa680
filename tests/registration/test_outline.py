"""The weak direction of point-to-plane ICP moved to where the plan-view outlines agree (closest_point/outline.py)."""

import numpy as np
import pytest

from labkit.registration import icp
from labkit.registration.closest_point.outline import outline_points, outline_shift, weak_direction
from labkit.synthetic import flat_floor, wavy_surface

ANGLE = np.radians(30.0)
#: along the ridges, across them (plan view)
ALONG = np.array([np.cos(ANGLE), np.sin(ANGLE), 0.0])
ACROSS = np.array([-np.sin(ANGLE), np.cos(ANGLE), 0.0])
SHIFT = np.array([0.3, -0.2, 0.05])


def gable_roof(n, rng, *, size=(40.0, 30.0), slope=30.0, noise=0.02, window=None):
    """One gable roof 40 x 30 m, ridge 30 degrees from X, clipped at its outline (no ground around it).

    ``window``: the roof continues beyond its ends and the points are clipped to this (along-ridge) range,
    as two epochs cut to the same tile are.
    """
    lo, hi = (-size[0] / 2, size[0] / 2) if window is None else window
    a = rng.uniform(lo - 2.0, hi + 2.0, n) if window is not None else rng.uniform(lo, hi, n)
    b = rng.uniform(-size[1] / 2, size[1] / 2, n)
    z = 10.0 - np.tan(np.radians(slope)) * np.abs(b) + rng.normal(0, noise, n)
    return a[:, None] * ALONG + b[:, None] * ACROSS + z[:, None] * np.array([0, 0, 1.0])


def test_outline_points_lie_on_the_edges_and_point_outwards():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, [30, 20], (4000, 2))  # spacing about 0.4 m
    rows, normals = outline_points(xy)
    edge = np.minimum.reduce([xy[rows, 0], 30 - xy[rows, 0], xy[rows, 1], 20 - xy[rows, 1]])
    assert len(rows) > 150
    assert np.quantile(edge, 0.95) < 1.2  # on the outline, not inside
    outward = np.where(xy[rows] < [15, 10], -1.0, 1.0)  # the quadrant's outward diagonal
    assert np.mean(np.einsum("ij,ij->i", normals, outward) > 0) > 0.95


def test_outline_shift_along_a_rectangle_is_unbiased():
    """Independent samplings of a 40 x 30 m outline, 3.3 points per m^2: the along-ridge shift to about 7 cm."""
    errors = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        a, b = gable_roof(4000, rng)[:, :2], gable_roof(4000, rng)[:, :2]
        est = outline_shift(a - 0.3 * ALONG[:2], b, ALONG[:2])
        assert est.converged
        errors.append(est.shift - 0.3)
    errors = np.array(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.1
    assert abs(errors.mean()) < 3 * errors.std() / np.sqrt(len(errors)) + 0.01


def test_icp_moves_the_along_ridge_shift_but_states_no_precision_for_it():
    """Parallel ridges oblique to the axes: X and Y held (outlines=False) or moved to the outlines, never stated.

    Across the ridges and in Z the point-to-plane solution of the turned frame is right and its std honest.
    """
    along, across, z, z_std = [], [], [], []
    for seed in range(6):
        rng = np.random.default_rng(10 + seed)
        src, tgt = gable_roof(8000, rng) - SHIFT, gable_roof(8000, rng)  # 6.7 points per m^2
        held = icp(src, tgt, outlines=False)
        assert np.allclose(held.translation[:2], 0.0)  # X and Y held at the start
        res = icp(src, tgt)
        assert not np.isfinite(res.translation_std[:2]).any()
        assert "MOVED ALONG THE WEAK DIRECTION" in res.message
        # held across the ridges, the quadrants disagree in Z; solved, they agree and the stale warning goes
        assert "INCONSISTENT" in held.message and "INCONSISTENT" not in res.message
        err = res.translation - SHIFT
        along.append(err @ ALONG)
        across.append(err @ ACROSS)
        z.append(err[2])
        z_std.append(res.translation_std[2])
    assert np.sqrt(np.mean(np.square(along))) < 0.08  # held: 0.16 m (the shift along the ridges); 31 mm over 12
    assert np.max(np.abs(across)) < 0.02
    z, z_std = np.array(z), np.array(z_std)
    assert np.all(np.abs(z) <= 3 * z_std)
    assert np.sqrt(np.mean(z**2)) < 1.5 * z_std.mean()


def test_a_common_clip_pulls_the_outline_estimate_so_it_stays_undetermined():
    """Two epochs cut to one tile: the cut is an outline at the same place in both and pulls to zero shift."""
    rng = np.random.default_rng(7)
    window = (-20.0, 20.0)
    src, tgt = gable_roof(6000, rng, window=window) - SHIFT, gable_roof(6000, rng, window=window)
    keep = lambda p: p[np.abs(p @ ALONG) <= 20.0]  # noqa: E731 - the same tile for both
    res = icp(keep(src), keep(tgt))
    assert abs(res.translation @ ALONG) < 0.06  # pulled to zero: the truth is 0.16 m
    assert not np.isfinite(res.translation_std[:2]).any()


@pytest.mark.parametrize("scene", ["wavy", "floor"])
def test_results_without_one_oblique_weak_direction_are_unchanged(scene):
    """Determined X, Y (wavy surface) and two weak directions (a floor): bit-identical with and without."""
    rng = np.random.default_rng(1)
    cloud = wavy_surface(3000, rng) if scene == "wavy" else flat_floor(3000, rng, size=20)
    src, tgt = cloud[::3] + [0.05, -0.03, 0.02], cloud
    a, b = icp(src, tgt), icp(src, tgt, outlines=False)
    assert np.array_equal(a.translation, b.translation)
    assert np.array_equal(a.covariance, b.covariance, equal_nan=True)
    assert weak_direction(b) is None


def test_real_roof_halves_move_toward_the_truth_and_state_only_z(realdata):
    """sample_c (one large gable roof, ridges oblique): X and Y held at the start before (0.39 m off
    for this shift), moved to 20-140 mm (three random splits), stated never; Z within 3 of its std."""
    from labkit import read_cloud

    path = realdata / "als/sample_c.las"
    if not path.is_file():
        pytest.skip("sample_c.las absent")
    cloud = read_cloud(path)
    shift = np.array([-0.25, 0.30, -0.10])
    off = []
    for seed in range(3):
        half = np.random.default_rng(seed).random(len(cloud.xyz)) < 0.5
        tgt, src = cloud.subset(half), cloud.subset(~half)
        res = icp(src.with_xyz(src.xyz - shift), tgt, rng=0)
        err, std = res.translation - shift, res.translation_std
        assert not np.isfinite(std[:2]).any() and "MOVED" in res.message
        assert abs(err[2]) <= 3 * std[2] and std[2] < 0.01
        off.append(np.hypot(*err[:2]))
    assert max(off) < 0.2 and np.sqrt(np.mean(np.square(off))) < 0.12, off  # held: 0.39 m


def test_sparse_clouds_are_left_held():
    """Spacing beyond half the matching distance: the outline band is wider than the gate, nothing moves."""
    rng = np.random.default_rng(4)
    src, tgt = gable_roof(800, rng) - SHIFT, gable_roof(800, rng)  # 0.6 m median spacing
    res, held = icp(src, tgt), icp(src, tgt, outlines=False)
    assert "outlines: not used (point spacing" in res.message
    assert np.array_equal(res.translation, held.translation)
