"""Bad and unusual input to the consensus cube and maximum consensus.

Every case gives one clear LabkitError (checked by type and message fragment) or a right
answer; none modifies its input.
"""

import numpy as np
import pytest

from labkit.core.errors import DegenerateGeometryError, EmptyRegionError, LabkitError
from labkit.registration import consensus_cube, max_consensus


def _surface(n, rng, noise=0.01):
    """A gently curved surface with bumps in X and Y, so every component is determined."""
    xy = rng.uniform(0, 20, (n, 2))
    z = 0.8 * np.sin(xy[:, 0] / 1.5) + 0.8 * np.cos(xy[:, 1] / 1.7)
    return np.column_stack([xy, z]) + rng.normal(0, noise, (n, 3))


@pytest.fixture(scope="module")
def clouds():
    rng = np.random.default_rng(5)
    return _surface(1500, rng), _surface(3000, rng)


FAST = {"extent": 0.1, "tol": 0.02, "max_time": 5.0}

# (keyword, value, message fragment)
BAD_OPTIONS = [
    ("reject_sigma", 0, "reject_sigma"),
    ("reject_sigma", -3, "reject_sigma"),
    ("reject_sigma", np.nan, "reject_sigma"),
    ("reject_sigma", "three", "reject_sigma"),
    ("max_boxes", -1, "max_boxes"),
    ("max_boxes", 2.5, "max_boxes"),
    ("max_boxes", np.nan, "max_boxes"),
    ("gap_tol", -1.0, "gap_tol"),
    ("gap_tol", np.nan, "gap_tol"),
    ("gap_tol", np.inf, "gap_tol"),
    ("tol", 0.0, "tol"),
    ("tol", -0.001, "tol"),
    ("max_time", 0.0, "max_time"),
    ("max_time", -1.0, "max_time"),
    ("max_time", np.nan, "max_time"),
    ("max_points", 0, "max_points"),
    ("max_points", 2, "max_points"),
    ("max_points", -5, "max_points"),
    ("max_points", 100.5, "max_points"),
    ("init_step", 0.0, "init_step"),
    ("init_step", -0.05, "init_step"),
    ("block_size", 0.0, "block_size"),
    ("block_size", -2.0, "block_size"),
    ("eps", 0.0, "eps"),
    ("eps", -0.05, "eps"),
    ("eps", np.nan, "eps"),
    ("radius", 0.0, "radius"),
    ("radius", -1.0, "radius"),
    ("extent", 0.0, "extent"),
    ("extent", -1.0, "extent"),
    ("extent", np.nan, "extent"),
    ("extent", (1.0, 2.0), "extent"),
    ("center", (np.nan, 0.0, 0.0), "center"),
    ("metric", "nearest", "metric"),
    ("k", 2, "k must"),
    ("k", 12.5, "k must"),
    ("max_angle_deg", 0.0, "max_angle_deg"),
    ("max_angle_deg", -10.0, "max_angle_deg"),
]


@pytest.mark.parametrize("key, value, fragment", BAD_OPTIONS, ids=[f"{k}={v!r}" for k, v, _ in BAD_OPTIONS])
def test_max_consensus_refuses_bad_options(clouds, key, value, fragment):
    src, tgt = clouds
    with pytest.raises(LabkitError, match=fragment):
        max_consensus(src, tgt, **{**FAST, key: value})


BAD_ARRAYS = [
    ("source with NaN", lambda s, t: (np.vstack([s, [np.nan, 0, 0]]), t), LabkitError, "source"),
    ("source of wrong shape", lambda s, t: (s[:, :2], t), LabkitError, "source"),
    ("empty source", lambda s, t: (s[:0], t), LabkitError, "source"),
    ("target of two points", lambda s, t: (s, t[:2]), LabkitError, "target"),
    ("target with inf", lambda s, t: (s, np.vstack([t, [np.inf, 0, 0]])), LabkitError, "target"),
    ("clouds 500 m apart", lambda s, t: (s + 500.0, t), EmptyRegionError, "overlap"),
    ("identical points", lambda s, t: (np.repeat(s[:1], 400, 0), np.repeat(s[:1], 400, 0)),
     DegenerateGeometryError, "normal"),
    ("collinear target", lambda s, t: (s, np.column_stack([np.linspace(0, 20, 900), np.zeros((900, 2))])),
     DegenerateGeometryError, "normal"),
]


@pytest.mark.parametrize("name, make, error, fragment", BAD_ARRAYS, ids=[c[0] for c in BAD_ARRAYS])
def test_max_consensus_refuses_bad_clouds(clouds, name, make, error, fragment):
    src, tgt = make(*clouds)
    with pytest.raises(error, match=fragment):
        max_consensus(src, tgt, **FAST)


BAD_WEIGHTS_AND_NORMALS = [
    ("weights of wrong length", {"weights": np.ones(7)}, "weights"),
    ("negative weight", {"weights": "negative"}, "weights"),
    ("all weights zero", {"weights": "zero"}, "weights"),
    ("weights with NaN", {"weights": "nan"}, "weights"),
    ("weights per class without classes", {"weights": {2: 1.0}}, "classification"),
    ("target normals of wrong shape", {"target_normals": np.ones((5, 3))}, "normals"),
]


@pytest.mark.parametrize("name, kwargs, fragment", BAD_WEIGHTS_AND_NORMALS, ids=[c[0] for c in BAD_WEIGHTS_AND_NORMALS])
def test_max_consensus_refuses_bad_weights_and_normals(clouds, name, kwargs, fragment):
    src, tgt = clouds
    w = kwargs.get("weights")
    if isinstance(w, str):
        w = np.ones(len(src))
        w[3] = {"negative": -1.0, "nan": np.nan, "zero": 0.0}[kwargs["weights"]]
        if kwargs["weights"] == "zero":
            w[:] = 0.0
        kwargs = {"weights": w}
    with pytest.raises(LabkitError, match=fragment):
        max_consensus(src, tgt, **FAST, **kwargs)


BAD_CUBE = [
    ({"step": 0.0}, "step"),
    ({"step": -0.01}, "step"),
    ({"extent": 3.0, "step": 0.01}, "cells"),
    ({"eps": 0.0, "step": 0.05}, "eps"),
    ({"metric": "closest", "step": 0.05}, "metric"),
    ({"k": 1, "step": 0.05}, "k must"),
]


@pytest.mark.parametrize("kwargs, fragment", BAD_CUBE, ids=[repr(c[0]) for c in BAD_CUBE])
def test_consensus_cube_refuses_bad_options(clouds, kwargs, fragment):
    src, tgt = clouds
    with pytest.raises(LabkitError, match=fragment):
        consensus_cube(src[::5], tgt, **kwargs)


@pytest.mark.slow
def test_invalid_target_normals_are_dropped_not_used(clouds):
    """Target points stacked on one spot have no normal: they must not vote; the rest still registers."""
    src, tgt = clouds
    pile = np.repeat(tgt[:1] + [0.0, 0.0, 0.05], 50, axis=0)  # 50 identical points just above the surface
    clean = max_consensus(src, tgt, **FAST)
    dirty = max_consensus(src, np.vstack([tgt, pile]), **FAST)
    np.testing.assert_allclose(dirty.translation, clean.translation, atol=3 * clean.translation_std.max())


def test_identical_clouds_state_a_real_precision():
    """max_consensus(P, P): zero shift, stated with a positive, finite standard deviation."""
    P = _surface(3000, np.random.default_rng(8), noise=0.005)
    res = max_consensus(P, P, extent=0.2, tol=0.005)
    assert res.degeneracy.well_posed
    std = res.translation_std
    assert np.isfinite(std).all() and (std > 1e-5).all(), std
    assert (np.abs(res.translation) < 3 * std + 1e-4).all(), (res.translation, std)


def test_budget_zero_splits_returns_the_first_level_best_with_its_gap(clouds):
    src, tgt = clouds
    shift = np.array([0.05, -0.04, 0.03])
    res = max_consensus(src - shift, tgt, extent=0.1, max_boxes=0)
    bb = res.history[0]
    assert bb.splits == 0 and not bb.converged and "box budget" in bb.reason
    assert bb.upper >= bb.lower and bb.gap == pytest.approx(bb.upper - bb.lower)
    assert "gap" in res.message and not res.converged
    # the refinement still reaches the truth from the coarse optimum
    assert np.abs(res.translation - shift).max() < 3 * res.translation_std.max() + 0.002


def test_inputs_are_not_modified(clouds):
    src, tgt = clouds
    w = np.ones(len(src))
    before = src.copy(), tgt.copy(), w.copy()
    max_consensus(src, tgt, weights=w, **FAST)
    for a, b in zip((src, tgt, w), before):
        np.testing.assert_array_equal(a, b)
