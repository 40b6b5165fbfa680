"""Output files of the command line and the demo: figures and renders saved as PNG, and staged outputs.

Output files are staged next to their destination and moved into place only
when every file of a command has been written; if moving one fails, those
already moved are rolled back (files they replaced are restored) and folders
the command created are removed, so a failure leaves nothing new behind.
Used by :mod:`labkit.cli` and :mod:`labkit.demo` (which therefore do not import
each other's helpers).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

from .atomic import temporary_path
from .errors import LabkitError


def save_figure(fig, path) -> Path:
    """Save a matplotlib figure as PNG (to ``path``, which should be a staged path) and close it.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import matplotlib
    >>> matplotlib.use("Agg")
    >>> import matplotlib.pyplot as plt
    >>> from labkit.core.outputs import save_figure
    >>> fig, ax = plt.subplots()
    >>> _ = ax.plot([0, 1], [0, 1])
    >>> path = save_figure(fig, Path(tempfile.mkdtemp()) / "line.png")
    >>> path.read_bytes()[:4] == b"\\x89PNG"
    True
    """
    import matplotlib.pyplot as plt

    try:
        fig.savefig(path, format="png", dpi=110)
    finally:
        plt.close(fig)
    return Path(path)


def save_render(plotter, path) -> Path:
    """Render a pyvista plotter off screen into a PNG and close it.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from labkit.core.outputs import save_render
    >>> class Plotter:  # stands in for a pyvista.Plotter: screenshot() and close()
    ...     def screenshot(self, path):
    ...         Path(path).write_bytes(b"png")
    ...     def close(self):
    ...         print("closed")
    >>> path = save_render(Plotter(), Path(tempfile.mkdtemp()) / "view.png")
    closed
    >>> path.read_bytes()
    b'png'
    """
    try:
        plotter.screenshot(str(path))
    finally:
        plotter.close()
    return Path(path)


class _Stage:
    """Hands out temporary paths next to their destinations; :meth:`commit` moves them all into place.

    The commit is all or nothing: a destination that exists is first set aside;
    if any move fails, the files already moved are removed, the set-aside files
    restored, and folders the stage created are deleted again.
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.pending: list[tuple[Path, Path]] = []
        self.written: list[Path] = []
        self.created: list[Path] = []  # folders made for the outputs, deepest last

    def __call__(self, name: str) -> Path:
        self._make_folder()
        final = self.folder / name
        if final.is_dir():
            raise LabkitError(f"cannot write {final}: a folder of that name exists")
        tmp = temporary_path(final)
        self.pending.append((tmp, final))
        return tmp

    def _make_folder(self) -> None:
        if self.folder.exists() and not self.folder.is_dir():
            raise LabkitError(f"cannot write into {self.folder}: it is a file, not a folder")
        missing = [p for p in (self.folder, *self.folder.parents) if not p.exists()]
        for folder in reversed(missing):
            folder.mkdir()
            self.created.append(folder)

    def commit(self) -> None:
        moved: list[tuple[Path, Path | None]] = []  # (final, set-aside old file or None)
        try:
            for tmp, final in self.pending:
                old = None
                if final.exists() or final.is_symlink():
                    old = temporary_path(final, ".old")
                    os.replace(final, old)
                moved.append((final, old))
                os.replace(tmp, final)
        except BaseException:
            for final, old in reversed(moved):  # roll back: new files out, old files back
                with contextlib.suppress(OSError):
                    if old is not None:
                        os.replace(old, final)
                    else:
                        final.unlink(missing_ok=True)
            raise
        for final, old in moved:
            if old is not None:
                with contextlib.suppress(OSError):
                    old.unlink()
            self.written.append(final)
        self.pending = []

    def discard(self) -> None:
        for tmp, _ in self.pending:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        self.pending = []
        for folder in reversed(self.created):
            with contextlib.suppress(OSError):  # only empty folders go
                folder.rmdir()
        self.created = []


@contextlib.contextmanager
def staged_folder(folder):
    """``with staged_folder(dir) as work: ...``: files written into the empty folder ``work`` move into
    ``dir`` together when the block succeeds (all or nothing, as :func:`staged_outputs`).

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from labkit.core.outputs import staged_folder
    >>> folder = Path(tempfile.mkdtemp()) / "figures"
    >>> with staged_folder(folder) as work:
    ...     _ = (work / "one.txt").write_text("1")
    ...     _ = (work / "two.txt").write_text("2")
    >>> sorted(p.name for p in folder.iterdir())
    ['one.txt', 'two.txt']
    """
    stage = _Stage(Path(folder))
    stage._make_folder()
    work = Path(tempfile.mkdtemp(dir=stage.folder, prefix=".staging-"))
    try:
        yield work
        stage.pending = [(f, stage.folder / f.name) for f in sorted(work.iterdir()) if f.is_file()]
        stage.commit()
    except BaseException:
        stage.pending = []
        shutil.rmtree(work, ignore_errors=True)
        stage.discard()
        raise
    shutil.rmtree(work, ignore_errors=True)


@contextlib.contextmanager
def staged_outputs(folder):
    """``with staged_outputs(dir) as stage: write(stage("a.laz")) ...``: all files appear together or none.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from labkit.core.outputs import staged_outputs
    >>> folder = Path(tempfile.mkdtemp()) / "out"
    >>> with staged_outputs(folder) as stage:
    ...     _ = stage("a.txt").write_text("first")
    ...     _ = stage("b.txt").write_text("second")
    ...     sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))  # nothing moved yet
    []
    >>> [p.name for p in stage.written]
    ['a.txt', 'b.txt']
    >>> try:
    ...     with staged_outputs(folder) as stage:
    ...         _ = stage("a.txt").write_text("replaced")
    ...         raise RuntimeError("a later step failed")
    ... except RuntimeError:
    ...     pass
    >>> (folder / "a.txt").read_text()
    'first'
    """
    stage = _Stage(Path(folder))
    try:
        yield stage
        stage.commit()
    except BaseException:
        stage.discard()
        raise
