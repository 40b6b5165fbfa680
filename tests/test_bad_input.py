"""Nothing silent: the shared validators at the entry points, tiles, distances, regions, the command line.

Every case states its exact outcome: the value returned, or the error type and a
fragment of its message. The other modules' cases live in test_bad_input_*.py.
"""

import os
from pathlib import Path

import numpy as np
import pytest

import labkit
import labkit.cli.main as cli
from labkit.cli.main import main
from labkit.cloud import PointCloud
from labkit.change.distances import DistanceChange, point_to_plane_distance
from labkit.core.errors import DegenerateGeometryError, EmptyRegionError, LabkitError
from labkit.io import read_cloud, write_cloud
from labkit.regions import as_classes, crop_box, density_grid, merge, thin_random, thin_voxel
from labkit.tiles import MAX_TILES, ShiftField, neighbour_test, register_tiles, tile_grid

UTM = np.array([540_000.0, 5_400_000.0, 300.0])


def _float32_step(x: float) -> float:
    """Spacing of float32 at |x| from its 24-bit significand (independent of numpy's spacing)."""
    return 2.0 ** (np.floor(np.log2(abs(x))) - 23)


def _cloud(n=200, seed=0, offset=0.0):
    return np.random.default_rng(seed).uniform(0, 10, (n, 3)) + offset


# --------------------------------------------------------------------------- the shared checks at the entry points
# (the checks themselves, labkit.core.checks: tests/test_checks.py)
def test_float32_utm_refused_by_public_functions_and_files(tmp_path):
    pts = (_cloud() + UTM).astype(np.float32)
    with pytest.raises(LabkitError, match="float32"):
        PointCloud(pts)
    with pytest.raises(LabkitError, match="float32"):
        labkit.cloud_to_cloud(pts, pts.astype(np.float64))
    np.save(tmp_path / "utm32.npy", pts)
    with pytest.raises(LabkitError, match="utm32.npy: float32 coordinates up to 5.4e\\+06 m"):
        read_cloud(tmp_path / "utm32.npy")
    local = (pts.astype(np.float64) - UTM).astype(np.float32)
    np.save(tmp_path / "local32.npy", local)
    np.testing.assert_array_equal(read_cloud(tmp_path / "local32.npy").xyz, local.astype(np.float64))


@pytest.mark.parametrize("name, call", [
    ("ransac_sphere", lambda a, b: labkit.ransac_sphere(a, 0.01, radius_range=(0.1, 1.0))),
    ("gauss_helmert_model", lambda a, b: labkit.gauss_helmert_model(a)),
    ("local_pca", lambda a, b: labkit.local_pca(a)),
    ("icp source", lambda a, b: labkit.icp(a, b)),
    ("icp target", lambda a, b: labkit.icp(b, a)),
    ("max_consensus", lambda a, b: labkit.max_consensus(a, b)),
    ("point_to_plane_distance", lambda a, b: labkit.point_to_plane_distance(b, a)),
    ("register_tiles", lambda a, b: labkit.register_tiles(a, b, progress=False)),
])
def test_float32_utm_refused_by_every_entry_point(name, call):
    b = _cloud(500) + UTM
    with pytest.raises(LabkitError, match=r"float32 has steps of 0\.5 m"):
        call(b.astype(np.float32), b)


def test_a_bad_rng_is_refused_by_a_public_function():
    with pytest.raises(LabkitError, match="rng must be a whole number >= 0"):
        thin_random(PointCloud(_cloud()), 0.5, rng=-1)  # the checks of labkit.core.checks: tests/test_checks.py


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


# --------------------------------------------------------------------------- distances
def _plane(n=2000, seed=5):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 10, (n, 2))
    return np.c_[xy, 0.2 * xy[:, 0]]


def test_zero_and_nan_normals_give_nan_distances_with_a_count():
    tgt = _plane()
    src = tgt[::4] + [0, 0, 0.1]
    n = np.tile(np.array([-0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0), (len(tgt), 1))
    bad = np.zeros(len(tgt), bool)
    bad[::7] = True
    given = n.copy()
    given[bad] = 0.0
    given[1::7] = np.nan
    nearest = np.argmin(((src[:, None, :] - tgt[None, :, :]) ** 2).sum(-1), axis=1)  # brute force
    expect_nan = bad[nearest] | (np.arange(len(tgt)) % 7 == 1)[nearest]
    d = point_to_plane_distance(src, tgt, given)
    assert np.array_equal(np.isnan(d), expect_nan) and expect_nan.any()
    np.testing.assert_allclose(d[~expect_nan], 0.1 / np.hypot(0.2, 1.0), atol=1e-9)  # the closed form
    change = DistanceChange(d, d, "point_to_plane")
    assert change.n_undetermined == expect_nan.sum()
    assert change.stats()["n"] == (~expect_nan).sum()
    assert f"{expect_nan.sum()} points (no usable target normal" in change.summary()


def test_given_normals_are_scaled_to_unit_length():
    tgt = _plane()
    src = tgt[::5] + [0, 0, 0.1]
    n = np.tile(np.array([-0.2, 0.0, 1.0]), (len(tgt), 1))
    np.testing.assert_allclose(point_to_plane_distance(src, tgt, 3.0 * n),
                               point_to_plane_distance(src, tgt, n / np.linalg.norm(n, axis=1, keepdims=True)),
                               atol=1e-12)


@pytest.mark.parametrize("normals, error, fragment", [
    ("zeros", DegenerateGeometryError, "none of the 2000 target normals is usable"),
    ("nan", DegenerateGeometryError, "none of the 2000 target normals is usable"),
    ("inf", LabkitError, "infinite"),
    ("short", LabkitError, "target_normals must have shape (2000, 3), got (3, 3)"),
    ("text", LabkitError, "target_normals must be numbers"),
])
def test_unusable_normals_are_refused(normals, error, fragment):
    tgt = _plane()
    given = {"zeros": np.zeros((2000, 3)), "nan": np.full((2000, 3), np.nan),
             "inf": np.tile([0, 0, np.inf], (2000, 1)), "short": np.eye(3), "text": [["a", "b", "c"]] * 2000}[normals]
    with pytest.raises(error) as exc:
        point_to_plane_distance(tgt, tgt, given)
    assert fragment in str(exc.value)


def test_distance_options_are_checked():
    tgt = _plane()
    with pytest.raises(LabkitError, match="k must be a whole number >= 3, got 10.5"):
        point_to_plane_distance(tgt, tgt, k=10.5)
    with pytest.raises(LabkitError, match="which must be one of 'before', 'after'"):
        DistanceChange(np.zeros(3), np.zeros(3), "x").stats("middle")


# --------------------------------------------------------------------------- regions
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


# --------------------------------------------------------------------------- command line
@pytest.fixture(scope="module")
def clouds(tmp_path_factory):
    from labkit.synthetic import als_epochs

    d = tmp_path_factory.mktemp("bad_cli")
    pair = als_epochs("xyz", size=(30.0, 30.0), density=4.0, rng=12)
    write_cloud(pair.source, d / "s.laz")
    write_cloud(pair.target, d / "t.laz")
    return d


def _run(argv, capsys):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    cap = capsys.readouterr()
    return code, cap.err


REG = ["register", "{s}", "{t}"]
TIL = ["tiles", "{s}", "--target", "{t}"]
SPH = ["sphere", "{s}"]
CMP = ["compare", "{p}"]


@pytest.mark.parametrize("argv, fragment", [
    (REG + ["--seed", "-1"], "argument --seed: expected a whole number >= 0, got '-1'"),
    (REG + ["--seed", "1.5"], "argument --seed: expected a whole number >= 0, got '1.5'"),
    (REG + ["--seed", "abc"], "argument --seed: expected a whole number >= 0, got 'abc'"),
    (REG + ["--max-points", "-5"], "argument --max-points: expected a whole number >= 1, got '-5'"),
    (REG + ["--max-points", "0"], "argument --max-points: expected a whole number >= 1, got '0'"),
    (REG + ["--max-points", "2.5"], "argument --max-points: expected a whole number >= 1, got '2.5'"),
    (REG + ["--extent", "0"], "argument --extent: expected a positive number, got '0'"),
    (REG + ["--extent", "nan"], "argument --extent: expected a positive number, got 'nan'"),
    (REG + ["--extent", "inf"], "argument --extent: expected a positive number, got 'inf'"),
    (REG + ["--method", "magic"], "argument --method: invalid choice: 'magic'"),
    (REG + ["--dof", "affine"], "argument --dof: invalid choice: 'affine'"),
    (REG + ["--frob"], "unrecognized arguments: --frob"),
    (["register", "{s}"], "the following arguments are required: target"),
    (REG + ["--method", "consensus", "--dof", "rigid"], "translation only"),
    (SPH + ["--threshold", "nan"], "argument --threshold: expected a positive number, got 'nan'"),
    (SPH + ["--threshold", "0"], "argument --threshold: expected a positive number, got '0'"),
    (SPH + ["--p", "1"], "argument --p: expected a number between 0 and 1, got '1'"),
    (SPH + ["--p", "nan"], "argument --p: expected a number between 0 and 1, got 'nan'"),
    (SPH + ["--radius", "-0.1"], "argument --radius: expected a positive number, got '-0.1'"),
    (SPH + ["--sigma", "0"], "argument --sigma: expected a positive number, got '0'"),
    (SPH + ["--seed", "-3"], "argument --seed: expected a whole number >= 0, got '-3'"),
    (SPH + ["--radius-range", "0.1"], "argument --radius-range: expected 2 arguments"),
    (TIL + ["--buffer", "nan"], "argument --buffer: expected a number >= 0, got 'nan'"),
    (TIL + ["--buffer", "-1"], "argument --buffer: expected a number >= 0, got '-1'"),
    (TIL + ["--extra-std", "nan"], "argument --extra-std: expected a number >= 0, got 'nan'"),
    (TIL + ["--extra-std", "-0.1"], "argument --extra-std: expected a number >= 0, got '-0.1'"),
    (TIL + ["--alpha", "0"], "argument --alpha: expected a number between 0 and 1, got '0'"),
    (TIL + ["--alpha", "1.5"], "argument --alpha: expected a number between 0 and 1, got '1.5'"),
    (TIL + ["--min-points", "0"], "argument --min-points: expected a whole number >= 1, got '0'"),
    (TIL + ["--min-points", "1.5"], "argument --min-points: expected a whole number >= 1, got '1.5'"),
    (TIL + ["--size", "0"], "argument --size: expected a positive number, got '0'"),
    (TIL + ["--size", "nan"], "argument --size: expected a positive number, got 'nan'"),
    (TIL + ["--max-tiles", "0"], "argument --max-tiles: expected a whole number >= 1, got '0'"),
    (TIL + ["--scheduler", "gpu"], "argument --scheduler: expected threads, processes, sync, serial, cluster or tcp://"),
    (TIL + ["--size", "0.01"], "tiles of 0.01 m"),
    (TIL + ["--method", "consensus", "--dof", "rigid"], "consensus estimates a translation only"),
    (CMP + ["--methods", "icp", "consensus", "--dof", "rigid"], "consensus estimates a translation only"),
    (TIL + ["--size", "15", "--max-tiles", "3"], "4 tiles of 15 m (2 x 2)"),
    (["tiles", "{s}"], "the following arguments are required: --target"),
    (CMP + ["--alpha", "nan"], "argument --alpha: expected a number between 0 and 1, got 'nan'"),
    (["frobnicate"], "argument command: invalid choice: 'frobnicate'"),
    ([], "the following arguments are required: command"),
    (["sphere", "{missing}"], "not found"),
])
def test_cli_bad_input_is_exit_2_and_one_line(clouds, tmp_path, capsys, argv, fragment):
    names = {"s": clouds / "s.laz", "t": clouds / "t.laz", "p": clouds / "pairs.json", "missing": tmp_path / "no.laz"}
    argv = [a.format(**names) for a in argv]
    out = tmp_path / "out"
    if argv and argv[0] in ("register", "tiles"):
        argv += ["--out", str(out)]
    code, err = _run(argv, capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("labkit") and ": error: " in lines[0]
    assert fragment in lines[0]
    assert not out.exists()


def test_cli_second_move_fails_rolls_back_and_restores(clouds, tmp_path, capsys, monkeypatch):
    """A moved cloud does not stay behind when moving the PNG fails; an older file keeps its content."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "s_registered.laz").write_bytes(b"older result")
    real_replace = os.replace

    def replace(src, dst):
        if str(dst).endswith("s_distances.png"):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(cli.os, "replace", replace)
    code, err = _run(["register", clouds / "s.laz", clouds / "t.laz", "--out", out], capsys)
    assert code == 2 and "No space left on device" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == ["s_registered.laz"]
    assert (out / "s_registered.laz").read_bytes() == b"older result"


def test_cli_out_is_a_file(clouds, tmp_path, capsys):
    (tmp_path / "out").write_text("not a folder")
    code, err = _run(["register", clouds / "s.laz", clouds / "t.laz", "--out", tmp_path / "out"], capsys)
    assert code == 2 and "it is a file, not a folder" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and (tmp_path / "out").read_text() == "not a folder"


def test_cli_failure_removes_the_folders_it_created(clouds, tmp_path, capsys, monkeypatch):
    def broken(fig, path):
        Path(path).write_bytes(b"half")
        raise OSError("disk full")

    monkeypatch.setattr(cli, "save_figure", broken)
    code, err = _run(["register", clouds / "s.laz", clouds / "t.laz", "--out", tmp_path / "a" / "b"], capsys)
    assert code == 2 and "disk full" in err
    assert list(tmp_path.iterdir()) == []


def test_cli_output_name_taken_by_a_folder(clouds, tmp_path, capsys):
    (tmp_path / "s_distances.png").mkdir()
    code, err = _run(["register", clouds / "s.laz", clouds / "t.laz", "--out", tmp_path], capsys)
    assert code == 2 and "a folder of that name exists" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s_distances.png"]
    assert list((tmp_path / "s_distances.png").iterdir()) == []


def test_cli_internal_error_is_one_line_exit_3(clouds, tmp_path, capsys, monkeypatch):
    import labkit.registration.compare as C

    def bug(*args, **kwargs):
        raise TypeError("unsupported operand")

    monkeypatch.setattr(C, "standard_methods", bug)
    monkeypatch.delenv("LABKIT_TRACEBACK", raising=False)
    code, err = _run(["register", clouds / "s.laz", clouds / "t.laz", "--out", tmp_path / "o"], capsys)
    assert code == 3 and len(err.strip().splitlines()) == 1
    assert "internal error: TypeError: unsupported operand" in err and "LABKIT_TRACEBACK=1" in err
    monkeypatch.setenv("LABKIT_TRACEBACK", "1")
    with pytest.raises(TypeError, match="unsupported operand"):
        main(["register", str(clouds / "s.laz"), str(clouds / "t.laz"), "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_cli_float32_utm_file_is_refused(tmp_path, capsys):
    np.save(tmp_path / "utm32.npy", (_cloud() + UTM).astype(np.float32))
    code, err = _run(["sphere", tmp_path / "utm32.npy", "--radius-range", "0.1", "0.5"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"float32 has steps of {_float32_step(5.4e6):.3g} m" in err


def test_cli_warnings_before_an_error_do_not_add_lines(clouds, tmp_path, capsys, monkeypatch):
    import warnings

    import labkit.registration.compare as C

    def noisy(*args, **kwargs):
        warnings.warn("Mean of empty slice", RuntimeWarning)
        warnings.warn("Mean of empty slice", RuntimeWarning)
        raise LabkitError("bad\ninput")

    monkeypatch.setattr(C, "standard_methods", noisy)
    code, err = _run(["register", clouds / "s.laz", clouds / "t.laz", "--out", tmp_path / "o"], capsys)
    assert code == 2 and err == "labkit register: error: bad input\n"

    def demo_ok(args):
        warnings.warn("Mean of\nempty slice", RuntimeWarning)
        warnings.warn("Mean of\nempty slice", RuntimeWarning)
        return 0

    monkeypatch.setattr(cli, "_cmd_demo", demo_ok)
    code, err = _run(["demo", "--out", tmp_path / "o"], capsys)
    assert code == 0 and err == "labkit demo: warning: RuntimeWarning: Mean of empty slice\n"  # once, one line


def test_cli_tile_limit_on_real_epochs(realdata, tmp_path, capsys):
    """Real ALS epochs (35 m x 42 m): a size typed in millimetres is refused at once, naming the count."""
    import laspy

    a, b = realdata / "epochs" / "autzen-bmx-2023.las", realdata / "epochs" / "autzen-bmx-2010.las"
    with laspy.open(a) as ra, laspy.open(b) as rb:
        lo = np.maximum(ra.header.mins[:2], rb.header.mins[:2])
        hi = np.minimum(ra.header.maxs[:2], rb.header.maxs[:2])
    cols, rows = np.floor(hi / 0.001) - np.floor(lo / 0.001) + 1  # tiles from index arithmetic
    code, err = _run(["tiles", a, "--target", b, "--size", "0.001", "--out", tmp_path / "o"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    count = float(err.split("error: ")[1].split(" tiles of 0.001 m")[0].replace(",", ""))
    assert abs(count - cols * rows) <= cols + rows + 1  # a bound on a 1 mm edge may round to either side
    assert not (tmp_path / "o").exists()
