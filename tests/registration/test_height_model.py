"""Height-model matching: the horizontal shift from height jumps, with a jackknife std that holds."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.registration.height_model import height_model_shift

SHIFT = np.array([0.3, 0.2, 0.05])


def gable_scene(n, rng, *, size=60.0, noise=0.02, hall=False, trees=False):
    """Flat ground with houses 12 x 8 m whose ridges run along X (gable ends at both X ends), no walls.

    The same houses in every call (their layout has its own seed); ``rng`` draws the points.
    ``hall``: a new flat-roofed hall 20 x 14 m, 8 m high, over the corner x > 40, y < 14 (7.8 % of
    the area); ``trees``: a stand of conical trees 12 m high, 3 m radius, over x < 20, y > 40 (11 %).
    """
    rng = np.random.default_rng(rng)
    xy = rng.uniform(0, size, (n, 2))
    z = np.zeros(n)
    layout = np.random.default_rng(7)
    for cx in np.arange(9.0, size - 8, 16.0):
        for cy in np.arange(8.0, size - 6, 13.0):
            cx_, cy_ = cx + layout.uniform(-2, 2), cy + layout.uniform(-1.5, 1.5)
            inside = (np.abs(xy[:, 0] - cx_) < 6.0) & (np.abs(xy[:, 1] - cy_) < 4.0)
            roof = 4.0 + 0.7 * (4.0 - np.abs(xy[:, 1] - cy_))  # eaves 4 m, ridge 6.8 m
            z = np.where(inside, np.maximum(z, roof), z)
    if hall:
        z = np.where((xy[:, 0] > size - 20) & (xy[:, 1] < 14), 8.0, z)
    if trees:
        for tx in np.arange(2.5, 20, 5.0):
            for ty in np.arange(size - 17.5, size, 5.0):
                cx_, cy_ = tx + layout.uniform(-1, 1), ty + layout.uniform(-1, 1)
                r = np.hypot(xy[:, 0] - cx_, xy[:, 1] - cy_)
                z = np.maximum(z, np.where(r < 3.0, 12.0 * (1 - r / 3.0) + 2.0, 0.0))
    return np.column_stack([xy, z + rng.normal(0, noise, n)])


@pytest.mark.parametrize("robust", [False, True])
def test_gable_roofs_give_the_along_ridge_shift_with_an_honest_std(robust):
    est, std = [], []
    for i in range(40):  # independent samplings of both epochs
        rng = np.random.default_rng(100 + i)
        hm = height_model_shift(gable_scene(8000, rng) - SHIFT, gable_scene(8000, rng), robust=robust)
        assert hm.converged and hm.determined.all(), hm.message
        est.append(hm.translation)
        std.append(hm.translation_std)
    est, std = np.array(est), np.array(std)
    stated = np.sqrt((std**2).mean(axis=0))
    spread = est.std(axis=0, ddof=1)
    assert np.all(np.abs(est.mean(axis=0) - SHIFT) < 3 * spread / np.sqrt(len(est)) + 0.002)  # no bias
    assert stated[0] < 0.1  # X, along the ridges: from the gable ends
    assert np.all((spread / stated > 0.8) & (spread / stated < 1.25)), spread / stated


def test_a_changed_fifth_of_the_scene_is_rejected_and_the_shift_stays_within_its_std():
    """A new hall in the target, a stand of trees cut since the source: 19 % of the area changed."""
    for i in range(4):
        rng = np.random.default_rng(200 + i)
        src, tgt = gable_scene(8000, rng, trees=True) - SHIFT, gable_scene(8000, rng, hall=True)
        hm = height_model_shift(src, tgt, robust=True)
        assert hm.converged and hm.determined.all(), hm.message
        assert np.all(np.abs(hm.translation - SHIFT) <= 3 * hm.translation_std), (hm.translation, hm.translation_std)
        assert hm.n_rejected > 0.08 * hm.n_cells  # the hall and the trees, not the edges alone
        assert "cells rejected" in hm.summary()
    plain = height_model_shift(src, tgt, robust=False)  # every cell weight 1: the change pulls the shift
    assert np.abs(plain.translation - SHIFT).max() > 0.1 or not plain.determined.all()


def test_a_flat_floor_leaves_the_horizontal_undetermined():
    rng = np.random.default_rng(0)
    floor = lambda n: np.column_stack([rng.uniform(0, 40, (n, 2)), rng.normal(0, 0.02, n)])  # noqa: E731
    hm = height_model_shift(floor(4000) - SHIFT, floor(4000))
    assert not hm.determined[:2].any() and not np.isfinite(hm.translation_std[:2]).any()
    assert not hm.determined[2]  # dz only together with dx, dy
    assert "undetermined" in hm.message and "undetermined" in hm.summary()


def test_clouds_without_a_common_area_are_refused():
    rng = np.random.default_rng(1)
    a = gable_scene(3000, rng)
    with pytest.raises(LabkitError, match="overlap"):
        height_model_shift(a + [500.0, 0.0, 0.0], a)
    with pytest.raises(LabkitError):
        height_model_shift(a, a, max_std=-1.0)


#: the files where point-to-plane on the stable surfaces leaves X and Y undetermined
HARD_FILES = ("als/MixedConifer.laz", "als/sample_c.las", "als/warsaw_small.las")
SHIFTS = np.array([[0.15, -0.12, 0.05], [-0.25, 0.30, -0.10], [0.42, 0.30, 0.12], [-0.50, -0.55, 0.20]])


@pytest.mark.parametrize("name", HARD_FILES)
def test_real_halves_state_only_what_holds(realdata, name):
    """12 random halves, shifted by 0.2-0.8 m: every stated component within 3.5 std, spread / stated 0.75-1.3."""
    from labkit import read_cloud

    path = realdata / name
    if not path.is_file():
        pytest.skip(f"{name} absent")
    cloud = read_cloud(path)
    err, std = [], []
    for seed in range(12):
        half = np.random.default_rng(seed).random(len(cloud.xyz)) < 0.5
        s = SHIFTS[seed % 4]
        src, tgt = cloud.subset(~half), cloud.subset(half)
        hm = height_model_shift(src.with_xyz(src.xyz - s), tgt)
        err.append(hm.translation - s)
        std.append(hm.translation_std)
    err, std = np.array(err), np.array(std)
    stated = np.isfinite(std)
    assert np.all(np.abs(err[stated]) <= 3.5 * std[stated]), (err, std)
    for k in range(2):
        if stated[:, k].sum() >= 8:  # enough halves for a spread
            ratio = err[stated[:, k], k].std(ddof=1) / np.sqrt(np.mean(std[stated[:, k], k] ** 2))
            assert 0.75 <= ratio <= 1.3, (name, "XY"[k], ratio)
    if name == "als/MixedConifer.laz":  # the crowns fix X and Y to a few centimetres in every half
        assert stated[:, :2].all() and np.all(std[:, :2] < 0.05)


def test_icp_defaults_fill_the_along_ridge_axis_and_say_so():
    from labkit.registration import icp

    rng = np.random.default_rng(5)
    src, tgt = gable_scene(8000, rng) - SHIFT, gable_scene(8000, rng)
    plain = icp(src, tgt, rng=0, height_model=False)
    assert plain.degeneracy.undetermined_axes == ("X",)  # point-to-plane: roof normals have no X component
    res = icp(src, tgt, rng=0)
    err, std = res.translation - SHIFT, res.translation_std
    assert res.degeneracy.undetermined_axes == () and np.all(np.isfinite(std)), res.message
    assert np.all(np.abs(err) <= 3 * std) and std[0] < 0.1, (err, std)
    assert np.allclose(res.translation[1:], plain.translation[1:], atol=3 * std[1:])  # Y, Z: point-to-plane
    assert "X FROM THE HEIGHT MODEL" in res.message and "Height model" in res.summary()
    assert res.height_model is not None and res.height_model.determined[0]
    assert np.isclose(res.translation_cov[0, 0], res.height_model.covariance[0, 0])


def test_real_conifer_plot_gets_x_and_y_from_the_crowns(realdata):
    from labkit import read_cloud
    from labkit.registration import icp

    path = realdata / "als" / "MixedConifer.laz"
    if not path.is_file():
        pytest.skip("MixedConifer.laz absent")
    cloud = read_cloud(path)
    half = np.random.default_rng(3).random(len(cloud.xyz)) < 0.5
    s = SHIFTS[2]
    src, tgt = cloud.subset(~half), cloud.subset(half)
    res = icp(src.with_xyz(src.xyz - s), tgt, rng=0)  # ground only: a flat, height-normalised floor
    err, std = res.translation - s, res.translation_std
    assert np.all(std < 0.1) and np.all(np.abs(err) <= 3 * std), (err, std, res.message)
    assert "X, Y FROM THE HEIGHT MODEL" in res.message


def test_max_consensus_defaults_fill_the_along_ridge_axis_too():
    from labkit.registration import max_consensus

    rng = np.random.default_rng(6)
    src, tgt = gable_scene(8000, rng) - SHIFT, gable_scene(8000, rng)
    plain = max_consensus(src, tgt, height_model=False)
    assert "X" in plain.degeneracy.undetermined_axes, plain.message
    res = max_consensus(src, tgt)
    err, std = res.translation - SHIFT, res.translation_std
    assert "X" not in res.degeneracy.undetermined_axes and std[0] < 0.1, res.message
    assert np.all(np.abs(err) <= 3 * std), (err, std)
    assert "FROM THE HEIGHT MODEL" in res.message and res.height_model is not None
    assert max_consensus(src, tgt, metric="point_to_point", eps=0.05).height_model is None  # point-to-plane only


def test_real_conifer_plot_max_consensus_gets_x_and_y_from_the_crowns(realdata):
    from labkit import read_cloud
    from labkit.registration import max_consensus

    path = realdata / "als" / "MixedConifer.laz"
    if not path.is_file():
        pytest.skip("MixedConifer.laz absent")
    cloud = read_cloud(path)
    half = np.random.default_rng(4).random(len(cloud.xyz)) < 0.5
    s = SHIFTS[1]
    src, tgt = cloud.subset(~half), cloud.subset(half)
    res = max_consensus(src.with_xyz(src.xyz - s), tgt)
    err, std = res.translation - s, res.translation_std
    assert np.all(std < 0.1) and np.all(np.abs(err) <= 3 * std), (err, std, res.message)
    assert "X, Y FROM THE HEIGHT MODEL" in res.message


def test_consensus_then_icp_matches_the_height_models_once(monkeypatch):
    """consensus+icp: ICP holds X where max_consensus filled it and takes that match instead of making another.

    Matching again from ICP's end point (the route before) moves X by a few hundredths of its std
    (the Gauss-Newton stops within 5 % of the formal std of its start); Y and Z come from ICP alone.
    """
    import labkit.registration.height_model as height_model
    from labkit.registration import icp, max_consensus
    from labkit.registration.compare import standard_methods

    rng = np.random.default_rng(6)
    src, tgt = gable_scene(8000, rng) - SHIFT, gable_scene(8000, rng)
    start = max_consensus(src, tgt, max_points=5000)
    assert "X FROM THE HEIGHT MODEL" in start.message, start.message
    twice = icp(src, tgt, robust="tukey", initial=start.matrix, rng=0)  # matches again at its end
    calls = []
    match = height_model.height_model_shift
    monkeypatch.setattr(height_model, "height_model_shift", lambda *a, **k: calls.append(1) or match(*a, **k))
    res = standard_methods(["consensus+icp"])["consensus+icp"](src, tgt)
    assert len(calls) == 1  # inside max_consensus only
    assert "X FROM THE HEIGHT MODEL" in res.message and "matched once, at the start" in res.message, res.message
    assert res.height_model is not None and res.degeneracy.undetermined_axes == ()
    std = twice.translation_std
    assert np.all(np.abs(res.translation - twice.translation) < 0.1 * std), (res.translation, twice.translation, std)
    assert np.allclose(res.translation_std, std, rtol=0.1)
    assert np.all(np.abs(res.translation - SHIFT) <= 3 * res.translation_std)
