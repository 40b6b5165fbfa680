"""ICP gives bit-identical results for the same input: across processes, thread counts and call order."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labkit.registration import icp

HERE = Path(__file__).resolve().parent

#: one ICP run with defaults (point selection, threaded kd-tree build and queries on > 100,000 points,
#: height-model fill of the along-ridge X) in a fresh interpreter; prints the bytes
CHILD = """
import sys
sys.path.insert(0, {here!r})
import numpy as np
from test_height_model import SHIFT, gable_scene
from labkit.registration import icp
rng = np.random.default_rng(11)
src, tgt = gable_scene(120_000, rng) - SHIFT, gable_scene(120_000, rng)
if not {first!r}:  # another call on the same target first (its kept kd-tree and neighbours): no effect
    icp(tgt[::7] + [0.1, 0.0, 0.0], tgt)
res = icp(src, tgt)
assert res.height_model is not None and res.height_model.determined[0]
hist = np.array([r.translation for r in res.history])
print(b"".join(np.ascontiguousarray(a).tobytes() for a in (res.translation, res.covariance, hist)).hex())
"""


def test_icp_is_bit_identical_across_processes_thread_counts_and_call_order(all_cores_and_one):
    code = lambda first: CHILD.format(here=str(HERE), first=first)  # noqa: E731
    out = all_cores_and_one(code(True), code(False))  # every core vs one core, one thread per pool
    assert out[0] and out[0] == out[1]


def test_the_default_seed_makes_a_sampled_icp_repeatable():
    from labkit.synthetic import wavy_surface

    rng = np.random.default_rng(3)
    target = wavy_surface(6000, rng)
    source = wavy_surface(6000, rng) - [0.05, 0.02, 0.03]
    a = icp(source, target, sample=("random", 1500), select="all")  # the sampling draws from rng
    b = icp(source, target, sample=("random", 1500), select="all")
    c = icp(source, target, sample=("random", 1500), select="all", rng=1)
    assert np.array_equal(a.translation, b.translation) and np.array_equal(a.covariance, b.covariance)
    assert not np.array_equal(a.translation, c.translation)  # another seed: another sample
