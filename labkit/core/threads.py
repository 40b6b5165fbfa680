"""Independent calls side by side on the cores: the two clouds of a registration, each in its own thread.

The steps of a registration that treat the source and the target alike (the kd-tree, the surface test,
the normals) are independent. Each of them already spreads its compiled loops over the cores, but each
also has serial parts (numpy passes, the root split of a kd-tree, gathers): run one after the other, a
two-core machine waits there with one core idle. Run side by side, one cloud's serial part overlaps the
other's work. The compiled kernels release the GIL (``labkit.core.jit.compiled``), and so do numpy's
larger array operations; every call computes the same numbers as alone.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

__all__ = ["cores", "side_by_side"]


def cores():
    """The cores this process may run on (its CPU affinity where the system has one).

    Examples
    --------
    >>> cores() >= 1
    True
    """
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def side_by_side(*calls):
    """The results of the calls ``(function, *args)``, run at the same time (the last one in this thread).

    An exception of any call is raised here once every call has ended (the first in the order given).

    Examples
    --------
    >>> side_by_side((sum, [1, 2, 3]), (max, 3, 7))
    [6, 7]
    """
    if len(calls) <= 1:
        return [f(*args) for f, *args in calls]
    with ThreadPoolExecutor(len(calls) - 1, "labkit-side") as pool:
        jobs = [pool.submit(f, *args) for f, *args in calls[:-1]]
        f, *args = calls[-1]
        try:
            last = f(*args)
        except BaseException:
            for job in jobs:
                job.exception()  # let the others end before raising
            raise
        return [job.result() for job in jobs] + [last]
