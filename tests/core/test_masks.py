"""labkit.core.masks: boxes, circles, polygons and classes as point masks, checked against independent routes."""

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from labkit.core.errors import LabkitError
from labkit.core.masks import (
    ASPRS_NAMES, STABLE_CLASSES, as_bbox, as_classes, as_rings, box_mask, circle_mask, class_mask, polygon_mask,
)


def test_polygon_mask_agrees_with_matplotlib_for_a_concave_polygon_with_a_hole_at_utm_size():
    rng = np.random.default_rng(3)
    origin = np.array([612_000.0, 5_701_000.0])
    outer = origin + np.array([[0, 0], [10, 0], [10, 10], [5, 4], [0, 10]], float)  # concave (a notch from above)
    hole = origin + np.array([[2, 1], [4, 1], [4, 3], [2, 3]], float)
    xyz = np.c_[origin + rng.uniform(-1, 11, (20_000, 2)), rng.normal(size=20_000)]
    got = polygon_mask(xyz, as_rings([outer, hole]))
    # independent route: matplotlib's point-in-polygon on coordinates reduced to the origin
    inside_outer = MplPath(outer - origin).contains_points(xyz[:, :2] - origin)
    inside_hole = MplPath(hole - origin).contains_points(xyz[:, :2] - origin)
    want = inside_outer & ~inside_hole
    off_edge = ~np.isclose(xyz[:, :2] - origin, np.round(xyz[:, :2] - origin), atol=1e-9).any(axis=1)
    assert got.sum() > 5000 and (got[off_edge] == want[off_edge]).all()


def test_box_circle_and_class_masks_equal_their_definitions():
    xyz = np.random.default_rng(4).uniform(-5, 5, (5000, 3))
    box = as_bbox((-1, -2, 0, 3, 2, 4))  # with z
    want_box = ((xyz >= [-1, -2, 0]) & (xyz <= [3, 2, 4])).all(axis=1)
    np.testing.assert_array_equal(box_mask(xyz, box), want_box)
    want_circle = np.hypot(xyz[:, 0] - 1.0, xyz[:, 1] + 0.5) <= 2.0
    np.testing.assert_array_equal(circle_mask(xyz, np.array([1.0, -0.5]), 2.0), want_circle)
    cls = np.random.default_rng(5).integers(0, 12, 5000)
    np.testing.assert_array_equal(class_mask(cls, as_classes(STABLE_CLASSES)),
                                  (cls == 2) | (cls == 6) | (cls == 11))


@pytest.mark.parametrize("bad", ["2", [], [1.5], [-1], [256]])
def test_as_classes_refuses_what_is_no_class_code(bad):
    with pytest.raises(LabkitError, match="class"):
        as_classes(bad)


def test_one_table_of_class_names_and_the_stable_classes_are_named_in_it():
    from labkit.plotting import clouds, compare, features

    assert compare.ASPRS_NAMES is ASPRS_NAMES and features.ASPRS_NAMES is ASPRS_NAMES
    assert clouds.ASPRS_NAMES is ASPRS_NAMES
    assert [ASPRS_NAMES[c] for c in STABLE_CLASSES] and all(c in ASPRS_NAMES for c in STABLE_CLASSES)
