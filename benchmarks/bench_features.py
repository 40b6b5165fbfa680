"""Benchmark: labkit.features.normals vs Open3D estimate_normals (KNN 20) at 10^5 and 10^6 points.

The scene is a synthetic ALS epoch (``labkit.synthetic.als_scene``, village on
undulating terrain, 20 pts/m^2) cut to n points; if the synthetic module is
unavailable, a noisy undulating terrain with box buildings is used instead.

Each method runs in its own fresh process (same input file), so the peak
resident memory (``ru_maxrss``) belongs to that method alone; for labkit the
numpy peak seen by ``tracemalloc`` is printed as well. Normals are compared up
to sign (Open3D does not orient them). Targets: median angle < 1 deg,
labkit time <= 1.5 x Open3D time, memory < 2 GB at 10^6 points.

Real rows: the real TLS scan ``tls/TLS_scan_vz400i.laz`` from the development
data (``../shared/realdata`` or ``LABKIT_REALDATA``; skipped with a message where absent):
every second point (523,422, scanner-centred, density falling with range squared) and the
whole scan (1,046,843). Target: labkit no slower than Open3D (ratio <= 1). On a shared,
loaded machine wall-clock times swing by 2x between runs; compare the ratio within a run.
Both timings cover the same work: from the raw array to the normals (labkit's kd-tree, Open3D's
point cloud and its tree); labkit's numpy peak comes from a second, untimed run (tracemalloc's
hooks slowed the timed run by 10-20 %).

Measured 2026-12-01 (``--real``; 2 shared cores, load about 3; best of 3, wall s, CPU s):
TLS/2 labkit 1.12 (CPU 1.00) vs Open3D 1.01 (CPU 1.08); TLS 1.98 (2.01) vs 2.09 (2.12);
ALS 1.02 (1.11) vs 1.35 (1.49). On a nearly idle machine, in one process (after a warm-up):
TLS/2 0.56 vs 0.62 s, TLS 1.08-1.21 vs 1.20-1.23 s. Before the kd-tree work: TLS/2 1.29 s vs 0.73 s.

The kd-tree (``labkit.neighbours.kdtree``), measured on the real TLS scan (523,422 points, k = 20, one thread,
CPU s on a loaded 2-core machine): self-kNN 0.9-1.1 s against cKDTree's 1.5-1.8 s in leaf order; a warm
start from the previous query's neighbours, a per-leaf candidate list and a branch-free two-pass leaf
scan gave no further gain; the leaf-batched search brought it to 0.66 s. Building with the children's
boxes taken while the points are moved and the median selected in place: 0.20 -> 0.145 s with the
same tree; an insertion written out on the 2-D buffers (no row views) gave nothing.

Usage::

    python benchmarks/bench_features.py            # 10^5 and 10^6, then the real TLS rows
    python benchmarks/bench_features.py --quick    # 10^4 and 10^5, then the real TLS rows
    python benchmarks/bench_features.py --real     # only the real TLS rows
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

K = 20
REPEATS = 3  # each method's time is the best of this many runs, labkit and Open3D alternating (shared machine)
COLUMNS = ("time s", "ratio", "median deg", "p95 deg", "median deg, local", "peak RSS MB", "numpy peak MB")
WIDTHS = [len(c) for c in COLUMNS]


def make_scene(n: int, seed: int = 0) -> np.ndarray:
    """n points of an ALS-like scene, UTM-sized coordinates."""
    rng = np.random.default_rng(seed)
    try:
        from labkit.synthetic import als_scene

        side = float(np.sqrt(n / 20.0 * 0.8))  # the scene adds returns and a margin
        xyz = als_scene("xyz", size=(side, side), rng=seed).xyz
        while len(xyz) < n:  # top up with a neighbouring tile
            extra = als_scene("xyz", size=(side, side), rng=seed + len(xyz)).xyz + [side + 5.0, 0.0, 0.0]
            xyz = np.vstack([xyz, extra])
        return xyz[rng.choice(len(xyz), n, replace=False)]
    except ImportError:
        return _fallback_scene(n, rng)


def _fallback_scene(n, rng):
    side = np.sqrt(n / 20.0)
    xy = rng.uniform(0, side, (n, 2))
    z = 2.0 * np.sin(xy[:, 0] / 25.0) + 1.5 * np.cos(xy[:, 1] / 18.0) + rng.normal(0, 0.03, n)
    centres = rng.uniform(0, side, (max(1, n // 20000), 2))
    for cx, cy in centres:  # flat-roofed boxes 12 m x 8 m, 6 m high
        inside = (np.abs(xy[:, 0] - cx) < 6) & (np.abs(xy[:, 1] - cy) < 4)
        z[inside] += 6.0
    return np.column_stack([xy, z]) + [600000.0, 5400000.0, 300.0]


REAL = (("TLS", "tls/TLS_scan_vz400i.laz"), ("ALS", "als/las_with_several_extra_byte_bloc.laz"))


def realdata_dir() -> Path | None:
    """The real development data folder, or None (then the real rows are skipped)."""
    env = os.environ.get("LABKIT_REALDATA")
    here = Path(__file__).resolve().parents[1]
    candidates = ([Path(env)] if env else []) + [here.parent / "shared" / "realdata", here.parents[1] / "shared" / "realdata"]
    for cand in candidates:
        if any((cand / rel).exists() for _, rel in REAL):
            return cand
    return None


def real_scenes() -> list[tuple[str, np.ndarray]]:
    """(label, xyz) of the real rows; empty with a message where the data are absent."""
    root = realdata_dir()
    if root is None:
        print("real rows skipped: no development data found (../shared/realdata or LABKIT_REALDATA)")
        return []
    from labkit.io import read_cloud

    scenes = []
    for label, rel in REAL:
        if not (root / rel).exists():
            print(f"real {label} rows skipped: {rel} not found")
            continue
        xyz = read_cloud(root / rel).xyz
        scenes += [(f"{label}/2", xyz[::2].copy()), (label, xyz)] if label == "TLS" else [(label, xyz)]
    return scenes


def run_worker(method: str, path: str, out: str) -> None:
    """Compute normals with one method; write time, memory and normals."""
    xyz = np.load(path)
    if method == "labkit":
        import tracemalloc

        from labkit.features import normals

        normals(xyz[:1000], k=K)  # warm up imports
        t0, c0 = time.perf_counter(), time.process_time()
        N = normals(xyz, k=K, orient="none")
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        # untimed: the numpy peak in a second run (tracemalloc's hooks would slow the timed one)
        tracemalloc.start()
        normals(xyz, k=K, orient="none")
        traced = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    else:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz[:1000]))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(K))  # warm up
        t0, c0 = time.perf_counter(), time.process_time()
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))  # Open3D needs its own copy
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(K))
        N = np.asarray(pcd.normals)
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        traced = float("nan")
        # untimed: the same on coordinates reduced to a local origin (Open3D sums x x^T in one pass)
        local = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz - np.round(xyz.mean(axis=0))))
        local.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(K))
        np.save(out + "_local.npy", np.asarray(local.normals))
    np.save(out + ".npy", N)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kB on Linux
    Path(out + ".json").write_text(json.dumps({"seconds": seconds, "cpu": cpu, "rss": rss, "traced": traced}))


def run_method(method: str, path: str, tmp: str) -> tuple[dict, np.ndarray]:
    out = os.path.join(tmp, method)
    subprocess.run([sys.executable, __file__, "--worker", method, path, out], check=True)
    return json.loads(Path(out + ".json").read_text()), np.load(out + ".npy")


def run_pair(path: str, tmp: str):
    """labkit and Open3D alternately, REPEATS times each; per method the best wall and CPU time."""
    best = {}
    for _ in range(REPEATS):
        for method in ("labkit", "open3d"):
            r, N = run_method(method, path, tmp)
            if method not in best:
                best[method] = (r, N)
            else:
                b = best[method][0]
                b["seconds"], b["cpu"] = min(b["seconds"], r["seconds"]), min(b["cpu"], r["cpu"])
                b["rss"] = max(b["rss"], r["rss"])
    return best["labkit"], best["open3d"]


def _row(n, name, r, ratio, ang=None, ang_local=None):
    angles = ("", "", "") if ang is None else (
        f"{np.median(ang):.4f}", f"{np.percentile(ang, 95):.4f}", f"{np.median(ang_local):.2e}")
    traced = "" if not np.isfinite(r["traced"]) else f"{r['traced'] / 2**20:.0f}"
    cells = (f"{r['seconds']:.2f}", f"{ratio:.2f}", *angles, f"{r['rss'] / 2**20:.0f}", traced)
    return f"{n:>9} {name:>7} " + " ".join(f"{c:>{w}}" for c, w in zip(cells, WIDTHS))


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between normals up to sign, degrees."""
    c = np.abs(np.einsum("ij,ij->i", a, b)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10^4 and 10^5 points")
    parser.add_argument("--real", action="store_true", help="only the real TLS and ALS rows")
    args = parser.parse_args()
    sizes = () if args.real else (10_000, 100_000) if args.quick else (100_000, 1_000_000)
    print(f"normals, k = {K}; {os.cpu_count()} CPU(s); times are the best of {REPEATS} alternating wall-clock runs (shared machine)")
    print("angles: labkit vs Open3D up to sign, both on the UTM input; 'local': vs Open3D on reduced coordinates")
    header = f"{'n':>9} {'method':>7} " + " ".join(COLUMNS)
    print(header)
    print("-" * len(header))
    ok = True
    real_ok = True
    with tempfile.TemporaryDirectory() as tmp:
        scenes = [(str(n), make_scene(n)) for n in sizes] + real_scenes()
        for label, xyz in scenes:
            path = os.path.join(tmp, "scene.npy")
            np.save(path, xyz)
            (lab, N_lab), (o3d, N_o3d) = run_pair(path, tmp)
            valid = np.isfinite(N_lab[:, 0])  # labkit: NaN where the neighbourhood is degenerate
            ang = angles_deg(N_lab[valid], N_o3d[valid])
            ang_local = angles_deg(N_lab[valid], np.load(os.path.join(tmp, "open3d_local.npy"))[valid])
            ratio = lab["seconds"] / o3d["seconds"]
            print(_row(label, "open3d", o3d, 1.0))
            print(_row(label, "labkit", lab, ratio, ang, ang_local))
            print(f"{'':>9} {'':>7} CPU s: labkit {lab['cpu']:.2f}, Open3D {o3d['cpu']:.2f}, ratio {lab['cpu'] / o3d['cpu']:.2f}")
            if label.startswith(("TLS", "ALS")):
                real_ok &= ratio <= 1.0
            elif len(xyz) >= 100_000:  # the sizes; 10^4 (--quick) only shows the fixed overhead
                ok &= np.median(ang) < 1.0 and ratio <= 1.5 and lab["rss"] < 2 * 2**30
    if sizes:
        print("targets at n >= 10^5 (median < 1 deg, time <= 1.5 x Open3D, RSS < 2 GB):", "met" if ok else "NOT met")
    print("real-cloud target (time <= Open3D):", "met" if real_ok else "NOT met")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        run_worker(*sys.argv[2:5])
    else:
        main()
