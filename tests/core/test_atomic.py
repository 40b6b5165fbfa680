"""labkit.core.atomic: a write either completes or leaves the destination as it was, with the usual permissions.

The writers built on it (write_cloud, the CLI outputs) are tested in tests/test_io.py and tests/test_cli.py.
"""

import os
import stat

import pytest

from labkit.core.atomic import atomic_path, atomic_write_text, file_mode, temporary_path
from labkit.core.errors import LabkitError


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    try:
        yield
    finally:
        os.umask(old)


@pytest.mark.parametrize("path, text, fragment", [
    (None, "x", "must be a file path (str or pathlib.Path), got None"),
    (3, "x", "must be a file path (str or pathlib.Path), got 3"),
    ("", "x", "must be a file path"),
    ("{tmp}/missing/a.txt", "x", "the folder"),
    ("{tmp}", "x", "a folder of that name exists"),
])
def test_atomic_write_refuses(tmp_path, path, text, fragment):
    path = path.format(tmp=tmp_path) if isinstance(path, str) else path
    with pytest.raises(LabkitError) as exc:
        atomic_write_text(path, text)
    assert fragment in str(exc.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no temporary left behind


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    path = atomic_write_text(tmp_path / "a.csv", "old\n")
    with pytest.raises(TypeError):
        atomic_write_text(path, b"bytes are not text")  # fails inside the write
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv"]


def test_text_is_written_exactly_and_replaces_an_existing_file(tmp_path):
    path = tmp_path / "r.txt"
    path.write_text("an older and longer content\n" * 10)
    with open(path) as reader:  # a reader of the old file keeps reading the old file
        assert atomic_write_text(str(path), "Höhe\r\nz = 1\n") == path
        assert reader.read().startswith("an older")
    assert path.read_bytes() == "Höhe\r\nz = 1\n".encode()  # UTF-8, newlines untouched, nothing of the old left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.txt"]


@pytest.mark.parametrize("error", [RuntimeError("half way"), KeyboardInterrupt()])
def test_no_partial_file_while_writing_or_after_a_failure(tmp_path, error):
    new, old = tmp_path / "new.bin", tmp_path / "old.bin"
    old.write_bytes(b"old")
    for path, before in ((new, None), (old, b"old")):
        with pytest.raises(type(error)):
            with atomic_path(path) as tmp:
                assert tmp.parent == path.parent and tmp.name.startswith(".") and tmp != path
                tmp.write_bytes(b"half")
                assert (path.read_bytes() if path.exists() else None) == before  # not visible while writing
                raise error
        assert (path.read_bytes() if path.exists() else None) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.bin"]  # no temporary left


def test_new_and_replaced_files_get_the_umask_permissions_not_mkstemps(tmp_path, umask_027):
    assert file_mode() == 0o640
    assert os.umask(0o027) == 0o027  # asking for the mode leaves the umask as it was
    tmp = temporary_path(tmp_path / "a.txt")
    assert stat.S_IMODE(tmp.stat().st_mode) == 0o640 and tmp.stat().st_size == 0
    tmp.unlink()
    path = atomic_write_text(tmp_path / "a.txt", "1")
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    path.chmod(0o600)
    atomic_write_text(path, "2")  # a replacement gets the umask's mode, like a new file
    assert stat.S_IMODE(path.stat().st_mode) == 0o640 and path.read_text() == "2"
