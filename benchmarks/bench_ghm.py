"""Benchmark: labkit.gauss_helmert_model against two peers, in one table.

1. scipy.optimize.least_squares (analytic Jacobian, orthogonal distances
   d_i = |p_i - c| - r) at 10^4, 10^5, 10^6 points, methods 'trf' and 'lm'.
   Target: labkit at 10^6 points in at most half of scipy's time.
2. A dense textbook Gauss-Helmert model (B as a dense n x 3n matrix, eqs. 6-21
   literally, B Sigma_ll B^T as a dense n x n matrix) at n = 1000, 2000, 4000.
   Target: labkit at least 100x faster at n = 4000.

The points are the visible cap of the synthetic tripod sphere (r = 72.5 mm,
1 mm noise), in a local frame. scipy gets the algebraic initial values for
free (not timed); labkit's time includes its own initial values, all checks and
all statistics (redundancy numbers, w-test, global test). Every peer's
solution is compared with labkit's (max |dx|). Timings are wall-clock, best of
a few runs; on a shared machine they are pessimistic.

Usage::

    python benchmarks/bench_ghm.py            # full table (the dense n = 4000 run takes a while)
    python benchmarks/bench_ghm.py --quick    # small sizes only
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.linalg import lu_factor, lu_solve
from scipy.optimize import least_squares

from labkit.sphere.ghm import gauss_helmert_model
from labkit.sphere.model import algebraic_sphere
from labkit.synthetic import sphere_on_tripod

SIGMA = 0.001


def cap_points(n: int, seed: int = 0) -> np.ndarray:
    return sphere_on_tripod(n_sphere=n, outlier_ratio=0.0, noise=SIGMA, rng=seed).points


def best_time(fn, repeats: int):
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run_labkit(points):
    fit = gauss_helmert_model(points, sigma=SIGMA)
    assert fit.ok, fit.reason
    return fit.x, fit.iterations


def run_scipy(points, x0, method):
    def fun(x):
        return np.linalg.norm(points - x[:3], axis=1) - x[3]

    def jac(x):
        d = points - x[:3]
        return np.column_stack([-d / np.linalg.norm(d, axis=1, keepdims=True), -np.ones(len(d))])

    sol = least_squares(fun, x0, jac=jac, method=method)
    return sol.x, sol.nfev


def run_dense(points, x0, tol=1e-10, max_iter=50):
    """Textbook Gauss-Helmert model: dense B (n x 3n), dense B Sigma B^T (n x n)."""
    n = len(points)
    lx = points.T.ravel()  # l as in eq. (2), ordered x1..xn, y1..yn, z1..zn (eq. 5)
    v = np.zeros(3 * n)
    x = x0.copy()
    rows = np.arange(n)
    for it in range(1, max_iter + 1):
        p = (lx + v).reshape(3, n).T
        d = p - x[:3]
        ri = np.linalg.norm(d, axis=1)  # (eq. 11)
        A = np.column_stack([-d / ri[:, None], -np.ones(n)])  # (eq. 9)
        B = np.zeros((n, 3 * n))  # (eq. 10)
        for j in range(3):
            B[rows, j * n + rows] = d[:, j] / ri
        w = -B @ v + (ri - x[3])  # (eq. 8)
        M = SIGMA**2 * (B @ B.T)  # B Sigma_ll B^T with Sigma_ll = sigma^2 I
        lu = lu_factor(M)  # one factorization of the n x n matrix per iteration
        MiA, Miw = lu_solve(lu, A), lu_solve(lu, w)
        N = A.T @ MiA  # (eq. 21)
        dx = -np.linalg.solve(N, A.T @ Miw)
        k = -lu_solve(lu, A @ dx + w)  # (eq. 19)
        v = SIGMA**2 * (B.T @ k)  # (eq. 13)
        x = x + dx  # (eq. 22)
        if np.abs(dx).max() < tol:
            break
    return x, it


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes only")
    args = parser.parse_args()
    big = [10**3, 10**4, 10**5] if args.quick else [10**4, 10**5, 10**6]
    dense = [200, 400, 800] if args.quick else [1000, 2000, 4000]

    header = f"{'peer':<32} {'n':>9} {'labkit [s]':>11} {'peer [s]':>10} {'speed-up':>9} {'max|dx| [m]':>12} {'iter/nfev':>10}"
    print(header)
    print("-" * len(header))
    for n in big:
        pts = cap_points(n)
        x0 = algebraic_sphere(pts)
        reps = 3 if n <= 10**5 else 2
        t_lab, (x_lab, it_lab) = best_time(lambda: run_labkit(pts), reps)
        for method in ("trf", "lm"):
            t_peer, (x_peer, nfev) = best_time(lambda: run_scipy(pts, x0, method), reps)
            print(f"{'scipy least_squares ' + method:<32} {n:>9d} {t_lab:>11.3f} {t_peer:>10.3f} "
                  f"{t_peer / t_lab:>8.1f}x {np.abs(x_peer - x_lab).max():>12.1e} {f'{it_lab}/{nfev}':>10}")
    for n in dense:
        pts = cap_points(n)
        x0 = algebraic_sphere(pts)
        t_lab, (x_lab, it_lab) = best_time(lambda: run_labkit(pts), 5)
        t_peer, (x_peer, it_peer) = best_time(lambda: run_dense(pts, x0), 1)
        print(f"{'dense textbook GHM (B n x 3n)':<32} {n:>9d} {t_lab:>11.4f} {t_peer:>10.2f} "
              f"{t_peer / t_lab:>8.0f}x {np.abs(x_peer - x_lab).max():>12.1e} {f'{it_lab}/{it_peer}':>10}")
    print("\nspeed-up = peer time / labkit time. Targets: >= 2x vs scipy at 10^6, >= 100x vs dense at 4000.")


if __name__ == "__main__":
    main()
