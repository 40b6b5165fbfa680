"""ICP's matching step (labkit.registration.matching.matcher): the grouped nearest-neighbour search changes no result."""

import numpy as np
import pytest

from labkit.neighbours.kdtree import KDTree
from labkit.registration import icp
from labkit.synthetic import wavy_surface


def test_icp_with_grouped_search_equals_the_per_point_search(monkeypatch):
    """The whole ICP (every source point, rigid) bitwise as with one tree walk per source point,
    on coordinates rounded to the millimetre (as in LAS files: equally near target points occur)."""
    rng = np.random.default_rng(5)
    target = np.round(wavy_surface(20_000, rng, noise=0.002), 3)
    source = np.round(wavy_surface(8_000, rng, noise=0.002), 3) - [0.021, -0.013, 0.008]
    kw = dict(dof="rigid", sample=None, rng=0, covariance="formal", consistency_alpha=None)
    new = icp(source, target, **kw)

    def per_point(self, q, starts, distance_upper_bound=np.inf, workers=1, warm=None, memory=None):
        return self.query(q, k=1, distance_upper_bound=distance_upper_bound, workers=workers)

    monkeypatch.setattr(KDTree, "nearest_in_groups", per_point)
    old = icp(source, target, **kw)
    assert new.iterations == old.iterations > 1
    assert np.array_equal(new.matrix, old.matrix) and np.array_equal(new.covariance, old.covariance)
    assert np.array_equal(new.correspondences.target_index, old.correspondences.target_index)


def test_compiled_matching_steps_equal_their_numpy_route(monkeypatch):
    """ICP (rigid, every source point, plane and quadric) bitwise as with the numpy forms of the compiled steps
    of the matcher: the cached normals and noise scattered to the pairs, the foot points on the quadrics and
    their normals, the angle between the normals and the distances of the duplicate rule."""
    from labkit.registration import consistency
    from labkit.registration.closest_point import covariance
    from labkit.registration.matching import local_surface, matcher

    rng = np.random.default_rng(7)
    target = np.round(wavy_surface(20_000, rng, noise=0.002), 3)
    source = np.round(wavy_surface(8_000, rng, noise=0.002), 3) - [0.021, -0.013, 0.008]
    for surface in ("plane", "quadric"):
        kw = dict(dof="rigid", sample=None, rng=0, surface=surface, select="all")
        new = icp(source, target, **kw)
        with monkeypatch.context() as m:
            m.setattr(matcher, "HAVE_NUMBA", False)  # the matcher's numpy route (_Matcher._numpy_call)
            m.setattr(consistency, "have_numba", lambda: False)  # N and n, the cell sums by einsum
            m.setattr(covariance, "have_numba", lambda: False)
            m.setattr(local_surface, "_scatter_cached", local_surface._scatter_cached_numpy)
            m.setattr(local_surface, "_foot_into", local_surface._foot_into_numpy)
            m.setattr(matcher, "_cos_normals", matcher._cos_normals_numpy)
            m.setattr(matcher, "_dot_rows_at", matcher._dot_rows_at_numpy)
            old = icp(source, target, **kw)
        assert new.iterations == old.iterations > 1
        assert np.array_equal(new.matrix, old.matrix) and np.array_equal(new.covariance, old.covariance)
        for name in ("target_index", "rule", "weight", "normal_angle", "target_normal", "d"):
            assert np.array_equal(getattr(new.correspondences, name), getattr(old.correspondences, name),
                                  equal_nan=name != "target_index" and name != "rule"), name


@pytest.mark.parametrize("n_source, surface", [(8_000, "plane"), (12_000, "plane"), (12_000, "quadric")])
def test_first_search_made_ahead_changes_no_correspondence(n_source, surface):
    """prepare(start=(R, t)) searches the first call's nearest target points beside the source's normals:
    the first and later calls give the same correspondences as a matcher that searches them itself. The
    target's normals come at the points found (a source of fewer queries than half the target's points) or
    at every target point at once (at least half as many): the same numbers either way."""
    from labkit.registration.matching.match import WHOLE_TARGET, prepare

    rng = np.random.default_rng(11)
    target = np.round(wavy_surface(20_000, rng, noise=0.002), 3)
    source = np.round(wavy_surface(n_source, rng, noise=0.002), 3) - [0.021, -0.013, 0.008]
    R, t = np.eye(3), np.array([0.02, -0.01, 0.01])
    ahead, plain = prepare(source, target, start=(R, t), surface=surface), prepare(source, target, surface=surface)
    assert ahead.search_memory is not None and plain.search_memory is None
    whole = n_source >= WHOLE_TARGET * ahead.tree.n
    assert (ahead.geometry.n_computed == ahead.tree.n) == whole and plain.geometry.n_computed == 0
    for move in (t, t + 0.001, t + 1e-6):
        a, b = ahead(R, move), plain(R, move)
        for name in ("target_index", "d", "target_normal", "weight", "rule"):
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True)


@pytest.mark.parametrize("options", [
    dict(),
    dict(max_angle_deg=None),
    dict(max_angle_deg=5.0, unique=False),
    dict(noise_weighting=False),
    dict(max_noise=0.0025, classes=(2, 6)),
    dict(class_sigma={2: 0.01, 6: 0.03}, default_sigma=0.02),
    dict(surface="quadric", max_distance=0.05),
])
@pytest.mark.parametrize("in_ranges", [False, True])
def test_compiled_matcher_call_equals_its_numpy_route(options, in_ranges, monkeypatch):
    """_Matcher._compiled_call gives the correspondences of _Matcher._numpy_call, array for array and to the bit,
    under every gate and weighting (classes, noise, angle, duplicates, class sigmas, quadric feet, no partner),
    in one thread and with its passes cut into ranges on two threads (as on large clouds)."""
    from labkit import PointCloud
    from labkit.registration.matching import matcher_passes
    from labkit.registration.matching.match import prepare

    if in_ranges:
        monkeypatch.setattr(matcher_passes, "SERIAL_ROWS", 100)
        monkeypatch.setattr(matcher_passes, "cores", lambda: 2)

    rng = np.random.default_rng(3)
    target = np.round(wavy_surface(12_000, rng, noise=0.002), 3)
    source = np.round(wavy_surface(5_000, rng, noise=0.002), 3) - [0.021, -0.013, 0.008]
    target[:40] = target[40:80]  # exact duplicates in the target
    cls = lambda n: rng.choice([2, 5, 6], n)  # noqa: E731
    matcher = prepare(PointCloud(source, {"classification": cls(len(source))}),
                      PointCloud(target, {"classification": cls(len(target))}), sample=None, **options)
    R = np.array([[1.0, -0.002, 0.0], [0.002, 1.0, 0.001], [0.0, -0.001, 1.0]])
    for t in (np.zeros(3), np.array([0.02, -0.01, 0.005])):
        new, old = matcher._compiled_call(R, t), matcher._numpy_call(R, t)
        assert (new.rule != 0).any() and (new.rule == 0).any()
        for name in ("source_index", "target_index", "source_xyz", "d", "plane_distance", "normal_angle",
                     "target_normal", "weight", "rule"):
            a, b = getattr(new, name), getattr(old, name)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name


def test_work_arrays_kept_between_calls_change_no_result():
    """The matcher keeps its work arrays from one call to the next (no new memory per iteration): a call's
    correspondences stay as they were after later calls (none of them is a work array), and every call
    gives what a new matcher gives at the same transformation, also where fewer pairs are found than before."""
    import copy

    from labkit.registration.matching.match import prepare

    rng = np.random.default_rng(11)
    target = np.round(wavy_surface(12_000, rng, noise=0.002), 3)
    source = np.round(wavy_surface(5_000, rng, noise=0.002), 3) - [0.021, -0.013, 0.008]
    kw = dict(sample=None, max_distance=0.05)
    names = ("source_index", "target_index", "source_xyz", "d", "plane_distance", "normal_angle",
             "target_normal", "weight", "rule")
    moves = [np.zeros(3), np.array([0.04, -0.03, 0.02]), np.array([0.021, -0.013, 0.008])]  # the second: fewer pairs
    kept = prepare(source, target, **kw)
    first = kept(np.eye(3), moves[0])
    before = copy.deepcopy([getattr(first, n) for n in names])
    work = dict(kept._work)
    counts = []
    for t in moves:
        got, fresh = kept(np.eye(3), t), prepare(source, target, **kw)(np.eye(3), t)
        counts.append(int((got.rule == 0).sum()))
        for name in names:
            a, b = getattr(got, name), getattr(fresh, name)
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name
            assert not any(np.shares_memory(a, w) for w in kept._work.values()), name
    assert counts[1] < counts[0] < counts[2]  # fewer pairs, then more than at first
    assert kept._work.keys() == work.keys() and all(kept._work[n] is w for n, w in work.items())  # the same memory
    for a, b in zip([getattr(first, n) for n in names], before):
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
