"""labkit.regions: crops against brute-force checks, thinning, densities."""

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from labkit.cloud import PointCloud
from labkit.core.errors import EmptyRegionError, LabkitError
from labkit.regions import (
    as_classes,
    crop_box,
    crop_circle,
    crop_classes,
    crop_polygon,
    density_grid,
    equalize_density,
    merge,
    point_density,
    thin_random,
    thin_voxel,
)

E0, N0 = 32_512_000.0, 5_611_000.0  # UTM with zone prefix: 8-digit eastings


def _uniform(density, width, height, seed=0, z=(90.0, 110.0)):
    """Poisson-like uniform cloud of ``density`` pts/m^2 on a width x height rectangle."""
    rng = np.random.default_rng(seed)
    n = int(density * width * height)
    xyz = np.column_stack([E0 + rng.uniform(0, width, n), N0 + rng.uniform(0, height, n), rng.uniform(*z, n)])
    cls = rng.choice(np.array([2, 3, 5, 6, 9], np.uint8), n)
    return PointCloud(xyz, {"classification": cls, "id": np.arange(n)}, name="test")


# ---------------------------------------------------------------------------- crops
def test_crop_box_2d_and_3d_against_loops():
    cloud = _uniform(5, 40, 40)
    box = (E0 + 10, N0 + 5, E0 + 25.5, N0 + 30)
    got = crop_box(cloud, box)
    expect = [i for i, (x, y, _) in enumerate(cloud.xyz) if box[0] <= x <= box[2] and box[1] <= y <= box[3]]
    np.testing.assert_array_equal(got["id"], expect)
    box3 = (E0 + 10, N0 + 5, 95.0, E0 + 25.5, N0 + 30, 100.0)
    got3 = crop_box(cloud, box3)
    expect3 = [i for i in expect if 95.0 <= cloud.xyz[i, 2] <= 100.0]
    np.testing.assert_array_equal(got3["id"], expect3)
    # a (2, 3) [min, max] array (as PointCloud.bounds gives) is accepted too
    np.testing.assert_array_equal(crop_box(cloud, np.reshape(box3, (2, 3)))["id"], expect3)


def test_crop_circle_against_loop():
    cloud = _uniform(5, 40, 40)
    centre, r = (E0 + 17.3, N0 + 22.1), 9.5
    got = crop_circle(cloud, centre, r)
    expect = [i for i, (x, y, _) in enumerate(cloud.xyz) if np.hypot(x - centre[0], y - centre[1]) <= r]
    np.testing.assert_array_equal(got["id"], expect)


def _star(cx, cy, n_tips=7, r_out=18.0, r_in=7.0):
    ang = np.arange(2 * n_tips) * np.pi / n_tips
    rad = np.where(np.arange(2 * n_tips) % 2 == 0, r_out, r_in)
    return np.column_stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)])


def test_crop_polygon_matches_matplotlib_on_a_concave_star():
    cloud = _uniform(8, 40, 40, seed=3)
    star = _star(E0 + 20, N0 + 20)
    got = crop_polygon(cloud, star)
    # independent route: matplotlib's C implementation, on reduced coordinates
    origin = np.array([E0, N0])
    inside = MplPath(star - origin).contains_points(cloud.xyz[:, :2] - origin)
    np.testing.assert_array_equal(got["id"], np.flatnonzero(inside))
    assert 0.2 < len(got) / len(cloud) < 0.6


def test_crop_polygon_with_hole_and_closed_ring():
    cloud = _uniform(8, 40, 40, seed=4)
    outer = np.array([[E0 + 2, N0 + 2], [E0 + 38, N0 + 2], [E0 + 38, N0 + 38], [E0 + 2, N0 + 38], [E0 + 2, N0 + 2]])
    hole = np.array([[E0 + 10, N0 + 10], [E0 + 20, N0 + 10], [E0 + 20, N0 + 30], [E0 + 10, N0 + 30]])
    got = crop_polygon(cloud, [outer, hole])
    x, y = cloud.xyz[:, 0] - E0, cloud.xyz[:, 1] - N0
    in_outer = (x >= 2) & (x <= 38) & (y >= 2) & (y <= 38)
    in_hole = (x >= 10) & (x <= 20) & (y >= 10) & (y <= 30)
    np.testing.assert_array_equal(got["id"], np.flatnonzero(in_outer & ~in_hole))


def test_crop_classes_and_exclude():
    cloud = _uniform(3, 20, 20)
    got = crop_classes(cloud, [2, 6])
    assert set(np.unique(got["classification"])) == {2, 6}
    rest = crop_classes(cloud, [2, 6], exclude=True)
    assert len(got) + len(rest) == len(cloud)
    assert not np.isin(rest["classification"], [2, 6]).any()
    assert len(crop_classes(cloud, 9)) == np.count_nonzero(cloud["classification"] == 9)


def test_empty_crops_name_the_region():
    cloud = _uniform(2, 10, 10)
    with pytest.raises(EmptyRegionError, match="box"):
        crop_box(cloud, (0, 0, 1, 1))
    with pytest.raises(EmptyRegionError, match="circle"):
        crop_circle(cloud, (0, 0), 5)
    with pytest.raises(EmptyRegionError, match="polygon with 3 vertices"):
        crop_polygon(cloud, [(0, 0), (1, 0), (0, 1)])
    with pytest.raises(EmptyRegionError, match=r"classes \[17\].*'test'"):
        crop_classes(cloud, 17)


def test_bad_region_arguments():
    cloud = _uniform(2, 10, 10)
    with pytest.raises(LabkitError, match="bbox"):
        crop_box(cloud, (1, 2, 3))
    with pytest.raises(LabkitError, match="min <= max"):
        crop_box(cloud, (E0 + 5, N0, E0, N0 + 5))
    with pytest.raises(LabkitError, match="m >= 3"):
        crop_polygon(cloud, [(0, 0), (1, 1)])
    with pytest.raises(LabkitError, match="radius"):
        crop_circle(cloud, (E0, N0), -1)
    with pytest.raises(LabkitError, match="integer"):
        crop_classes(cloud, [2.5])
    with pytest.raises(LabkitError, match="classification"):
        crop_classes(PointCloud(cloud.xyz), 2)


# ---------------------------------------------------------------------------- thinning
def test_thin_random():
    cloud = _uniform(5, 20, 20)
    a = thin_random(cloud, 0.25, rng=7)
    b = thin_random(cloud, 0.25, rng=7)
    assert len(a) == round(0.25 * len(cloud))
    np.testing.assert_array_equal(a["id"], b["id"])  # reproducible
    assert (np.diff(a["id"]) > 0).all()  # a subset in the original order, no repeats
    assert len(thin_random(cloud, n=10, rng=1)) == 10
    with pytest.raises(LabkitError):
        thin_random(cloud, 1.5)
    with pytest.raises(LabkitError):
        thin_random(cloud)


@pytest.mark.parametrize("keep", ["centre", "first"])
def test_voxel_thinning_one_point_per_occupied_cell(keep):
    cloud = _uniform(30, 10, 10, seed=5, z=(100.0, 103.0))
    size = 0.5
    got = thin_voxel(cloud, size, keep=keep)
    # independent cell bookkeeping with a Python dict
    origin = np.floor(cloud.xyz.min(axis=0) / size) * size
    members = {}
    for i, p in enumerate(cloud.xyz):
        members.setdefault(tuple(np.floor((p - origin) / size).astype(int)), []).append(i)
    kept_cells = [tuple(np.floor((p - origin) / size).astype(int)) for p in got.xyz]
    assert len(kept_cells) == len(set(kept_cells)) == len(members)  # one per cell, every cell
    for cell, i in zip(kept_cells, got["id"]):
        idx = members[cell]
        if keep == "first":
            assert i == idx[0]
        else:
            centre = origin + (np.array(cell) + 0.5) * size
            d = np.linalg.norm(cloud.xyz[idx] - centre, axis=1)
            assert i == idx[int(np.argmin(d))]


# ---------------------------------------------------------------------------- densities
def test_point_density_of_a_known_area():
    cloud = _uniform(20, 100, 60, seed=8)
    assert point_density(cloud) == pytest.approx(20, rel=0.05)
    # a lake without returns must not dilute the density (a hull-based density would)
    xy = cloud.xyz[:, :2] - [E0, N0]
    dry = PointCloud(cloud.xyz[np.hypot(xy[:, 0] - 50, xy[:, 1] - 30) > 20])
    assert point_density(dry) == pytest.approx(20, rel=0.07)


def test_density_grid_matches_histogram2d():
    cloud = _uniform(4, 30, 20, seed=9)
    grid = density_grid(cloud, cell=2.0)
    x0, _, y0, _ = grid.extent
    ny, nx = grid.counts.shape
    H, _, _ = np.histogram2d(
        cloud.xyz[:, 1], cloud.xyz[:, 0], bins=[y0 + 2.0 * np.arange(ny + 1), x0 + 2.0 * np.arange(nx + 1)]
    )
    np.testing.assert_array_equal(grid.counts, H)
    assert grid.counts.sum() == len(cloud)
    assert "Density grid" in grid.summary()


def test_equalize_dim_to_als_density():
    dim = _uniform(100, 60, 50, seed=10)  # dense image matching
    als = _uniform(20, 60, 50, seed=11)
    thinned = equalize_density(dim, als, cell=1.0, rng=0)
    area = 60 * 50
    assert len(thinned) / area == pytest.approx(len(als) / area, rel=0.10)
    assert len(thinned) / area == pytest.approx(20, rel=0.10)
    # cells are evened out: the count spread per 1 m cell shrinks far below Poisson(100)
    counts = density_grid(thinned, 1.0).counts[1:-1, 1:-1]
    assert counts.std() < 0.5 * np.sqrt(20)
    assert set(thinned["id"]) <= set(dim["id"])


def test_equalize_keeps_sparse_cells_whole():
    sparse = _uniform(5, 20, 20, seed=12)
    got = equalize_density(sparse, 50.0, rng=1)
    assert len(got) == len(sparse)
    with pytest.raises(LabkitError):
        equalize_density(sparse, -3)


def test_merge_keeps_common_attributes():
    a, b = _uniform(1, 10, 10, seed=1), _uniform(1, 10, 10, seed=2)
    b = PointCloud(b.xyz, {"classification": b["classification"]})
    m = merge(a, b, name="both")
    assert len(m) == len(a) + len(b) and list(m.attributes) == ["classification"]
    np.testing.assert_array_equal(m.xyz[len(a):], b.xyz)
    with pytest.raises(LabkitError, match="reference systems"):
        merge(PointCloud(a.xyz, crs="EPSG:25832"), PointCloud(b.xyz, crs="EPSG:25833"))


def test_class_colours_are_the_asprs_table():
    from labkit.plotting.clouds import ASPRS_COLORS, class_colors

    rgb = class_colors(np.array([2, 6, 9, 200], np.uint8))
    assert rgb.shape == (4, 3) and rgb.dtype == np.uint8
    assert "#%02x%02x%02x" % tuple(rgb[1]) == ASPRS_COLORS[6]
    assert (rgb[3] == 0).all()  # user-defined codes are black


# --------------------------------------------------------------------------- bad input
def _cloud(n=200, seed=0, offset=0.0):
    return np.random.default_rng(seed).uniform(0, 10, (n, 3)) + offset


@pytest.mark.parametrize("call, error, fragment", [
    (lambda c: thin_random(c, n=20.5), LabkitError, "n must be a whole number >= 0, got 20.5"),
    (lambda c: thin_random(c, n="5"), LabkitError, "got '5' (str)"),
    (lambda c: thin_random(c, n=True), LabkitError, "got True (bool)"),
    (lambda c: thin_random(c, n=0), EmptyRegionError, "between 1 and 200 points, asked for 0"),
    (lambda c: thin_voxel(c, "0.5"), LabkitError, "size must be a number > 0, got '0.5' (str)"),
    (lambda c: thin_voxel(c, 1e-300), LabkitError, "too small for the cloud's extent"),
    (lambda c: density_grid(c, 1e-4), LabkitError, "cells, more than 50,000,000; is the cell in metres?"),
    (lambda c: as_classes([300]), LabkitError, "class codes lie in 0..255"),
    (lambda c: as_classes([-1, 2]), LabkitError, "class codes lie in 0..255"),
    (lambda c: as_classes("ground"), LabkitError, "got the string 'ground'"),
    (lambda c: as_classes([2.5]), LabkitError, "integer class codes"),
    (lambda c: merge(c, c.xyz), LabkitError, "merge takes PointClouds"),
    (lambda c: crop_box("cloud.laz", (0, 0, 1, 1)), LabkitError, "got a string"),
])
def test_regions_refuse(call, error, fragment):
    with pytest.raises(error) as exc:
        call(PointCloud(_cloud()))
    assert fragment in str(exc.value)


def test_regions_accept_arrays_as_clouds():
    pts = _cloud()
    inside = np.all((pts[:, :2] >= 2) & (pts[:, :2] <= 6), axis=1)
    np.testing.assert_array_equal(crop_box(pts, (2, 2, 6, 6)).xyz, pts[inside])
    assert len(thin_random(pts, n=20, rng=1)) == 20
