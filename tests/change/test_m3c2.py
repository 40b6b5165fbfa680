"""M3C2 change (labkit.m3c2): real references (PDAL, CloudCompare), synthetic truth, Monte Carlo LoD."""

from pathlib import Path

import numpy as np
import pytest

import labkit
from labkit.core.errors import LabkitError
from labkit.change.m3c2 import m3c2, registration_variance
from labkit.transforms import rotation_from_angles

EPOCHS = Path(__file__).resolve().parents[2] / "data" / "real" / "epochs"
PDAL_PARAMS = dict(normal_radius=1.390432, cylinder_radius=2.890432, max_depth=5.5, quantile="normal")  # their z
ROUND = 0.0005 + 1e-9  # the reference files carry 3 decimals


# --------------------------------------------------------------------------- helpers
def _raw_las(name):
    """Raw file coordinates (X/Y metres, Z US survey feet: the frame the references were computed in)."""
    import laspy

    las = laspy.read(EPOCHS / name)
    return np.c_[las.x, las.y, las.z]


@pytest.fixture(scope="module")
def autzen():
    a, b = _raw_las("autzen-bmx-2010.las"), _raw_las("autzen-bmx-2023.las")
    load = lambda f: np.loadtxt(EPOCHS / f, delimiter=",", skiprows=1)  # noqa: E731
    cores = load("autzen-bmx-largersample.txt")[:, :3]
    return a, b, cores, load("autzen-bmx-m3c2.txt"), load("autzen-bmx-cc.txt")


def _plane(rng, n, size, sigma, slope=(0.0, 0.0)):
    xy = rng.uniform(0, size, (n, 2))
    z = slope[0] * xy[:, 0] + slope[1] * xy[:, 1] + rng.normal(0, sigma, n)
    return np.c_[xy, z]


def _grid_cores(size, spacing, slope=(0.0, 0.0), margin=1.0):
    g = np.arange(margin, size - margin + 1e-9, spacing)
    X, Y = np.meshgrid(g, g)
    return np.c_[X.ravel(), Y.ravel(), slope[0] * X.ravel() + slope[1] * Y.ravel()]


# --------------------------------------------------------------------------- real references
def test_autzen_distances_agree_with_pdal(autzen):
    a, b, cores, pdal, _ = autzen
    r = m3c2(a, b, cores, **PDAL_PARAMS)
    dist, unc, sig, sd1, sd2, n1, n2 = pdal[:, 21:28].T
    # the same cores get a value: PDAL leaves 0 with count 0 where a cylinder (or the normal) is empty
    assert np.array_equal(r.valid, (n1 > 0) & (n2 > 0))
    assert r.valid.sum() == 91
    # PDAL drops the first neighbour of a core that coincides with the first point of the epoch
    # (M3C2Filter::filterPoints); core 0 is that point, so PDAL counts one point less there
    assert np.allclose(cores[0], a[0]) and r.count1[0] == n1[0] + 1
    ok = r.valid.copy()
    ok[0] = False
    assert np.abs(r.distance - dist)[ok].max() <= ROUND  # 90 cores: within the files' rounding (< 1 mm)
    assert np.array_equal(r.count1[ok], n1[ok]) and np.array_equal(r.count2, n2)
    # PDAL's spread divides by n (ddof = 0), labkit's by n - 1
    pop = lambda s, n: s * np.sqrt((n - 1) / np.maximum(n, 1))  # noqa: E731
    assert np.abs(pop(r.spread1, r.count1) - sd1)[ok].max() <= ROUND
    assert np.abs(pop(r.spread2, r.count2) - sd2)[ok].max() <= ROUND
    lod_pdal = 1.96 * np.sqrt(pop(r.spread1, r.count1) ** 2 / r.count1 + pop(r.spread2, r.count2) ** 2 / r.count2)
    assert np.abs(lod_pdal - unc)[ok].max() <= ROUND
    assert np.array_equal(r.significant[ok], sig[ok] == 1)


def test_autzen_distances_agree_with_cloudcompare(autzen):
    a, b, cores, _, cc = autzen
    r = m3c2(a, b, cores, **PDAL_PARAMS)
    n1, n2, sd1, sd2, sig, unc, dist = cc[:, 18:25].T
    normal = cc[:, 25:28]
    # CloudCompare has no value where a cylinder of the compared epoch is empty: labkit neither
    assert not r.valid[np.isnan(dist)].any()
    # Where both used the same normal (3 printed decimals) and the same points: the same distance
    angle = np.degrees(np.arccos(np.clip(np.abs(np.einsum("nd,nd->n", r.normals, normal)), 0, 1)))
    both = r.valid & np.isfinite(dist)
    same = both & (angle < 0.3) & (r.count1 == n1) & (r.count2 == n2)
    assert both.sum() == 91 and same.sum() >= 45
    assert np.abs(r.distance - dist)[same].max() < 0.001
    # CloudCompare's normals differ by 0.5-2 deg at the other cores (its own normal fit): still close
    diff = np.abs(r.distance - dist)[both]
    assert np.median(diff) <= ROUND and (diff < 0.002).sum() >= 85
    same = both & (r.count1 == n1) & (r.count2 == n2) & (np.abs(r.distance - dist) < 0.002)
    # CloudCompare's STD is ddof = 0 as PDAL's
    assert np.abs(r.spread1 * np.sqrt((r.count1 - 1) / r.count1) - sd1)[same].max() < 0.003
    assert (r.significant[same] == (sig[same] == 1)).mean() > 0.97


def test_normals_oriented_up_and_result_in_input_frame(autzen):
    a, b, cores, _, _ = autzen
    r = m3c2(a, b, cores, **PDAL_PARAMS)
    ok = np.isfinite(r.normals).all(axis=1)
    assert (r.normals[ok, 2] >= 0).all()
    assert np.allclose(np.linalg.norm(r.normals[ok], axis=1), 1)
    assert np.array_equal(r.corepoints, cores)
    # a shift of the whole scene changes nothing (local origin inside)
    shift = np.array([5e5, 5e6, 100.0])
    r2 = m3c2(a + shift, b + shift, cores + shift, **PDAL_PARAMS)
    assert np.allclose(r2.distance, r.distance, atol=1e-8, equal_nan=True)
    assert np.allclose(r2.corepoints, cores + shift)


# --------------------------------------------------------------------------- synthetic truth
def test_step_change_found_with_right_size_and_significance():
    rng = np.random.default_rng(1)
    size, sigma, step = 20.0, 0.01, 0.05
    ref = _plane(rng, 40_000, size, sigma)
    cmp_ = _plane(rng, 40_000, size, sigma)
    cmp_[cmp_[:, 0] > 10, 2] += step  # the right half rose by 5 cm
    r = m3c2(ref, cmp_, 0.8, normal_radius=0.5, cylinder_radius=0.4, max_depth=0.5)
    x = r.corepoints[:, 0]
    up, flat = x > 10.6, x < 9.4  # away from the step edge by more than the cylinder radius
    assert r.valid.all()
    # distance within 3 standard errors of the truth
    se = r.lod_without_registration / r.z
    assert np.all(np.abs(r.distance[up] - step) < 4 * se[up] + 1e-3)
    assert np.all(np.abs(r.distance[flat]) < 4 * se[flat] + 1e-3)
    assert r.significant[up].all()
    assert r.significant[flat].mean() < 0.12
    assert "significant" in r.summary()


def test_default_corepoints_are_an_even_subsample_of_the_reference():
    rng = np.random.default_rng(2)
    ref = _plane(rng, 20_000, 10.0, 0.005)
    r = m3c2(ref, ref + [0, 0, 0.01], normal_radius=0.5, cylinder_radius=0.5, max_depth=1.0)
    # every core is a reference point, at most one per 0.5 m cube, and cubes are covered
    assert np.isin(r.corepoints.view([("", float)] * 3), ref.view([("", float)] * 3)).all()
    cells = np.floor((r.corepoints - ref.min(axis=0)) / 0.5).astype(int)
    assert len(np.unique(cells, axis=0)) == len(cells)
    assert len(cells) > 0.9 * 20 * 20
    assert np.allclose(np.nanmedian(r.distance), 0.01, atol=1e-3)


def test_multiscale_normals_choose_the_most_planar_radius():
    rng = np.random.default_rng(3)
    ref = _plane(rng, 30_000, 10.0, 0.01, slope=(0.3, 0.0))
    cores = _grid_cores(10.0, 2.0, slope=(0.3, 0.0), margin=2.0)
    r = m3c2(ref, ref, cores, normal_radius=[0.15, 1.0], cylinder_radius=0.5, max_depth=1.0)
    assert (r.normal_radius == 1.0).all()  # on a noisy plane the larger scale is smoother
    truth = np.array([-0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)
    assert np.degrees(np.arccos(r.normals @ truth)).max() < 1.0
    # given normals are used as they are (normalised, oriented up)
    g = m3c2(ref, ref, cores, normal_radius=None, normals=-2 * truth, cylinder_radius=0.5, max_depth=1.0)
    assert np.allclose(g.normals, truth) and np.isnan(g.normal_radius).all()


def test_long_cylinders_cut_into_slabs_count_every_point_once():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-3, 3, (30_000, 3))
    cores = rng.uniform(-1, 1, (50, 3))
    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    r = m3c2(pts, pts, cores, normal_radius=None, normals=nrm, cylinder_radius=0.3, max_depth=1.7,
             orientation=(0, 0, 1))
    # brute force: all points against all cylinders
    n = r.normals
    D = pts[None, :, :] - cores[:, None, :]
    d = np.einsum("cpd,cd->cp", D, n)
    inside = (np.abs(d) <= 1.7) & (np.einsum("cpd,cpd->cp", D, D) - d**2 <= 0.09)
    assert np.array_equal(r.count1, inside.sum(axis=1))
    mean = (d * inside).sum(axis=1) / inside.sum(axis=1)
    assert np.allclose(r.distance, 0, atol=1e-12)
    sd = np.sqrt(((d - mean[:, None]) ** 2 * inside).sum(axis=1) / (inside.sum(axis=1) - 1))
    assert np.allclose(r.spread1, sd, rtol=1e-10)


def test_compiled_grid_and_kdtree_routes_agree():
    """The numba voxel-grid kernels against the kd-tree ball queries (two independent searches)."""
    from labkit.change import search

    rng = np.random.default_rng(12)
    pts = rng.uniform(-5, 5, (40_000, 3)) * [1, 1, 0.3]
    cores = rng.uniform(-4, 4, (500, 3)) * [1, 1, 0.3]
    for radius in (0.3, 1.1):
        n_c, v_c = search.pca_normals(pts, cores, radius, use_numba=True)
        n_t, v_t = search.pca_normals(pts, cores, radius, use_numba=False)
        assert np.allclose(np.abs(np.einsum("nd,nd->n", n_c, n_t)), 1, atol=1e-9)
        assert np.allclose(v_c, v_t, rtol=1e-8)
    nrm = search.orient(n_c, np.array([0, 0, 1.0]))
    for r, h in ((0.5, 0.3), (0.4, 2.5)):
        c = search.cylinder_stats(pts, cores, nrm, r, h, use_numba=True)
        t = search.cylinder_stats(pts, cores, nrm, r, h, use_numba=False)
        assert np.array_equal(c[0], t[0]) and c[0].min() > 2
        assert np.allclose(c[1], t[1], atol=1e-12) and np.allclose(c[2], t[2], rtol=1e-9)


# --------------------------------------------------------------------------- level of detection
def _no_change_epochs(rng, sigma=0.01, slope=(0.0, 0.0)):
    return _plane(rng, 25_000, 20.0, sigma, slope), _plane(rng, 25_000, 20.0, sigma, slope)


@pytest.mark.parametrize("radius", [0.4, 0.6])  # about 30 and 70 points per cylinder
def test_lod_false_alarm_rate_without_change_is_alpha(radius):
    """Monte Carlo: no change, alpha = 0.05 -> about 5 % of independent cores flagged (binomial bounds).

    With the normal quantile z = 1.96, 5.7 % were flagged with about 30 points per cylinder (d / se
    follows a Student t there); the default Student t quantile holds alpha.
    """
    rng = np.random.default_rng(5)
    cores = _grid_cores(20.0, 2.0)  # 100 cores, cylinders 1.2 m apart: independent
    flags, dists, se = [], [], []
    for _ in range(20):
        ref, cmp_ = _no_change_epochs(rng)
        r = m3c2(ref, cmp_, cores, normal_radius=1.0, cylinder_radius=radius, max_depth=0.5)
        flags.append(r.significant)
        dists.append(r.distance)
        se.append(r.lod / r.z)
    flags = np.concatenate(flags)
    n = len(flags)  # 2000 core tests
    rate = flags.mean()
    bound = 3 * np.sqrt(0.05 * 0.95 / n)
    assert 0.05 - bound < rate <= 0.05 + bound / 3, (rate, bound)  # at most alpha (within 1 sigma)
    # the stated standard error of the distance against the Monte Carlo spread
    ratio = np.std(np.concatenate(dists)) / np.sqrt(np.mean(np.concatenate(se) ** 2))
    assert 0.8 < ratio < 1.25


def test_registration_covariance_widens_lod_by_exactly_the_projected_term():
    rng = np.random.default_rng(6)
    ref, cmp_ = _no_change_epochs(rng, slope=(1.0, 0.0))
    cores = _grid_cores(20.0, 2.0, slope=(1.0, 0.0), margin=2.0)
    Sigma = np.diag([0.02, 0.001, 0.004]) ** 2
    plain = m3c2(ref, cmp_, cores, normal_radius=1.0, cylinder_radius=0.4, max_depth=0.5)
    reg = m3c2(ref, cmp_, cores, normal_radius=1.0, cylinder_radius=0.4, max_depth=0.5,
               registration_covariance=Sigma)
    term = np.einsum("mi,ij,mj->m", plain.normals, Sigma, plain.normals)
    assert np.allclose(reg.registration_variance, term, rtol=1e-12)
    assert np.allclose(reg.lod**2 - plain.lod**2, reg.z**2 * term, rtol=1e-9)
    assert np.array_equal(reg.distance, plain.distance)
    # a 45 degree slope feels half of the X variance; flat ground would feel only Z
    assert np.allclose(term, 0.5 * (0.02**2 + 0.004**2), rtol=0.01)


def test_lod_with_registration_covariance_holds_over_random_shifts():
    """Monte Carlo: each repetition shifts the compared epoch by a draw from Sigma; 5 % false alarms."""
    rng = np.random.default_rng(7)
    cores = _grid_cores(20.0, 2.0, slope=(1.0, 0.0), margin=1.0)
    Sigma = np.array([[0.02**2, 0.5 * 0.02 * 0.01, 0], [0.5 * 0.02 * 0.01, 0.01**2, 0], [0, 0, 0.003**2]])
    rates, plain_rates = [], []
    for _ in range(60):
        ref, cmp_ = _no_change_epochs(rng, sigma=0.005, slope=(1.0, 0.0))
        cmp_ = cmp_ + rng.multivariate_normal(np.zeros(3), Sigma)
        r = m3c2(ref, cmp_, cores, normal_radius=1.0, cylinder_radius=0.4, max_depth=0.5,
                 registration_covariance=Sigma)
        rates.append(r.significant.mean())
        plain_rates.append((np.abs(r.distance) > r.lod_without_registration).mean())
    rates = np.array(rates)
    # cores share one shift per repetition: the uncertainty of the rate comes from the repetitions
    se = max(rates.std(ddof=1), 0.01) / np.sqrt(len(rates))
    assert abs(rates.mean() - 0.05) < 3 * se + 0.01, (rates.mean(), se)
    assert np.mean(plain_rates) > 0.3  # ignoring the registration: far too many false alarms


def test_rigid_registration_term_matches_monte_carlo():
    """g^T Sigma g (eq. 6) against the spread of random rigid transformations along the normal."""
    rng = np.random.default_rng(8)
    names = ("rx", "ry", "rz", "tx", "ty", "tz")
    sd = np.array([2e-4, 3e-4, 5e-4, 0.01, 0.02, 0.005])
    C = np.diag(sd**2)
    C[2, 3] = C[3, 2] = 0.5 * sd[2] * sd[3]

    class Reg:  # the fields m3c2 reads from a RegistrationResult
        parameter_names, covariance, origin = names, C, np.array([100.0, 200.0, 10.0])

    pts = np.array([[130.0, 170.0, 12.0], [100.0, 200.0, 10.0], [80.0, 260.0, 5.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.0, 0.8]])
    var = registration_variance(Reg, pts, nrm)
    draws = rng.multivariate_normal(np.zeros(6), C, size=20_000)
    moved = np.stack([(rotation_from_angles(*w[:3]) @ (pts - Reg.origin).T).T + Reg.origin + w[3:] for w in draws])
    along = np.einsum("spd,pd->sp", moved - pts, nrm)
    ratio = along.std(axis=0) / np.sqrt(var)
    assert np.all((ratio > 0.95) & (ratio < 1.05)), ratio


def test_undetermined_registration_direction_gives_infinite_lod_where_it_matters():
    C = np.diag([np.inf, 1e-4, 1e-4])

    class Reg:
        parameter_names, covariance, origin = ("tx", "ty", "tz"), C, np.zeros(3)

    var = registration_variance(Reg, np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]]))
    assert var[0] == pytest.approx(1e-4) and np.isinf(var[1])
    # a held rotation about Z: infinite unless a prior is given; then the lever arm times the prior
    Cr = np.diag([1e-8, 1e-8, np.inf, 1e-4, 1e-4, 1e-4])

    class Rigid:
        parameter_names, covariance, origin = ("rx", "ry", "rz", "tx", "ty", "tz"), Cr, np.zeros(3)

    p, n = np.array([[10.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])  # rz moves this point along Y
    assert np.isinf(registration_variance(Rigid, p, n)[0])
    held = registration_variance(Rigid, p, n, {"rz": 1e-3})[0]
    assert held == pytest.approx(1e-4 + (10 * 1e-3) ** 2)
    with pytest.raises(LabkitError, match="held_std"):
        registration_variance(Rigid, p, n, {"rq": 1e-3})


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "change, match",
    [
        (dict(reference=np.empty((0, 3))), "reference"),
        (dict(compared=np.full((10, 3), np.nan)), "NaN"),
        (dict(cylinder_radius=0.0), "cylinder_radius"),
        (dict(max_depth=-1.0), "max_depth"),
        (dict(normal_radius=[0.5, -1.0]), "normal_radius"),
        (dict(registration_covariance=np.diag([1.0, -1.0, 1.0])), "positive semi-definite"),
        (dict(registration_covariance=np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]])), "symmetric"),
        (dict(registration_covariance=np.eye(2)), "shape"),
        (dict(normals=np.ones((5, 3))), "normals"),
        (dict(alpha=1.5), "alpha"),
        (dict(min_points=1), "min_points"),
    ],
)
def test_bad_input_raises_a_clear_labkit_error(change, match):
    rng = np.random.default_rng(9)
    args = dict(reference=_plane(rng, 500, 5.0, 0.01), compared=_plane(rng, 500, 5.0, 0.01), normal_radius=0.5,
                cylinder_radius=0.5, max_depth=1.0)
    args.update(change)
    with pytest.raises(LabkitError, match=match):
        m3c2(**args)


def test_inputs_not_modified_and_exported():
    rng = np.random.default_rng(10)
    ref, cmp_ = _plane(rng, 2000, 5.0, 0.01), _plane(rng, 2000, 5.0, 0.01)
    ref0, cmp0 = ref.copy(), cmp_.copy()
    r = labkit.m3c2(ref, cmp_, normal_radius=0.5, cylinder_radius=0.5, max_depth=1.0)
    assert np.array_equal(ref, ref0) and np.array_equal(cmp_, cmp0)
    cloud = r.to_cloud()
    assert set(cloud.attributes) >= {"distance", "lod", "significant"}
    assert "M3C2" in repr(r) and "<table>" in r._repr_html_()


def test_progress_bar_and_summary_without_any_distance(capsys):
    rng = np.random.default_rng(13)
    ref = _plane(rng, 3000, 5.0, 0.01)
    r = m3c2(ref, ref + [0, 0, 0.02], normal_radius=0.5, cylinder_radius=0.5, max_depth=1.0, progress=True)
    assert "m3c2" in capsys.readouterr().err
    assert abs(np.nanmedian(r.distance) - 0.02) < 1e-4  # the vertical shift along nearly vertical normals
    # the compared epoch lies elsewhere: no cylinder holds a point of it, every distance is NaN
    far = m3c2(ref, ref + [100.0, 0, 0], normal_radius=0.5, cylinder_radius=0.5, max_depth=1.0)
    assert not far.valid.any() and not far.significant.any() and (far.count2 == 0).all()
    assert "0 of 0 core points significant" in far.summary()


def test_agrees_with_py4dgeo():
    """Peer check (py4dgeo is optional: ``pip install py4dgeo``, the ``bench`` extra)."""
    py4dgeo = pytest.importorskip("py4dgeo")
    rng = np.random.default_rng(11)
    ref = _plane(rng, 30_000, 20.0, 0.02, slope=(0.2, 0.1))
    cmp_ = _plane(rng, 30_000, 20.0, 0.02, slope=(0.2, 0.1)) + [0, 0, 0.03]
    cores = ref[::50]
    # max_depth 1.2 = 3 slabs of py4dgeo's cylinder search; with an even number of slabs py4dgeo
    # counts a point lying on the boundary between two slabs twice, which hits the core point itself
    r = m3c2(ref, cmp_, cores, normal_radius=1.0, cylinder_radius=0.5, max_depth=1.2)
    algo = py4dgeo.M3C2(epochs=(py4dgeo.Epoch(ref), py4dgeo.Epoch(cmp_)), corepoints=cores, normal_radii=(1.0,),
                        cyl_radius=0.5, max_distance=1.2)
    dist, unc = algo.run()
    assert np.array_equal(np.isfinite(dist), r.valid)
    assert np.array_equal(unc["num_samples1"], r.count1) and np.array_equal(unc["num_samples2"], r.count2)
    assert np.abs(r.distance - dist)[r.valid].max() < 1e-9
    assert np.abs(r.spread1 - unc["spread1"])[r.valid].max() < 1e-9
    assert np.allclose(r.lod[r.valid] * 1.96 / r.z, unc["lodetection"][r.valid], rtol=1e-9)


# --------------------------------------------------------------------------- command line
@pytest.fixture(scope="module")
def epoch_files(tmp_path_factory):
    from labkit.cloud import PointCloud
    from labkit.io import write_cloud
    from labkit.synthetic import als_epochs

    d = tmp_path_factory.mktemp("change_data")
    pair = als_epochs("xyz", size=(30.0, 30.0), density=4.0, rng=12)
    write_cloud(pair.target, d / "als_2014.laz")
    write_cloud(pair.source, d / "als_2016.laz")
    return d, pair


def test_cli_change_with_register_icp_writes_cores_csv_and_png(epoch_files, tmp_path, capsys):
    import laspy

    from labkit.cli.main import main
    from labkit.io import read_cloud

    d, pair = epoch_files
    out = tmp_path / "out"
    args = ["change", str(d / "als_2014.laz"), str(d / "als_2016.laz"), "--register", "icp", "--dof", "rigid",
            "--normal-radius", "1.0", "2.0", "--cylinder-radius", "1.0", "--max-depth", "3.0", "--out", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "Registration result" in text and "M3C2 change" in text
    stem = "als_2014_als_2016_m3c2"
    assert sorted(p.name for p in out.iterdir()) == [f"{stem}.csv", f"{stem}.laz", f"{stem}.png", f"{stem}.tif"]
    assert (out / f"{stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    las = laspy.read(out / f"{stem}.laz")
    assert {"distance", "lod", "significant"} <= set(las.point_format.extra_dimension_names)
    # the files hold what the library computes on the registered pair
    from labkit.registration.compare import standard_methods

    ref, cmp_ = read_cloud(d / "als_2014.laz"), read_cloud(d / "als_2016.laz")
    reg = standard_methods(["icp"], dof="rigid", rng=0)["icp"](cmp_, ref)
    held = {n: np.radians(0.02) for n, v in zip(reg.parameter_names, np.diag(reg.covariance)) if np.isinf(v)}
    # a rotation the registration left undetermined enters the LoD with the stated prior, and the CLI says so
    held_rot = [n for n in held if n.startswith("r")]
    if held_rot:
        assert f"undetermined {', '.join(held_rot)}: prior std 0.02 deg" in text
    else:
        assert "prior std" not in text
    r = m3c2(ref, reg.apply(cmp_.xyz), normal_radius=[1.0, 2.0], cylinder_radius=1.0, max_depth=3.0,
             registration_covariance=reg, held_std=held)
    csv_cloud = read_cloud(out / f"{stem}.csv")
    assert len(csv_cloud) == len(r.distance) == len(las.points)
    assert np.allclose(np.asarray(las["distance"]), r.distance, atol=1e-9, equal_nan=True)
    assert np.array_equal(np.asarray(las["significant"]).astype(bool), r.significant)
    assert np.allclose(csv_cloud["lod"], r.lod, rtol=1e-12, equal_nan=True)
    assert np.isfinite(r.registration_variance[r.valid]).all() and (r.registration_variance[r.valid] > 0).all()
    assert r.significant.sum() > 0.05 * r.valid.sum()  # the scene has real change (vegetation, buildings)


def test_cli_change_with_registration_json_and_all_or_nothing(epoch_files, tmp_path, capsys):
    from labkit.change.m3c2 import load_registration, save_registration
    from labkit.cli.main import main
    from labkit.registration.compare import standard_methods

    d, pair = epoch_files
    reg = standard_methods(["icp"], dof="rigid", rng=0)["icp"](pair.source, pair.target)
    path = save_registration(reg, tmp_path / "reg.json")
    back = load_registration(path)
    assert np.allclose(back.matrix, reg.matrix) and back.parameter_names == tuple(reg.parameter_names)
    pts, nrm = pair.target.xyz[:5], np.tile([0.6, 0.0, 0.8], (5, 1))
    assert np.allclose(registration_variance(back, pts, nrm), registration_variance(reg, pts, nrm), rtol=1e-12)
    out = tmp_path / "out"
    base = ["change", str(d / "als_2014.laz"), str(d / "als_2016.laz"), "--normal-radius", "1.5",
            "--cylinder-radius", "1.0", "--max-depth", "3.0", "--out", str(out)]
    assert main(base + ["--registration", str(path)]) == 0
    assert len(list(out.iterdir())) == 4  # LAS/LAZ, CSV, PNG, GeoTIFF
    # a bare 3x3 covariance that is not positive semi-definite: clear error, nothing written
    bad = tmp_path / "bad.json"
    bad.write_text("[[1e-4, 0, 0], [0, -1e-4, 0], [0, 0, 1e-4]]")
    out2 = tmp_path / "out2"
    assert main(base[:-1] + [str(out2), "--registration", str(bad)]) == 2
    assert "positive semi-definite" in capsys.readouterr().err
    assert not out2.exists() or list(out2.iterdir()) == []


def test_quantiles_are_scipy_stats_quantiles():
    """z of every core is scipy.stats' Student t quantile at the Welch-Satterthwaite dof (eq. 5)."""
    from scipy import stats

    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 10, (4000, 2))
    ref = np.c_[xy, rng.normal(0, 0.01, len(xy))]
    cmp_ = np.c_[xy[::-1], 0.03 + rng.normal(0, 0.02, len(xy))]
    r = m3c2(ref, cmp_, ref[::100], normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0, alpha=0.05)
    a, b = r.spread1**2 / r.count1, r.spread2**2 / r.count2
    dof = (a + b) ** 2 / (a**2 / (r.count1 - 1) + b**2 / (r.count2 - 1))
    ok = np.isfinite(r.z)
    assert ok.sum() > 20
    np.testing.assert_allclose(r.z[ok], stats.t.ppf(0.975, dof[ok]), rtol=1e-12)
    z = m3c2(ref, cmp_, ref[::100], normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0, quantile="normal").z
    np.testing.assert_allclose(z[np.isfinite(z)], stats.norm.ppf(0.975), rtol=1e-14)


def test_importing_change_does_not_load_scipy_stats():
    """`labkit change` starts without scipy.stats (about a second of imports)."""
    import subprocess
    import sys

    code = "import sys, labkit.change; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
