"""References, distances and the comparison table (labkit.registration.references, .distances, .compare)."""

from __future__ import annotations

import csv
import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from labkit.registration import compare
from labkit.core.errors import EmptyRegionError, LabkitError
from labkit.registration.result import RegistrationResult
from labkit.transforms import make_transform, rotation_from_angles

UTM = np.array([512_345.0, 5_403_210.0, 250.0])


def _grid(n=30, spacing=1.0, offset=np.zeros(3)):
    g = np.arange(n) * spacing
    x, y = np.meshgrid(g, g)
    return np.c_[x.ravel(), y.ravel(), np.zeros(x.size)] + offset


def _result(T, cov=None, names=("tx", "ty", "tz"), origin=np.zeros(3), method="fake", **kw):
    T = np.asarray(T, dtype=float)
    # RegistrationResult.matrix = [R, t + o - R o]; choose t so that it reproduces T
    t = T[:3, 3] - origin + T[:3, :3] @ origin
    cov = np.eye(len(names)) * 1e-6 if cov is None else cov
    return RegistrationResult(t, T[:3, :3], origin, cov, tuple(names), 1.0, 100, 0.5, True, 3, method=method, **kw)


# --------------------------------------------------------------------------- distances
@pytest.mark.parametrize("offset", [np.zeros(3), UTM])
def test_cloud_to_cloud_exact_heights(offset):
    tgt = _grid(offset=offset)
    rng = np.random.default_rng(1)
    h = rng.uniform(-0.4, 0.4, 200)
    idx = rng.choice(len(tgt), 200, replace=False)
    src = tgt[idx] + np.c_[np.zeros((200, 2)), h]  # straight above a grid node, |h| < spacing/2
    np.testing.assert_allclose(compare.cloud_to_cloud(src, tgt), np.abs(h), atol=1e-9)


@pytest.mark.parametrize("offset", [np.zeros(3), UTM])
def test_point_to_plane_on_tilted_plane(offset):
    """Signed distance to a tilted plane equals n.(p - p0) for any xy position (estimated normals)."""
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 20, (3000, 2))
    a, b = 0.3, -0.2  # z = a x + b y
    tgt = np.c_[xy, a * xy[:, 0] + b * xy[:, 1]] + offset
    n = np.array([-a, -b, 1.0]) / np.sqrt(a * a + b * b + 1)
    sxy = rng.uniform(2, 18, (500, 2))
    d_true = rng.normal(0, 0.05, 500)
    src = np.c_[sxy, a * sxy[:, 0] + b * sxy[:, 1]] + offset + d_true[:, None] * n
    d = compare.point_to_plane_distance(src, tgt, k=8)
    np.testing.assert_allclose(d, d_true, atol=1e-7)
    # given normals, and the distance after a transform that undoes a known shift
    shift = np.array([0.0, 0.0, 0.25])
    T = make_transform(translation=-shift)
    d2 = compare.point_to_plane_distance(src + shift, tgt, np.tile(n, (len(tgt), 1)), transform=T)
    np.testing.assert_allclose(d2, d_true, atol=1e-7)


def test_distances_before_after_and_transform_sources():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 30, (4000, 2))
    tgt = np.c_[xy, np.sin(xy[:, 0] / 4) + np.cos(xy[:, 1] / 5)]
    T = make_transform(rotation_from_angles(0, 0, 0.01), [0.1, -0.05, 0.2])
    src = (tgt[::3] - T[:3, 3]) @ T[:3, :3]  # source = T^-1 (target subset)
    ref = compare.truth_reference(T)
    for transform in (T, ref, _result(T)):
        change = compare.distances_before_after(src, tgt, transform, kind="cloud_to_cloud")
        assert change.stats("after")["q95_abs"] < 1e-9 < change.stats("before")["median_abs"]
    assert "median |d|" in change.summary()
    with pytest.raises(LabkitError, match="kind"):
        compare.distances_before_after(src, tgt, T, kind="hausdorff")


def test_distance_bad_input():
    tgt = _grid()
    with pytest.raises(LabkitError, match="4x4"):
        compare.cloud_to_cloud(tgt, tgt, transform=np.eye(3))
    with pytest.raises(LabkitError, match="rotation"):
        compare.cloud_to_cloud(tgt, tgt, transform=np.diag([2.0, 1, 1, 1]))
    with pytest.raises(EmptyRegionError, match="do not overlap"):
        compare.cloud_to_cloud(tgt + [1000, 0, 0], tgt)
    with pytest.raises(LabkitError, match="target_normals"):
        compare.point_to_plane_distance(tgt, tgt, np.zeros((3, 3)))
    with pytest.raises(LabkitError, match="NaN"):
        compare.cloud_to_cloud(np.array([[np.nan, 0, 0]]), tgt)


# --------------------------------------------------------------------------- references
def test_reference_from_targets_matches_stacked_gls():
    """Weighted mean of eq. 1-3 against an independent whitened least-squares solution."""
    rng = np.random.default_rng(4)
    m = 5
    cs = rng.uniform(0, 50, (m, 3)) + UTM
    t_true = np.array([0.12, -0.07, 0.03])
    L = rng.normal(0, 0.003, (m, 3, 3))
    Cs = np.einsum("mij,mkj->mik", L, L) + 1e-6 * np.eye(3)
    Ct = np.array([np.diag(rng.uniform(1e-6, 4e-6, 3)) for _ in range(m)])
    ct = cs + t_true + rng.normal(0, 0.002, (m, 3))
    ref = compare.reference_from_targets(cs, Cs, ct, Ct, region="r1")
    # independent route: stack d = A t + e with A = [I; I; ...], whiten by Cholesky of each C_i
    A_rows, b_rows = [], []
    for i in range(m):
        Li = np.linalg.cholesky(Cs[i] + Ct[i])
        A_rows.append(np.linalg.solve(Li, np.eye(3)))
        b_rows.append(np.linalg.solve(Li, ct[i] - cs[i]))
    A, b = np.vstack(A_rows), np.concatenate(b_rows)
    t_hat, res, *_ = np.linalg.lstsq(A, b, rcond=None)
    Q = np.linalg.inv(A.T @ A)
    s0 = np.sqrt(res[0] / (3 * m - 3))
    np.testing.assert_allclose(ref.translation, t_hat, atol=1e-12)
    np.testing.assert_allclose(ref.sigma0, s0, rtol=1e-9)
    np.testing.assert_allclose(ref.covariance, Q * max(1.0, s0**2), rtol=1e-9)
    assert ref.kind == "targets" and ref.n == m and ref.residuals.shape == (m, 3)


def test_reference_from_pairs_is_targets_with_picking_std():
    rng = np.random.default_rng(5)
    ps = rng.uniform(0, 10, (4, 3))
    pt = ps + [0.5, 0.2, -0.1] + rng.normal(0, 0.01, (4, 3))
    a = compare.reference_from_pairs(ps, pt, std=0.01)
    b = compare.reference_from_targets(ps, np.eye(3) * 1e-4, pt, np.eye(3) * 1e-4)
    np.testing.assert_allclose(a.translation, (pt - ps).mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-12)
    with pytest.raises(LabkitError, match="same targets"):
        compare.reference_from_pairs(ps, pt[:3])
    with pytest.raises(LabkitError, match="std"):
        compare.reference_from_pairs(ps, pt, std=0.0)
    with pytest.raises(LabkitError, match="shape"):
        compare.reference_from_targets(ps, np.eye(2), pt, np.eye(3))


def test_average_references_internal_and_external_accuracy():
    t = np.array([[0.10, 0.20, 0.30], [0.11, 0.19, 0.30], [0.09, 0.21, 0.33], [0.10, 0.20, 0.27]])
    # no stated uncertainty: plain mean, covariance of the mean from the sample covariance
    plain = compare.average_references([compare.manual_reference(x) for x in t])
    np.testing.assert_allclose(plain.translation, t.mean(axis=0), atol=1e-15)
    np.testing.assert_allclose(plain.covariance, np.cov(t.T) / 4, atol=1e-15)
    np.testing.assert_allclose(plain.spread, t.std(axis=0, ddof=1), atol=1e-15)
    # stated 1 mm: the repeats scatter far more -> external accuracy (s0^2 > 1) wins
    tight = compare.average_references([compare.manual_reference(x, 0.001) for x in t])
    s0sq = ((t - t.mean(axis=0)) ** 2).sum() / 1e-6 / (3 * 3)
    np.testing.assert_allclose(tight.sigma0**2, s0sq, rtol=1e-12)
    np.testing.assert_allclose(tight.covariance, np.eye(3) * 1e-6 / 4 * s0sq, rtol=1e-12)
    # stated 1 m: the scatter is small -> internal accuracy sigma^2/n
    loose = compare.average_references([compare.manual_reference(x, 1.0) for x in t])
    np.testing.assert_allclose(loose.covariance, np.eye(3) / 4, rtol=1e-12)
    with pytest.raises(LabkitError, match="at least one"):
        compare.average_references([])


def test_reference_file_round_trip_and_repeats(tmp_path):
    T = make_transform(rotation_from_angles(0.001, 0, 0.002), [0.3, 0.1, -0.2])
    refs = [compare.truth_reference(T, region="r1", case="als-als"),
            compare.manual_reference([0.1, 0.2, 0.3], [0.01, 0.02, 0.03], region="r2", case="als-dim")]
    path = compare.save_references(refs, tmp_path / "refs.json")
    back = compare.load_references(path)
    np.testing.assert_allclose(back[("r1", "als-als")].matrix, T, atol=1e-15)
    np.testing.assert_allclose(back[("r2", "als-dim")].std, [0.01, 0.02, 0.03], rtol=1e-12)
    # a hand-written file with repeats (the registration study's "several times for certainty")
    doc = {"references": [{"region": "r3", "case": "als-als", "repeats": [[0.1, 0, 0], [0.12, 0, 0], [0.14, 0, 0]],
                           "std": 0.005}, {"region": "r4", "matrix": np.eye(4).tolist()}]}
    (tmp_path / "hand.json").write_text(json.dumps(doc))
    hand = compare.load_references(tmp_path / "hand.json")
    r3 = hand[("r3", "als-als")]
    assert r3.n == 3 and r3.kind == "mean of manual"
    np.testing.assert_allclose(r3.translation, [0.12, 0, 0], atol=1e-12)
    np.testing.assert_allclose(r3.spread[0], 0.02, rtol=1e-9)
    assert hand[("r4", "")].kind == "truth"


def test_reference_file_bad_input(tmp_path):
    with pytest.raises(LabkitError, match="not found"):
        compare.load_references(tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(LabkitError, match="not a labkit reference file"):
        compare.load_references(tmp_path / "bad.json")
    (tmp_path / "shape.json").write_text(json.dumps({"references": [{"region": "a", "translation": [1, 2]}]}))
    with pytest.raises(LabkitError, match="entry 0"):
        compare.load_references(tmp_path / "shape.json")
    (tmp_path / "mat.json").write_text(json.dumps({"references": [{"region": "a", "matrix": [[1, 0, 0], [0, 1, 0]]}]}))
    with pytest.raises(LabkitError, match="4x4"):
        compare.load_references(tmp_path / "mat.json")
    with pytest.raises(LabkitError, match="does not exist"):
        compare.save_references([compare.manual_reference([0, 0, 0])], tmp_path / "no" / "r.json")
    with pytest.raises(LabkitError, match="positive semi-definite"):
        compare.manual_reference([0, 0, 0], covariance=-np.eye(3))


# --------------------------------------------------------------------------- the table
def _pair(region, truth, constrained=(True, True, True), n=400, offset=UTM, seed=0):
    rng = np.random.default_rng(seed)
    src = rng.uniform(0, 40, (n, 3)) * [1, 1, 0.1] + offset
    tgt = (src - offset) @ truth[:3, :3].T + truth[:3, 3] + offset  # truth given about `offset`
    T_world = make_transform(truth[:3, :3], truth[:3, 3] + offset - truth[:3, :3] @ offset)
    return SimpleNamespace(source=src, target=tgt, truth=T_world, region=region, constrained=constrained)


def test_table_values_against_known_truth(tmp_path):
    truth = make_transform(rotation_from_angles(0, 0, 0.002), [0.2, -0.1, 0.05])
    pairs = {("flat", "als-als"): _pair("flat", truth, (True, True, True)),
             ("ridge_y", "als-dim"): _pair("ridge_y", truth, (True, False, True), seed=1)}
    err = np.array([0.01, 0.30, -0.002])  # y error is large but y is unconstrained in ridge_y
    cov = np.diag([1e-4, 1e-4, 1e-6])

    def biased(src, tgt):  # the truth plus a known error of the shift, with a stated covariance
        p = next(p for p in pairs.values() if p.source is src)
        return _result(make_transform(p.truth[:3, :3], p.truth[:3, 3] + err), cov, method="biased")

    def rigid_exact(src, tgt):  # exact rigid result with the rotation about a local origin
        p = next(p for p in pairs.values() if p.source is src)
        o = src.mean(axis=0) + [5.0, -3.0, 0.0]
        names = ("rx", "ry", "rz", "tx", "ty", "tz")
        return _result(p.truth, np.eye(6) * 1e-8, names, origin=o, method="rigid")

    def broken(src, tgt):
        raise LabkitError("no correspondences left")

    table = compare.compare_methods(pairs, {"biased": biased, "rigid": rigid_exact, "broken": broken})
    assert len(table) == 6 and table.methods == ("biased", "rigid", "broken")
    for (region, case), pair in pairs.items():
        row = table.select(method="biased", region=region, case=case).rows[0]
        c = pair.source.mean(axis=0)
        ref_shift = pair.truth[:3, :3] @ c + pair.truth[:3, 3] - c
        np.testing.assert_allclose(row.reference, ref_shift, atol=1e-9)
        np.testing.assert_allclose(row.error, err, atol=1e-9)
        mask = np.asarray(pair.constrained)
        e = err[mask]
        chi2 = e @ np.linalg.solve(cov[np.ix_(mask, mask)], e)
        assert row.chi2 == pytest.approx(chi2, rel=1e-6)
        assert row.inside == (chi2 <= stats.chi2.ppf(0.95, mask.sum()))
        assert row.error_norm_constrained == pytest.approx(np.linalg.norm(e), rel=1e-9)
        np.testing.assert_allclose(row.shift_std, np.sqrt(np.diag(cov)), rtol=1e-9)
    flat, ridge = (table.select(method="biased", region=r).rows[0] for r in ("flat", "ridge_y"))
    assert not flat.inside and ridge.inside and ridge.constrained == "XZ" and ridge.dof == 2
    for row in table.select(method="rigid").rows:
        assert np.abs(row.error).max() < 1e-8 and row.rotation_error_arcsec < 1e-3
        assert row.inside and row.dof == len(row.constrained)
    fail = table.select(method="broken").rows[0]
    assert not fail.ok and not fail.inside and "no correspondences" in fail.message
    # CSV round trip and text rendering
    path = table.to_csv(tmp_path / "table.csv")
    with open(path, newline="") as fh:
        recs = list(csv.DictReader(fh))
    assert len(recs) == 6 and tuple(recs[0]) == compare.COLUMNS
    assert float(recs[0]["ex"]) == pytest.approx(err[0], rel=1e-5)
    text = table.text()
    assert "biased" in text and "ridge_y" in text and len(text.splitlines()) == 8
    assert "2/2 ran" in table.summary() and "<table>" in table._repr_html_()


def test_table_uses_given_references_and_rejects_bad_pairs():
    truth = make_transform(translation=[0.2, 0.0, 0.0])
    pair = _pair("a", truth)
    ref = compare.manual_reference([0.25, 0.0, 0.0], 0.02, region="a", case="c")

    def exact(src, tgt):
        return _result(pair.truth, np.eye(3) * 1e-6)

    table = compare.compare_methods({("a", "c"): pair}, {"exact": exact}, references={("a", "c"): ref})
    row = table.rows[0]
    np.testing.assert_allclose(row.error, [-0.05, 0, 0], atol=1e-9)
    assert row.chi2 == pytest.approx(0.05**2 / (0.02**2 + 1e-6), rel=1e-6)
    assert row.inside == (row.chi2 <= stats.chi2.ppf(0.95, 3))
    far = SimpleNamespace(source=pair.source, target=pair.target + [0, 500, 0], truth=pair.truth)
    with pytest.raises(EmptyRegionError, match="region 'far'"):
        compare.compare_methods({"far": far}, {"exact": exact})
    with pytest.raises(LabkitError, match="no reference"):
        compare.compare_methods({"x": SimpleNamespace(source=pair.source, target=pair.target)}, {"exact": exact})
    with pytest.raises(LabkitError, match="methods"):
        compare.compare_methods({"a": pair}, {})
    with pytest.raises(LabkitError, match="source"):
        compare.compare_methods([object()], {"exact": exact})


def test_undetermined_axis_with_infinite_covariance_is_left_out():
    """ICP reports inf/NaN covariance for an undetermined axis; the test runs on the other two."""
    truth = make_transform(translation=[0.2, -0.1, 0.05])
    pair = _pair("ridge", truth, (True, False, True))
    cov = np.array([[1e-6, np.nan, 0.0], [np.nan, np.inf, np.nan], [0.0, np.nan, 4e-6]])
    err = np.array([0.002, 0.1, -0.001])

    def method(src, tgt):
        return _result(make_transform(translation=pair.truth[:3, 3] + err), cov)

    row = compare.compare_methods({"ridge": pair}, {"m": method}).rows[0]
    assert np.isinf(row.sy) and row.sx == pytest.approx(1e-3) and row.dof == 2
    assert row.chi2 == pytest.approx(0.002**2 / 1e-6 + 0.001**2 / 4e-6, rel=1e-6)


def test_synthetic_cases_follow_the_seed():
    cases = compare.synthetic_cases(["xz", "trees_felled"], size=(40.0, 40.0), density=3.0, dim_density=6.0, rng=7)
    assert list(cases) == [("xz", "als-als"), ("trees_felled", "changes"), ("xz", "als-dim")]
    assert cases[("xz", "als-dim")].source.name.startswith("DIM")
    with pytest.raises(LabkitError, match="region"):
        compare.synthetic_cases(["moon"])


def test_plots_return_their_targets(tmp_path):
    import matplotlib.pyplot as plt

    from labkit.plotting import compare as pc
    from labkit.plotting import screenshot
    from labkit.tiles import ShiftField, TileShift, neighbour_test, tile_grid

    rng = np.random.default_rng(8)
    xyz = rng.uniform(0, 20, (500, 3)) + UTM
    d = rng.normal(0, 0.05, 500)
    plotter = pc.plot_distance_cloud(xyz, d)
    img = screenshot(plotter, tmp_path / "cloud.png")
    assert img.ndim == 3 and (tmp_path / "cloud.png").stat().st_size > 0
    plotter.close()
    assert pc.symmetric_limits(d)[0] == -pc.symmetric_limits(d)[1]
    fig, ax = plt.subplots()
    assert pc.plot_distance_map(xyz, d, ax=ax) is ax
    over = pc.plot_distance_overview([("a", xyz, d, d / 2), ("b", xyz, d, d / 4)], title="t")
    assert len(over.axes) == 5  # 2 x 2 maps and one shared colour bar
    with pytest.raises(LabkitError, match="at least one"):
        pc.plot_distance_overview([])
    assert pc.plot_profile([xyz, xyz + 0.1], UTM, UTM + [20, 20, 0], width=2.0, ax=ax) is ax
    assert pc.plot_class_histograms(d, rng.choice([2, 6], 500), ax=ax) is ax
    truth = make_transform(translation=[0.2, -0.1, 0.05])
    pair = _pair("a", truth)
    table = compare.compare_methods({("a", "c"): pair}, {"m": lambda s, t: _result(pair.truth)})
    axes = pc.plot_transformation_components(table.rows)
    assert len(axes) == 3
    assert pc.plot_transformation_arrows(table.rows, exaggerate=50).name == "3d"
    assert pc.plot_error_overview(table, ax=ax) is ax
    grid = tile_grid((0, 0, 199, 99), 100.0)
    field = ShiftField(tuple(TileShift(g, np.array([0.01 * i, 0, 0]), np.eye(3) * 1e-6, np.ones(3, bool), 9, 9, 9,
                                       0.1, True, 0.0, "ok") for i, g in enumerate(grid)), 100.0)
    assert pc.plot_shift_field(field, ax=ax, test=neighbour_test(field)) is ax
    plt.close("all")


def test_standard_methods_and_pair_file(tmp_path):
    io = pytest.importorskip("labkit.io")
    with pytest.raises(LabkitError, match="method"):
        compare.standard_methods(["ndt"])
    with pytest.raises(LabkitError, match="dof"):
        compare.standard_methods(["icp"], dof="affine")
    pair = compare.synthetic_cases(["xyz"], ["als-als"], size=(40.0, 40.0), density=4.0, rng=3)[("xyz", "als-als")]
    io.write_cloud(pair.source, tmp_path / "s.laz")
    io.write_cloud(pair.target, tmp_path / "t.laz")
    (tmp_path / "pairs.json").write_text(json.dumps(
        [{"region": "xyz", "case": "als-als", "source": "s.laz", "target": "t.laz", "constrained": [1, 1, 1]}]))
    pairs = compare.load_pairs(tmp_path / "pairs.json")
    refs = {("xyz", "als-als"): compare.truth_reference(pair.truth)}
    table = compare.compare_methods(pairs, compare.standard_methods(["icp"]), references=refs)
    row = table.rows[0]
    assert row.ok and row.constrained == "XYZ" and row.error_norm < 0.01  # ICP on a well-constrained region
    (tmp_path / "bad.json").write_text(json.dumps([{"region": "xyz", "source": "s.laz"}]))
    with pytest.raises(LabkitError, match="pair 0"):
        compare.load_pairs(tmp_path / "bad.json")
    # a known transformation in the pair file serves as the reference when none is given
    (tmp_path / "truth.json").write_text(json.dumps(
        [{"region": "xyz", "case": "als-als", "source": "s.laz", "target": "t.laz", "truth": pair.truth.tolist()}]))
    with_truth = compare.compare_methods(compare.load_pairs(tmp_path / "truth.json"), compare.standard_methods(["icp"]))
    assert np.allclose(with_truth.rows[0].error, row.error, atol=1e-12)
    (tmp_path / "badtruth.json").write_text(json.dumps(
        [{"region": "xyz", "source": "s.laz", "target": "t.laz", "truth": [[1, 0, 0], [0, 1, 0]]}]))
    with pytest.raises(LabkitError, match="truth"):
        compare.load_pairs(tmp_path / "badtruth.json")


def test_missed_axis_fails_the_test_and_tables_add_up():
    """The data constrain Y, the method calls Y undetermined: not 'inside', whatever the chi-square says."""
    truth = make_transform(translation=[0.2, -0.1, 0.05])
    pair = _pair("town", truth, (True, True, True))
    cov = np.diag([1e-6, np.inf, 1e-6])

    def method(src, tgt):
        return _result(make_transform(translation=pair.truth[:3, 3] + [0.0005, 0.2, 0.0]), cov)

    a = compare.compare_methods({("town", "c"): pair}, {"m": method})
    row = a.rows[0]
    assert row.missed == "Y" and row.dof == 2 and row.chi2 == pytest.approx(0.25, rel=1e-5) and not row.inside
    b = compare.compare_methods({("town", "c"): pair}, {"exact": lambda s, t: _result(pair.truth)})
    both = a + b
    assert both.methods == ("m", "exact") and len(both) == 2
    piv = both.pivot()
    assert piv.splitlines()[1].split()[:4] == ["town", "c", "200.0", "0.0"]
    with pytest.raises(LabkitError, match="metric"):
        both.pivot("nonsense")


def test_icp_on_stable_classes_resists_grown_vegetation():
    """Old town (xy): the low vegetation grew 0.2 m; plain ICP sinks in Z, ICP on ground/roofs does not."""
    pairs = compare.synthetic_cases(["xy"], ["als-als"], size=(30.0, 30.0), density=4.0, rng=7)
    table = compare.compare_methods(pairs, compare.standard_methods(["icp", "icp-classes"]))
    plain, stable = table.rows
    # the default icp selects the stable classes itself (with every class it sank more than 3 cm)
    assert abs(plain.ez) < 0.005 and abs(stable.ez) < 0.005
    assert stable.ok and stable.error_norm_constrained < 0.015
    assert "converged" in table.text().splitlines()[0]
    assert plain.consistent and stable.consistent
    assert "consistent" in table.text().splitlines()[0]


def test_axes_tested_come_from_the_pair_never_from_the_method():
    # a method that declares Y undetermined (inf std, shift off by 0.3 m) on a pair without a
    # 'constrained' entry: every axis is tested and Y counts as missed (the method's own verdict
    # used to remove Y from the test, so the row passed)
    truth = make_transform(np.eye(3), [0.2, -0.1, 0.05])
    bare = _pair("plain", truth)
    del bare.constrained
    known = _pair("ridge_y", truth, (True, False, True), seed=1)
    cov = np.diag([1e-4, np.inf, 1e-6])

    def gives_up_y(src, tgt):
        p = bare if src is bare.source else known
        return _result(make_transform(np.eye(3), p.truth[:3, 3] + [0.0, 0.3, 0.0]), cov, method="gives-up-y")

    table = compare.compare_methods({("plain", "a"): bare, ("ridge_y", "b"): known}, {"m": gives_up_y})
    plain = table.select(region="plain").rows[0]
    assert plain.constrained == "XYZ" and plain.missed == "Y" and not plain.inside
    ridge = table.select(region="ridge_y").rows[0]  # the pair's geometry leaves Y free: not tested
    assert ridge.constrained == "XZ" and ridge.missed == "" and ridge.inside and ridge.dof == 2


def test_consensus_then_icp_recovers_a_large_shift_and_says_where_it_started():
    """consensus+icp (the route for large shifts) on a synthetic pair moved by 0.6 m: the table's
    error against the known truth is small and inside the stated uncertainty, and the message keeps
    the branch and bound's certified gap (the ICP result alone would not say where it started)."""
    pairs = compare.synthetic_cases(["xyz"], ["als-als"], size=(30.0, 30.0), density=6.0,
                                    shift=(0.45, -0.35, 0.2), rng=11)
    table = compare.compare_methods(pairs, compare.standard_methods(["consensus+icp"], max_points=2000))
    row = table.rows[0]
    assert row.ok and row.converged and row.missed == "", row.message
    assert row.error_norm < 0.01 and row.inside, (row.error, row.message)
    assert "started at max_consensus" in row.message and "certified gap" in row.message


def test_disagreement_with_the_start_is_covered_and_agreement_keeps_the_precision():
    """The covariance of consensus+icp when ICP leaves its start: the closed form (scale max(1, T/k), and
    (1 - k/T) d d^T beyond the 3 std level), and a Monte Carlo of the two estimates with the stds of a sparse
    ALS tile (ICP 13, 9, 3 mm; consensus 3.4, 8.3, 0.9 mm; independent errors, the worst case for the cost):
    both right -> no component beyond 3 std and the stated std at most 1.25 times ICP's own on average
    (measured 1.13); ICP 60 mm off in Y (6.7 std of its own) -> at most 4 % of the draws beyond 3 std
    (measured 2 %; without the terms: nearly all)."""
    from scipy.stats import chi2

    from labkit.registration.agreement import disagreement_covariance

    cr, cs = np.diag([13e-3, 9e-3, 3e-3]) ** 2, np.diag([3.4e-3, 8.3e-3, 0.9e-3]) ** 2
    d = np.array([0.004, -0.05, 0.002])
    scale, extra, T, k = disagreement_covariance(d, np.zeros(3), cr, cs)
    T_ref = d @ np.linalg.solve(cr + cs, d)
    assert k == 3 and np.isclose(T, T_ref) and T_ref > chi2.ppf(0.9973, 3) and np.isclose(scale, T_ref / 3)
    assert np.allclose(extra, (1 - 3 / T_ref) * np.outer(d, d))
    scale, extra, T, k = disagreement_covariance(d / 2, np.zeros(3), cr, cs)  # below the level: scaled only
    assert 1 < scale == T / 3 and not extra.any()
    held = np.diag([np.inf, 1e-4, 1e-6])  # a component one estimate leaves free is not tested
    scale, extra, T, k = disagreement_covariance(d, np.zeros(3), held, cs)
    assert k == 2 and extra[0].sum() == 0
    assert np.isclose(T, d[1] ** 2 / (1e-4 + cs[1, 1]) + d[2] ** 2 / (1e-6 + cs[2, 2]))
    rng = np.random.default_rng(5)
    for bias, max_ratio, max_share in ((0.0, 1.25, 0.0), (0.06, np.inf, 0.04)):
        er = rng.multivariate_normal([0, bias, 0], cr, 1000)
        es = rng.multivariate_normal(np.zeros(3), cs, 1000)
        std = []
        for a, b in zip(er, es):
            f, extra, _, _ = disagreement_covariance(a, b, cr, cs)
            std.append(np.sqrt(np.diag(f * cr + extra)))
        std = np.array(std)
        assert (np.abs(er) > 3 * std).mean() <= max_share
        assert 1.0 <= (std.mean(axis=0) / np.sqrt(np.diag(cr))).max() <= max_ratio
    assert (np.abs(er[:, 1]) > 3 * np.sqrt(cr[1, 1])).mean() > 0.9


def _terrain(n, rng, size):
    """Smooth hills (wavelengths of 60-75 m) sampled at ``n`` random places of a square."""
    xy = rng.uniform(0, size, (n, 2))
    z = 3 * np.sin(xy[:, 0] / 10) + 3 * np.cos(xy[:, 1] / 12) + rng.normal(0, 0.02, n)
    return np.column_stack([xy, z])


def test_consensus_then_icp_widens_the_gate_on_sparse_points_and_refuses_clouds_apart():
    """Points about 10 m apart have no pair within ICP's 1 m gate: consensus+icp takes twice the target's
    spacing as the gate (the precision limit stays a tenth of 1 m) and states nothing wrong; two dense clouds
    50 m apart are still refused."""
    from labkit.core.errors import LabkitError

    rng = np.random.default_rng(3)
    method = compare.standard_methods(["consensus+icp"], max_points=2000)["consensus+icp"]
    shift = np.array([0.3, -0.2, 0.1])
    res = method(_terrain(400, rng, 200.0) - shift, _terrain(400, rng, 200.0))
    std = res.translation_std
    stated = np.isfinite(std) & (std < 0.1)
    assert np.all(np.abs(res.translation - shift)[stated] <= 3 * std[stated]), (res.translation, std)
    dense = _terrain(3000, rng, 20.0)
    with pytest.raises(LabkitError):
        method(dense + [50.0, 0, 0], _terrain(3000, rng, 20.0))
