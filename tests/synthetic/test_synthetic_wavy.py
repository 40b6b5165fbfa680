"""The wavy test surface: shape, the surface it lies on, its noise, reproducibility, bad input."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.synthetic import wavy_surface


def _height(xy):
    return 0.5 * np.sin(2 * xy[:, 0]) + 0.5 * np.cos(2 * xy[:, 1])


def test_noise_free_points_lie_on_the_surface_inside_the_square():
    pts = wavy_surface(2000, 5, noise=0.0, size=3.0)
    assert pts.shape == (2000, 3)
    assert np.allclose(pts[:, 2], _height(pts[:, :2]), atol=1e-15)
    assert pts[:, :2].min() >= 0.0 and pts[:, :2].max() <= 3.0
    assert pts[:, :2].max() > 2.9 and pts[:, :2].min() < 0.1  # the whole square is used


def test_noise_has_the_stated_spread_in_every_coordinate():
    clean = wavy_surface(50_000, 7, noise=0.0)
    noisy = wavy_surface(50_000, 7, noise=0.004)  # same seed: same xy draws, then the noise
    diff = noisy - clean
    assert np.allclose(diff.std(axis=0), 0.004, rtol=0.02)
    assert np.all(np.abs(diff.mean(axis=0)) < 1e-4)


def test_one_generator_gives_independent_samplings_and_matches_the_written_out_draws():
    rng = np.random.default_rng(1)
    a, b = wavy_surface(100, rng), wavy_surface(100, rng)
    assert not np.allclose(a[:, :2], b[:, :2])
    ref = np.random.default_rng(1)  # the same draws written out, in the same order
    xy = ref.uniform(0, 6, (100, 2))
    expected = np.column_stack([xy, _height(xy)]) + ref.normal(0, 0.002, (100, 3))
    assert np.array_equal(a, expected)
    assert np.array_equal(wavy_surface(100, 3), wavy_surface(100, 3))


def test_noise_zero_draws_nothing_for_the_noise():
    rng = np.random.default_rng(2)
    wavy_surface(10, rng, noise=0.0)
    ref = np.random.default_rng(2)
    ref.uniform(0, 6, (10, 2))
    assert rng.random() == ref.random()


@pytest.mark.parametrize("kwargs", [{"n": 0}, {"n": 2.5}, {"n": 10, "noise": -0.1}, {"n": 10, "size": 0.0},
                                    {"n": 10, "rng": "seed"}])
def test_bad_input_is_refused(kwargs):
    with pytest.raises(LabkitError):
        wavy_surface(**kwargs)


def test_wavy_pair_is_the_two_samplings_drawn_in_turn_and_refuses_a_bad_shift():
    from labkit.synthetic import wavy_pair

    source, target = wavy_pair(40, 60, 3, shift=(0.1, -0.2, 0.3), noise=0.001)
    rng = np.random.default_rng(3)
    assert np.array_equal(target, wavy_surface(60, rng, noise=0.001))
    assert np.array_equal(source, wavy_surface(40, rng, noise=0.001) - [0.1, -0.2, 0.3])
    for bad in ((1.0, 2.0), (np.nan, 0, 0)):
        with pytest.raises(LabkitError, match="shift"):
            wavy_pair(shift=bad)


def test_flat_floor_has_its_noise_in_z_only_and_refuses_bad_input():
    from labkit.synthetic import flat_floor

    floor = flat_floor(20_000, 4, noise=0.003, size=2.0)
    assert floor.shape == (20_000, 3)
    assert 0.0 <= floor[:, :2].min() and floor[:, :2].max() <= 2.0 and floor[:, :2].max() > 1.99
    assert abs(floor[:, 2].std() / 0.003 - 1) < 0.03 and abs(floor[:, 2].mean()) < 1e-4
    assert np.all(flat_floor(10, 0, noise=0.0)[:, 2] == 0.0)
    for kwargs in ({"n": 0}, {"n": 5, "noise": -1.0}, {"n": 5, "size": 0.0}):
        with pytest.raises(LabkitError):
            flat_floor(**kwargs)


def test_sphere_points_lie_on_the_sphere_with_the_stated_noise_and_bad_input_is_refused():
    from labkit.synthetic import sphere_points

    exact = sphere_points(500, 2, center=[1.0, -2.0, 3.0], radius=0.3)
    assert np.allclose(np.linalg.norm(exact - [1.0, -2.0, 3.0], axis=1), 0.3, atol=1e-14)
    assert np.allclose(exact.mean(axis=0), [1.0, -2.0, 3.0], atol=0.05)  # directions spread over the sphere
    noisy = sphere_points(50_000, 2, radius=0.3, noise=0.002)
    clean = sphere_points(50_000, 2, radius=0.3)  # same directions, then the noise
    assert abs((noisy - clean).std() / 0.002 - 1) < 0.02
    for kwargs in ({"radius": 0.0}, {"noise": -0.1}, {"center": [0, 0]}, {"center": [0, np.nan, 0]}):
        with pytest.raises(LabkitError):
            sphere_points(10, **kwargs)
