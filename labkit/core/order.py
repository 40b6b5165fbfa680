"""Order statistics of large arrays without a partition of the whole array: the median as ``np.median`` gives it.

``np.median`` partitions all n values (introselect, about 10 ns a value). The robust scale of ICP takes two
medians of some 10^5 residuals in every iteration. Here a sorted even sample of the values brackets the
wanted ranks, one compiled pass counts the values below the bracket and copies those inside it, and
only these few are partitioned. The answer is an element of the array (and for an even count the mean of
two, formed as ``np.median`` forms it), so it is the same number; where the bracket misses the ranks, or
the array holds NaN or the answer is a zero (whose sign a partition may pick either way), ``np.median``
itself answers.
"""

from __future__ import annotations

import numpy as np

from .jit import compiled, have_numba

__all__ = ["median"]

#: Below this many values ``np.median`` is about as fast.
MIN_SIZE = 40_000
#: Values in the sorted sample that brackets the wanted ranks.
SAMPLE = 8192
#: Half-width of the bracket in the sample, in standard deviations of a sample rank (sqrt(SAMPLE) / 2).
MARGIN_SD = 6.0


def median(x):
    """``np.median(x)`` of a 1-D float64 array, the same number, by a partition of a bracket of its values.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.random.default_rng(0).normal(size=100_001)
    >>> float(median(x)) == float(np.median(x)), float(median(x[1:])) == float(np.median(x[1:]))
    (True, True)
    """
    x = np.asarray(x)
    n = len(x)
    if x.ndim != 1 or n < MIN_SIZE or x.dtype != np.float64 or not have_numba():
        return np.median(x)
    k1, k2 = (n - 1) // 2, n // 2
    sample = np.sort(x[:: n // SAMPLE])
    s = len(sample)
    margin = int(MARGIN_SD * 0.5 * np.sqrt(s)) + 2
    j1, j2 = (k1 * s) // n - margin, (k2 * s) // n + margin
    lo = sample[j1] if j1 >= 0 else -np.inf
    hi = sample[j2] if j2 < s else np.inf
    a, b, ok = compiled(_bracketed_pair)(x, k1, k2, lo, hi)
    if not ok:
        return np.median(x)
    a, b = np.float64(a), np.float64(b)
    return a if k1 == k2 else (a + b) / 2  # np.median: the mean of the two middle values


def _bracketed_pair(x, k1, k2, lo, hi):  # pragma: no cover - compiled
    """The k1-th and k2 = k1 or k1 + 1-th smallest values of x when both lie in [lo, hi], and True; else False.

    One pass without branches counts the values below ``lo`` and copies those in [lo, hi] (NaN is neither,
    and is counted apart); the copies are partitioned at the first rank, the second is the smallest above it.
    """
    n = x.shape[0]
    buf = np.empty(n)
    below = 0
    k = 0
    nan = 0
    for i in range(n):
        v = x[i]
        below += v < lo
        buf[k] = v
        k += (v >= lo) & (v <= hi)
        nan += v != v
    if nan > 0 or below > k1 or below + k <= k2:
        return 0.0, 0.0, False
    r = k1 - below
    part = np.partition(buf[:k], r)
    a = part[r]
    b = a
    if k2 > k1:
        b = part[r + 1]
        for j in range(r + 2, k):
            if part[j] < b:
                b = part[j]
    if a == 0.0 or b == 0.0:  # -0.0 and 0.0 compare equal: which one a partition returns is its own choice
        return 0.0, 0.0, False
    return a, b, True
