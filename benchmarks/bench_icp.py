"""Benchmark: labkit ICP beside Open3D ``registration_icp`` (point-to-plane) on real clouds.

Both run in one process on the same pairs. Rows (from ``../shared/realdata/``; a row is skipped
with a message where its file or the folder is absent):

- ``tls halves``: two disjoint random halves of ``tls/TLS_scan_vz400i.laz`` (about 520,000 points
  each), the source moved by a known shift of about 0.41 m;
- ``als halves``: the same with ``als/las_with_several_extra_byte_bloc.laz`` (about 350,000 each);
- ``faceraster strips``: the two flight strips (point source 305 vs 306) of
  ``als/faceraster_numerical_imprecision.laz``: no known shift, the columns show each estimate;
- ``sample_c strips``: strips 54 vs 56 of ``als/sample_c.las`` (roofs, no CRS);
- ``autzen epochs``: ``epochs/autzen-bmx-2010.las`` onto ``-2023.las`` (ground, 13 years apart),
  read with :func:`labkit.read_cloud`. Z is stored in US survey feet; the row says whether
  ``read_cloud`` converted it to metres (its X/Y are metres).

Random halves, not alternating scan lines, make the honest epochs: disjoint points of one surface
with independent noise (alternating lines of the ALS file differ systematically, e.g. by mirror
facet, and blocks of lines leave no overlap). Times include each library's own normal estimation
(Open3D ``estimate_normals`` KNN 20 on the target; labkit inside ``icp``). labkit estimates a
translation (its default); Open3D's point-to-plane estimator is rigid. ALS rows also show
``surface='plane'`` beside the default 'auto' (the local quadric on metre-wide neighbourhoods). Errors are the difference
of the estimated and the true motion of the source's centre, in mm. The machine may be loaded by
other jobs: compare the two libraries within one row, not across runs.

Fair peers: both libraries get the same points, the same gate (labkit ``max_distance`` = Open3D's
``max_correspondence_distance`` = 1 m) and k = 20 for the target normals; each time covers all the
work from the raw arrays (labkit: its kd-trees - the kept tree is dropped before every run -, the
surface selection of ``select='auto'`` on both whole clouds and the normals and noise of both
selected clouds; Open3D: its point clouds, ``estimate_normals`` of the target and the ICP). labkit
thus does more per run (a second cloud's normals, the selection), never less. labkit's default pairs a source above 300,000 points from a thinned sample of about 100,000
(``sample='auto'``); the row 'labkit all pts' uses every source point, as Open3D does. Every time
is the best of ``--repeats`` (3) runs, the methods taking turns, after a warm-up (numba compiled).

Measured 2026-12-01 (2 shared cores, load 0.4-3 from other jobs; times in s, best of 3):

===================  =====================  ===============  ===========
pair                 labkit icp (default)   labkit all pts   Open3D
===================  =====================  ===============  ===========
tls halves           1.88 (2.60)            7.65 (8.62)      2.95 (3.79)
als halves           2.27 (1.83)            6.92 (5.87)      6.65 (3.92)
faceraster strips    0.10                   -                0.07
sample_c strips      0.08                   -                0.04
autzen 2010->2023    0.03                   -                0.01
===================  =====================  ===============  ===========

(in brackets: an earlier run the same evening). Errors on the TLS halves: labkit 0.07, -0.08, -0.06 mm
(all points 0.03, 0.01, -0.02 mm), Open3D -0.02, -0.27, 0.04 mm, the same before and after the kd-tree
speed work; before it labkit took 6.2-6.7 s against Open3D's 5.8-8.0 s (machine load 6-8).

Findings behind the defaults of ``icp`` (its docstring gives the method, these the numbers):

- ``surface='auto'``: on the real ALS halves at full density (2.7 pts/m^2, mostly ground) the local
  plane's X was 13 mm off at a stated 3.5 mm (3.8 std, the same sign over three random splits: the
  sagitta on gently curved ground, weighted by the slopes that determine X); the quadric gave -1.5,
  3.2, 0.2 mm at a stated 2.9, 2.2, 0.12 mm. Monte Carlo spread / stated with the quadric: 1.16, 0.98,
  0.99 on the sparse hills, 1.16, 1.19, 1.08 on the test scene with roofs (the plane: 1.15, 1.02, 0.98
  and 1.15, 1.19, 1.08).
- ``covariance='block'``: the formal sigma0^2 N^-1 is optimistic in Monte Carlo runs of independent
  epoch pairs (tests/test_icp.py): spread / stated 1.15, 1.17, 1.06 in X, Y, Z on the small test scene
  (200 pairs, 3-sigma deletion), 1.3-1.45 in X and Y and 1.2-1.3 in Z on the village at 20 pts/m^2,
  1.15-1.45 with Tukey or Huber weights. The cause is the weights: the local-noise weights (eq. 5.6)
  are estimated from the same data and miss the larger errors at ridges, eaves and walls (with the true
  noise of each material as weights the village gives 1.8, 1.6, 1.1), and sigma0^2 N^-1 ignores psi'
  of robust weights and the moving deletion limit. Not the cause: the target's plane-fit noise (a
  target 10 times less noisy leaves the ratio unchanged), k of the normals and the sampling density (no
  trend for k = 10-40 and 1000-16000 points); the re-selection of the pairs by the estimate adds about
  6 % on the village (the fixed-point map has a slope of about 0.01). The block sandwich over 2 m cells
  gave 1.11, 1.15, 0.97 on the test scene, 1.16, 1.13, 0.98 and 1.06, 1.18, 1.09 on two sets of village
  pairs, 1.12, 1.14, 1.0 with Tukey weights; cells of 4-8 m were worse (the two faces of a roof have
  opposite scores).
- ``sample='auto'`` (sources beyond 300,000 points matched from a thinned sample): the block covariance
  takes its variance from the pairs used, so the stated precision stays honest (Monte Carlo spread /
  stated in tests/test_icp_sampling.py).

Every point (``--keep 0.5 --halves-only``: 262,000 vs 262,000 TLS points, 174,000 vs 175,000 ALS points;
below 300,000 source points the default uses every point, and ``select='auto'`` keeps the surface points:
103,914 and 105,272 pairs). Three runs on 2026-12-03 at 12:16 (load 0.3-1.6), best of 3 each, CPU s of the
process in brackets (Open3D's threads count there too); the estimates are bit-identical to those before
the speed work:

===================  ============================  ====================  ===================
pair                 labkit icp (every point)      Open3D                labkit / Open3D
===================  ============================  ====================  ===================
tls halves           0.83, 0.86, 1.04 (1.49-1.85)  0.83, 0.89, 1.03      1.01, 0.97, 1.00
als halves           0.72, 0.90, 0.84 (1.26-1.55)  1.77, 1.95, 1.88      0.41, 0.46, 0.45
als, plane           0.50, 0.49, 0.52 (0.84-0.90)  1.77, 1.95, 1.88      0.28, 0.25, 0.28
===================  ============================  ====================  ===================

(The same day: TLS 1.04-1.12 at 10:55, 1.07-1.18 at 08:28, 1.27-1.31 before that day's speed work. This
VM's speed drifts by 10-20 % within an hour: both libraries took about 0.83 s at 12:16 and 1.03 s a
minute later; compare within a row.) What changed since 10:55, the same numbers throughout: where the
source queries are at least half as many as the target's points, ICP computes the target's normals at
every point in one batch beside the source's (later steps meet most of them; in a few batches inside the
first matching steps they had cost 108 ms of CPU for 198,000 points, in one batch 92 ms for all 248,000),
which took the iterations from 277 to 223 ms (medians, 2 cores); the kd-tree's box is taken column by
column (numpy's ``min(axis=0)`` on an (n, 3) array: 12.6 against 0.5 ms) and the rows of a mask or an index
by ``np.compress`` / ``np.take`` (``labkit.core.arrays``). Where the time goes on the TLS halves (one sitting,
medians of 9 runs, 2 cores, wall / CPU ms): the surface selection of both whole clouds 424 / 797 (their
kd-trees, the 20 nearest neighbours of every point with the covariances summed and ties at the 20th distance
flagged in the search, the PCA, the local quadric where the plane's bound leaves the test open), ICP's
preparation (the normals of both selected clouds from the kept PCA, the first search from the 0.41 m
start) 132 / 232, eight matching steps and eight adjustments 223 / 384, the result 20 / 29. Pinned to one
core, in one process taking turns (12:19): labkit best 1.56 s, median 1.71 s; Open3D best 1.64 s, median
1.83 s. labkit does less work; on two cores it uses them less fully (about 1.8 cores against Open3D's 1.9):
each adjustment runs on one core (about 5 ms: the gathers of the accepted rows, two medians, the tilt
information of eq. 5.12b), and the ends of the two clouds' selection do not meet. The early matching
steps are what they are: a query 4-13 cm off the surface scans 40-52 target points (33 near the end), at
0.2-0.3 us per query, as counted in the search kernel.

The same afternoon (``--repeats 9``, the ratio of every round's two runs beside the best-of ratio):
Open3D had become faster and labkit had not; best of 9 labkit 0.93 and 0.93 s against Open3D's 0.78 and
0.82 s (1.20x, 1.14x), the rounds' ratios median 1.21 and 1.14 (0.92-2.58, 3 of 18 rounds below 1); 15
more rounds in one process: median 1.12, quartiles 1.02-1.23. Best-of-3 ratios had ranged over 0.97-1.39
within that afternoon, hence the per-round column. ALS halves: 0.42x and 0.48x, every round below 1.
Then labkit's working memory was cut (the same digests): the plane from the kept PCA no longer holds an
(m, k) neighbour array of every point for the 23,000 points per cloud searched again, the selection's
neighbours are int32, and the matcher keeps its work arrays between iterations (traced peak of one call
410 -> 307 MB; Open3D's whole run adds about 33 MB to its process). In alternating processes each step
was faster in 3-4 of 4 rounds, by 3-5 % each (medians). Six runs from 15:28 (load 1.6-1.9): 0.97x, 0.99x,
1.04x, 0.92x, 0.93x, 0.96x, rounds below 1 in 5-7 of 9; that morning's code in the same window 1.00x;
the final code at 15:54: 1.08x and 0.91x, the rounds' medians 0.95 and 0.97 (6 and 5 of 9 below 1).
The machine's phases move the ratio by more than that: the margin is a few percent, not one that
holds in every phase.

Where labkit's CPU goes in the timed runs (``perf``, 1999 Hz, the samples after the warm-up): the
k-neighbour kernel of the surface selection 31 %, the matching's nearest-point kernel 17 %, the kernel
zeroing fresh pages 6 %, the per-point k-neighbour search of the points whose kept neighbourhood held a
left-out point (23,000 per cloud) 5 %, the gathers of the matching 4 %, the kd-tree builds 4 %, the
3x3 eigen-decompositions 4 %. Tried and not kept: glibc's malloc told to keep freed memory
(``mallopt`` M_TRIM_THRESHOLD 256 MB, M_MMAP_THRESHOLD 32 MB) and the helper threads of
``labkit.core.threads`` kept between calls cut the page faults per call from 10,000-20,000 to 2,500-4,500,
but not the time (base faster in 3 of 5 alternating rounds: the zeroing is mostly the first call's and
the import's, 2-6 % of a warm call); a single malloc arena (M_ARENA_MAX 1) was faster for labkit but made
Open3D about 3 % slower in the same process, a cost imposed on every other library; leaf sizes 16,
32, 40 and 48 for the selection's k-neighbour search (24 stays fastest).

One source of this VM's phases, found later that day: the host takes back the guest's free memory (pages
free for about two seconds), and using such pages again costs the host's page faults (100 MB: 8 ms when
freed a moment before, 390-700 ms after 2-8 s at one time, 21 ms at another). Open3D's run touches no
new page after its first (0 page faults per call, ``getrusage``); labkit's freed 300-400 MB per call and
paid 3,000-22,000 faults and 40-370 ms of system time per call when the rounds took turns with Open3D.
Since then ``import labkit`` keeps up to 256 MB of freed memory in the process (``labkit.core.memory``):
20-2,800 faults and 2-120 ms per call in the same alternation, the same estimates (``bench_memory.py``).
Not a cause: the wake-up of sleeping worker threads (a pool whose idle workers spin for 5 ms, as OpenMP's
do, was as fast: median 1.00 s against 1.02 s in 10 rounds) and the threads of ``side_by_side``
kept between calls (more page faults in their arenas, not fewer). Three runs at 17:15-17:42 (load
0.9-1.7), best of 9: TLS 0.84x, 1.07x, 0.95x Open3D, the rounds' medians 0.90x, 1.05x, 1.00x (7, 2 and
3 of 9 below 1); ALS 0.41x and 0.43x, plane 0.24x and 0.27x, every round below 1. The TLS row is at
parity, not ahead by a margin that holds in every phase of this machine.

The same code on a freshly started machine of the same kind that evening (both libraries about 1.6 times
slower than that afternoon): TLS 0.92x, 0.85x and 1.05x best of 9, the rounds' medians 0.88, 0.86 and
0.87 (8, 8 and 7 of 9 below 1; the 1.05x run came right after ``bench_tiles`` at load 4, from one fast
Open3D run); ALS 0.35x-0.37x, plane 0.23x-0.24x. Per call (wall / CPU ms, medians of 7): the selection
750 / 1418, the preparation 227 / 403, eight matchings 366 / 644 (their nearest-point searches 228 / 449),
eight adjustments 78 / 78, the result 50 / 74. labkit spends 2.45-2.6 CPU s per call against Open3D's
2.7-2.9 s but keeps fewer cores busy while it runs (1.67 against 1.79: the run time of every thread read
from /proc each millisecond), in its serial steps (the adjustments, the result) and at the ends of its
parallel ones. Beside another job (``--load 1``: one busy process at normal priority during a second set of
rounds): TLS labkit 1.54 s, Open3D 1.87 s, 0.82x (the rounds' median 0.82, 8 of 9 below 1; the same
sitting without it 0.87x, median 0.88), ALS 0.32x, plane 0.21x; switched on in every other round of one
process: 2.01 against 2.52 s (0.77x, without it 0.88x); at nice 19 it made both 4 % slower (0.93x). Measured and not a cause: the wake-up of an idle
virtual CPU (65-83 us median, up to 4 ms, two threads passing a token; with the guest's halt polling set
to 200 us it fell to 7 us and labkit's time stayed the same), Python's thread switch interval (5, 0.5 and
0.1 ms: the same), the second nearest point in the early searches (it saves 9-16 ms of CPU where the
queries move far, and costs as much in the next search), gathering the found pairs in the pass that
writes them (no faster), one thread per cloud in the selection (no faster), numba's numpy error model in
the k-neighbour kernel and a branch-free rank count in its first stage (2 % and less).

Run:  python benchmarks/bench_icp.py [--quick] [--realdata PATH] [--repeats N] [--keep SHARE] [--halves-only] [--load N]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from labkit import read_cloud
from labkit.neighbours.treecache import forget
from labkit.registration import icp
from labkit.registration.matching.match import AUTO_LIMIT
from labkit.transforms import apply_transform, make_transform

SHIFT = np.array([0.31, -0.24, 0.12])  # about 0.41 m
FT_US = 1200.0 / 3937.0


def _realdata(arg):
    for c in (arg, os.environ.get("LABKIT_REALDATA"), Path(__file__).resolve().parents[2] / "shared" / "realdata",
              "/work/shared/realdata"):
        if c and (Path(c) / "README.md").is_file():
            return Path(c)
    return None


def _halves(xyz, seed=0, keep=1.0):
    rng = np.random.default_rng(seed)
    pick = rng.random(len(xyz)) < keep
    half = rng.random(len(xyz)) < 0.5
    return xyz[pick & half], xyz[pick & ~half]


def pairs(root, quick, keep=None):
    """(name, source, target, truth 4x4 or None, note) for every row whose file exists."""
    keep = keep if keep is not None else (0.25 if quick else 1.0)
    out = []

    def load(rel):
        path = root / rel
        if not path.is_file():
            print(f"skipped: {rel} not found under {root}")
            return None
        return read_cloud(path)

    truth = make_transform(np.eye(3), SHIFT)
    if (c := load("tls/TLS_scan_vz400i.laz")) is not None:
        tgt, src = _halves(c.xyz, 0, keep)
        out.append(("tls halves", src - SHIFT, tgt, truth, ""))
    if (c := load("als/las_with_several_extra_byte_bloc.laz")) is not None:
        tgt, src = _halves(c.xyz, 0, keep)
        out.append(("als halves", src - SHIFT, tgt, truth, ""))
    if (c := load("als/faceraster_numerical_imprecision.laz")) is not None:
        ps = c["point_source_id"]
        out.append(("faceraster strips", c.xyz[ps == 306], c.xyz[ps == 305], None, "306 onto 305"))
    if (c := load("als/sample_c.las")) is not None:
        ps = c["point_source_id"]
        out.append(("sample_c strips", c.xyz[ps == 56], c.xyz[ps == 54], None, "56 onto 54"))
    a, b = load("epochs/autzen-bmx-2010.las"), load("epochs/autzen-bmx-2023.las")
    if a is not None and b is not None:
        feet = np.ptp(b.xyz[:, 2]) > 0 and b.xyz[:, 2].min() > 300  # ground at 129-134 m = 423-439 ftUS
        note = "Z still in US survey feet (read_cloud does not convert it yet)" if feet else "Z in metres"
        out.append(("autzen 2010->2023", a.xyz, b.xyz, None, note))
    return out


def run_labkit(src, tgt, **kw):
    forget()  # the target's kd-tree is built inside the timing, as Open3D builds its own
    t, c = time.perf_counter(), time.process_time()
    res = icp(src, tgt, rng=0, **kw)
    return time.perf_counter() - t, res.matrix, res, time.process_time() - c


def run_open3d(src, tgt, o3d):
    o = tgt.mean(axis=0)
    t, c = time.perf_counter(), time.process_time()
    s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src - o))
    g = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt - o))
    g.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    reg = o3d.pipelines.registration
    out = reg.registration_icp(
        s, g, 1.0, np.eye(4), reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=50),
    )  # fmt: skip
    elapsed, cpu = time.perf_counter() - t, time.process_time() - c
    T = np.asarray(out.transformation).copy()
    T[:3, 3] = T[:3, 3] + o - T[:3, :3] @ o  # back to the caller's frame
    return elapsed, T, None, cpu


def shift_mm(T, c):
    return 1000 * (apply_transform(T, c[None])[0] - c)


def best_of(repeats, runs):
    """Per method the fastest of ``repeats`` runs, the methods taking turns (a load that comes and goes
    on a shared machine then meets all of them; every other round in the reverse order, so that no method
    always runs right after the same one), and every run's wall time per method (rounds x methods); the
    results of the runs are the same (deterministic)."""
    best = [None] * len(runs)
    times = np.empty((repeats, len(runs)))
    for r in range(repeats):
        for i in range(len(runs)) if r % 2 == 0 else reversed(range(len(runs))):
            out = runs[i]()
            times[r, i] = out[0]
            if best[i] is None or out[0] < best[i][0]:
                best[i] = out
    return best, times


class BusyProcesses:
    """``n`` other processes that each keep a core busy (a busy loop at normal priority), paused except inside
    ``with``: the runs then compete with another job for the cores, as on a shared machine."""

    def __init__(self, n):
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
        self._send(signal.SIGSTOP)

    def _send(self, sig):
        for p in self.procs:
            os.kill(p.pid, sig)

    def __enter__(self):
        self._send(signal.SIGCONT)
        return self

    def __exit__(self, *exc):
        self._send(signal.SIGSTOP)

    def close(self):
        for p in self.procs:
            p.kill()
            p.wait()


def warm_up(o3d):
    """Compile (numba) and load both libraries once, outside the timings."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 20, (4000, 2))
    tgt = np.c_[xy, 0.1 * np.sin(xy[:, 0]) + 0.05 * np.cos(xy[:, 1])]
    run_labkit(tgt[::2] + [0.05, 0.02, 0.01], tgt[1::2])
    if o3d is not None:
        run_open3d(tgt[::2], tgt[1::2], o3d)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="thin the halves to a quarter")
    ap.add_argument("--realdata", default=None, help="folder of the real development clouds")
    ap.add_argument("--repeats", type=int, default=3, help="each time is the best of this many runs")
    ap.add_argument("--keep", type=float, default=None,
                    help="share of the halves' points kept (0.5: about 260,000 TLS points each; default 1, --quick 0.25)")
    ap.add_argument("--halves-only", action="store_true", help="only the TLS and ALS halves")
    ap.add_argument("--load", type=int, default=0,
                    help="run every row a second time beside this many busy processes (another job on the cores)")
    args = ap.parse_args(argv)
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover
        o3d = None
        print("open3d not installed: labkit rows only")
    root = _realdata(args.realdata)
    if root is None:
        print("skipped: real development data not found (set LABKIT_REALDATA or --realdata)")
        return
    warm_up(o3d)
    busy = BusyProcesses(args.load) if args.load > 0 and hasattr(signal, "SIGSTOP") else None
    try:
        _rows(args, root, o3d, busy)
    finally:
        if busy is not None:
            busy.close()


def _rows(args, root, o3d, busy):
    print(f"{os.cpu_count()} CPU(s), load average {os.getloadavg()}; every time is the best of {args.repeats} "
          "wall-clock runs, the methods taking turns (shared machine: compare within a row); the ratios also "
          "per round (the runs next to each other)")
    head = f"{'pair':18s} {'points src/tgt':>16s} {'method':14s} {'time s':>7s} {'dX mm':>8s} {'dY mm':>8s} {'dZ mm':>8s}"
    print(head + "   (error vs the known shift; for pairs without one: the estimated shift; CPU s of that run)")
    for name, src, tgt, truth, note in pairs(root, args.quick, args.keep):
        if args.halves_only and "halves" not in name:
            continue
        c = src.mean(axis=0)
        ref = shift_mm(truth, c) if truth is not None else np.zeros(3)
        n = f"{len(src)}/{len(tgt)}"
        variants = [("labkit icp", {})]
        if name.startswith("als"):  # the default 'auto' picks the local quadric here; the plane beside it
            variants.append(("labkit plane", {"surface": "plane"}))
        if len(src) > AUTO_LIMIT:  # the default pairs a thinned source; every source point beside it
            variants.append(("labkit all pts", {"sample": None}))
        runs = [lambda kw=kw: run_labkit(src, tgt, **kw) for _, kw in variants]
        if o3d is not None:
            runs.append(lambda: run_open3d(src, tgt, o3d))
        timed, times = best_of(args.repeats, runs)
        for (label, kw), (t, T, res, cpu) in zip(variants, timed):
            print(f"{name if not kw else '':18s} {n if not kw else '':>16s} {label:14s} {t:7.2f} "
                  + " ".join(f"{v:8.2f}" for v in shift_mm(T, c) - ref) + f"   CPU {cpu:.2f}")
            std = 1000 * res.translation_std
            print(f"{'':18s} {'':16s} {'  stated std':14s} {'':7s} " + " ".join(f"{v:8.2f}" for v in std)
                  + f"   {res.iterations} it., {'converged' if res.converged else 'NOT converged'}"
                  + (f"; undetermined {','.join(res.degeneracy.undetermined_axes)}" if res.degeneracy.undetermined_axes else "")
                  + f"; {res.method.split('surface=')[-1].rstrip(')')}; {res.correspondences.n_accepted} pairs")  # fmt: skip
        if o3d is not None:
            t, T, _, cpu = timed[-1]
            print(f"{'':18s} {'':16s} {'open3d p2pl':14s} {t:7.2f} " + " ".join(f"{v:8.2f}" for v in shift_mm(T, c) - ref)
                  + f"   CPU {cpu:.2f}")
            for i, ((label, kw), (t_l, _, _, _)) in enumerate(zip(variants, timed)):
                q = times[:, i] / times[:, -1]  # each round's labkit run against the Open3D run next to it
                print(f"{'':18s} {'':16s} {'  ratio':14s} {t_l / t:7.2f}   ({label} / open3d; per round: median "
                      f"{np.median(q):.2f}, {np.min(q):.2f}-{np.max(q):.2f}, below 1 in {np.sum(q < 1)} of {len(q)})")
        if busy is not None:  # the same runs beside other jobs: the same estimates, the times under load
            with busy:
                loaded, times_l = best_of(args.repeats, runs)
            # labkit's estimates are deterministic (Open3D's parallel sums may differ in the last bits)
            same = all(np.array_equal(a[1], b[1]) for a, b in zip(timed[:len(variants)], loaded[:len(variants)]))
            for i, (label, kw) in enumerate(variants):
                line = f"{'':18s} {'':16s} {'  under load':14s} {loaded[i][0]:7.2f}   ({label}, {args.load} busy process(es) beside"
                if o3d is not None:
                    q = times_l[:, i] / times_l[:, -1]
                    line += (f"; open3d {loaded[-1][0]:.2f} s, ratio {loaded[i][0] / loaded[-1][0]:.2f}, per round: median "
                             f"{np.median(q):.2f}, below 1 in {np.sum(q < 1)} of {len(q)}")
                print(line + ")" + ("" if same else "   NOTE: labkit's estimates differ from the runs without load"))
        print(f"{'':18s} load average after the row: {os.getloadavg()[0]:.1f}")
        if note:
            print(f"{'':18s} note: {note}")


if __name__ == "__main__":
    main()
