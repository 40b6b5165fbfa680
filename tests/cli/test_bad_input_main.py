"""Bad input at the command line: exit 2 and one line; failures roll back what they wrote."""

import os
from pathlib import Path

import numpy as np
import pytest

import labkit.cli.main as cli
from labkit.cli.main import main
from labkit.core.errors import LabkitError
from labkit.io import write_cloud

UTM = np.array([540_000.0, 5_400_000.0, 300.0])


def _float32_step(x: float) -> float:
    """Spacing of float32 at |x| from its 24-bit significand (independent of numpy's spacing)."""
    return 2.0 ** (np.floor(np.log2(abs(x))) - 23)


def _cloud(n=200, seed=0, offset=0.0):
    return np.random.default_rng(seed).uniform(0, 10, (n, 3)) + offset


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
