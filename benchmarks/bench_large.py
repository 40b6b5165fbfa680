"""Benchmark: large ALS epochs - write, read, normals and ``labkit register``, with peak memory.

Builds two ALS-like epochs at 20 pts/m^2 over a square of ``sqrt(N / 20)`` m
(about 0.7 x 0.7 km for the default 10 million points), with a fixed seed and a
vectorised terrain generator (smooth hills, one block building per 20 m cell
on about half the cells, a small first-return noise) whose cost is linear in the
number of points. The source epoch samples the same surface independently and
is moved by the known shift (0.23, -0.17, 0.11) m. Both are written as LAZ
(LAS 1.4 point format 6, with classification, intensity, GPS time and returns)
in a temporary folder.

Every step runs in a fresh Python process, which reports its wall time and
its own peak resident memory (``ru_maxrss``); the peak of a bare process with
numpy, laspy and labkit imported is printed as the baseline. Steps and peers,
side by side in one run:

- write: ``labkit.write_cloud`` (lazrs on all cores, then on one) vs laspy's ``LasData.write``
- read: ``labkit.read_cloud`` (parallel, serial) vs ``laspy.read`` (+ x, y, z as float64)
- normals (k = 20) on the target: ``labkit.features.normals`` vs Open3D ``estimate_normals``
- ``labkit register source.laz target.laz`` end to end (read, ICP, distances, figure,
  write; per-step times from wrapped functions) and the error of the estimated shift.

The machine's load matters: run the peers in one run and compare ratios.

Run:  python benchmarks/bench_large.py [--points 2e6] [--skip-register] [--keep DIR]
            [--als-sizes 100 300 700] [--als-only]

Measured 2026-12-01 on 2 shared cores at load 6-7 (noisy; compare within a run):

    points/epoch   step                     labkit   peer              peak RSS MB (labkit / peer)
    2 M            write LAZ                1.26 s   laspy 1.52 s      243 / 157
    2 M            read LAZ                 2.01 s   laspy.read 1.52 s 232 / 210
    2 M            normals k=20             20.9 s   Open3D 51.2 s     725 / 433
    2 M            labkit register          173 s (read 2.9, icp 126.5, distances 33.2, write 1.9), 1757 MB,
                                            shift error (-0.16, -0.42, -0.03) mm
    10 M           write LAZ                12.2 s   laspy 10.4 s      639 / 466
    10 M           read LAZ                 12.2 s   laspy.read 12.7 s 597 / 804
    10 M           normals k=20             101.7 s  Open3D 304.0 s    2648 / 1671

(baseline process 54 MB; lazrs on all cores gave no gain on the loaded machine.)

``--als-sizes 100 200 300 700 --als-only`` (``labkit.synthetic.als_epochs``, both epochs), same day,
loaded machine; "before" is the route that evaluated every roof on every point (same output):

    size (m)       points  time (s)  us/point  peak RSS (MB)   before (s)
         100      432,512       0.5      1.09            142          0.6
         200    1,737,054       2.9      1.64            314          4.7
         300    3,905,601       6.8      1.74            596         16.8
         700   21,286,806      37.6      1.77           2766    about 480
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SHIFT = np.array([0.23, -0.17, 0.11])
ORIGIN = np.array([600_000.0, 5_400_000.0, 300.0])
DENSITY = 20.0
CELL = 20.0  # building layout cell (m)


# ---------------------------------------------------------------------------- data
def surface(x, y, roofs):
    """Height and class of the first surface at x, y (hills plus block buildings; linear cost)."""
    z = 3.0 * np.sin(x / 97.0) * np.cos(y / 131.0) + 0.02 * x - 0.015 * y
    i = np.floor(x / CELL).astype(np.int64)
    j = np.floor(y / CELL).astype(np.int64)
    i = np.clip(i, 0, roofs.shape[0] - 1)
    j = np.clip(j, 0, roofs.shape[1] - 1)
    u, v = x / CELL - i, y / CELL - j  # position inside the cell, 0..1
    height = roofs[i, j]
    along_x = (i + j) % 2 == 0  # ridges along x and along y in a chequerboard
    a, b = np.where(along_x, u, v), np.where(along_x, v, u)  # a along the ridge, b across it
    inside = (height > 0) & (np.abs(a - 0.5) < 0.3) & (np.abs(b - 0.5) < 0.25)
    gable = height * (1.0 - 0.25 * np.abs(b - 0.5) / 0.25)
    z = np.where(inside, z + gable, z)
    cls = np.where(inside, 6, 2).astype(np.uint8)
    return z, cls


def epoch(side, rng, roofs, shift=None):
    """One ALS epoch: uniform pulses over the square, the surface, noise and attributes."""
    n = int(round(DENSITY * side * side))
    x, y = rng.uniform(0, side, n), rng.uniform(0, side, n)
    z, cls = surface(x, y, roofs)
    z += rng.normal(0.0, 0.02, n)
    xyz = np.column_stack([x, y, z]) + ORIGIN
    if shift is not None:
        xyz -= shift  # the source, so that source + shift lies on the target surface
    attrs = {
        "classification": cls,
        "intensity": rng.integers(200, 3000, n).astype(np.uint16),
        "gps_time": 3e8 + y / 60.0 + rng.uniform(0, 1e-3, n),
        "return_number": np.ones(n, np.uint8),
        "number_of_returns": np.ones(n, np.uint8),
        "scanner_channel": np.zeros(n, np.uint8),  # asks for point format 6 (LAS 1.4, layered LAZ)
    }
    return xyz, attrs


def make_pair(n_points, seed=2026):
    from labkit.cloud import PointCloud

    rng = np.random.default_rng(seed)
    side = float(np.sqrt(n_points / DENSITY))
    cells = int(np.ceil(side / CELL))
    roofs = np.where(rng.random((cells, cells)) < 0.5, rng.uniform(4.0, 12.0, (cells, cells)), 0.0)
    tgt = PointCloud(*epoch(side, rng, roofs), crs="EPSG:25832", name="target")
    src = PointCloud(*epoch(side, rng, roofs, SHIFT), crs="EPSG:25832", name="source")
    return src, tgt, side


# ---------------------------------------------------------------------------- steps (run in a child process)
def _peak_mb():
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def step_make(args):
    """Generate the pair and write both LAZ files (in a child, so the parent never holds the clouds)."""
    from labkit.io import write_cloud

    t = time.perf_counter()
    src, tgt, side = make_pair(int(args["points"]))
    t_gen = time.perf_counter() - t
    t = time.perf_counter()
    write_cloud(tgt, args["laz"])
    write_cloud(src, args["src"])
    return {"seconds": t_gen, "write_s": time.perf_counter() - t, "n_target": len(tgt), "n_source": len(src),
            "side": side}


def _best(fn, repeat):
    """Least time of ``repeat`` runs of ``fn`` (returns seconds, last value)."""
    best, value = float("inf"), None
    for _ in range(max(1, int(repeat))):
        value = None  # the last run's cloud is let go first: the peak is that of one run
        t = time.perf_counter()
        value = fn()
        best = min(best, time.perf_counter() - t)
    return best, value


def step_als_epochs(args):
    """``labkit.synthetic.als_epochs`` (town region 'xyz', 20 pts/m^2) on a square of ``size`` m."""
    from labkit.synthetic import als_epochs

    t = time.perf_counter()
    pair = als_epochs("xyz", size=(args["size"], args["size"]), density=DENSITY, rng=1)
    return {"seconds": time.perf_counter() - t, "points": len(pair.source) + len(pair.target)}


def run_als_sizes(sizes, timeout) -> None:
    """Time the synthetic ALS generator at several areas: its cost should grow like the number of points."""
    print(f"\nlabkit.synthetic.als_epochs('xyz', density={DENSITY:.0f}), both epochs, one fresh process each")
    print(f"{'size (m)':>9s} {'points':>12s} {'time (s)':>9s} {'us/point':>9s} {'peak RSS (MB)':>14s}")
    for size in sizes:
        r = run_step("als_epochs", {"size": float(size)}, timeout)
        if "error" in r:
            print(f"{size:9.0f} {'-':>12s} {'-':>9s} {'-':>9s} {'-':>14s}  {r['error']}")
            continue
        print(f"{size:9.0f} {r['points']:12,d} {r['seconds']:9.1f} {1e6 * r['seconds'] / r['points']:9.2f} "
              f"{r['peak_mb']:14.0f}", flush=True)


def step_baseline(args):
    import laspy  # noqa: F401

    import labkit.io  # noqa: F401

    return {}


def step_write_labkit(args, parallel):
    from labkit.io import read_cloud, write_cloud

    cloud = read_cloud(args["laz"])
    secs, _ = _best(lambda: write_cloud(cloud, Path(args["tmp"]) / "w.laz", parallel=parallel), args["repeat"])
    return {"seconds": secs}


def step_write_laspy(args):
    import laspy

    las = laspy.read(args["laz"])
    secs, _ = _best(lambda: las.write(str(Path(args["tmp"]) / "w_laspy.laz")), args["repeat"])
    return {"seconds": secs}


def step_read_labkit(args, parallel):
    from labkit.io import read_cloud

    secs, cloud = _best(lambda: read_cloud(args["laz"], parallel=parallel), args["repeat"])
    return {"seconds": secs, "points": len(cloud)}


def step_read_laspy(args):
    import laspy

    def read():
        las = laspy.read(args["laz"])
        return np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]), las

    secs, (xyz, _) = _best(read, args["repeat"])
    return {"seconds": secs, "points": len(xyz)}


def step_normals_labkit(args):
    from labkit.features import normals
    from labkit.io import read_cloud

    xyz = read_cloud(args["laz"], attributes=[]).xyz
    t = time.perf_counter()
    n = normals(xyz, k=20)
    return {"seconds": time.perf_counter() - t, "points": len(n)}


def step_normals_open3d(args):
    import open3d as o3d

    from labkit.io import read_cloud

    cloud = read_cloud(args["laz"], attributes=[])
    t = time.perf_counter()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.xyz - ORIGIN))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    return {"seconds": time.perf_counter() - t, "points": len(pc.normals)}


def step_register(args):
    """``labkit register`` in this process, with the time of each of its steps."""
    import contextlib
    import io as _io

    import labkit.cli.main as cli
    import labkit.registration.compare as compare
    import labkit.change.distances as distances
    import labkit.io as lio

    times = {}

    def timed(name, fn):
        def wrapper(*a, **kw):
            t = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                times[name] = times.get(name, 0.0) + time.perf_counter() - t
        return wrapper

    lio.read_cloud = timed("read", lio.read_cloud)
    lio.write_cloud = timed("write", lio.write_cloud)
    distances.distances_before_after = timed("distances", distances.distances_before_after)
    cli._distance_figure = timed("figure", cli._distance_figure)
    real_methods = compare.standard_methods
    found = {}

    def keep(m):
        def run(*a, **kw):
            found["result"] = res = m(*a, **kw)
            return res
        return run

    compare.standard_methods = lambda *a, **kw: {k: timed("icp", keep(m)) for k, m in real_methods(*a, **kw).items()}
    out = _io.StringIO()
    t = time.perf_counter()
    with contextlib.redirect_stdout(out):
        code = cli.main(["register", args["src"], args["laz"], "--out", args["tmp"]])
    total = time.perf_counter() - t
    text = out.getvalue()
    err = (1000 * (np.asarray(found["result"].matrix)[:3, 3] - SHIFT)).round(2).tolist() if found else None
    return {"seconds": total, "code": code, "steps": times, "error_mm": err, "summary": text[-3000:]}


STEPS = {
    "make": step_make,
    "baseline": step_baseline,
    "write labkit (parallel)": lambda a: step_write_labkit(a, True),
    "write labkit (1 core)": lambda a: step_write_labkit(a, False),
    "write laspy": step_write_laspy,
    "read labkit (parallel)": lambda a: step_read_labkit(a, True),
    "read labkit (1 core)": lambda a: step_read_labkit(a, False),
    "read laspy.read": step_read_laspy,
    "normals labkit k=20": step_normals_labkit,
    "normals Open3D k=20": step_normals_open3d,
    "labkit register": step_register,
    "als_epochs": step_als_epochs,
}


def child(name, payload):
    """Run one step in this (fresh) process and print its result as JSON."""
    import laspy  # imported before any timing, for every step alike
    import lazrs  # noqa: F401

    import labkit.io  # noqa: F401

    laspy.LazBackend.detect_available()
    result = STEPS[name](payload)
    result["peak_mb"] = _peak_mb()
    print("BENCH-RESULT " + json.dumps(result))


def run_step(name, payload, timeout):
    cmd = [sys.executable, os.path.abspath(__file__), "--child", name, json.dumps(payload)]
    t = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout} s"}
    wall = time.perf_counter() - t
    for line in proc.stdout.splitlines():
        if line.startswith("BENCH-RESULT "):
            out = json.loads(line[len("BENCH-RESULT "):])
            out["process_s"] = wall
            return out
    return {"error": (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]}


# ---------------------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=10e6, help="points per epoch (default: %(default).0f)")
    ap.add_argument("--skip-register", action="store_true", help="leave out labkit register")
    ap.add_argument("--skip-open3d", action="store_true", help="leave out the Open3D normals")
    ap.add_argument("--keep", help="folder for the LAZ files (default: a temporary folder)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per step")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each read/write step, the least time counts")
    ap.add_argument("--als-sizes", type=float, nargs="*", default=None, metavar="M",
                    help="also time labkit.synthetic.als_epochs on squares of these sizes (e.g. 100 200 300 700)")
    ap.add_argument("--als-only", action="store_true", help="only the als_epochs timings")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args.child[0], json.loads(args.child[1]))
    if args.als_sizes:
        run_als_sizes(args.als_sizes, args.timeout)
    if args.als_only:
        return 0

    with tempfile.TemporaryDirectory(dir=args.keep) as tmp:
        laz, src_laz = Path(tmp) / "target.laz", Path(tmp) / "source.laz"
        payload = {"laz": str(laz), "src": str(src_laz), "tmp": tmp, "points": args.points, "repeat": args.repeat}
        made = run_step("make", payload, args.timeout)
        if "error" in made:
            print(f"making the epochs failed: {made['error']}")
            return 1
        side, mb = made["side"], laz.stat().st_size / 1e6
        print(f"epochs: {made['n_target']:,} + {made['n_source']:,} points, {side:.0f} x {side:.0f} m at "
              f"{DENSITY:.0f} pts/m^2; generated in {made['seconds']:.1f} s, both written in {made['write_s']:.1f} s "
              f"(peak {made['peak_mb']:.0f} MB); target.laz {mb:.0f} MB")
        print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f} (timings are noisy under load); "
              f"io steps: least of {args.repeat} runs")
        names = [n for n in STEPS if n not in ("make", "als_epochs")
                 and not (args.skip_register and n == "labkit register")
                 and not (args.skip_open3d and "Open3D" in n)]
        print(f"\n{'step':28s} {'time (s)':>9s} {'peak RSS (MB)':>14s}  note")
        results = {}
        for name in names:
            r = results[name] = run_step(name, payload, args.timeout)
            if "error" in r:
                print(f"{name:28s} {'-':>9s} {'-':>14s}  {r['error']}")
                continue
            secs = "" if "seconds" not in r else f"{r['seconds']:9.2f}"
            print(f"{name:28s} {secs:>9s} {r['peak_mb']:14.0f}  {_note(name, r, results)}", flush=True)
        reg = results.get("labkit register", {})
        if "steps" in reg:
            print("\nlabkit register, time per step (s): "
                  + ", ".join(f"{k} {v:.1f}" for k, v in reg["steps"].items())
                  + f"; shift error (mm): {reg.get('error_mm')}")
            print(reg["summary"])
    return 0


def _note(name, r, results):
    if name.startswith("read") and "laspy" not in name and "read laspy.read" in results:
        return ""
    if name == "read laspy.read":
        base = results.get("read labkit (parallel)", {}).get("seconds")
        return f"labkit parallel / laspy = {base / r['seconds']:.2f}" if base else ""
    if name == "normals Open3D k=20":
        base = results.get("normals labkit k=20", {}).get("seconds")
        return f"labkit / Open3D = {base / r['seconds']:.2f}" if base else ""
    if name == "write laspy":
        base = results.get("write labkit (parallel)", {}).get("seconds")
        return f"labkit parallel / laspy = {base / r['seconds']:.2f}" if base else ""
    if name == "labkit register":
        return f"exit {r.get('code')}"
    if name == "baseline":
        return "python + numpy + laspy + labkit.io imported"
    return ""


if __name__ == "__main__":
    sys.exit(main())
