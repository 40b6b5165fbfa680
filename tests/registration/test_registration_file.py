"""The registration file: save/load round trip, refusals, the inverse, and the command line's use of it."""

import json

import numpy as np
import pytest

from labkit import LabkitError, RegistrationFile, load_registration, save_registration
from labkit.change.m3c2 import registration_variance
from labkit.registration import RegistrationResult
from labkit.transforms import make_transform, rotation_from_angles

def _rigid_result():
    names = ("rx", "ry", "rz", "tx", "ty", "tz")
    A = np.random.default_rng(1).normal(size=(6, 6))
    D = np.diag([2e-5, 2e-5, 5e-5, 2e-3, 2e-3, 1e-3])  # rad, m: correlated, positive definite
    cov = D @ (A @ A.T / 6) @ D
    return RegistrationResult(translation=np.array([0.2, -0.1, 0.05]),
                              rotation=rotation_from_angles(*np.radians([0.01, -0.02, 0.3])),
                              origin=np.array([194490.0, 259240.0, 130.0]), covariance=cov, parameter_names=names,
                              sigma0=1.0, n_used=100, share_used=1.0, converged=True, iterations=3, method="icp")


def test_round_trip_of_a_registration_result(tmp_path):
    reg = _rigid_result()
    path = save_registration(tmp_path / "registration.json", reg, crs="EPSG:2992",
                             inputs={"source": "2023.las", "target": "2010.las"})
    back = load_registration(path)
    assert isinstance(back, RegistrationFile)
    assert np.array_equal(back.matrix, reg.matrix) and np.array_equal(back.covariance, reg.covariance)
    assert back.parameter_names == reg.parameter_names and np.array_equal(back.origin, reg.origin)
    assert back.crs == "EPSG:2992" and dict(back.inputs) == {"source": "2023.las", "target": "2010.las"}
    assert back.method == "icp" and back.units == "m"
    pts = np.array([[194500.0, 259250.0, 131.0], [194480.0, 259230.0, 129.0]])
    assert np.allclose(back.apply(pts), reg.apply(pts), atol=1e-9)
    nrm = np.array([[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
    assert np.allclose(registration_variance(back, pts, nrm), registration_variance(reg, pts, nrm), rtol=1e-12)
    with pytest.raises(AttributeError):  # frozen
        back.crs = "EPSG:1"


def test_undetermined_parameters_round_trip_as_inf(tmp_path):
    path = save_registration(tmp_path / "r.json", matrix=make_transform(np.eye(3), [0, 0, -0.3]),
                             covariance=np.diag([np.inf, np.inf, 0.066**2]), parameter_names=("tx", "ty", "tz"))
    doc = json.loads(path.read_text())
    assert doc["covariance"][0][0] is None and doc["covariance"][2][2] == pytest.approx(0.066**2)
    back = load_registration(path)
    assert np.isinf(back.std[:2]).all() and back.std[2] == pytest.approx(0.066)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(sigma=1.0), "unknown keys: sigma"),
    (lambda d: d.pop("origin"), "missing keys: origin"),
    (lambda d: d.update(format_version=1), "not a labkit registration file"),
    (lambda d: d.update(matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]), "4x4"),
    (lambda d: d.update(matrix=[[2, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "rotation"),
    (lambda d: d.update(parameter_names=["tx", "ty", "shear"]), "parameter_names"),
    (lambda d: d.update(covariance=[[1e-4, 0], [0, 1e-4]]), "3 x 3"),
    (lambda d: d.update(covariance=[[1e-4, 0, 0], [0, -1e-4, 0], [0, 0, 1e-4]]), "positive semi-definite"),
    (lambda d: d.update(units="ft"), "units"),
])
def test_malformed_files_are_refused(tmp_path, edit, message):
    path = save_registration(tmp_path / "r.json", matrix=np.eye(4), covariance=np.eye(3) * 1e-6,
                             parameter_names=("tx", "ty", "tz"))
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(LabkitError, match=message):
        load_registration(path)


def test_save_refuses_incomplete_input(tmp_path):
    with pytest.raises(LabkitError, match="needs a registration result"):
        save_registration(tmp_path / "r.json", matrix=np.eye(4))
    assert not (tmp_path / "r.json").exists()


def test_inverse_maps_back_and_its_lod_term_matches_monte_carlo(tmp_path):
    """The inverse's stated covariance, propagated along a normal, against a Monte Carlo of inverted transforms."""
    reg = _rigid_result()
    path = save_registration(tmp_path / "r.json", reg, inputs={"source": "a", "target": "b"})
    fwd = load_registration(path)
    inv = fwd.inverse()
    pts = np.array([[194510.0, 259260.0, 135.0], [194470.0, 259220.0, 126.0]])
    assert np.allclose(inv.apply(fwd.apply(pts)), pts, atol=1e-9)
    assert dict(inv.inputs) == {"source": "b", "target": "a"}
    nrm = np.array([[0.0, 0.0, 1.0], [0.8, 0.0, 0.6]])
    stated = np.sqrt(registration_variance(inv, pts, nrm))
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(np.zeros(6), reg.covariance, 4000)
    moved = []
    for d in draws:  # a forward transformation drawn about its estimate, inverted exactly
        R = rotation_from_angles(*d[:3]) @ reg.rotation
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, reg.translation + d[3:] + reg.origin - R @ reg.origin
        moved.append(np.linalg.solve(M, np.c_[pts, np.ones(2)].T).T[:, :3])
    spread = np.std(np.einsum("kij,ij->ki", np.array(moved), nrm), axis=0, ddof=1)
    assert np.all((spread / stated > 0.9) & (spread / stated < 1.1)), (spread, stated)


def test_change_orients_the_file_by_its_inputs(tmp_path):
    from labkit.cli.change import _maps_reference_onto_compared as inverted

    a, b = str(tmp_path / "2014" / "tile.laz"), str(tmp_path / "2016" / "tile.laz")
    assert inverted({"source": a, "target": b}, a, b) and not inverted({"source": b, "target": a}, a, b)
    assert not inverted({}, a, b)
    # moved elsewhere: by file name, unless the names cannot tell the roles apart
    assert inverted({"source": "/old/x_2014.laz", "target": "/old/x_2016.laz"}, "x_2014.laz", "x_2016.laz")
    assert not inverted({"source": "/old/tile.laz", "target": "/other/tile.laz"}, a, b)


def test_a_scale_parameter_enters_the_lod_term_as_monte_carlo_says(tmp_path):
    """A similarity registration (targets): the stated n^T Sigma n with a scale against drawn transformations."""
    names = ("tx", "ty", "tz", "scale")
    cov = np.diag([2e-3, 2e-3, 3e-3, 20e-6]) ** 2
    o = np.array([1000.0, 2000.0, 100.0])
    path = save_registration(tmp_path / "r.json", matrix=np.eye(4), covariance=cov, parameter_names=names, origin=o,
                             method="targets")
    reg = load_registration(path)
    pts = o + np.array([[150.0, -80.0, 5.0], [-200.0, 10.0, -3.0]])
    nrm = np.array([[0.6, 0.0, 0.8], [0.0, 1.0, 0.0]])
    stated = np.sqrt(registration_variance(reg, pts, nrm))
    d = np.random.default_rng(3).multivariate_normal(np.zeros(4), cov, 20000)
    moved = (1 + d[:, 3, None, None]) * (pts - o)[None] + o + d[:, None, :3]  # p' = (1 + s)(p - o) + o + t
    spread = np.std(np.einsum("kij,ij->ki", moved - pts, nrm), axis=0, ddof=1)
    assert np.all((spread / stated > 0.95) & (spread / stated < 1.05)), (spread, stated)


def test_icp_carries_the_inputs_crs_into_its_result_and_the_file(tmp_path):
    from labkit import PointCloud
    from labkit.registration import icp
    from labkit.synthetic import wavy_pair

    src, tgt = wavy_pair(300, noise=0.001, shift=[-0.02, 0.01, -0.03])
    res = icp(PointCloud(src, crs="EPSG:25832"), PointCloud(tgt, crs="EPSG:25832"), dof="translation")
    assert res.crs == "EPSG:25832" and "25832" in res.summary()
    assert load_registration(save_registration(tmp_path / "r.json", res)).crs == "EPSG:25832"
    assert icp(src, tgt, dof="translation").crs is None  # arrays state no CRS
