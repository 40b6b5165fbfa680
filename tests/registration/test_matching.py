"""Tests of labkit.registration.match: sampling, gating rules, weights, the table, bad input."""

import numpy as np
import pytest

from labkit import PointCloud
from labkit.core.errors import LabkitError
from labkit.registration import Correspondences, match
from labkit.registration.matching.match import MIN_SIGMA, RULES

ORIGIN = np.array([600000.0, 5400000.0, 300.0])


def plane(n, rng, half=10.0, sigma=0.01, z0=0.0):
    xy = rng.uniform(-half, half, (n, 2))
    return np.c_[xy, z0 + rng.normal(0, sigma, n)] + ORIGIN


def counts(corr):
    return dict(corr.rejected)


def test_table_and_counts_are_consistent():
    rng = np.random.default_rng(1)
    tgt, src = plane(4000, rng), plane(3000, rng, z0=0.05)
    corr = match(src, tgt)
    assert isinstance(corr, Correspondences)
    tab = corr.table()
    assert tab.dtype.names[:4] == ("source_index", "target_index", "dx", "dy")
    assert len(tab) == len(src)
    assert sum(c for r, c in corr.rejected if r != "sampling") + corr.n_accepted == len(corr)
    ok = corr.accepted
    # dx, dy, dz are target minus source, in the caller's frame
    d = tgt[corr.target_index[ok]] - src[corr.source_index[ok]]
    np.testing.assert_allclose(np.c_[tab["dx"], tab["dy"], tab["dz"]][ok], d, atol=1e-9)
    # point-to-plane distance of a horizontal plane = dz (about -5 cm)
    assert abs(np.median(corr.plane_distance[ok]) + 0.05) < 0.005
    assert "accepted" in corr.summary() and "<table>" in corr._repr_html_()
    assert set(tab["rule"]) <= set(RULES)


def test_inputs_are_not_modified_and_arrays_or_clouds_work():
    rng = np.random.default_rng(2)
    tgt, src = plane(2000, rng), plane(1500, rng)
    keep = src.copy()
    a = match(src, tgt, rng=0)
    b = match(PointCloud(src), PointCloud(tgt), rng=0)
    np.testing.assert_array_equal(src, keep)
    np.testing.assert_array_equal(a.target_index, b.target_index)


def test_distance_gate_rejects_a_block_far_above():
    rng = np.random.default_rng(3)
    tgt = plane(4000, rng)
    src = np.vstack([plane(2000, rng), plane(500, rng, half=3, z0=3.0)])  # a new roof 3 m up
    corr = match(src, tgt, max_distance=1.0)
    assert counts(corr)["distance"] >= 490
    assert corr.rule[2000:].tolist().count(RULES.index("distance")) >= 490
    loose = match(src, tgt, max_distance=None)
    assert counts(loose)["distance"] == 0


def test_normal_angle_gate_rejects_a_ramp():
    rng = np.random.default_rng(4)
    tgt = plane(6000, rng)
    xy = rng.uniform(-2, 2, (800, 2))
    ramp = np.c_[xy, 0.2 + 0.15 * xy[:, 0]] + ORIGIN  # 8.5 deg is fine ...
    steep = np.c_[xy, 0.5 + 0.25 * (xy[:, 0] + 2)] + ORIGIN + [5, 5, 0]  # ... 14 deg: rejected below 10 deg
    src = np.vstack([plane(3000, rng), ramp, steep])
    corr = match(src, tgt, max_angle_deg=10.0, max_distance=2.0)
    rule = corr.rule
    assert np.mean(rule[3800:] == RULES.index("normal_angle")) > 0.8
    assert np.mean(rule[3000:3800] == RULES.index("normal_angle")) < 0.2
    assert np.nanmedian(corr.normal_angle[3800:]) == pytest.approx(14.0, abs=2.0)


def test_class_rule_on_both_sides():
    rng = np.random.default_rng(5)
    t_xyz, s_xyz = plane(3000, rng), plane(3000, rng)
    t_cls = np.where(t_xyz[:, 0] - ORIGIN[0] > 5, 5, 2)  # vegetation in the east of the target
    s_cls = np.where(s_xyz[:, 1] - ORIGIN[1] > 5, 3, 2)  # low vegetation in the north of the source
    src = PointCloud(s_xyz, {"classification": s_cls})
    tgt = PointCloud(t_xyz, {"classification": t_cls})
    corr = match(src, tgt, classes=(2,), unique=False)
    rejected = corr.rule == RULES.index("class")
    expected = (s_cls != 2) | (t_cls[np.maximum(corr.target_index, 0)] != 2)
    assert np.mean(rejected == expected) > 0.99
    assert corr.accepted.sum() == pytest.approx(3000 * 0.75 * 0.75, rel=0.1)


@pytest.mark.parametrize("side", ["source", "target"])
@pytest.mark.parametrize("plain", [True, False])
def test_class_rule_without_classification_raises(side, plain):
    # the rule used to be skipped silently on a cloud without classes: all its points passed
    rng = np.random.default_rng(5)
    xyz = {"source": plane(500, rng), "target": plane(500, rng)}
    clouds = {k: PointCloud(v, {"classification": np.full(len(v), 2)}) for k, v in xyz.items()}
    clouds[side] = xyz[side] if plain else PointCloud(xyz[side], {"intensity": np.ones(len(xyz[side]))})
    with pytest.raises(LabkitError, match=f"the {side} cloud is a (plain array|PointCloud without)"):
        match(clouds["source"], clouds["target"], classes=(2,))
    assert match(clouds["source"], clouds["target"]).n_accepted > 0  # fine without the class rule


def test_noise_rule_and_noise_weights():
    rng = np.random.default_rng(6)
    tgt = plane(6000, rng, sigma=0.01)
    quiet = plane(4000, rng, sigma=0.01)
    noisy = plane(4000, rng, sigma=0.15)
    quiet, noisy = quiet[quiet[:, 0] < ORIGIN[0] - 1], noisy[noisy[:, 0] > ORIGIN[0] + 1]
    src = np.vstack([quiet, noisy])  # west quiet, east noisy (a 2 m gap between)
    q = len(quiet)
    corr = match(src, tgt, max_noise=0.05, max_distance=2.0, max_angle_deg=None)
    assert np.mean(corr.rule[q:] == RULES.index("noise")) > 0.9
    assert np.mean(corr.rule[:q] == RULES.index("noise")) < 0.01
    w = match(src, tgt, max_distance=2.0, max_angle_deg=None, unique=False).weight
    # p = 1 / (sigma_s^2 + sigma_t^2): about (0.15^2 + 0.01^2) / (2 * 0.01^2) ~ 100 times smaller
    ratio = np.median(w[:q]) / np.median(w[q:][w[q:] > 0])
    assert 30 < ratio < 300


def test_class_sigma_sets_the_weights():
    rng = np.random.default_rng(7)
    t_xyz, s_xyz = plane(3000, rng), plane(3000, rng)
    s_cls = np.where(s_xyz[:, 0] - ORIGIN[0] > 0, 6, 5)
    corr = match(
        PointCloud(s_xyz, {"classification": s_cls}), t_xyz, class_sigma={6: 0.02, 5: 0.2}, noise_weighting=False
    )
    ok = corr.accepted
    w6, w5 = np.median(corr.weight[ok & (s_cls == 6)]), np.median(corr.weight[ok & (s_cls == 5)])
    floor = MIN_SIGMA**2  # the target has no classes: only the floor of its sigma counts
    assert w6 == pytest.approx(1 / (0.02**2 + floor))
    assert w5 == pytest.approx(1 / (0.2**2 + floor))
    unit = match(s_xyz, t_xyz, noise_weighting=False)
    np.testing.assert_allclose(unit.weight[unit.accepted], 1.0)


def test_unique_keeps_one_source_point_per_target_point():
    rng = np.random.default_rng(8)
    tgt, src = plane(1000, rng), plane(4000, rng)  # source four times denser
    corr = match(src, tgt)
    j = corr.target_index[corr.accepted]
    assert len(np.unique(j)) == len(j)
    assert counts(corr)["duplicate"] > 2000
    # the one kept is the closest of its group
    all_rows = match(src, tgt, unique=False)
    d_all = all_rows.distance
    best = np.full(len(tgt), np.inf)
    np.minimum.at(best, all_rows.target_index[all_rows.accepted], d_all[all_rows.accepted])
    np.testing.assert_allclose(corr.distance[corr.accepted], best[j])


def test_sampling_methods():
    rng = np.random.default_rng(9)
    floor = plane(20000, rng, half=20)
    yz = rng.uniform(0, 3, (600, 2))
    wall = np.c_[np.full(600, 2.0), yz[:, 0], yz[:, 1]] + ORIGIN  # a rare normal direction
    src = np.vstack([floor, wall])
    tgt = np.vstack([plane(20000, rng, half=20), wall + rng.normal(0, 0.01, wall.shape)])
    rand = match(src, tgt, sample=("random", 2000), rng=1)
    ns = match(src, tgt, sample=("normal_space", 2000), rng=1)
    assert len(rand) == 2000 and abs(len(ns) - 2000) <= 200
    share = lambda c: np.mean(c.source_index >= 20000)  # noqa: E731
    assert share(rand) < 0.06 and share(ns) > 0.12  # normal-space sampling keeps the wall
    assert counts(ns)["sampling"] == len(src) - len(ns)
    vox = match(src, tgt, sample=("voxel", 1.0), rng=1)
    keys = np.floor(src[vox.source_index] / 1.0)
    assert len(np.unique(keys, axis=0)) == len(vox)


def test_given_normals_are_used():
    rng = np.random.default_rng(10)
    tgt, src = plane(2000, rng), plane(2000, rng)
    tilted = np.tile([0.0, np.sin(0.2), np.cos(0.2)], (len(tgt), 1))
    corr = match(src, tgt, target_normals=tilted, max_angle_deg=None)
    np.testing.assert_allclose(corr.target_normal[corr.accepted], tilted[: corr.n_accepted], atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(sample=("octree", 10)), "sample method"),
        (dict(k=2), "k must"),
        (dict(max_distance=-1), "max_distance"),
        (dict(max_angle_deg=0), "max_angle_deg"),
        (dict(target_normals=np.zeros((5, 3))), "target_normals"),
    ],
)
def test_bad_arguments(kwargs, message):
    rng = np.random.default_rng(11)
    tgt, src = plane(100, rng), plane(100, rng)
    with pytest.raises(LabkitError, match=message):
        match(src, tgt, **kwargs)


def test_bad_points():
    rng = np.random.default_rng(12)
    tgt, src = plane(100, rng), plane(100, rng)
    src[3, 1] = np.nan
    with pytest.raises(LabkitError, match="NaN"):
        match(src, tgt)
    with pytest.raises(LabkitError, match=r"\(n, 3\)"):
        match(tgt[:, :2], tgt)


# ----------------------------------------------------------------------------- local surface model


def _sparse_hills(rng, side=160.0, density=0.75, amplitude=20.0, length=15.0, sigma=0.03):
    """Sparse ALS-like ground (0.75 pts/m^2, 40 m relief) on z = A sin(x/L) cos(y/L); points and curvature."""
    n = int(side * side * density)
    xy = rng.uniform(0, side, (n, 2))
    z = amplitude * np.sin(xy[:, 0] / length) * np.cos(xy[:, 1] / length)
    laplacian = -2.0 / length**2 * z  # z_xx + z_yy of the analytic surface
    return np.column_stack([xy, z + rng.normal(0, sigma, n)]), laplacian


def test_quadric_surface_removes_curvature_bias_and_inflated_noise_on_sparse_hills():
    """Independent route: the analytic surface. Two samplings of it, no shift between them.

    The plane's residuals n . (q - p) carry the sagitta between p and q (positive on
    hilltops, negative in hollows) and its noise sigma_n holds the curvature; the
    quadric's residuals are centred on both and its noise is the measurement noise
    (projected on the normal: at most 0.03 m, as the slopes reach 53 deg).
    """
    sigma = 0.03
    target, _ = _sparse_hills(np.random.default_rng(11), sigma=sigma)
    source, lap = _sparse_hills(np.random.default_rng(12), sigma=sigma)
    out = {}
    for surface in ("plane", "quadric"):
        c = match(source, target, max_distance=5.0, max_angle_deg=None, surface=surface)
        ok = c.accepted
        r = np.einsum("ij,ij->i", c.target_normal[ok], c.d[ok])
        curv = lap[c.source_index[ok]]
        top, hollow = curv < -0.05, curv > 0.05
        noise_t = 1.0 / np.sqrt(c.weight[ok])  # sqrt(sigma_s^2 + sigma_t^2)
        s0 = np.mean(r**2 * c.weight[ok])  # variance factor: 1 when the stated sigmas match the residuals
        out[surface] = (r[top].mean(), r[hollow].mean(), np.median(noise_t), np.sqrt(np.mean(r**2)), s0)
    top_p, hollow_p, noise_p, rms_p, s0_p = out["plane"]
    top_q, hollow_q, noise_q, rms_q, s0_q = out["quadric"]
    assert top_p > 0.004 and hollow_p < -0.004  # the plane's sagitta bias
    assert abs(top_q) < 0.0015 and abs(hollow_q) < 0.0015
    assert rms_q < rms_p
    assert noise_p > 2.5 * sigma and s0_p < 0.3  # curvature taken for noise: weights 3x too pessimistic
    assert 0.5 < s0_q < 1.25  # stated sigmas within 1.0-1.4x of the actual residual spread


def test_quadric_surface_equals_plane_on_a_plane():
    rng = np.random.default_rng(13)
    xy = rng.uniform(0, 30, (6000, 2))
    z = 0.2 * xy[:, 0] - 0.1 * xy[:, 1]
    target = np.column_stack([xy, z + rng.normal(0, 0.005, len(z))])
    source = target[::3] + [0.0, 0.0, 0.02]
    n_true = np.array([-0.2, 0.1, 1.0]) / np.linalg.norm([-0.2, 0.1, 1.0])
    for surface in ("plane", "quadric"):
        c = match(source, target, max_distance=1.0, surface=surface)
        ok = c.accepted
        r = np.einsum("ij,ij->i", c.target_normal[ok], c.d[ok])
        assert abs(np.median(r) - (-0.02 * n_true[2])) < 0.002  # the 2 cm lift, seen along the normal
        assert np.degrees(np.arccos(np.median(c.target_normal[ok] @ n_true))) < 1.5


def test_quadric_needs_enough_neighbours():
    pts = np.random.default_rng(0).normal(size=(200, 3))
    with pytest.raises(LabkitError, match="k must be at least 10"):
        match(pts, pts, surface="quadric", k=8)
    with pytest.raises(LabkitError, match="surface must be one of"):
        match(pts, pts, surface="cubic")


def test_auto_surface_chooses_by_neighbourhood_size():
    # sparse ALS-like ground (k-neighbourhoods metres wide): quadric; the same ground 400 times
    # denser (a few centimetres wide, as TLS): plane, whose sagitta is negligible there
    sparse, _ = _sparse_hills(np.random.default_rng(14), side=60.0)
    assert match(sparse[::2], sparse[1::2], surface="auto").settings["surface"] == "quadric"
    dense = sparse[:2000] * 0.02
    assert match(dense[::2], dense[1::2], surface="auto", max_distance=None).settings["surface"] == "plane"



def test_quadric_duplicates_are_chosen_by_distance_not_by_residual():
    # one source point per target point, the nearest one: the same choice as the plane's. Keeping
    # the one with the smallest quadric offset selected on the residual itself (stated covariance
    # 1.3-1.65 times too small in Monte Carlo runs)
    target, _ = _sparse_hills(np.random.default_rng(15), side=80.0)
    source, _ = _sparse_hills(np.random.default_rng(16), side=80.0)
    dup = RULES.index("duplicate")
    rules = [match(source, target, max_angle_deg=None, max_distance=5.0, surface=s).rule for s in ("plane", "quadric")]
    assert (rules[0] == dup).sum() > 100
    np.testing.assert_array_equal(rules[0] == dup, rules[1] == dup)
