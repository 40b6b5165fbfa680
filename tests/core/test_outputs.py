"""labkit.core.outputs: the files of one command appear together or not at all (direct, without a registration).

The same through the command line (a real registration, the PNG's move failing): tests/cli/test_bad_input_main.py.
"""

import os

import pytest

from labkit.core import outputs as _outputs
from labkit.core.outputs import staged_folder, staged_outputs
from labkit.core.errors import LabkitError


def _visible(folder):
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_nothing_appears_before_the_block_ends_then_everything_does(tmp_path):
    out = tmp_path / "a" / "b"
    with staged_outputs(out) as stage:
        for name in ("x.txt", "y.txt", "z.txt"):
            stage(name).write_text(name)
        assert _visible(out) == []
    assert _visible(out) == ["x.txt", "y.txt", "z.txt"] == sorted(p.name for p in out.iterdir())  # no temporaries
    assert [p.read_text() for p in stage.written] == ["x.txt", "y.txt", "z.txt"]


def test_a_failed_move_rolls_back_the_moved_files_and_restores_the_old_ones(tmp_path, monkeypatch):
    (tmp_path / "x.txt").write_text("old x")
    real = os.replace

    def replace(src, dst):
        if str(dst).endswith("z.txt"):
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(_outputs.os, "replace", replace)
    with pytest.raises(OSError, match="No space left"):
        with staged_outputs(tmp_path) as stage:
            for name in ("x.txt", "y.txt", "z.txt"):
                stage(name).write_text("new " + name)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.txt"]  # y went again, no temporaries stay
    assert (tmp_path / "x.txt").read_text() == "old x"


@pytest.mark.parametrize("use", [staged_outputs, staged_folder])
def test_a_failure_in_the_block_leaves_nothing_new_not_even_the_folders(tmp_path, use):
    (tmp_path / "keep.txt").write_text("k")
    with pytest.raises(RuntimeError):
        with use(tmp_path / "new" / "deeper") as stage:
            path = stage("f.txt") if use is staged_outputs else stage / "f.txt"
            path.write_text("half")
            raise RuntimeError("a later step failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]


def test_staged_folder_moves_every_file_written_into_the_work_folder(tmp_path):
    (tmp_path / "one.txt").write_text("older")
    with staged_folder(tmp_path) as work:
        assert work.parent == tmp_path and list(work.iterdir()) == []
        (work / "one.txt").write_text("1")
        (work / "two.txt").write_text("2")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.txt", "two.txt"]
    assert (tmp_path / "one.txt").read_text() == "1"


def test_a_file_in_the_way_is_refused_clearly(tmp_path):
    (tmp_path / "out").write_text("not a folder")
    with pytest.raises(LabkitError, match="it is a file, not a folder"):
        with staged_outputs(tmp_path / "out") as stage:
            stage("a.txt")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "a.png").mkdir()
    with pytest.raises(LabkitError, match="a folder of that name exists"):
        with staged_outputs(tmp_path / "d") as stage:
            stage("a.png")
    assert (tmp_path / "out").read_text() == "not a folder"
    assert list((tmp_path / "d").iterdir()) == [tmp_path / "d" / "a.png"]
