"""The synthetic room scene: counts, geometry of the sphere points, reproducibility, bad input."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.sphere.model import algebraic_sphere, sphere_residuals
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


# ----------------------------------------------------------------- the 16-beam multi-beam room
from labkit.synthetic.multibeam import (  # noqa: E402
    PERSON, SPHERE as MB_SPHERE, VLP16_ELEVATIONS, WALLS as MB_WALLS, multibeam_room,
)


def test_multibeam_rays_lie_on_the_16_beam_elevations_with_range_noise_only():
    scene = multibeam_room(rng=1)
    assert scene.points.shape == (16 * 1800, 3)  # every ray hits something in a closed room
    el = np.degrees(np.arcsin(scene.points[:, 2] / np.linalg.norm(scene.points, axis=1)))
    # range noise moves a point along its ray: the elevation is exactly the beam's
    np.testing.assert_allclose(el, VLP16_ELEVATIONS[scene.ring], atol=1e-9)
    assert np.unique(scene.ring).size == 16 and VLP16_ELEVATIONS[1] - VLP16_ELEVATIONS[0] == 2.0
    # azimuth step 0.2 deg within a ring
    ring0 = scene.points[scene.ring == 0]
    az = np.sort(np.degrees(np.arctan2(ring0[:, 1], ring0[:, 0])))
    assert np.median(np.diff(az)) == pytest.approx(0.2, abs=1e-6)
    counts = np.bincount(scene.labels, minlength=len(scene.label_names))
    assert counts[MB_SPHERE] > 0 and counts[MB_WALLS] > 0 and counts[PERSON] > 0


def test_multibeam_sphere_points_are_the_near_cap_with_the_stated_noise():
    for seed in range(5):
        scene = multibeam_room(rng=seed, noise=0.01)
        c, r = scene.sphere[:3], scene.sphere[3]
        assert 0.15 <= r <= 0.35 and 1.0 <= np.linalg.norm(c) <= 8.0
        assert scene.n_sphere_rings >= 3  # at least min_rings scan lines cross the sphere
        P = scene.sphere_points
        # range noise along the ray: its radial share is ~ the noise on a cap seen head-on (independent route:
        # the exact hit points without noise lie on the sphere; with noise the residual std is <= noise)
        d = sphere_residuals(P, scene.sphere)
        assert 0.5 * 0.01 < d.std() < 1.05 * 0.01
        # only the side facing the scanner (origin) is hit
        normals = (P - c) / np.linalg.norm(P - c, axis=1, keepdims=True)
        assert np.mean(np.einsum("ij,ij->i", normals, -P) > 0) > 0.97


def test_multibeam_same_room_without_the_sphere_and_reproducible():
    a, b = multibeam_room(rng=3), multibeam_room(rng=3)
    assert np.array_equal(a.points, b.points)
    empty = multibeam_room(rng=3, sphere=False)
    assert not empty.has_sphere and not empty.is_sphere.any() and empty.n == a.n
    # the rays that did not hit the sphere or its stand hit the same surfaces
    same = ~np.isin(a.labels, [MB_SPHERE, 6])
    assert np.array_equal(a.labels[same], empty.labels[same])
    assert "16-beam" in a.summary()


@pytest.mark.parametrize(
    "kwargs",
    [dict(noise=0.0), dict(noise=-1.0), dict(radius_range=(0.3, 0.1)), dict(radius_range=(0.0, 0.3)),
     dict(distance_range=(1.0,)), dict(azimuth_step=0.0), dict(azimuth_step=10.0), dict(min_rings=0),
     dict(min_rings=2.5)],
)
def test_multibeam_bad_input(kwargs):
    with pytest.raises(LabkitError):
        multibeam_room(rng=0, **kwargs)
