"""labkit.core.threads: calls side by side give the results of calls one after the other."""

import threading

import numpy as np
import pytest

from labkit.core.threads import side_by_side


def test_results_in_the_order_given_and_on_several_threads():
    seen = []
    meet = threading.Barrier(3, timeout=20)  # passes only when the three calls run at the same time

    def work(x):
        seen.append(threading.get_ident())
        meet.wait()
        return np.sort(x)

    rng = np.random.default_rng(0)
    a, b, c = (rng.normal(size=1000) for _ in range(3))
    out = side_by_side((work, a), (work, b), (work, c))
    assert all(np.array_equal(o, np.sort(x)) for o, x in zip(out, (a, b, c)))
    assert threading.get_ident() in seen and len(set(seen)) == 3
    assert side_by_side((len, "abc")) == [3] and side_by_side() == []


def test_an_exception_of_any_call_is_raised():
    def fail(msg):
        raise ValueError(msg)

    with pytest.raises(ValueError, match="first"):
        side_by_side((fail, "first"), (len, "ok"))
    with pytest.raises(ValueError, match="last"):
        side_by_side((len, "ok"), (fail, "last"))
