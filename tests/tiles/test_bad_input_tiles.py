"""Bad input to the tile grid, register_tiles and neighbour_test: one clear LabkitError before any work."""

import numpy as np
import pytest

from labkit.cloud import PointCloud
from labkit.core.errors import LabkitError
from labkit.tiles import MAX_TILES, ShiftField, neighbour_test, register_tiles, tile_grid


# --------------------------------------------------------------------------- tiles
@pytest.mark.parametrize("bounds, size, kwargs, fragment", [
    ((0, 0, 1e5, 1e5), 1, {}, "10,000,200,001 tiles of 1 m"),
    ((0, 0, 60, 60), 0.01, {}, "36,012,001 tiles of 0.01 m (6,001 x 6,001)"),
    ((0, 0, 60, 60), 0.01, {}, "exceed the limit of 100,000"),
    ((0, 0, 60, 60), 10, {"max_tiles": 48}, "49 tiles of 10 m (7 x 7)"),
    ((0, 0, 10, 10), 0, {}, "size must be a finite number > 0, got 0"),
    ((0, 0, 10, 10), np.nan, {}, "size must be a finite number > 0, got nan"),
    ((0, 0, 10, 10), "5", {}, "size must be a number > 0, got '5' (str)"),
    ((0, 0, 10, 10), 5, {"buffer": np.nan}, "buffer must be a finite number >= 0, got nan"),
    ((0, 0, 10, 10), 5, {"buffer": "1"}, "buffer must be a number >= 0, got '1' (str)"),
    ((0, 0, 10, 10), 5, {"buffer": -1}, "buffer must be a finite number >= 0, got -1"),
    ((0, 0, 10, 10), 5, {"max_tiles": 0}, "max_tiles must be a whole number >= 1, got 0"),
    ((0, 0, np.nan, 10), 5, {}, "bounds must be finite"),
    ((10, 0, 0, 10), 5, {}, "min <= max"),
    ((0, 0, 10), 5, {}, "bounds must be four numbers"),
])
def test_tile_grid_refuses(bounds, size, kwargs, fragment):
    with pytest.raises(LabkitError) as exc:
        tile_grid(bounds, size, **kwargs)
    assert fragment in str(exc.value)


def test_tile_limit_suggests_a_size_that_fits():
    with pytest.raises(LabkitError) as exc:
        tile_grid((0, 0, 1e5, 1e5), 1)
    suggested = float(str(exc.value).split("size of at least ")[1].split(" m")[0])
    assert len(tile_grid((0, 0, 1e5, 1e5), suggested)) <= MAX_TILES
    assert len(tile_grid((0, 0, 60, 60), 10, max_tiles=49)) == 49  # 7 x 7 anchored at 0: at the limit


@pytest.fixture(scope="module")
def epochs():
    """Two epochs of a wavy 40 m x 40 m surface, the second shifted by a known vector; half of it class 2."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(1, 39, (6000, 2))  # inside one 40 m tile anchored at 0
    z = np.sin(xy[:, 0] / 3) + np.cos(xy[:, 1] / 4) + 0.3 * np.sin((xy[:, 0] + xy[:, 1]) / 2)
    target = np.c_[xy, z] + rng.normal(0, 0.002, (6000, 3))
    shift = np.array([0.04, -0.03, 0.02])
    source = target[::2] + rng.normal(0, 0.002, (3000, 3)) - shift
    cls = np.where(xy[:, 0] < 20, 2, 5).astype(np.uint8)
    return {"source": source, "target": target, "shift": shift,
            "source_cloud": PointCloud(source, {"classification": cls[::2]}),
            "target_cloud": PointCloud(target, {"classification": cls})}


def _tiles(epochs, **kwargs):
    args = {"size": 40.0, "scheduler": "serial", "progress": False} | kwargs
    return register_tiles(epochs["source"], epochs["target"], **args)


@pytest.mark.parametrize("kwargs, error, fragment", [
    ({"buffer": "1"}, LabkitError, "buffer must be a number >= 0, got '1' (str)"),
    ({"buffer": np.nan}, LabkitError, "buffer must be a finite number >= 0, got nan"),
    ({"method": "magic"}, LabkitError, "method must be one of 'icp'"),
    ({"method": 42}, LabkitError, "method must be a callable"),
    ({"classes": [2]}, LabkitError, "needs a 'classification' attribute, but the source is an array"),
    ({"classes": "ground"}, LabkitError, "integer class codes"),
    ({"min_points": 20.5}, LabkitError, "min_points must be a whole number >= 1, got 20.5"),
    ({"min_points": 0}, LabkitError, "min_points must be a whole number >= 1, got 0"),
    ({"size": 1e-3}, LabkitError, "tiles of 0.001 m"),
    ({"size": -5}, LabkitError, "size must be a finite number > 0"),
    ({"scheduler": "gpu"}, LabkitError, "scheduler must be one of threads, processes, sync, serial, cluster"),
    ({"max_tiles": 2.5}, LabkitError, "max_tiles must be a whole number"),
    ({"progress": "no"}, LabkitError, "progress must be True, False, 'bar', 'lines' or a callable, got 'no'"),
])
def test_register_tiles_refuses_before_any_work(epochs, kwargs, error, fragment, monkeypatch):
    import labkit.tiles.register as T  # register_tiles runs the register_tile of its own module

    monkeypatch.setattr(T, "register_tile", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(error) as exc:
        _tiles(epochs, **kwargs)
    assert fragment in str(exc.value)


def test_register_tiles_classes_are_honoured_for_clouds(epochs):
    field = register_tiles(epochs["source_cloud"], epochs["target_cloud"], size=20.0, classes=[2],
                           min_points=10**6, scheduler="serial", progress=False)  # count only, no registration
    for t in field.tiles:
        inside_src = t.tile.contains(epochs["source"]) & (epochs["source_cloud"]["classification"] == 2)
        inside_tgt = t.tile.contains(epochs["target"]) & (epochs["target_cloud"]["classification"] == 2)
        assert (t.n_source, t.n_target) == (inside_src.sum(), inside_tgt.sum())
    every = register_tiles(epochs["source_cloud"], epochs["target_cloud"], size=20.0, min_points=10**6,
                           scheduler="serial", progress=False)
    assert [t.n_source for t in every.tiles] == [t.tile.contains(epochs["source"]).sum() for t in every.tiles]
    assert sum(t.n_source for t in field.tiles) < sum(t.n_source for t in every.tiles)  # the filter acted
    with pytest.raises(LabkitError, match="the target is a PointCloud without one"):
        register_tiles(epochs["source_cloud"], PointCloud(epochs["target"]), classes=[2], size=20.0,
                       scheduler="serial", progress=False)


@pytest.mark.slow
def test_register_tiles_method_by_name_equals_the_callable(epochs):
    from labkit.registration.compare import standard_methods

    by_name = _tiles(epochs, method="icp")
    by_callable = _tiles(epochs, method=standard_methods(["icp"], dof="translation", rng=0)["icp"])
    assert by_name.tiles[0].ok and by_name.method == "icp"
    np.testing.assert_array_equal(by_name.translations, by_callable.translations)
    sd = by_name.std[0]
    assert np.all(np.abs(by_name.translations[0] - epochs["shift"]) < 4 * sd + 1e-3)


@pytest.fixture(scope="module")
def small_field(epochs):
    return register_tiles(epochs["source"], epochs["target"], size=20.0, scheduler="serial", progress=False)


@pytest.mark.parametrize("kwargs, fragment", [
    ({"extra_std": np.nan}, "extra_std must be a finite number >= 0, got nan"),
    ({"extra_std": -0.001}, "extra_std must be a finite number >= 0, got -0.001"),
    ({"extra_std": "0.005"}, "extra_std must be a number >= 0, got '0.005' (str)"),
    ({"alpha": 0}, "alpha must lie strictly between 0 and 1"),
    ({"alpha": np.nan}, "alpha must lie strictly between 0 and 1, got nan"),
    ({"diagonal": "no"}, "diagonal must be True or False, got 'no'"),
])
def test_neighbour_test_refuses(small_field, kwargs, fragment):
    with pytest.raises(LabkitError) as exc:
        neighbour_test(small_field, **kwargs)
    assert fragment in str(exc.value)


def test_neighbour_test_needs_a_field_and_accepts_zero_extra_std(small_field):
    with pytest.raises(LabkitError, match="needs a ShiftField"):
        neighbour_test(small_field.translations)
    assert isinstance(small_field, ShiftField)
    test = neighbour_test(small_field, extra_std=0)
    assert test.extra_std == 0.0 and len(test.pairs) == 4  # 2 x 2 tiles: 4 edge pairs
