"""Bad normals and options of the distances: NaN with a count, or one clear LabkitError."""

import numpy as np
import pytest

from labkit.change.distances import DistanceChange, point_to_plane_distance
from labkit.core.errors import DegenerateGeometryError, LabkitError


# --------------------------------------------------------------------------- distances
def _plane(n=2000, seed=5):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 10, (n, 2))
    return np.c_[xy, 0.2 * xy[:, 0]]


def test_zero_and_nan_normals_give_nan_distances_with_a_count():
    tgt = _plane()
    src = tgt[::4] + [0, 0, 0.1]
    n = np.tile(np.array([-0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0), (len(tgt), 1))
    bad = np.zeros(len(tgt), bool)
    bad[::7] = True
    given = n.copy()
    given[bad] = 0.0
    given[1::7] = np.nan
    nearest = np.argmin(((src[:, None, :] - tgt[None, :, :]) ** 2).sum(-1), axis=1)  # brute force
    expect_nan = bad[nearest] | (np.arange(len(tgt)) % 7 == 1)[nearest]
    d = point_to_plane_distance(src, tgt, given)
    assert np.array_equal(np.isnan(d), expect_nan) and expect_nan.any()
    np.testing.assert_allclose(d[~expect_nan], 0.1 / np.hypot(0.2, 1.0), atol=1e-9)  # the closed form
    change = DistanceChange(d, d, "point_to_plane")
    assert change.n_undetermined == expect_nan.sum()
    assert change.stats()["n"] == (~expect_nan).sum()
    assert f"{expect_nan.sum()} points (no usable target normal" in change.summary()


def test_given_normals_are_scaled_to_unit_length():
    tgt = _plane()
    src = tgt[::5] + [0, 0, 0.1]
    n = np.tile(np.array([-0.2, 0.0, 1.0]), (len(tgt), 1))
    np.testing.assert_allclose(point_to_plane_distance(src, tgt, 3.0 * n),
                               point_to_plane_distance(src, tgt, n / np.linalg.norm(n, axis=1, keepdims=True)),
                               atol=1e-12)


@pytest.mark.parametrize("normals, error, fragment", [
    ("zeros", DegenerateGeometryError, "none of the 2000 target normals is usable"),
    ("nan", DegenerateGeometryError, "none of the 2000 target normals is usable"),
    ("inf", LabkitError, "infinite"),
    ("short", LabkitError, "target_normals must have shape (2000, 3), got (3, 3)"),
    ("text", LabkitError, "target_normals must be numbers"),
])
def test_unusable_normals_are_refused(normals, error, fragment):
    tgt = _plane()
    given = {"zeros": np.zeros((2000, 3)), "nan": np.full((2000, 3), np.nan),
             "inf": np.tile([0, 0, np.inf], (2000, 1)), "short": np.eye(3), "text": [["a", "b", "c"]] * 2000}[normals]
    with pytest.raises(error) as exc:
        point_to_plane_distance(tgt, tgt, given)
    assert fragment in str(exc.value)


def test_distance_options_are_checked():
    tgt = _plane()
    with pytest.raises(LabkitError, match="k must be a whole number >= 3, got 10.5"):
        point_to_plane_distance(tgt, tgt, k=10.5)
    with pytest.raises(LabkitError, match="which must be one of 'before', 'after'"):
        DistanceChange(np.zeros(3), np.zeros(3), "x").stats("middle")
