"""MatchOptions: one checked object for the matching options of icp, match and prepare."""

import dataclasses
import inspect

import numpy as np
import pytest

import labkit
from labkit.core.errors import LabkitError
from labkit.registration import MatchOptions, icp, match
from labkit.registration.matching.match import prepare

FIELDS = [f.name for f in dataclasses.fields(MatchOptions)]


def _wavy(n, rng, noise=0.002):
    xy = rng.uniform(0, 6, (n, 2))
    z = 0.5 * np.sin(2 * xy[:, 0]) + 0.5 * np.cos(2 * xy[:, 1])
    return np.column_stack([xy, z]) + rng.normal(0, noise, (n, 3))


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(21)
    target = _wavy(3000, rng)
    source = _wavy(800, rng) + [0.03, -0.02, 0.01]
    return source, target


def _defaults(func):
    params = inspect.signature(func).parameters
    return {name: params[name].default for name in FIELDS}


def test_exported_from_labkit_and_registration():
    assert labkit.MatchOptions is MatchOptions


def test_every_function_takes_every_option_and_options():
    for func in (icp, match, prepare):
        params = inspect.signature(func).parameters
        assert set(FIELDS) <= set(params), func.__name__
        assert params["options"].default is None


def test_defaults_are_those_of_icp():
    opts = MatchOptions()
    assert {name: getattr(opts, name) for name in FIELDS} == _defaults(icp)


@pytest.mark.parametrize("func", [match, prepare])
def test_match_and_prepare_differ_only_in_sample_and_surface(func):
    opts, own = MatchOptions(), _defaults(func)
    differ = {name for name in FIELDS if own[name] != getattr(opts, name)}
    assert differ == {"sample", "surface"}
    assert (own["sample"], own["surface"]) == (None, "plane")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(max_distance=-1), "max_distance"),
        (dict(max_distance="1"), "max_distance"),
        (dict(max_angle_deg=0), "max_angle_deg"),
        (dict(k=2), "k must lie between 3"),
        (dict(k=20.5), "k must be a whole number"),
        (dict(k=True), "k must be a whole number"),
        (dict(default_sigma=-0.01), "default_sigma"),
        (dict(max_noise=0), "max_noise"),
        (dict(noise_weighting="yes"), "noise_weighting"),
        (dict(unique=None), "unique"),
        (dict(surface="cubic"), "surface must be one of"),
        (dict(surface="quadric", k=8), "k must be at least 10"),
        (dict(sample="all"), "sample must be None"),
        (dict(sample=("octree", 10)), "sample method"),
        (dict(sample=("voxel", -0.5)), "voxel size"),
        (dict(sample=0), "sample size"),
        (dict(classes=6), "classes"),
        (dict(class_sigma=[0.01]), "class_sigma"),
    ],
)
def test_bad_values_raise_when_built(kwargs, message):
    with pytest.raises(LabkitError, match=message):
        MatchOptions(**kwargs)


def test_values_are_normalised_and_copied():
    sigma = {6: 0.01}
    opts = MatchOptions(k=20.0, classes=[2, 6], class_sigma=sigma, sample=["voxel", 0.5], max_distance=1)
    sigma[6] = 5.0  # a later change of the caller's dict does not reach the options
    assert opts.k == 20 and isinstance(opts.k, int)
    assert opts.classes == (2, 6) and opts.class_sigma == {6: 0.01} and opts.sample == ("voxel", 0.5)
    assert isinstance(opts.max_distance, float)


def test_frozen_and_replace_checks():
    opts = MatchOptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.k = 30
    assert opts.replace(k=30).k == 30 and opts.k == 20
    with pytest.raises(LabkitError, match="k must lie between 3"):
        opts.replace(k=1)
    with pytest.raises(LabkitError, match="no option normal_k"):
        opts.replace(normal_k=10)


def test_options_must_be_a_match_options(pair):
    with pytest.raises(LabkitError, match="options must be"):
        match(*pair, options={"k": 10})


def _same_result(a, b):
    np.testing.assert_array_equal(a.matrix, b.matrix)
    np.testing.assert_array_equal(a.covariance, b.covariance)
    assert a.iterations == b.iterations and a.method == b.method


def test_icp_with_options_is_bitwise_the_keyword_run(pair):
    kw = dict(max_distance=0.3, max_angle_deg=20.0, k=15, unique=False, noise_weighting=False, surface="plane")
    by_keywords = icp(*pair, dof="rigid", **kw)
    by_options = icp(*pair, dof="rigid", options=MatchOptions(**kw))
    _same_result(by_keywords, by_options)
    default = icp(*pair, dof="rigid")
    assert not np.array_equal(default.covariance, by_options.covariance)  # the options did change the run


def test_icp_default_options_equal_no_options(pair):
    _same_result(icp(*pair), icp(*pair, options=MatchOptions()))


def test_keyword_overrides_the_options_field(pair):
    opts = MatchOptions(max_distance=0.3, k=15)
    mixed = icp(*pair, options=opts, k=25)
    _same_result(mixed, icp(*pair, max_distance=0.3, k=25))
    assert opts.k == 15  # the given object is not changed
    corr = match(*pair, options=opts, max_distance=0.02)
    assert corr.settings["max_distance"] == 0.02 and corr.settings["k"] == 15


def test_match_uses_the_options_values_and_its_own_defaults_without(pair):
    src, tgt = pair
    plain = match(src, tgt)
    assert plain.settings["surface"] == "plane" and len(plain) == len(src)
    thinned = match(src, tgt, options=MatchOptions(sample=200), rng=1)
    assert len(thinned) == 200
    np.testing.assert_array_equal(
        match(src, tgt, options=MatchOptions(sample=None, surface="plane", max_distance=0.2)).d,
        match(src, tgt, max_distance=0.2).d,
    )


def test_pyramid_passes_the_options_to_every_level(pair):
    src, tgt = pair
    moved = src + [0.4, -0.3, 0.0]  # beyond the gate: the pyramid runs
    kw = dict(max_distance=0.15, k=15, surface="plane")
    a = icp(moved, tgt, reach=0.8, **kw)
    b = icp(moved, tgt, reach=0.8, options=MatchOptions(**kw))
    assert "coarse_to_fine" in a.method
    _same_result(a, b)


def test_consensus_shares_the_names_of_the_options_it_takes():
    from labkit.registration import consensus_cube, max_consensus

    for func in (consensus_cube, max_consensus):
        params = inspect.signature(func).parameters
        shared = {"max_angle_deg", "k", "source_normals", "target_normals"}
        assert shared <= set(params) and shared <= set(FIELDS)
        assert (params["max_angle_deg"].default, params["k"].default) == (None, 12)  # their own defaults
