"""Registration on real airborne scans: right, or honest about what it does not know.

Two disjoint random halves of one real ALS file are two epochs with a known truth: the source half
is moved by a shift of 0.2-0.8 m. With their defaults, ``icp``, ``max_consensus`` and
``consensus+icp`` must never state a component with a standard deviation below 0.1 m that is more
than 3 of those standard deviations off, and ``icp`` must be right within 10 cm (or call the
component undetermined) for at least three of four shifts. The full sweep (every file x four shifts
x three methods, beside Open3D) is benchmarks/bench_trust.py; here every file is checked with
four ICP shifts and one consensus shift. Files in feet are converted by ``read_cloud``; the
geographic file is refused by it. Skipped where ``../shared/realdata`` is absent.
"""

from __future__ import annotations

import numpy as np
import pytest

from labkit import read_cloud
from labkit.core.errors import LabkitError
from labkit.registration import icp, max_consensus

SHIFTS = np.array([[0.15, -0.12, 0.05], [-0.25, 0.30, -0.10], [0.42, 0.30, 0.12], [-0.50, -0.55, 0.20]])
RIGHT, CONFIDENT, SIGMAS = 0.10, 0.10, 3.0
#: the real airborne files (one of each kind: sparse, forest, urban, roofs, strips, UAV, feet, epochs)
FILES = [
    "als/4_6_crop.las", "als/MixedConifer.laz", "als/append-bug.laz", "als/faceraster_numerical_imprecision.laz",
    "als/file_with_both_wkt_and_geotiff_vlrs.las", "als/fullwave.laz", "als/interesting.las",
    "als/las_with_several_extra_byte_bloc.laz", "als/sample_c.las", "als/warsaw_small.las",
    "epochs/autzen-bmx-2010.las", "epochs/autzen-bmx-2023.las",
]  # fmt: skip
#: keep a random share of the largest file (700,000 points) so that the test stays short
KEEP = {"als/las_with_several_extra_byte_bloc.laz": 0.1}


def _halves(path, seed=0):
    cloud = read_cloud(path)
    rng = np.random.default_rng(seed)
    pick = rng.random(len(cloud.xyz)) < KEEP.get(f"{path.parent.name}/{path.name}", 1.0)
    half = rng.random(len(cloud.xyz)) < 0.5
    return cloud.subset(pick & half), cloud.subset(pick & ~half)


def _verdict(res, truth):
    """'ok' (every stated component within 10 cm), 'miss' (off but honest) or 'WRONG' (confident and wrong)."""
    err, std = res.translation - truth, res.translation_std
    stated = np.isfinite(std) & (std < CONFIDENT)
    if np.any(stated & (np.abs(err) > SIGMAS * std)):
        return "WRONG"
    return "ok" if np.all(~stated | (np.abs(err) <= RIGHT)) else "miss"


def _run(method, *args, **kw):
    """The result, or None when the method refuses with a LabkitError (no pairs within the gate: nothing stated)."""
    try:
        return method(*args, **kw)
    except LabkitError as exc:
        assert "correspondences" in str(exc) or "overlap" in str(exc), exc  # a reason, not a crash
        return None


@pytest.mark.slow
@pytest.mark.parametrize("name", FILES)
def test_defaults_are_right_or_honest_on_real_halves(realdata, name):
    path = realdata / name
    if not path.is_file():
        pytest.skip(f"{name} absent")
    tgt, src0 = _halves(path)
    verdicts = []
    for s in SHIFTS:
        res = _run(icp, src0.with_xyz(src0.xyz - s), tgt, rng=0)
        verdicts.append("refused" if res is None else _verdict(res, s))
        if res is not None:  # which points were used and why
            assert res.selection is not None and str(res.selection) in res.message
    assert "WRONG" not in verdicts, verdicts
    assert sum(v in ("ok", "refused") for v in verdicts) >= 3, verdicts


@pytest.mark.slow
@pytest.mark.parametrize("name", FILES)
def test_consensus_routes_are_not_confidently_wrong(realdata, name):
    path = realdata / name
    if not path.is_file():
        pytest.skip(f"{name} absent")
    tgt, src0 = _halves(path)
    s = SHIFTS[FILES.index(name) % len(SHIFTS)]
    src = src0.with_xyz(src0.xyz - s)
    # maximum consensus (a smaller box budget than the default keeps the test short; both count work, so
    # the result does not depend on the load of the machine), then ICP from there
    mc = max_consensus(src, tgt, max_boxes=1000)
    refined = _run(icp, src, tgt, robust="tukey", initial=mc.matrix, rng=0)  # labkit register consensus+icp
    assert refined is None or _verdict(refined, s) != "WRONG", (refined.translation - s, refined.translation_std)
    assert _verdict(mc, s) != "WRONG", (mc.translation - s, mc.translation_std)


def test_geographic_file_is_refused(realdata):
    path = realdata / "als" / "epsg_4326.las"
    if not path.is_file():
        pytest.skip("epsg_4326.las absent")
    with pytest.raises(LabkitError, match="degrees"):
        read_cloud(path)


def test_classified_and_unclassified_selections_say_why(realdata):
    path = realdata / "als" / "4_6_crop.las"  # ground (2) and unclassified (1): crowns and shrubs
    if not path.is_file():
        pytest.skip("4_6_crop.las absent")
    tgt, src = _halves(path)
    res = icp(src.with_xyz(src.xyz - SHIFTS[1]), tgt, rng=0)
    assert res.selection.rule == "stable classes" and res.selection.classes == (2,)
    assert "left out" in res.summary() and "ground" in res.summary()
    bare = icp(src.xyz - SHIFTS[1], tgt.xyz, rng=0)  # no classes: the vegetation goes by its local noise
    assert bare.selection.rule == "surface points" and bare.selection.used_source < 0.6 * len(src.xyz)
    assert _verdict(bare, SHIFTS[1]) == "ok"


def test_autzen_epochs_icp_converges_and_agrees_with_max_consensus(realdata):
    a, b = realdata / "epochs" / "autzen-bmx-2010.las", realdata / "epochs" / "autzen-bmx-2023.las"
    if not (a.is_file() and b.is_file()):
        pytest.skip("Autzen epochs absent")
    src, tgt = read_cloud(a), read_cloud(b)  # Z in US survey feet, converted by read_cloud
    ri = icp(src, tgt, rng=0)
    rc = max_consensus(src, tgt, max_boxes=1000)
    assert ri.converged, ri.message
    combined = np.hypot(ri.translation_std, rc.translation_std)
    assert np.all(np.isfinite(combined)), (ri.translation_std, rc.translation_std)  # X, Y and Z stated by both
    assert np.all(np.abs(ri.translation - rc.translation) <= SIGMAS * combined)
    # real change between the epochs: the spatial blocks disagree, and their spread is in the stated covariance
    assert ri.consistency is not None and not ri.consistency.agree
    assert np.all(ri.consistency.std_ratio[np.isfinite(ri.consistency.std_ratio)] >= 1.0)


def test_left_out_classes_are_tested_against_the_shift(realdata):
    path = realdata / "als" / "warsaw_small.las"  # ground and buildings used; vegetation and class 0 left out
    if not path.is_file():
        pytest.skip("warsaw_small.las absent")
    tgt, src = _halves(path)
    res = icp(src.with_xyz(src.xyz - SHIFTS[0]), tgt, rng=0)
    codes = [c.code for c in res.class_checks]
    big = [c for c in np.unique(src.attributes["classification"]) if c not in res.selection.classes
           and min((src.attributes["classification"] == c).sum(), (tgt.attributes["classification"] == c).sum()) >= 50]
    assert sorted(codes) == sorted(big) and 5 in codes  # every class left out with 50 points in both halves
    assert "Other classes against the shift" in res.summary()
    # moved vegetation is reported as moved: the same halves with class 5 lifted by 0.3 m in the source
    cls = src.attributes["classification"]
    lifted = src.with_xyz(src.xyz - SHIFTS[0] + np.where(cls[:, None] == 5, [0.0, 0.0, 0.3], 0.0))
    res = icp(lifted, tgt, rng=0)
    veg = {c.code: c for c in res.class_checks}[5]
    assert not veg.agree and abs(veg.offset[2] + 0.3) < 3 * veg.offset_std[2], str(veg)
    assert "5 moved" in res.message


def test_identical_copy_never_states_zero_precision(realdata):
    path = realdata / "als" / "faceraster_numerical_imprecision.laz"
    if not path.is_file():
        pytest.skip("faceraster_numerical_imprecision.laz absent")
    cloud = read_cloud(path)
    res = icp(cloud, cloud, rng=0)
    std = res.translation_std
    assert np.all(std[np.isfinite(std)] > 0), std
    assert np.allclose(res.translation, 0, atol=1e-9)


def test_stated_std_matches_the_spread_over_random_halves(realdata):
    """Monte Carlo over random halves of the sparse Autzen ground (0.5 pts/m^2, few pairs): the errors in
    units of the stated std have an rms of about 1 (neither confident nor inflated)."""
    paths = [realdata / "epochs" / f"autzen-bmx-{y}.las" for y in (2010, 2023)]
    if not all(p.is_file() for p in paths):
        pytest.skip("Autzen epochs absent")
    for path in paths:
        cloud = read_cloud(path)
        z = []
        for seed in range(16):
            rng = np.random.default_rng(seed)
            half = rng.random(len(cloud.xyz)) < 0.5
            s = SHIFTS[seed % 4]
            res = icp(cloud.subset(~half).with_xyz(cloud.xyz[~half] - s), cloud.subset(half), rng=0)
            std = res.translation_std
            z.extend(((res.translation - s) / std)[np.isfinite(std)])
        rms = float(np.sqrt(np.mean(np.square(z))))
        assert 0.8 <= rms <= 1.25, (path.name, rms, len(z))
        assert np.max(np.abs(z)) <= 3.0, (path.name, np.max(np.abs(z)))


@pytest.mark.slow
def test_max_consensus_std_against_random_halves(realdata):
    """Monte Carlo over 16 random splits of the UAV scan (fullwave.laz): stated std against the spread.

    The two fits of the symmetric estimate differ by twice the bias of the k-neighbourhood planes
    (about (-2, 8) mm); their mean is still 1.3, 1.5 mm off on average in X, Y, a remainder no
    jackknife shows. With the jackknife alone the rms of error / stated std was 1.74, 1.90 in X, Y
    and one split of 16 (seed 5) 5 std off; with half the measured bias as the std of the
    remainder: 1.10, 0.74 (0.79 in Z), largest |error| / std 2.7.
    """
    path = realdata / "als" / "fullwave.laz"
    if not path.is_file():
        pytest.skip("fullwave.laz absent")
    cloud = read_cloud(path)
    s = SHIFTS[1]
    z = []
    for seed in range(16):
        rng = np.random.default_rng(seed)
        half = rng.random(len(cloud.xyz)) < 0.5
        res = max_consensus(cloud.subset(~half).with_xyz(cloud.xyz[~half] - s), cloud.subset(half))
        assert res.degeneracy.well_posed and "symmetric" in res.message, res.message
        z.append((res.translation - s) / res.translation_std)
    z = np.array(z)
    rms_xy = float(np.sqrt(np.mean(z[:, :2] ** 2)))
    assert 0.8 <= rms_xy <= 1.25, rms_xy
    assert np.abs(z).max() <= 3.5, np.abs(z).max(axis=0)
    assert float(np.sqrt(np.mean(z[:, 2] ** 2))) <= 1.25, z[:, 2]


@pytest.mark.slow
def test_consensus_icp_widens_the_gate_on_sparse_data_instead_of_refusing(realdata):
    from labkit.registration.compare import standard_methods

    path = realdata / "als" / "interesting.las"  # about 19 m between points: no pair within 1 m
    if not path.is_file():
        pytest.skip("interesting.las absent")
    tgt, src = _halves(path)
    s = SHIFTS[0]
    res = standard_methods(("consensus+icp",), rng=0)["consensus+icp"](src.with_xyz(src.xyz - s), tgt)
    assert _verdict(res, s) != "WRONG", (res.translation - s, res.translation_std)


def _right(res, truth):
    """Every component within 10 cm of the truth, whether stated or reported undetermined."""
    return res is not None and bool(np.all(np.abs(res.translation - truth) <= RIGHT))


#: where the data carry the shift, the values (not only the stated ones) land within 10 cm in three of
#: four shifts: also along the ridges of sample_c's roofs (outlines, the consensus hill's centre) and
#: across warsaw_small's 1,500 points a half. interesting.las is left out: 19-27 m between points
#: (NN in one half), so no method can place a half to 10 cm and every one reports X and Y undetermined.
DETERMINED = [f for f in FILES if f != "als/interesting.las"]


@pytest.mark.slow
@pytest.mark.parametrize("name", DETERMINED)
def test_icp_values_right_within_10_cm(realdata, name):
    path = realdata / name
    if not path.is_file():
        pytest.skip(f"{name} absent")
    tgt, src0 = _halves(path)
    right = [_right(icp(src0.with_xyz(src0.xyz - s), tgt, rng=0), s) for s in SHIFTS]
    assert sum(right) >= 3, right


@pytest.mark.slow
def test_max_consensus_values_right_along_the_ridges(realdata):
    """sample_c's parallel ridges leave one horizontal direction to the ends of the roofs; the centre of
    the consensus hill along it lands within 10 cm (the argmax was 0.2-0.6 m off). Not asserted on
    warsaw_small: its 1,500 points a half leave the hill's centre 0.1-0.3 m off in some splits."""
    path = realdata / "als" / "sample_c.las"
    if not path.is_file():
        pytest.skip("sample_c.las absent")
    tgt, src0 = _halves(path)
    results = [(max_consensus(src0.with_xyz(src0.xyz - s), tgt), s) for s in SHIFTS]
    assert all(not r.degeneracy.well_posed or np.any(r.translation_std[:2] >= CONFIDENT) for r, _ in results)
    assert sum(_right(r, s) for r, s in results) >= 3, [r.translation - s for r, s in results]


def test_sparse_file_states_no_horizontal_shift(realdata):
    path = realdata / "als" / "interesting.las"
    if not path.is_file():
        pytest.skip("interesting.las absent")
    tgt, src = _halves(path)
    res = max_consensus(src.with_xyz(src.xyz - SHIFTS[0]), tgt, max_boxes=1000)
    assert np.all(res.translation_std[:2] >= CONFIDENT), res.translation_std
