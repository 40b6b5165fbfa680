"""The multi-station TLS generator: geometry of the targets, rigid poses, polar noise, reproducibility."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.synthetic import target_stations
from labkit.synthetic.stations import CRATE, DECOY, POLE, TARGET


@pytest.fixture(scope="module")
def yard():
    return target_stations(n_stations=3, n_points=150_000, rng=7)


def _world(yard, i):
    return yard.scans[i] @ yard.poses[i, :3, :3].T + yard.poses[i, :3, 3]


def test_poses_are_rigid_and_nearly_level(yard):
    for T in yard.poses:
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(T[3], [0, 0, 0, 1])
        assert np.degrees(np.arccos(R[2, 2])) <= 0.5 + 1e-9  # tilt of the scanner's z axis
    stations = yard.stations
    assert np.all((stations[:, 2] > 1.3) & (stations[:, 2] < 1.8))
    assert np.min(np.linalg.norm(stations[:, None] - stations[None], axis=2) + 9 * np.eye(3)) > 0.5


def test_target_points_lie_on_their_spheres_with_the_stated_noise(yard):
    for i in range(yard.n_stations):
        world = _world(yard, i)
        for j, (c, r) in enumerate(zip(yard.centers, yard.radii)):
            on = yard.target[i] == j
            assert on.sum() == yard.hits[i, j]
            if on.sum() < 20:
                continue
            d = np.linalg.norm(world[on] - c, axis=1) - r
            # the range noise acts along the ray, which is close to the normal on the visible cap
            assert 0.4 * yard.range_noise < d.std() < 1.25 * yard.range_noise
            assert abs(d.mean()) < 4 * yard.range_noise / np.sqrt(on.sum()) + 2e-4
            # the cap faces the station
            normals = (world[on] - c) / r
            view = yard.stations[i] - world[on]
            assert np.mean(np.einsum("ij,ij->i", normals, view) > 0) > 0.99


def test_scanner_frame_and_centres_in_scan(yard):
    for i in range(yard.n_stations):
        local = yard.centers_in_scan(i)
        back = local @ yard.poses[i, :3, :3].T + yard.poses[i, :3, 3]
        assert np.allclose(back, yard.centers, atol=1e-12)
        rng_ = np.linalg.norm(yard.scans[i], axis=1)  # the station is the origin of its own scan
        assert rng_.min() > 0.3
        # every target lies 2-9 m from every station
        assert np.all((np.linalg.norm(local, axis=1) > 2) & (np.linalg.norm(local, axis=1) < 9))


def test_scene_holds_the_clutter_and_the_targets_are_seen(yard):
    for i in range(yard.n_stations):
        labels = np.bincount(yard.labels[i], minlength=7)
        assert labels[TARGET] == yard.hits[i].sum()
        assert labels[POLE] > 0 and labels[DECOY] > 0 and labels[CRATE] > 0
        assert len(yard.scans[i]) > 0.99 * 150_000  # a closed hall: every shot hits
    assert (yard.hits > 3).mean() > 0.8  # (150,000 shots: few points per target; visible needs min_hits)
    assert np.array_equal(yard.visible, yard.hits >= yard.min_hits)
    assert abs(yard.decoy[3] - 0.15) < 1e-12 and np.allclose(yard.radii, 0.1)


def test_same_seed_same_scans_and_ring_free():
    a = target_stations(n_stations=1, n_points=20_000, rng=3)
    b = target_stations(n_stations=1, n_points=20_000, rng=3)
    assert np.array_equal(a.scans[0], b.scans[0]) and np.array_equal(a.poses, b.poses)
    # jittered grid: zenith angles do not repeat row by row as in a multi-beam scan
    P = a.scans[0]
    zen = np.degrees(np.arccos(P[:, 2] / np.linalg.norm(P, axis=1)))
    assert np.unique(np.round(zen, 3)).size > 0.5 * len(P)
    assert "stations" in a.summary()


@pytest.mark.parametrize("kwargs", [dict(n_stations=0), dict(n_points=10), dict(decoy_radius=0.1),
                                    dict(range_noise=-1.0), dict(n_stations=13)])
def test_bad_arguments_raise(kwargs):
    with pytest.raises(LabkitError):
        target_stations(**kwargs)
