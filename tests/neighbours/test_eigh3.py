"""Tests of labkit.neighbours.eigh3: Jacobi eigen decomposition of stacks of symmetric 3x3 matrices."""

import numpy as np
import pytest

from labkit.neighbours import eigh3 as E
from labkit.neighbours.eigh3 import eigh3

EPS = np.finfo(np.float64).eps
# Integer matrices M with M^T M = q I: C = M diag(d) M^T is exact in float64 and has the
# eigenvalues q d_i with eigenvectors M[:, i] / sqrt(q), known without any rounding.
M9 = np.array([[1, 2, 2], [2, 1, -2], [2, -2, 1]], dtype=np.float64)  # q = 9
M49 = np.array([[2, 3, 6], [3, -6, 2], [6, 2, -3]], dtype=np.float64)  # q = 49


def random_rotations(rng, m):
    Q, R = np.linalg.qr(rng.normal(size=(m, 3, 3)))
    return Q * np.sign(np.diagonal(R, axis1=1, axis2=2))[:, None, :]


def from_spectrum(rng, lam):
    """Symmetric matrices Q diag(lam) Q^T with random rotations Q."""
    Q = random_rotations(rng, len(lam))
    C = np.einsum("mij,mj,mkj->mik", Q, lam, Q)
    return 0.5 * (C + C.transpose(0, 2, 1))


def check_decomposition(C, lam, V, tol=20 * EPS):
    """Independent of numpy's eigh: residual C V - V diag(lam) and V^T V - I, relative to ||C||."""
    norm = np.maximum(np.abs(C).max(axis=(1, 2)), 1e-300)
    resid = np.einsum("mij,mjk->mik", C, V) - V * lam[:, None, :]
    assert np.all(np.abs(resid).max(axis=(1, 2)) <= tol * norm)
    assert np.allclose(np.einsum("mji,mjk->mik", V, V), np.eye(3), atol=tol, rtol=0)
    assert np.all(np.diff(lam, axis=1) >= 0)  # ascending


def cluster_projectors(lam, V, rel_gap):
    """Projectors onto the clusters of eigenvalues closer than rel_gap * max|lam| (one per eigenvalue)."""
    scale = np.abs(lam).max(axis=1, keepdims=True)
    P = np.empty(lam.shape + (3, 3))
    for i in range(3):
        same = np.abs(lam - lam[:, i : i + 1]) <= rel_gap * scale  # (m, 3): columns in i's cluster
        W = V * same[:, None, :]
        P[:, i] = np.einsum("mij,mkj->mik", W, W)
    return P


def compare_with_numpy(C, rel_gap=1e-6, tol=1e-12):
    """Eigenvalues within tol ||C|| of np.linalg.eigh; eigen-subspaces alike up to sign."""
    lam, V = eigh3(C)
    lam0, V0 = np.linalg.eigh(C)
    norm = np.maximum(np.abs(C).max(axis=(1, 2)), 1e-300)
    assert np.all(np.abs(lam - lam0).max(axis=1) <= tol * norm)
    P, P0 = cluster_projectors(lam, V, rel_gap), cluster_projectors(lam0, V0, rel_gap)
    # eigenvector error ~ eps ||C|| / gap: with gaps >= rel_gap ||C|| it stays below eps / rel_gap
    assert np.abs(P - P0).max() <= tol + 10 * EPS / rel_gap
    check_decomposition(C, lam, V)
    return lam, V


def test_exact_spectrum_from_integer_matrices():
    for M, q in ((M9, 9.0), (M49, 49.0)):
        for d in ([1, 2, 3], [1, 1e6, 1e7], [3, 2, 1], [0, 0, 1], [0, 1, 2], [-5, 1, 4], [1, 1, 2], [7, 7, 7]):
            C = (M * np.array(d, dtype=np.float64)) @ M.T
            assert np.array_equal(C, C.T)
            lam, V = eigh3(C[None])
            order = np.argsort(d, kind="stable")
            truth = q * np.array(d, dtype=np.float64)[order]
            assert np.allclose(lam[0], truth, rtol=0, atol=4 * EPS * np.abs(truth).max())
            if len(set(d)) == 3:  # distinct: each vector is +-M[:, i] / sqrt(q)
                dots = np.abs(np.einsum("ij,ij->j", V[0], M[:, order] / np.sqrt(q)))
                assert np.allclose(dots, 1.0, rtol=0, atol=1e-14)


def test_random_spd_and_indefinite_match_numpy():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(4000, 3, 3))
    compare_with_numpy(A @ A.transpose(0, 2, 1))  # SPD
    compare_with_numpy(A + A.transpose(0, 2, 1))  # indefinite
    X = rng.normal(size=(2000, 20, 3)) * [3.0, 1.0, 0.01]  # planar neighbourhoods, as in local PCA
    X -= X.mean(axis=1, keepdims=True)
    compare_with_numpy(np.einsum("mki,mkj->mij", X, X) / 20)


@pytest.mark.parametrize("spectrum", [(0, 0, 1), (0, 1, 2), (0, 0, 0), (1, 1, 1), (-1, 0, 0)], ids=str)
def test_rank_deficient_and_repeated(spectrum):
    rng = np.random.default_rng(2)
    lam_true = np.tile(np.array(spectrum, dtype=np.float64), (500, 1)) * rng.uniform(0.5, 2.0, (500, 1))
    C = from_spectrum(rng, lam_true)
    lam, _ = compare_with_numpy(C)
    assert np.allclose(lam, lam_true, rtol=0, atol=1e-14 * np.abs(lam_true).max())


@pytest.mark.parametrize("gap", [1e-4, 1e-8, 1e-12])
def test_near_degenerate_pairs(gap):
    rng = np.random.default_rng(3)
    for base in ([0.1, 0.1, 1.0], [0.1, 1.0, 1.0]):  # l2 ~ l3 (line-like) and l1 ~ l2 (plane)
        lam_true = np.tile(base, (1000, 1))
        lam_true[:, 1] += gap * rng.uniform(-1, 1, 1000)
        # the pair closer than 1e-6: only its 2-d subspace is defined, compare the projectors
        compare_with_numpy(from_spectrum(rng, lam_true), rel_gap=1e-6 if gap < 1e-6 else gap / 10)


def test_zero_and_diagonal_matrices():
    lam, V = eigh3(np.zeros((3, 3, 3)))
    assert np.array_equal(lam, np.zeros((3, 3)))
    assert np.array_equal(V, np.broadcast_to(np.eye(3), (3, 3, 3)))
    D = np.diag([3.0, -1.0, 2.0])
    lam, V = eigh3(D)
    assert np.array_equal(lam, [-1.0, 2.0, 3.0])
    assert np.array_equal(np.abs(V), np.eye(3)[:, [1, 2, 0]])


@pytest.mark.parametrize("scale", [1e-300, 1e-12, 1e-6, 1.0, 1e6, 1e300, 2.0**-1040])
def test_scale_invariance(scale):
    rng = np.random.default_rng(4)
    A = rng.normal(size=(500, 3, 3))
    C = A @ A.transpose(0, 2, 1)
    C[:100] = from_spectrum(rng, np.tile([0.0, 1e-9, 1.0], (100, 1)))  # rank-2, tiny l2
    lam1, V1 = eigh3(C)
    lam, V = eigh3(C * scale)  # scaling by a power of ten rounds: compare to eps, not exactly
    if scale < 1e-307:  # subnormal entries keep fewer digits
        assert np.allclose(lam / scale, lam1, rtol=0, atol=1e-9 * np.abs(lam1).max())
        return
    assert np.allclose(lam, lam1 * scale, rtol=1e-14, atol=1e-14 * scale * np.abs(lam1).max())
    assert np.allclose(np.abs(np.einsum("mij,mij->mj", V, V1)), 1.0, rtol=0, atol=1e-9)
    if 1e-150 < scale < 1e150:  # numpy has no trouble in this range
        compare_with_numpy(C * scale)


def test_nan_and_inf_rows_give_nan_and_leave_the_others():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 3, 3))
    C = A @ A.transpose(0, 2, 1)
    bad = C.copy()
    bad[1, 0, 0] = np.nan
    bad[3, 2, 1] = bad[3, 1, 2] = np.inf
    bad[4, 2, 0] = -np.inf
    before = bad.copy()
    lam, V = eigh3(bad)
    assert np.array_equal(bad, before, equal_nan=True)  # input untouched
    rows = np.array([1, 3, 4])
    assert np.isnan(lam[rows]).all() and np.isnan(V[rows]).all()
    good = np.setdiff1d(np.arange(6), rows)
    lam0, V0 = eigh3(C[good])
    assert np.array_equal(lam[good], lam0) and np.array_equal(V[good], V0)


def test_reads_only_the_lower_triangle_like_numpy():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(50, 3, 3))
    lam, V = eigh3(A)  # not symmetric: both use the lower triangle
    lam0, V0 = np.linalg.eigh(A)
    assert np.allclose(lam, lam0, rtol=0, atol=1e-13)
    assert np.allclose(np.abs(np.einsum("mij,mij->mj", V, V0)), 1.0, atol=1e-10)
    A[:, 0, 2] = np.nan  # garbage in the upper triangle is never read (as in numpy)
    assert np.array_equal(eigh3(A)[0], lam)


def test_shapes_threads_and_fallback():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(2, 4, 3, 3))
    C = A @ np.swapaxes(A, -1, -2)
    lam, V = eigh3(C)
    assert lam.shape == (2, 4, 3) and V.shape == (2, 4, 3, 3)
    assert np.array_equal(lam[1, 2], eigh3(C[1, 2])[0])
    assert eigh3(np.empty((0, 3, 3)))[0].shape == (0, 3)
    with pytest.raises(ValueError):
        eigh3(np.ones((4, 2, 2)))
    big = np.repeat(C.reshape(-1, 3, 3), 3000, axis=0)  # several threads' worth
    one, many = eigh3(big), eigh3(big, workers=-1)
    assert np.array_equal(one[0], many[0]) and np.array_equal(one[1], many[1])
    # the numpy fallback (used without numba) agrees, NaN rows included
    big[5, 1, 1] = np.nan
    lam_n, V_n = E._eigh_numpy(big)
    lam_j, V_j = eigh3(big)
    assert np.array_equal(np.isnan(lam_n), np.isnan(lam_j))
    ok = ~np.isnan(lam_j[:, 0])
    assert np.allclose(lam_n[ok], lam_j[ok], rtol=0, atol=1e-12 * np.abs(lam_j[ok]).max())
    assert np.isnan(V_n[~ok]).all() and np.isnan(V_j[~ok]).all()
    P_n, P_j = cluster_projectors(lam_n[ok], V_n[ok], 1e-6), cluster_projectors(lam_j[ok], V_j[ok], 1e-6)
    assert np.abs(P_n - P_j).max() < 1e-9


# ----------------------------------------------------------------------------- closed form (local PCA)


@pytest.mark.parametrize(
    "spectrum",
    [
        lambda rng, m: rng.uniform(-1, 1, (m, 3)),  # indefinite
        lambda rng, m: np.column_stack([rng.uniform(1, 2, m), rng.uniform(1, 2, m), 1e-6 * rng.uniform(size=m)]),  # planes
        lambda rng, m: np.column_stack([np.ones(m), 1e-9 * rng.uniform(size=m), np.zeros(m)]),  # lines
        lambda rng, m: np.column_stack([np.ones(m), np.ones(m) + 1e-10 * rng.normal(size=m), 1e-4 * np.ones(m)]),  # disks
        lambda rng, m: np.column_stack([np.ones(m), np.ones(m), np.ones(m) + 1e-9 * rng.normal(size=m)]),  # balls
    ],
)
def test_analytic_matches_numpy_within_its_stated_precision(spectrum):
    """eigh3_analytic: eigenvalues within 16 eps ||C|| of np.linalg.eigh, residual C V - V diag(lam)
    and V^T V - I within 20 eps, ascending: as accurate as Jacobi, also where two eigenvalues
    nearly coincide (lines, disks), where the angle formula alone loses half the digits."""
    rng = np.random.default_rng(11)
    lam_true = np.sort(spectrum(rng, 4000), axis=1)
    C = from_spectrum(rng, lam_true)
    lam, V = E.eigh3_analytic(C)
    lam0, _ = np.linalg.eigh(C)
    norm = np.abs(C).max(axis=(1, 2))
    assert np.all(np.abs(lam - lam0).max(axis=1) <= 16 * EPS * norm)
    check_decomposition(C, lam, V)


def test_analytic_special_matrices():
    lam, V = E.eigh3_analytic(np.stack([np.zeros((3, 3)), np.diag([2.0, -1.0, 5.0]), 7 * np.eye(3)]))
    assert np.array_equal(lam, [[0, 0, 0], [-1, 2, 5], [7, 7, 7]])
    assert np.allclose(np.abs(np.einsum("mij,mij->mj", V, V)), 1.0)
    bad = np.stack([np.eye(3), np.eye(3)])
    bad[1, 2, 0] = np.nan
    lam, V = E.eigh3_analytic(bad)
    assert np.isnan(lam[1]).all() and np.isnan(V[1]).all() and np.array_equal(lam[0], [1, 1, 1])
