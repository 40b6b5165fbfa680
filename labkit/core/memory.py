"""Freed memory kept in the process for the next call instead of handed back to the system (glibc only).

labkit's large steps (the surface selection, ICP, M3C2) allocate and free tens to hundreds of MB of
work arrays per call. glibc's malloc gives the free top of its heap back to the kernel once more than
``M_TRIM_THRESHOLD`` bytes are free there (at most 64 MB with its default, dynamic settings) and maps
larger arrays separately (``M_MMAP_THRESHOLD``). Handing pages back is cheap; taking them again is
not always: the kernel zeroes every page on first touch, and on a virtual machine whose host reclaims
the guest's free memory (free page reporting: pages free for about two seconds go back to the host)
the host must supply each page again. Measured on this project's 2-core VM: 100 MB of new pages took
8 ms when freed a moment before and 390-700 ms when freed two or more seconds before (at another time
21 ms: how much the host takes back varies with its own load; ``benchmarks/bench_memory.py``). A registration
of the real TLS halves (262,000 points each) paid 7,500 page faults and 150 ms of system time per call
that way, 2.5 s after the last one; with the freed memory kept, 300 faults and 9 ms.

:func:`keep_freed_memory` therefore raises the trim threshold to :data:`KEEP` (256 MB of free heap
stay in the process for reuse) and fixes the mmap threshold at 32 MB (glibc's own ceiling for its
dynamic threshold, which an explicit trim threshold would otherwise freeze at its 128 KB start: every
array beyond that would be a new mapping). It is called once when labkit is imported; the environment
variable ``LABKIT_KEEP_FREED_MEMORY=0`` leaves malloc as it is. Other C libraries (musl, macOS,
Windows) are left alone. The process's resident memory after a call is then up to 256 MB higher than
its live data; the peak of a call does not grow (the kept memory is what the next arrays reuse).
"""

from __future__ import annotations

import ctypes
import os
import platform

__all__ = ["KEEP", "keep_freed_memory"]

KEEP = 256 << 20  # bytes of free heap kept for reuse (M_TRIM_THRESHOLD)
MMAP = 32 << 20  # arrays from this size on get their own mapping (M_MMAP_THRESHOLD; glibc's dynamic ceiling)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (malloc.h)
_state = {"applied": None}


def keep_freed_memory() -> bool:
    """Tell glibc's malloc to keep up to :data:`KEEP` bytes of freed heap for reuse (module docstring).

    Returns
    -------
    bool
        True where the settings were made (glibc, not switched off by ``LABKIT_KEEP_FREED_MEMORY=0``),
        also on later calls; False elsewhere.

    Examples
    --------
    >>> import platform
    >>> keep_freed_memory() == (platform.libc_ver()[0] == "glibc" and
    ...                         os.environ.get("LABKIT_KEEP_FREED_MEMORY", "1") != "0")
    True
    """
    if os.environ.get("LABKIT_KEEP_FREED_MEMORY", "1").strip() == "0":
        return False
    if _state["applied"] is not None:
        return _state["applied"]
    ok = False
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        try:
            mallopt = ctypes.CDLL("libc.so.6").mallopt
            mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
            # the mmap threshold first: the trim threshold's call alone would freeze it at 128 KB
            ok = mallopt(_M_MMAP_THRESHOLD, MMAP) == 1 and mallopt(_M_TRIM_THRESHOLD, KEEP) == 1
        except (OSError, AttributeError):  # pragma: no cover - a glibc without mallopt
            pass
    _state["applied"] = ok
    return ok
