"""The synthetic room scene: counts, geometry of the sphere points, reproducibility, bad input."""

import numpy as np
import pytest

from labkit.errors import LabkitError
from labkit.sphere import algebraic_sphere, sphere_residuals
from labkit.synthetic.room import CLUTTER, FLOOR, SPHERE, room_scene


def test_counts_and_share():
    scene = room_scene(n_points=20000, sphere_share=0.02, rng=3)
    assert scene.points.shape == (20000, 3)
    assert scene.is_sphere.sum() == 400
    assert np.array_equal(scene.is_sphere, scene.labels == SPHERE)
    assert abs(scene.outlier_ratio - 0.98) < 1e-12
    counts = np.bincount(scene.labels, minlength=len(scene.label_names))
    assert (counts > 0).all()  # every kind of surface is present
    assert "sphere share" in scene.summary()


def test_sphere_points_lie_on_the_true_sphere_with_the_stated_noise():
    scene = room_scene(n_points=30000, sphere_share=0.04, noise=0.002, rng=4)
    d = sphere_residuals(scene.sphere_points, scene.sphere)
    # orthogonal distance of isotropic noise: std = noise
    assert abs(d.std() - 0.002) < 0.0003 and abs(d.mean()) < 0.0004
    # independent route: an algebraic fit of the labelled points recovers the truth
    x = algebraic_sphere(scene.sphere_points)
    assert np.linalg.norm(x[:3] - scene.sphere[:3]) < 0.003 and abs(x[3] - scene.sphere[3]) < 0.003
    # only the cap facing the station is scanned
    u = scene.sphere_points - scene.sphere[:3]
    assert (u @ (scene.station - scene.sphere[:3]) > 0).all()


def test_scene_geometry_is_plausible():
    scene = room_scene(rng=5)
    pts = scene.points
    assert pts.min(axis=0).min() > -0.02 and (pts.max(axis=0) < [6.02, 4.52, 2.82]).all()
    floor = pts[scene.labels == FLOOR]
    assert np.abs(floor[:, 2]).max() < 0.02
    # no non-sphere surface point lies inside the sphere (except clutter in the volume)
    other = pts[(scene.labels != SPHERE) & (scene.labels != CLUTTER)]
    assert (np.linalg.norm(other - scene.sphere[:3], axis=1) > scene.sphere[3] - 0.01).all()


def test_reproducible_and_seed_dependent():
    a, b, c = room_scene(rng=7), room_scene(rng=7), room_scene(rng=8)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.sphere, b.sphere)
    assert not np.array_equal(a.sphere, c.sphere)


def test_no_sphere_scene():
    scene = room_scene(n_points=2000, sphere_share=0.0, rng=1)
    assert not scene.is_sphere.any()


@pytest.mark.parametrize(
    "kwargs",
    [dict(n_points=10), dict(n_points=2.5e3 + 0.5), dict(sphere_share=0.7), dict(sphere_share=-0.1),
     dict(radius=0.0), dict(radius=1.0), dict(noise=-1.0), dict(rng="x")],
)
def test_bad_input(kwargs):
    with pytest.raises(LabkitError):
        room_scene(**kwargs)
