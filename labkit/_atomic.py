"""Atomic file writing: a failed write never leaves a half-written file."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import LabkitError


def atomic_write_text(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically: a temp file in the same folder, then ``os.replace``.

    On any failure the temp file is removed and an existing file at ``path`` is left untouched.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise LabkitError(f"cannot write {path}: the folder {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
