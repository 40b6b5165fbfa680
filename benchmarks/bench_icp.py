"""Benchmark: labkit ICP vs Open3D ``registration_icp`` (point-to-plane) on synthetic ALS epochs.

Both run in one process on the same epoch pairs (region 'xyz', true shift
(0.23, -0.17, 0.11) m) at about 50k and 500k points per epoch. Times include
each library's own normal estimation: Open3D's ``estimate_normals`` (KNN 20) on
the target, and labkit's normals and local noise (computed inside ``icp`` only
where needed). labkit runs translation-only point-to-plane ICP on a
normal-space sample of the source; Open3D estimates a rigid transformation
(its point-to-plane estimator has no translation-only mode). The error is the
difference of the estimated and the true motion of the area centre, in mm.

Run:  python benchmarks/bench_icp.py [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from labkit.registration import icp
from labkit.synthetic import als_epochs
from labkit.transforms import apply_transform

SIZES = {"50k": (50.0, 50.0), "500k": (158.0, 158.0)}  # at 20 pts/m^2


def error_mm(T, pair):
    """Error of the motion of the area centre (mm)."""
    c = pair.centre[None, :]
    return 1000 * (apply_transform(T, c) - apply_transform(pair.truth, c))[0]


def run_labkit(pair, n_sample):
    t = time.perf_counter()
    res = icp(pair.source, pair.target, sample=("normal_space", n_sample), rng=0)
    return time.perf_counter() - t, res.matrix, res


def run_open3d(pair, o3d):
    t = time.perf_counter()
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pair.source.xyz - pair.origin))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pair.target.xyz - pair.origin))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    reg = o3d.pipelines.registration
    out = reg.registration_icp(
        src, tgt, 1.0, np.eye(4), reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=50),
    )  # fmt: skip
    elapsed = time.perf_counter() - t
    T_local = np.asarray(out.transformation)  # in the frame reduced by pair.origin
    o = pair.origin
    T = T_local.copy()
    T[:3, 3] = T_local[:3, 3] + o - T_local[:3, :3] @ o  # back to the caller's frame
    return elapsed, T


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the 50k case")
    ap.add_argument("--sample", type=int, default=6000, help="normal-space sample of the source")
    args = ap.parse_args(argv)
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover
        o3d = None
    print(f"{'case':6s} {'points/epoch':>13s} {'method':28s} {'time s':>7s} {'dX mm':>7s} {'dY mm':>7s} {'dZ mm':>7s} {'|err| mm':>8s}")
    for case, size in SIZES.items():
        if args.quick and case != "50k":
            continue
        pair = als_epochs("xyz", size=size, density=20.0, rng=7)
        n = (len(pair.source) + len(pair.target)) // 2
        rows = []
        t, T, res = run_labkit(pair, args.sample)
        rows.append((f"labkit icp (t, p2pl, ns {args.sample})", t, error_mm(T, pair)))
        if o3d is not None:
            t, T = run_open3d(pair, o3d)
            rows.append(("open3d registration_icp p2pl", t, error_mm(T, pair)))
        for name, t, e in rows:
            print(f"{case:6s} {n:13d} {name:28s} {t:7.2f} {e[0]:7.2f} {e[1]:7.2f} {e[2]:7.2f} {np.linalg.norm(e):8.2f}")
        std = res.translation_std * 1000
        print(f"{'':6s} {'':13s} labkit stated std (mm): {std[0]:.2f} {std[1]:.2f} {std[2]:.2f}; "
              f"{res.iterations} iterations, {res.n_used} correspondences")  # fmt: skip


if __name__ == "__main__":
    main()
