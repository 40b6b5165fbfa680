"""find_spheres: every target in a scan, nothing else (synthetic TLS panoramas and real multi-beam scans)."""

import json

import numpy as np
import pytest

from labkit import LabkitError, find_spheres
from labkit.synthetic import multibeam_room, target_stations

RANGE = (0.09, 0.11)


@pytest.fixture(scope="module")
def yard():
    return target_stations(n_stations=1, n_points=1_000_000, rng=11)


@pytest.fixture(scope="module")
def spheres(yard):
    return find_spheres(yard.scans[0], RANGE, station=np.zeros(3), rng=0)


def _match(spheres, truth):
    """Distance of each found centre to its nearest true centre, and of each true centre to its nearest find."""
    F = np.array([s.center for s in spheres]).reshape(-1, 3)
    d = np.linalg.norm(F[:, None] - truth[None], axis=2)
    return d.min(axis=1), d.min(axis=0), d.argmin(axis=1)


@pytest.mark.slow
def test_every_visible_target_within_5_mm_and_nothing_else(yard, spheres):
    truth = yard.centers_in_scan(0)
    to_truth, _, which = _match(spheres, truth)
    assert np.all(to_truth < 0.005)  # no decoy ball, pole, crate corner or wall piece
    assert len(set(which.tolist())) == len(spheres)  # no target twice
    assert set(np.flatnonzero(yard.visible[0])) <= set(which.tolist())
    assert len(spheres) >= 5
    for s in spheres:
        assert abs(s.radius - 0.1) < 0.003
        assert s.covariance.shape == (4, 4)


def test_stated_precision_matches_the_errors(yard, spheres):
    truth = yard.centers_in_scan(0)
    _, _, which = _match(spheres, truth)
    z = [np.abs(s.center - truth[j]) / np.sqrt(np.diag(s.covariance)[:3]) for s, j in zip(spheres, which)]
    z = np.concatenate(z)
    assert np.all(z < 4.5)
    assert 0.4 < np.sqrt(np.mean(z**2)) < 2.0  # about 1 for honest standard deviations (18 components)


def test_ordered_by_quality_and_inliers_on_the_sphere(yard, spheres):
    std = [np.sqrt(np.trace(s.covariance[:3, :3])) for s in spheres]
    assert std == sorted(std)
    for s in spheres:
        assert s.inliers.shape == (len(yard.scans[0]),)
        on = yard.target[0][s.inliers]
        assert np.mean(on >= 0) > 0.95  # the inliers are target points
        assert len(np.unique(on[on >= 0])) == 1


@pytest.mark.slow
def test_without_station_and_max_spheres():
    small = target_stations(n_stations=1, n_points=400_000, rng=5)
    found = find_spheres(small.scans[0], RANGE, rng=1, max_spheres=3)
    assert len(found) == 3
    to_truth, _, _ = _match(found, small.centers_in_scan(0))
    assert np.all(to_truth < 0.005)


@pytest.mark.slow
def test_a_ball_of_another_size_and_a_thick_pole_are_not_spheres(yard):
    # the decoy (r = 0.15 m) is found when its size is asked for, never as a target
    decoy = (yard.decoy[:3] - yard.poses[0, :3, 3]) @ yard.poses[0, :3, :3]
    found = find_spheres(yard.scans[0], (0.135, 0.165), station=np.zeros(3), rng=0)
    assert len(found) == 1 and np.linalg.norm(found[0].center - decoy) < 0.005


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 3])
def test_sequential_scheme_on_a_multibeam_scan(seed):
    scene = multibeam_room(rng=seed)  # rings: neighbourhoods hold one scan line, normals say little
    found = find_spheres(scene.points, (0.13, 0.37), station=scene.station, rng=0)
    assert len(found) == 1
    assert np.linalg.norm(found[0].center - scene.sphere[:3]) < 0.02
    empty = multibeam_room(rng=seed, sphere=False)
    assert find_spheres(empty.points, (0.13, 0.37), station=empty.station, rng=0) == ()


@pytest.mark.slow
def test_real_multibeam_scans_reference_sphere_and_no_other(realdata):
    folder = realdata / "spheres"
    if not (folder / "reference.json").is_file():
        pytest.skip("spheres/ not in the real data")
    for name, ref in json.loads((folder / "reference.json").read_text()).items():
        points = np.loadtxt(folder / name)
        found = find_spheres(points, (0.25, 0.35), station=np.zeros(3), rng=0)
        assert len(found) == 1, name
        assert np.linalg.norm(found[0].center - ref["center"]) < 0.01, name
        assert abs(found[0].radius - ref["radius"]) < 0.01, name


@pytest.mark.parametrize("kwargs", [dict(radius_range=None), dict(radius_range=(0.2, 0.1)),
                                    dict(threshold=-1.0), dict(proposals="hough"), dict(max_spheres=0),
                                    dict(station=(0, 0))])
def test_bad_input_raises(kwargs):
    args = dict(radius_range=RANGE) | kwargs
    points = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(LabkitError):
        find_spheres(points, args.pop("radius_range"), **args)


@pytest.mark.slow
def test_utm_coordinates_give_the_same_spheres():
    small = target_stations(n_stations=1, n_points=300_000, rng=2)
    offset = np.array([512_345.0, 5_401_234.0, 312.0])
    local = find_spheres(small.scans[0], RANGE, station=np.zeros(3), rng=0)
    utm = find_spheres(small.scans[0] + offset, RANGE, station=offset, rng=0)
    assert len(local) == len(utm) >= 3
    a = np.array(sorted(s.center.tolist() for s in local))
    b = np.array(sorted((s.center - offset).tolist() for s in utm))
    assert np.abs(a - b).max() < 1e-3
