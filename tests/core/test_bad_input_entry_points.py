"""The shared checks of labkit.core.checks at the public entry points: float32 UTM coordinates, a bad rng.

Every case states its exact outcome: the value returned, or the error type and a fragment of its message.
"""

import numpy as np
import pytest

import labkit
from labkit.cloud import PointCloud
from labkit.core.errors import LabkitError
from labkit.io import read_cloud
from labkit.regions import thin_random

UTM = np.array([540_000.0, 5_400_000.0, 300.0])


def _cloud(n=200, seed=0, offset=0.0):
    return np.random.default_rng(seed).uniform(0, 10, (n, 3)) + offset


# --------------------------------------------------------------------------- the shared checks at the entry points
# (the checks themselves, labkit.core.checks: tests/core/test_checks.py)
def test_float32_utm_refused_by_public_functions_and_files(tmp_path):
    pts = (_cloud() + UTM).astype(np.float32)
    with pytest.raises(LabkitError, match="float32"):
        PointCloud(pts)
    with pytest.raises(LabkitError, match="float32"):
        labkit.cloud_to_cloud(pts, pts.astype(np.float64))
    np.save(tmp_path / "utm32.npy", pts)
    with pytest.raises(LabkitError, match="utm32.npy: float32 coordinates up to 5.4e\\+06 m"):
        read_cloud(tmp_path / "utm32.npy")
    local = (pts.astype(np.float64) - UTM).astype(np.float32)
    np.save(tmp_path / "local32.npy", local)
    np.testing.assert_array_equal(read_cloud(tmp_path / "local32.npy").xyz, local.astype(np.float64))


@pytest.mark.parametrize("name, call", [
    ("ransac_sphere", lambda a, b: labkit.ransac_sphere(a, 0.01, radius_range=(0.1, 1.0))),
    ("gauss_helmert_model", lambda a, b: labkit.gauss_helmert_model(a)),
    ("local_pca", lambda a, b: labkit.local_pca(a)),
    ("icp source", lambda a, b: labkit.icp(a, b)),
    ("icp target", lambda a, b: labkit.icp(b, a)),
    ("max_consensus", lambda a, b: labkit.max_consensus(a, b)),
    ("point_to_plane_distance", lambda a, b: labkit.point_to_plane_distance(b, a)),
    ("register_tiles", lambda a, b: labkit.register_tiles(a, b, progress=False)),
])
def test_float32_utm_refused_by_every_entry_point(name, call):
    b = _cloud(500) + UTM
    with pytest.raises(LabkitError, match=r"float32 has steps of 0\.5 m"):
        call(b.astype(np.float32), b)


def test_a_bad_rng_is_refused_by_a_public_function():
    with pytest.raises(LabkitError, match="rng must be a whole number >= 0"):
        thin_random(PointCloud(_cloud()), 0.5, rng=-1)  # the checks of labkit.core.checks: tests/test_checks.py
