"""Benchmark: what new memory costs on this machine, and labkit's ICP with its freed memory kept or handed back.

Two parts, printed as tables:

1. ``fresh pages``: 100 MB of new numpy memory written right after 100 MB were freed, and after a
   pause of ``--pause`` seconds. On a virtual machine whose host takes back the guest's free memory
   (free page reporting: pages free for about two seconds), the second needs the host to supply every
   page again.
2. ``icp``: :func:`labkit.registration.icp` with every point on the real TLS halves (the pair of
   ``bench_icp.py --keep 0.5 --halves-only``; a synthetic wavy surface of 262,000 points where the real
   data are absent), each call after a pause of ``--pause`` seconds (as between the rounds of a benchmark
   or the steps of an analyst), in child processes with ``LABKIT_KEEP_FREED_MEMORY=1`` (labkit's default,
   :mod:`labkit.core.memory`) and ``=0`` (glibc's own settings), taking turns. Per setting: the medians
   of wall time, system time and page faults per call. The results are the same (printed digest).

Measured 2026-12-03 17:36 (2 shared cores, load 1.6; times per call, medians of 10 calls per setting):

======================  ======  ========  ======  ===========
freed memory            wall s  system s  user s  page faults
======================  ======  ========  ======  ===========
kept (labkit default)   0.929   0.052     1.588   1336
handed back (glibc)     1.082   0.163     1.732   5436
======================  ======  ========  ======  ===========

The same result (digest). Fresh pages in that run: 100 MB in 8.0 ms at once, 20.6 ms after 2.5 s; at
16:3x the same test in a Python shell took 8 ms at once and 390-700 ms after 2-8 s: the host takes back
more or less of the guest's free memory with its own load, which is one source of the "phases" in which
this machine's timings drift (``bench_icp.py``). Earlier in that afternoon, ICP calls 2.5 s apart on the
TLS halves paid 7,500-17,000 faults and 98-150 ms of system time with glibc's settings, 300-1,200 and
5-57 ms with the freed memory kept; on the 10.6 M pair of ``bench_scale.py`` (its ``labkit register`` and
``labkit icp`` rows, one run each, a slow phase): kept 71.3 s and 40.4 s, peaks 3.6 and 3.9 GB; glibc's
74.5 s and 40.1 s, peaks 3.7 and 3.9 GB.

Run:  python benchmarks/bench_memory.py [--pause S] [--calls N] [--rounds R] [--realdata PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

_CHILD = r"""
import json, os, resource, sys, time, hashlib
import numpy as np
from labkit.registration import icp
from labkit.neighbours.treecache import forget
src, tgt = np.load(sys.argv[1]), np.load(sys.argv[2])
pause, calls = float(sys.argv[3]), int(sys.argv[4])
res = icp(src, tgt, rng=0, sample=None)  # compiled kernels loaded, the process warm
rows = []
for _ in range(calls):
    forget()
    time.sleep(pause)
    a, t = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    res = icp(src, tgt, rng=0, sample=None)
    b, w = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter() - t
    rows.append((w, b.ru_stime - a.ru_stime, b.ru_utime - a.ru_utime, b.ru_minflt - a.ru_minflt))
digest = hashlib.sha256(np.ascontiguousarray(res.matrix).tobytes()).hexdigest()[:16]
print(json.dumps({"rows": rows, "digest": digest}))
"""


def fresh_pages(pause, rounds=3):
    """ms for 100 MB of new memory written right after a free and after ``pause`` seconds."""
    out = {"at once": [], f"after {pause:g} s": []}
    n = 100_000_000 // 8
    np.ones(n)  # (made and freed once)
    for _ in range(rounds):
        for label, wait in (("at once", 0.0), (f"after {pause:g} s", pause)):
            time.sleep(wait)
            t = time.perf_counter()
            a = np.ones(n)
            out[label].append(1000 * (time.perf_counter() - t))
            del a
    return {k: float(np.median(v)) for k, v in out.items()}


def _pair(realdata, folder):
    rel = Path(realdata) / "tls" / "TLS_scan_vz400i.laz" if realdata else None
    if rel is not None and rel.is_file():
        from labkit import read_cloud

        xyz = read_cloud(rel).xyz
        rng = np.random.default_rng(0)
        pick, half = rng.random(len(xyz)) < 0.5, rng.random(len(xyz)) < 0.5
        tgt, src = xyz[pick & half], xyz[pick & ~half] - np.array([0.31, -0.24, 0.12])
        name = "real TLS halves"
    else:
        from labkit.synthetic import wavy_surface

        rng = np.random.default_rng(0)
        tgt, src = wavy_surface(262_000, rng), wavy_surface(262_000, rng) - np.array([0.05, 0.02, 0.03])
        name = "synthetic wavy surface (real data absent)"
    paths = folder / "src.npy", folder / "tgt.npy"
    np.save(paths[0], src)
    np.save(paths[1], tgt)
    return name, len(src), len(tgt), paths


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pause", type=float, default=2.5, help="seconds before every timed call (default %(default)g)")
    ap.add_argument("--calls", type=int, default=5, help="timed calls per child process (default %(default)d)")
    ap.add_argument("--rounds", type=int, default=2, help="child processes per setting, taking turns")
    ap.add_argument("--realdata", default=None)
    args = ap.parse_args()
    realdata = args.realdata or os.environ.get("LABKIT_REALDATA") or next(
        (c for c in (Path(__file__).resolve().parents[2] / "shared" / "realdata", Path("/work/shared/realdata"))
         if (Path(c) / "README.md").is_file()), None)
    print(f"{os.cpu_count()} CPU(s), load average {os.getloadavg()}")
    fp = fresh_pages(args.pause)
    print("\nfresh pages: 100 MB of new memory written (ms, median of 3)")
    for k, v in fp.items():
        print(f"  {k:14s} {v:8.1f}")
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        name, ns, nt, (ps, pt) = _pair(realdata, Path(tmp))
        results = {"1": [], "0": []}
        digests = set()
        for _ in range(args.rounds):
            for keep in ("1", "0"):
                env = {**os.environ, "LABKIT_KEEP_FREED_MEMORY": keep}
                out = subprocess.run([sys.executable, "-c", _CHILD, str(ps), str(pt), str(args.pause), str(args.calls)],
                                     env=env, capture_output=True, text=True, check=True)
                got = json.loads(out.stdout.strip().splitlines()[-1])
                results[keep] += got["rows"]
                digests.add(got["digest"])
    print(f"\nicp, every point: {name}, {ns:,} vs {nt:,} points; {args.pause:g} s pause before each call, "
          f"{args.rounds} x {args.calls} calls per setting (medians per call)")
    print(f"{'freed memory':24s} {'wall s':>8s} {'system s':>9s} {'user s':>8s} {'page faults':>12s}")
    for keep, label in (("1", "kept (labkit default)"), ("0", "handed back (glibc)")):
        r = np.array(results[keep])
        print(f"{label:24s} {np.median(r[:, 0]):8.3f} {np.median(r[:, 1]):9.3f} {np.median(r[:, 2]):8.3f} "
              f"{np.median(r[:, 3]):12.0f}")
    print(f"result digests: {', '.join(sorted(digests))} ({'the same' if len(digests) == 1 else 'DIFFERENT'})")
    print("machine load after:", os.getloadavg())


if __name__ == "__main__":
    main()
