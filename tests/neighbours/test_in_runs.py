"""labkit.neighbours.kdtree_build.in_runs: every range once, on the kept pool, errors raised, nesting safe."""

import threading

import numpy as np
import pytest

from labkit.neighbours.kdtree_build import in_runs


def test_every_range_is_run_once_whoever_runs_it():
    seen, lock = [], threading.Lock()

    def run(a, b):
        with lock:
            seen.append((a, b))

    cuts = np.linspace(0, 1000, 17).astype(int)
    in_runs(run, cuts, 4)
    assert sorted(seen) == list(zip(cuts[:-1].tolist(), cuts[1:].tolist()))


def test_an_error_in_a_range_is_raised_to_the_caller():
    def run(a, b):
        if a == 30:
            raise ValueError("range 30")

    with pytest.raises(ValueError, match="range 30"):
        in_runs(run, [0, 10, 20, 30, 40, 50], 2)


def test_nested_use_of_the_pool_finishes():
    out = np.zeros(64)

    def inner(a, b):
        out[a:b] += 1

    def outer(a, b):
        in_runs(inner, np.arange(a, b + 1), 2)  # every range may itself use the pool

    done = threading.Event()
    worker = threading.Thread(target=lambda: (in_runs(outer, np.arange(0, 65, 8), 2), done.set()), daemon=True)
    worker.start()
    worker.join(30)
    assert done.is_set(), "in_runs nested in in_runs did not finish"
    assert (out == 1).all()


@pytest.mark.parametrize("threads", [1, 2, 4])
def test_empty_ranges_are_skipped_not_taken_for_the_end(threads):
    seen, lock = [], threading.Lock()

    def run(a, b):
        with lock:
            seen.append((a, b))

    in_runs(run, np.linspace(0, 1, 5).astype(int), threads)  # [0, 0, 0, 0, 1]: only the last range holds rows
    in_runs(run, [0, 3, 3, 7], threads)
    assert sorted(seen) == [(0, 1), (0, 3), (3, 7)]
