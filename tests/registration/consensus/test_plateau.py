"""The centre of the consensus hill along held directions (labkit.registration.consensus.plateau).

Independent routes: the consensus profile against a brute-force count with a kd-tree per
translation; the hill centre against the known centre of noisy symmetric profiles; on a scene of
parallel gable roofs of finite length (ridges along y: the local planes leave Y undetermined, only
the gable ends bound it) the known truth over several random samplings, beside the
branch-and-bound maximum it replaces.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labkit.registration import max_consensus
from labkit.registration.consensus import cube
from labkit.registration.consensus.inputs import prepare_problem
from labkit.registration.consensus.plateau import consensus_profile, hill_centre
from labkit.synthetic import als_epochs

TRUTH = np.array([0.2, -0.3, 0.1])


def gable_town(rng, density=4.0, size=40.0, noise=0.02):
    """Flat ground and four parallel gable roofs 8 m wide and 14 m long, ridges along y (37 deg slopes)."""
    n = rng.poisson(density * size * size)
    x, y = rng.uniform(0, size, n), rng.uniform(0, size, n)
    z = np.zeros(n)
    for xc, yc in ((10.0, 12.0), (26.0, 10.0), (12.0, 29.0), (28.0, 30.0)):
        on = (np.abs(x - xc) < 4.0) & (np.abs(y - yc) < 7.0)
        z[on] = 6.0 + 3.0 * (1.0 - np.abs(x[on] - xc) / 4.0)
    return np.column_stack([x, y, z + rng.normal(0, noise, n)])


def brute_profile(pb, t, d, s):
    """Consensus by one kd-tree search per voting point and translation (eq. 6.2-6.4)."""
    tree, out = cKDTree(pb.tgt), []
    for si in s:
        x = pb.src + t + si * d
        total = 0.0
        for j, (xi, nb) in enumerate(zip(x, tree.query_ball_point(x, pb.radius))):
            nb = np.asarray(nb, dtype=int)
            e = xi - pb.tgt[nb]
            ok = (np.einsum("ij,ij->i", e, e) < pb.radius**2) & (np.abs(np.einsum("ij,ij->i", e, pb.tgt_normals[nb]))
                                                                 < pb.eps)
            total += pb.w[j] * ok.any()
        out.append(total)
    return np.array(out)


@pytest.mark.parametrize("use_numba", [False, True])
def test_profile_equals_brute_force(use_numba):
    pair = als_epochs("xyz", size=(20.0, 20.0), density=4, rng=5)
    pb = prepare_problem(pair.source, pair.target, "point_to_plane", 0.03, None, None, None, None, 12, max_points=300)
    d = np.array([0.6, 0.8, 0.0])
    s = np.linspace(-1.5, 1.5, 13)
    got = consensus_profile(pb, pair.translation, d, s, use_numba=use_numba)
    assert np.array_equal(got, brute_profile(pb, pair.translation, d, s))
    assert got[6] == got.max() > got[0]  # the truth has the most consensus along this line


def test_hill_centre_finds_the_centre_of_bumpy_flat_topped_hills():
    """A hill with a flat top 1 m wide, flanks of 100 counts per m and random bumps of up to 30 counts
    and 0.1 m width (as on the real profiles: single patches entering and leaving the tolerance): the
    centre within 0.2 m (rms 0.07 m) of the truth, while the highest sample lands on some bump."""
    rng = np.random.default_rng(1)
    s = np.linspace(-3, 3, 241)
    centre_err, argmax_err = [], []
    for _ in range(40):
        c0 = rng.uniform(-0.8, 0.8)
        mean = 4000.0 - 100.0 * np.clip(np.abs(s - c0) - 0.5, 0, None)
        bumps = sum(rng.uniform(0, 30) * np.exp(-((s - rng.uniform(-3, 3)) / 0.1) ** 2) for _ in range(20))
        counts = np.rint(mean + bumps + rng.normal(0, 5, s.size))
        centre_err.append(hill_centre(s, counts, 1.5) - c0)
        argmax_err.append(s[np.argmax(counts)] - c0)
    assert np.max(np.abs(centre_err)) < 0.2 and np.sqrt(np.mean(np.square(centre_err))) < 0.07
    assert np.sqrt(np.mean(np.square(argmax_err))) > 0.25


def test_hill_centre_keeps_a_sharp_peak():
    """A narrow peak at 0 on broad flanks centred at 1.5: the quadratic would follow the flanks to a
    translation far below the top; the start is kept."""
    s = np.linspace(-3, 3, 241)
    counts = np.rint(3000.0 - 100.0 * (s - 1.5) ** 2 + 1000.0 * np.exp(-(s / 0.05) ** 2))
    assert hill_centre(s, counts, 1.5) == 0.0
    assert abs(hill_centre(s, counts - 1000.0 * np.exp(-(s / 0.05) ** 2), 1.5) - 1.5) < 0.01  # without the peak


def test_hill_centre_without_a_maximum_stays_put():
    s = np.linspace(-2, 2, 81)
    assert hill_centre(s, 100.0 + 5.0 * s, 1.0) == 0.0  # a straight slope: no maximum in any window
    assert hill_centre(s, 100.0 + 5.0 * s**2, 1.0) == 0.0  # a valley


@pytest.mark.slow
def test_held_direction_lands_at_the_hill_centre_on_finite_gable_roofs(monkeypatch):
    """Y along the ridges: reported undetermined, but over 6 random samplings within 10 cm of the truth,
    where the branch-and-bound maximum (what was kept before) scatters three times as much or more; X and Z, which the
    roof planes determine, are exactly what the refinement gives without the move."""
    plateau, argmax, fixed = [], [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        tgt, src = gable_town(rng), gable_town(rng) - TRUTH
        res = max_consensus(src, tgt, height_model=False)
        assert res.degeneracy.undetermined_axes == ("Y",)
        assert res.translation_std[1] > 0.1 and np.all(res.translation_std[[0, 2]] < 0.01)
        plateau.append(res.translation - TRUTH)
        argmax.append(res.history[0].translation - TRUTH)
        if seed < 2:  # the determined axes do not move
            with monkeypatch.context() as m:
                m.setattr(cube, "centre_result", lambda r, *a, **k: r)
                kept = max_consensus(src, tgt, height_model=False)
            fixed.append(np.array_equal(kept.translation[[0, 2]], res.translation[[0, 2]]))
            assert "centre of the consensus hill" in res.message
    plateau, argmax = np.array(plateau), np.array(argmax)
    assert all(fixed)
    assert np.max(np.abs(plateau[:, 1])) < 0.1
    assert np.sqrt(np.mean(argmax[:, 1] ** 2)) > 3 * np.sqrt(np.mean(plateau[:, 1] ** 2))
    again = max_consensus(src, tgt, height_model=False)  # deterministic
    assert np.array_equal(again.translation, res.translation)


def test_hill_centre_does_not_depend_on_the_start():
    """The same bumpy flat-topped hill profiled from five starts on its top: one centre (within a
    sample), near the true one; the centre is a property of the profile, not of the start."""
    rng = np.random.default_rng(3)
    centres = rng.uniform(-3, 3, 20)

    def hill(x):
        return np.rint(4000.0 - 100.0 * np.clip(np.abs(x - 0.3) - 0.5, 0, None)
                       + sum(30.0 * np.exp(-((x - c) / 0.1) ** 2) for c in centres))

    s = np.linspace(-3, 3, 241)
    found = [start + hill_centre(s, hill(start + s), 1.5) for start in (-0.4, -0.13, 0.0, 0.13, 0.4)]
    assert np.ptp(found) <= 0.025 + 1e-9, found
    assert abs(np.mean(found) - 0.3) < 0.1
