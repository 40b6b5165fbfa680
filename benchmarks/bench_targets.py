"""Benchmark: scans registered by sphere targets, labkit's Gauss-Helmert network beside a closed-form SVD alignment.

Peer: Open3D's ``TransformationEstimationPointToPoint`` (closed-form SVD, Arun/Umeyama) on the target centres,
each scan aligned to the reference scan alone with the correspondences labkit found (the peer has no matching
of its own, so both get the same pairs); it gives no covariance and no test.

1. The issue's case: synthetic TLS panoramas (``labkit.synthetic.target_stations``, 4 stations, 1 M points each,
   six 0.1 m targets, a decoy ball, poles, a crate). labkit: ``register_scans`` (detection + matching + network),
   timed. Both: the error of every scan's rotation (deg) and translation (mm) against the true poses, and for
   labkit the largest |error| / stated std. Target: within 0.01 deg and 3 mm, every |error| < 3 std, <= 90 s.
2. The same with one target moved by 3 cm before scan 2 (its points shifted in that scan): labkit's test finds
   and leaves it out; the SVD alignment takes it in.
3. Monte Carlo at the level of the centres (the centres and covariances of case 1 as truth, 200 noisy draws):
   RMS error of each estimator and labkit's empirical spread / stated std for all parameters.

Usage::

    python benchmarks/bench_targets.py            # 1 M points per scan
    python benchmarks/bench_targets.py --quick    # 250 000 points per scan, 50 Monte Carlo draws
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import labkit
from labkit.synthetic import target_stations
from labkit.transforms import angles_from_rotation, invert


def errors(M, true):
    d = invert(true) @ M
    return np.degrees(np.linalg.norm(angles_from_rotation(d[:3, :3]))), np.abs(M[:3, 3] - true[:3, 3]).max() * 1e3


def open3d_alignment(net, centers, reference):
    """Closed-form SVD (Open3D point-to-point) of each scan onto the reference, with labkit's pairs."""
    import open3d as o3d

    est = o3d.pipelines.registration.TransformationEstimationPointToPoint()
    tab = net.table
    out, times = [], 0.0
    for s in range(len(centers)):
        mine = {int(t): i for sc, i, t in zip(tab.scan, tab.index, tab.target) if sc == s and t >= 0}
        ref = {int(t): i for sc, i, t in zip(tab.scan, tab.index, tab.target) if sc == reference and t >= 0}
        common = sorted(set(mine) & set(ref))
        if s == reference or len(common) < 3:
            out.append(np.eye(4) if s == reference else np.full((4, 4), np.nan))
            continue
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centers[s][[mine[t] for t in common]]))
        dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centers[reference][[ref[t] for t in common]]))
        corr = o3d.utility.Vector2iVector(np.column_stack([np.arange(len(common))] * 2))
        t0 = time.perf_counter()
        out.append(np.asarray(est.compute_transformation(src, dst, corr)))
        times += time.perf_counter() - t0
    return out, times


def table(hall, net, svd, t_lab, t_svd, title):
    print(f"\n{title}")
    print(f"{'scan':>4} | {'labkit deg':>10} {'labkit mm':>9} {'max|e|/std':>10} | {'SVD deg':>9} {'SVD mm':>7}")
    for s in range(1, len(hall.scans)):
        true = invert(hall.poses[0]) @ hall.poses[s]
        a, t = errors(net.matrices[s], true)
        b, u = errors(svd[s], true)
        x = np.r_[angles_from_rotation(true[:3, :3]), true[:3, 3]]
        z = np.abs(net.parameters[s] - x) / net.std[s]
        print(f"{s:>4} | {a:10.5f} {t:9.3f} {z.max():10.2f} | {b:9.5f} {u:7.3f}")
    print(f"time: labkit register_scans {t_lab:.1f} s (detection in 4 scans, matching, network); "
          f"Open3D SVD on the centres {t_svd * 1e3:.2f} ms; excluded by labkit: {list(net.excluded) or 'none'}; "
          f"global test passed: {net.global_test.passed}")
    if any(not np.isfinite(M).all() for M in svd):
        print("(SVD nan: the scan shares fewer than 3 targets with the reference; the network ties it in through "
              "the other scans)")


def monte_carlo(hall, net, runs, rng):
    """True centres of the spheres found in case 1, redrawn with their covariances: RMS errors, spread / std."""
    centers, covs = [], []
    for s, found in enumerate(net.spheres):
        c = np.array([sp.center for sp in found])
        true = hall.centers_in_scan(s)
        near = np.linalg.norm(c[:, None] - true[None], axis=2).argmin(axis=1)
        keep = np.linalg.norm(c - true[near], axis=1) < 0.05  # found spheres that are targets
        centers.append(true[near[keep]])
        covs.append(np.array([sp.covariance[:3, :3] for sp in found])[keep])
    poses = [invert(hall.poses[0]) @ P for P in hall.poses]
    xs, sds, svd_err, lab_err = [], [], [], []
    for _ in range(runs):
        obs = [c + np.einsum("nij,nj->ni", np.linalg.cholesky(S), rng.normal(size=c.shape)) for c, S in
               zip(centers, covs)]
        n2 = labkit.register_targets(obs, covs)
        svd, _ = open3d_alignment(n2, obs, 0)
        xs.append(n2.parameters[1:])
        sds.append(n2.std[1:])
        xs[-1] = xs[-1] - np.array([np.r_[angles_from_rotation(P[:3, :3]), P[:3, 3]] for P in poses[1:]])
        lab_err.append([errors(n2.matrices[s], poses[s]) for s in range(1, len(obs))])
        svd_err.append([errors(svd[s], poses[s]) for s in range(1, len(obs))])
    xs = np.array(xs)
    ratio = xs.std(axis=0, ddof=1) / np.mean(sds, axis=0)
    bias = np.abs(xs.mean(axis=0)) / (np.mean(sds, axis=0) / np.sqrt(runs))
    lab, svd = np.sqrt((np.array(lab_err) ** 2).mean(axis=0)), np.sqrt((np.array(svd_err) ** 2).mean(axis=0))
    print(f"\nMonte Carlo, {runs} draws of the centres (true centres of the spheres found in case 1, their "
          "covariances; the errors are against the true poses)")
    print(f"{'scan':>4} | {'labkit RMS deg':>14} {'mm':>7} | {'SVD RMS deg':>11} {'mm':>7} | spread/stated std "
          "rx ry rz tx ty tz")
    for s in range(len(lab)):
        print(f"{s + 1:>4} | {lab[s, 0]:14.5f} {lab[s, 1]:7.3f} | {svd[s, 0]:11.5f} {svd[s, 1]:7.3f} | "
              + " ".join(f"{r:.2f}" for r in ratio[s]))
    print(f"largest |mean error| / (std / sqrt(draws)): {bias.max():.1f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    n_points, runs = (250_000, 50) if args.quick else (1_000_000, 200)
    hall = target_stations(n_stations=4, n_points=n_points, rng=3)
    print(f"{n_points} points per scan, targets visible per scan: {hall.visible.sum(axis=1).tolist()}")

    t0 = time.perf_counter()
    net = labkit.register_scans(hall.scans, (0.09, 0.11), rng=0)
    t_lab = time.perf_counter() - t0
    centers = [np.array([sp.center for sp in f]) for f in net.spheres]
    covs = [np.array([sp.covariance[:3, :3] for sp in f]) for f in net.spheres]
    svd, t_svd = open3d_alignment(net, centers, 0)
    table(hall, net, svd, t_lab, t_svd, "1. Four stations")

    scans = [s.copy() for s in hall.scans]
    j = int(np.argmax(np.minimum(hall.hits[0], hall.hits[2])))  # well seen by the reference and by scan 2
    scans[2][hall.target[2] == j] += hall.poses[2][:3, :3].T @ np.array([0.0, 0.03, 0.0])
    t0 = time.perf_counter()
    moved = labkit.register_scans(scans, (0.09, 0.11), rng=0)
    t_moved = time.perf_counter() - t0
    c2 = [np.array([sp.center for sp in f]) for f in moved.spheres]
    svd2, t_svd2 = open3d_alignment(moved, c2, 0)
    table(hall, moved, svd2, t_moved, t_svd2, f"2. Target {j} moved by 3 cm before scan 2")

    monte_carlo(hall, net, runs, np.random.default_rng(0))


if __name__ == "__main__":
    main()
