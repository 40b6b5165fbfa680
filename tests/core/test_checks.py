"""labkit.core.checks: the shared input checks refuse bad values with a LabkitError that names them, and accept
the edge-valid ones unchanged. Their use at the public entry points: tests/core/test_bad_input_entry_points.py."""

import numpy as np
import pytest

import labkit
from labkit.core.checks import (
    PRECISION_TOLERANCE, as_points, as_rng, as_seed, check_precision, choice, count, finite, flag, non_negative, positive, precision_tolerance, probability,
)
from labkit.cloud import PointCloud
from labkit.core.units import Units
from labkit.core.errors import LabkitError

UTM = np.array([540_000.0, 5_400_000.0, 300.0])


def _float32_step(x: float) -> float:
    """Spacing of float32 at |x| from its 24-bit significand (independent of numpy's spacing)."""
    return 2.0 ** (np.floor(np.log2(abs(x))) - 23)


def _cloud(n=200, seed=0, offset=0.0):
    return np.random.default_rng(seed).uniform(0, 10, (n, 3)) + offset


# --------------------------------------------------------------------------- as_points
@pytest.mark.parametrize("points, fragment", [
    ("points.xyz", "got a string"),
    (np.zeros((5, 2)), "shape (n, 3), got (5, 2)"),
    (np.zeros(3), "shape (n, 3), got (3,)"),
    (np.zeros((2, 3, 1)), "shape (n, 3), got (2, 3, 1)"),
    (None, "shape (n, 3), got ()"),
    ([[0, 0, 0], [1, 2]], "numeric with shape (n, 3)"),
    ([["a", "b", "c"]], "numeric with shape (n, 3)"),
    (np.array([[0.0, 0, 0], [np.nan, 1, 1]]), "1 point(s) with NaN or infinite"),
    (np.array([[np.inf, 0, 0], [1, -np.inf, 1], [0, 0, 0]]), "2 point(s) with NaN or infinite"),
    (np.zeros((0, 3)), "at least 1 points, got 0"),
])
def test_as_points_refuses(points, fragment):
    with pytest.raises(LabkitError) as exc:
        as_points(points)
    assert fragment in str(exc.value)


@pytest.mark.parametrize("x", [5.4e6, 5.4e5, 1.3e4, 2048.0])
def test_float32_coordinates_too_coarse_are_refused(x):
    pts = (_cloud() + [x, 0, 0]).astype(np.float32)
    step = _float32_step(x)
    assert step / 2 > PRECISION_TOLERANCE  # the premise of the case
    with pytest.raises(LabkitError) as exc:
        as_points(pts)
    msg = str(exc.value)
    assert "float32" in msg and f"steps of {step:.3g} m" in msg and "precision_tolerance" in msg


@pytest.mark.parametrize("x", [0.0, 100.0, 1000.0, 2030.0])
def test_float32_local_coordinates_are_accepted_exactly(x):
    pts = (_cloud() + [x, -x, 0]).astype(np.float32)
    out = as_points(pts)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, pts.astype(np.float64))  # exact: every float32 is a float64


def test_float16_is_guarded_too():
    pts = (_cloud() + 100).astype(np.float16)
    with pytest.raises(LabkitError, match=r"float16 has steps of 0\.0625 m"):  # 2**(6 - 10)
        as_points(pts)


def test_precision_tolerance_by_argument_and_by_context():
    pts = (_cloud() + UTM).astype(np.float32)
    np.testing.assert_array_equal(as_points(pts, tolerance=0.25), pts.astype(np.float64))
    with labkit.precision_tolerance(0.25):
        np.testing.assert_array_equal(as_points(pts), pts.astype(np.float64))
        with pytest.raises(LabkitError, match="0.125 m"):
            as_points(pts, tolerance=0.125)  # an explicit tolerance wins over the context
    with pytest.raises(LabkitError, match="tolerance of 0.0001 m"):
        as_points(pts)  # the context ends with the block


@pytest.mark.parametrize("tol, fragment", [(-1, "tolerance must be a number > 0 (m), got -1"),
                                            (np.nan, "got nan"), ("0.5", "got '0.5' (str)")])
def test_tolerance_argument_is_checked(tol, fragment):
    with pytest.raises(LabkitError) as exc:
        as_points((_cloud() + UTM).astype(np.float32), tolerance=tol)
    assert fragment in str(exc.value)


@pytest.mark.parametrize("tol", [0, -1, np.nan])
def test_precision_tolerance_must_be_positive(tol):
    with pytest.raises(LabkitError, match="precision tolerance must be a number > 0"):
        with precision_tolerance(tol):
            pass


def test_float64_and_integers_pass_the_guard():
    check_precision(_cloud() + UTM)  # float64 at UTM size: steps of 1e-9 m
    check_precision((_cloud() + UTM).astype(np.int64))  # integers are exact
    np.testing.assert_array_equal(as_points([[1, 2, 3]]), [[1.0, 2.0, 3.0]])


def test_as_points_never_modifies_its_input():
    pts = _cloud()
    keep = pts.copy()
    out = as_points(pts, copy=True)
    out += 1
    np.testing.assert_array_equal(pts, keep)


# --------------------------------------------------------------------------- numbers
@pytest.mark.parametrize("check, value, expected", [
    (positive, 2, 2.0), (positive, np.float32(0.5), 0.5), (positive, 1e-300, 1e-300),
    (non_negative, 0, 0.0), (non_negative, 3.5, 3.5),
    (finite, -7.25, -7.25), (finite, 0, 0.0),
    (probability, 0.05, 0.05),
    (count, 20, 20), (count, 20.0, 20), (count, np.int64(7), 7),
    (flag, np.True_, True), (flag, 0, False),
])
def test_number_checks_accept(check, value, expected):
    out = check(value, "v")
    assert out == expected and type(out) is type(expected)


@pytest.mark.parametrize("check, value, fragment", [
    (positive, 0, "v must be a finite number > 0, got 0"),
    (positive, -1.0, "got -1.0"),
    (positive, np.nan, "got nan"),
    (positive, np.inf, "got inf"),
    (positive, "1", "v must be a number > 0, got '1' (str)"),
    (positive, True, "got True (bool)"),
    (positive, None, "got None (NoneType)"),
    (positive, [1.0], "got [1.0] (list)"),
    (non_negative, -1e-12, "v must be a finite number >= 0"),
    (non_negative, np.nan, "v must be a finite number >= 0, got nan"),
    (non_negative, "1", "v must be a number >= 0, got '1' (str)"),
    (finite, np.nan, "v must be a finite number, got nan"),
    (finite, -np.inf, "got -inf"),
    (probability, 0, "strictly between 0 and 1, got 0"),
    (probability, 1.0, "strictly between 0 and 1"),
    (probability, np.nan, "got nan"),
    (count, 20.5, "v must be a whole number >= 1, got 20.5"),
    (count, "20", "got '20' (str)"),
    (count, True, "got True (bool)"),
    (count, 0, "whole number >= 1, got 0"),
    (count, np.nan, "got nan"),
    (count, np.inf, "got inf"),
    (flag, "no", "v must be True or False, got 'no'"),
    (flag, 2, "v must be True or False, got 2"),
])
def test_number_checks_refuse(check, value, fragment):
    with pytest.raises(LabkitError) as exc:
        check(value, "v")
    assert fragment in str(exc.value)


def test_count_bounds_and_choice():
    assert count(0, "n", minimum=0) == 0
    with pytest.raises(LabkitError, match=r"whole number >= 1 and <= 5, got 6"):
        count(6, "n", maximum=5)
    assert choice("a", ("a", "b"), "x") == "a"
    with pytest.raises(LabkitError, match="x must be one of 1, 2; got True"):
        choice(True, (1, 2), "x")  # True == 1, but a bool is not a choice among numbers
    with pytest.raises(LabkitError, match=r"x must be one of .*; got \['a'\]"):
        choice(["a"], {"a", "b"}, "x")  # unhashable against a set: refused, not a TypeError


# --------------------------------------------------------------------------- random generators
@pytest.mark.parametrize("rng, fragment", [
    (-1, "rng must be a whole number >= 0, got -1"),
    (1.5, "rng must be an int >= 0, a numpy.random.Generator or None, got float"),
    ("3", "got str"),
    (True, "got bool"),
    (np.random.RandomState(0), "got RandomState"),
])
def test_as_rng_refuses(rng, fragment):
    with pytest.raises(LabkitError) as exc:
        as_rng(rng)
    assert fragment in str(exc.value)


def test_as_rng_accepts_seeds_and_generators():
    gen = np.random.default_rng(3)
    assert as_rng(gen) is gen
    np.testing.assert_array_equal(as_rng(np.int64(5)).random(4), np.random.default_rng(5).random(4))
    assert as_seed(None) is None and as_seed(7.0) == 7
    with pytest.raises(LabkitError, match="seed must be a whole number >= 0, got -2"):
        as_seed(-2)


# --------------------------------------------------------------------------- edges
@pytest.mark.parametrize("check, value", [
    (probability, 1e-12), (probability, 1 - 1e-12), (positive, np.finfo(float).tiny), (non_negative, -0.0),
    (finite, np.finfo(float).max), (finite, -np.finfo(float).max),
])
def test_values_just_inside_the_bounds_pass_unchanged(check, value):
    assert check(value, "v") == value


def test_count_accepts_its_bounds_and_names_them_when_refusing():
    assert count(3, "k", minimum=3, maximum=3) == 3
    assert count(np.float64(1e6), "n") == 1_000_000  # an integral float of any size
    with pytest.raises(LabkitError, match="k must be a whole number >= 3, got 2"):
        count(2, "k", minimum=3)


def test_as_points_edges_min_points_pointcloud_and_degrees():
    with pytest.raises(LabkitError, match="target needs at least 3 points, got 2"):
        as_points(np.zeros((2, 3)), min_points=3, name="target")
    pts = _cloud(3)
    np.testing.assert_array_equal(as_points(PointCloud(pts), min_points=3), pts)
    assert as_points(pts) is pts  # float64 input is not copied unless asked
    assert as_points(pts, copy=True) is not pts
    lonlat = PointCloud(np.array([[11.5, 48.1, 500.0], [11.6, 48.2, 510.0]]), units=Units("degree", "metre"))
    with pytest.raises(LabkitError, match=r"degrees of longitude/latitude; a metric step \(on points\) needs metric"):
        as_points(lonlat)  # UnitsError is a LabkitError


def test_seed_sequence_and_precision_guard_edge():
    seq = np.random.SeedSequence(4)
    np.testing.assert_array_equal(as_rng(seq).random(3), np.random.default_rng(np.random.SeedSequence(4)).random(3))
    # float32 at 2048 m has steps of 2**-12 m: half a step (0.12 mm) is just above the 0.1 mm tolerance
    pts = (_cloud() + [2048.0, 0, 0]).astype(np.float32)
    assert _float32_step(2048.0) / 2 > PRECISION_TOLERANCE
    with pytest.raises(LabkitError, match="float32"):
        check_precision(pts)
    check_precision(pts, tolerance=_float32_step(2048.0) / 2)  # exactly half a step passes
    with precision_tolerance(np.inf):
        check_precision((_cloud() + UTM).astype(np.float32))  # the guard switched off
    assert labkit.precision_tolerance is precision_tolerance
