"""Atomic file writing: a failed write never leaves a half-written file.

Everything is first written to a temporary file in the destination folder and
renamed over the destination (``os.replace``) only when complete. Temporary
files get the usual permissions (0666 minus the umask), not mkstemp's 0600.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from .errors import LabkitError


def file_mode() -> int:
    """Permissions of a new file under the current umask (what ``open`` would give)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def temporary_path(path: Path, suffix: str = ".part") -> Path:
    """A new empty temporary file next to ``path``, with the usual permissions."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f"{suffix}{path.suffix}")
    os.close(fd)
    os.chmod(tmp, file_mode())
    return Path(tmp)


def as_path(path, what: str = "output file") -> Path:
    """``path`` as a Path; anything but a str or os.PathLike (None, a number) is refused."""
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise LabkitError(f"the {what} must be a file path (str or pathlib.Path), got {path!r}")
    return Path(path)


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path next to ``path``; rename it over ``path`` only on success.

    On any failure the temporary file is removed and an existing file at ``path``
    is left untouched.
    """
    path = as_path(path)
    if not path.parent.is_dir():
        raise LabkitError(f"cannot write {path}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise LabkitError(f"cannot write {path}: a folder of that name exists")
    tmp = temporary_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    path = as_path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
    return path
