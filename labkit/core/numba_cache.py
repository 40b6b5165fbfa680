"""Where numba keeps labkit's compiled kernels, so that no process pays the compilation twice.

Every kernel of labkit is compiled with ``cache=True``: the first process that
calls it writes the machine code to disk, every later process loads it (about
a millisecond instead of 0.5-5 s of compilation). numba looks for a writable
place in this order: ``NUMBA_CACHE_DIR``, the ``__pycache__`` folder beside the
module, the user's cache folder (``~/.cache/numba``). When labkit is installed
read-only and the home folder is read-only too (containers, CI images), numba
finds none and *raises* at import time ("cannot cache function: no locator
available"). :func:`ensure_cache_dir` runs before any kernel is defined and, in
that case only, points numba to a per-user folder under the temporary
directory.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]


def _writable(folder: Path) -> bool:
    """True if ``folder`` exists or can be created, and a file can be written in it (numba's own test)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _user_cache() -> Path:
    """numba's user-wide cache folder (``numba.misc.appdirs``, without importing numba)."""
    if sys.platform == "win32":  # pragma: no cover - platform specific
        return Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local")) / "numba" / "Cache"
    if sys.platform == "darwin":  # pragma: no cover - platform specific
        return Path.home() / "Library" / "Caches" / "numba"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba"


def fallback_dir() -> Path:
    """The folder used when neither the package nor the user's cache folder is writable."""
    uid = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
    return Path(tempfile.gettempdir()) / f"labkit-numba-cache-{uid}"


def ensure_cache_dir(package: Path = PACKAGE, user_cache: Path | None = None) -> str | None:
    """Point numba to :func:`fallback_dir` if it would find no writable cache folder; return the folder set.

    Returns None (and changes nothing) when ``NUMBA_CACHE_DIR`` is set or numba's
    own search succeeds (package ``__pycache__`` or user cache folder writable).
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    if _writable(package / "__pycache__"):
        return None
    try:
        home_ok = _writable(user_cache if user_cache is not None else _user_cache())
    except RuntimeError:  # no home folder at all
        home_ok = False
    if home_ok:
        return None
    folder = fallback_dir()
    if not _writable(folder):
        return None
    os.environ["NUMBA_CACHE_DIR"] = str(folder)  # read by numba when it is imported (also by child processes)
    if "numba" in sys.modules:  # numba already imported: its configuration was read before
        sys.modules["numba"].config.CACHE_DIR = str(folder)
    return str(folder)
