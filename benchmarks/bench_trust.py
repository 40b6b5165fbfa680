"""Benchmark: registration you can trust on real ALS - right, or honest about what it does not know.

Two disjoint random halves of one real airborne cloud are two epochs of one surface with
independent sampling and noise; the source half is moved by a known shift of 0.2-0.8 m, so the
truth is known exactly. Every real ALS file in ``../shared/realdata/`` (``als/*.la[sz]`` and the
two Autzen epochs; files in feet are converted to metres by ``read_cloud``; a geographic file is
refused by ``read_cloud`` and listed as skipped with the reason) is registered with the DEFAULTS of

- ``icp``: :func:`labkit.registration.icp`;
- ``max_consensus``: :func:`labkit.registration.max_consensus`;
- ``consensus+icp``: the route of ``labkit register --method consensus+icp``
  (:func:`labkit.registration.compare.standard_methods`);

beside Open3D's point-to-plane ICP (1 m correspondence distance, KNN-20 normals; it states no
precision). Columns: error in mm per axis, the stated std in mm (``undet`` where labkit reports the
component undetermined or states a std of 0.1 m or more), and the verdict:

- ``ok``: every component within 10 cm of the truth or honestly undetermined, none confidently wrong;
- ``CONFIDENT-WRONG``: a component stated with a std below 0.1 m is more than 3 std from the truth;
- ``miss``: more than 10 cm off, but within its stated 3 std (honest, not useful).

Last, the two real Autzen epochs (2010 onto 2023, Z converted from US survey feet): ``icp``
against ``max_consensus``, the difference per axis in combined standard deviations.

Measured (one run each, 2 cores under load; 11 files x 4 shifts = 44 rows per method; ok / miss / CONFIDENT-WRONG):

- all points (select='all', the former default): icp 38 / 1 / 5, max_consensus 26 / 8 / 14, consensus+icp 41 / 0 / 3.
  Wrong were: 4_6_crop (vegetation; max_consensus 4 of 4, 4-6 cm at +-1.5 cm; consensus+icp 3 of 4, Y 21 mm at
  +-4 mm), MixedConifer (max_consensus Z 9-13 mm at +-3 mm), fullwave (max_consensus 4 of 4), warsaw (icp 3 of 4,
  X 18 cm at +-6 cm; max_consensus 4 of 4) and the Autzen 2023 half (icp 2 of 4, Z 15 mm at +-4.9 mm).
- defaults (select='auto': stable classes / surface points): icp 42 / 0 / 2, max_consensus 42 / 4 / 2,
  consensus+icp 44 / 0 / 0. Left: icp on the Autzen 2023 half, Z 15 mm off at +-4.9 mm (3.06 std, 86 pairs,
  one class: no group test); max_consensus on fullwave (UAV), Y 8 mm off at +-2.4 mm.
- icp with the group test by class, local noise and quadrants, the t(G-1) factor of the cluster sandwich and the
  observed normal tilt (eq. 5.12c): 44 / 0 / 0 (Autzen 2023 half: Z 15 mm at +-5.1 mm, 2.94 std); the stds of the other
  files changed by 0-10 % (faceraster Y 4.2 -> 5.2 mm); warsaw X now undetermined (was -71 +- 95 mm). The conifer plot
  (height-normalised: flat ground once the crowns are out) and the roofs of sample_c report X and Y undetermined.
  interesting.las (19 m point spacing) is refused by icp: no pair within the 1 m gate.
- Open3D point-to-plane: right within 10 cm on most files, but 0.2-0.5 m off on sample_c and warsaw and metres off
  on interesting.las, without any stated precision.
- Autzen 2010 -> 2023: icp converges (the pyramid retry: X and Y missed the precision limit by 1 % from the start)
  at (-0.46, +0.87, +0.26) m +-(0.54, 0.32, 0.063) m (the quadrants disagree: real change, their spread is in the
  +-); max_consensus (-0.81, +0.82, +0.18) m at +-(0.06, 0.07, 0.005) m: within (0.65, 0.19, 1.22) combined std;
  Open3D (-0.05, 1.43, 0.43) m. A TIN grid search (median |dZ| over horizontal shifts) also puts X, Y near
  (-0.8, +0.7) m.

max_consensus with the symmetric estimate (source->target and target->source averaged, joint block
jackknife) and the counted work budget, 2026-12-02, seed 0 (``--methods max_consensus,consensus+icp --no-epochs``):

- max_consensus 44 / 0 / 0 (was 42 / 4 / 2). Stated components: fullwave X, Y (0, -2) mm at +-(1.9, 2.0)
  (was Y 8 mm at +-2.4: the bias of the k-neighbourhood planes, the same in every random half);
  faceraster (4, 1) mm at +-(3.4, 1.8); the file in US feet (2, 3) mm at +-(2.5, 2.0); 4_6_crop (-13, -25) mm
  at +-(11, 15); the 350,000-point halves (4, -10) mm at +-(10, 8); Z everywhere within 1.3 std. X and Y
  undetermined (std >= 0.1 m, off by 0.1-1.5 m) on MixedConifer, sample_c, warsaw and interesting.las
  (all three axes there); these are the rows that are honest but not right within 10 cm. Not converged
  (work budget spent): interesting.las and the 350,000-point file.
- consensus+icp: 39 rows ok, none confidently wrong; refused by the ICP gate on interesting.las (4 rows);
  the last rows of the 350,000-point file not run before the deadline.
- Monte Carlo over 16 random halves of fullwave.laz (tests/registration/test_real_als_trust.py): with the
  joint jackknife alone rms error / stated std 1.74, 1.90, 0.85 in X, Y, Z and one half 5 std off (X, Y 7 mm
  at 1.5 mm): the symmetric mean leaves 1.3, 1.5 mm of the plane bias in every half (the two fits differ by
  2 x (-2, 8) mm). With half the measured bias as the std of that remainder: 1.10, 0.74, 0.79, largest
  |error| / std 2.7 (2026-12-02). The whole sweep with it (``--methods max_consensus --no-open3d --no-epochs``,
  seed 0, 12 files incl. the Autzen halves): 48 / 0 / 0; the seed-0 half of fullwave now states (1.9, 5.1) mm
  in X, Y (its two fits differ by 2 x (-1, 10) mm), faceraster (3.6, 1.8), 4_6_crop (11, 15) mm, unchanged.
- 4_6_crop (ground class, 0.4 pts/m^2 per half): stated std conservative. Over 12 random halves (all four
  shifts) rms error / stated std 0.55, 0.79, 0.63 in X, Y, Z for max_consensus (stated about 14 mm in X, Y)
  and 0.52, 0.66, 0.82 for icp. Not the group test (the groups agree in every half: no added spread), not
  the block edge (the 3.3 m blocks alone: 0.59, 0.87, 0.67), hardly the plane-bias term (0-30 % of the
  variance). Suspected: the delete-a-block jackknife counts the block-to-block spread of the local plane
  biases, the same in every half, as noise. Not a deliberate margin; left as is (honest, not tuned).

With the t factor of the effective cells per parameter (icp), the jackknife's t factor and per-axis block
edge (max_consensus) and the group test referred to Welch-James F at alpha / k (2026-12-02 afternoon, seed 0,
``--no-open3d``, idle machine beside a CI run): icp 44 / 0 / 0 (+4 refused on interesting.las), max_consensus
48 / 0 / 0, consensus+icp 48 / 0 / 0, the same rows undetermined as before; Autzen 2010 -> 2023: icp
(-457, +874, +257) mm +-(570, 322, 65), max_consensus (-975, +819, +161) mm +-(111, 89, 12), within (0.89, 0.17,
1.45) combined std.

Why X and Y stay undetermined where they do (icp defaults, 2026-12-02; seed 0, all four shifts):

- MixedConifer: the stable class is a height-normalised flat floor: the two horizontal directions
  have std 0.4-1.1 m from the information that survives re-matching (eq. 5.12a-b); nothing to find
  there. All points (crowns, stems) determine X, Y to +-10 mm, but over 16 random halves their
  spread is 1.4-1.5 times the stated std (one half 3.2 std off): not used.
- sample_c: one horizontal direction has std 0.16-0.25 m (0.16-0.18 m without the observed tilt of
  eq. 5.12c, so that term is not the cause), the other 7 mm; X and Y both have a share in the weak
  one and are held. With max_std=1 m the estimate lands 65-135 mm off at +-80-190 mm, and the ground
  class alone 0.22 m off in Y (direction std 0.2 m): the stable points do not fix that direction.
  All points: 0.29-0.32 m.
- warsaw: the weak direction's std is 98-101 mm, at the precision limit (max_std = 0.1 m);
  with max_std=1 m: X 75-81 mm off at +-112 mm (honest, not useful). All points: X 185 mm off at
  +-62 mm (3.0 std): the vegetation biases.
- interesting.las (27 m spacing in a half): no pair within ICP's 1 m gate. ``consensus+icp`` now
  widens the gate at the consensus start to twice the target's point spacing, keeping the precision
  limit of the 1 m gate: it reports X, Y, Z undetermined (4 of 4 rows ok; 0.9-1.5 m off in X, Y and
  0.3 m in Z) instead of refusing. consensus+icp over all 48 rows (12 files incl. the Autzen halves):
  48 / 0 / 0 (before: 44 / 0 / 0 and 4 refused); icp unchanged, 44 / 0 / 0 and 4 refused.

X and Y from the height model where point-to-plane leaves them undetermined (icp defaults and the
consensus+icp route; :func:`labkit.registration.height_model.fill_held_axes`: least-squares matching of
the two height models of all points, highest point per cell, delete-a-block jackknife), 2026-12-02,
seed 0, all 12 files x 4 shifts (``--methods icp,consensus+icp``):

- icp 44 / 0 / 0 (and 4 refused on interesting.las, as before); consensus+icp 48 / 0 / 0.
- MixedConifer: X, Y now stated and right, 4 of 4 shifts within 10 cm for both methods: icp
  (38-43, 38-43) mm at +-(20, 22) mm, consensus+icp (41-45, 32-42) mm at +-(20, 23) mm; Z from the
  floor as before. These halves are a 2-sigma case: over 12 other random halves of the estimator
  spread / stated is 1.03 / 1.02 and the largest error 2.2 std; over 24 halves the mean error
  is (2 +- 4, 5 +- 5) mm (tests/registration/test_height_model.py).
- sample_c: 0 of 4 within 10 cm, X and Y still undetermined (honest): the data are one large gable
  roof clipped at its outline plus a strip of ground, so no height jump crosses the ridge direction;
  the height model's along-ridge std is 0.42-0.81 m, or the two epochs share no information in it.
- warsaw: 0 of 4, X and Y undetermined (honest): the height model's weak direction has std
  0.15-0.80 m over 12 halves (1,500 points per half over 33 m, a few trees, no buildings in class 6).
- interesting.las: 0 of 4 (27 m spacing; consensus+icp X, Y, Z undetermined as before).
- Every other file: unchanged (ICP determines X and Y there, the height model is not run).
- Autzen 2010 -> 2023: as above (icp - max_consensus within (0.95, 0.17, 1.51) combined std).
- max_consensus fills the same way (point-to-plane defaults), seed 0, ``--methods max_consensus --no-open3d
  --no-epochs``: 48 / 0 / 0; MixedConifer 4 of 4 within 10 cm, (41-45, 32-42) mm at +-(20, 23) mm (before:
  Y 358 mm off, undetermined); sample_c, warsaw and interesting.las undetermined in X, Y as before.

Held directions moved to a better value, still reported undetermined (2026-12-02 evening, seed 0,
``--no-open3d``, the machine shared with a CI run): icp holds only the weak direction along sample_c's
parallel ridges, solves the rest and moves the weak one to where the plan-view outlines agree
(:mod:`labkit.registration.closest_point.outline`); max_consensus moves held directions to the centre of the
consensus hill along them instead of the branch-and-bound argmax (:mod:`labkit.registration.consensus.plateau`).
Tally unchanged (icp 44 / 0 / 0 and 4 refused on interesting.las, max_consensus 48 / 0 / 0, consensus+icp
48 / 0 / 0); rows within 10 cm in every component, stated or not:

- sample_c: icp 0 -> 4 of 4 (24 of 24 over six splits; Z now 1.6-4 mm, errors 0-2 mm), max_consensus and
  consensus+icp 1 -> 4 of 4 (24 of 24 over six splits, rms horizontal error 349 -> 38 mm).
- warsaw: max_consensus 0 -> 4 of 4 at seed 0; icp and consensus+icp 4 of 4 as before. Not robust: with
  1,500 points a half the held X scatters by 0.08-0.13 m between splits (12 splits x 4 shifts: 36 of 48 within
  10 cm on this benchmark's split, 32 of 48 on the split of tests/registration/test_real_als_trust.py, where
  seed 0 is 0.25 m off: the hill itself is lopsided there, and the reverse direction's hill with it).
- The hill's centre is the centre of mirror symmetry of the consensus profile (before the quadratic's vertex:
  warsaw 28 -> 36 and 22 -> 32 of 48, sample_c's rms 35 -> 18 and 72 -> 53 mm on the two kinds of split).
- interesting.las: 0 of 4 for every method, X and Y undetermined (19-27 m between points).
- every other file: the same numbers as before.

Run:  python benchmarks/bench_trust.py [--realdata PATH] [--files sample_c,warsaw] [--seed 0] [--no-open3d]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from labkit import read_cloud
from labkit.registration.compare import standard_methods
from labkit.core.errors import LabkitError
from labkit.registration import icp, max_consensus

#: four shifts of 0.2-0.8 m (the truth: source = half - shift, the result should be +shift)
SHIFTS = np.array([[0.15, -0.12, 0.05], [-0.25, 0.30, -0.10], [0.42, 0.30, 0.12], [-0.50, -0.55, 0.20]])
#: the shift (m) and std (m) limits of the verdicts
RIGHT, CONFIDENT, SIGMAS = 0.10, 0.10, 3.0
METHODS = ("icp", "max_consensus", "consensus+icp")


def realdata_root(arg=None):
    for c in (arg, os.environ.get("LABKIT_REALDATA"), Path(__file__).resolve().parents[2] / "shared" / "realdata",
              "/work/shared/realdata"):
        if c and (Path(c) / "README.md").is_file():
            return Path(c)
    return None


def als_files(root):
    """The real airborne files: als/*.la[sz] and the Autzen epochs."""
    return sorted((root / "als").glob("*.la[sz]")) + sorted((root / "epochs").glob("autzen-bmx-*.las"))


def halves(cloud, seed=0):
    """Two disjoint random halves of one cloud (PointClouds, attributes kept)."""
    rng = np.random.default_rng(seed)
    half = rng.random(len(cloud.xyz)) < 0.5
    return cloud.subset(half), cloud.subset(~half)


def run_method(name, source, target, rng=0):
    if name == "icp":
        return icp(source, target, rng=rng)
    if name == "max_consensus":
        return max_consensus(source, target)
    return standard_methods(("consensus+icp",), rng=rng)["consensus+icp"](source, target)


def verdict(estimate, std, truth):
    """'ok', 'miss' or 'CONFIDENT-WRONG' (module docstring) and the error (m)."""
    err = np.asarray(estimate) - truth
    std = np.asarray(std, dtype=float)
    stated = np.isfinite(std) & (std < CONFIDENT)
    if np.any(stated & (np.abs(err) > SIGMAS * std)):
        return "CONFIDENT-WRONG", err
    if np.all(~stated | (np.abs(err) <= RIGHT)):
        return "ok", err
    return "miss", err


def run_open3d(source, target, o3d, max_distance=1.0):
    o = target.mean(axis=0)
    s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source - o))
    g = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target - o))
    g.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    reg = o3d.pipelines.registration
    out = reg.registration_icp(s, g, max_distance, np.eye(4), reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(1e-7, 1e-7, 50))
    T = np.asarray(out.transformation)
    c = source.mean(axis=0) - o
    return T[:3, :3] @ c + T[:3, 3] - c


def cells(err, std=None):
    out = []
    for k in range(3):
        if std is not None and not (np.isfinite(std[k]) and std[k] < CONFIDENT):
            out.append(f"{1000 * err[k]:7.0f}{'(undet)':>9s}")
        elif std is None:
            out.append(f"{1000 * err[k]:7.0f}{'':9s}")
        else:
            out.append(f"{1000 * err[k]:7.0f}+-{1000 * std[k]:<7.1f}")
    return " ".join(out)


def epoch_pair(root, o3d):
    a, b = root / "epochs" / "autzen-bmx-2010.las", root / "epochs" / "autzen-bmx-2023.las"
    if not (a.is_file() and b.is_file()):
        return
    src, tgt = read_cloud(a), read_cloud(b)
    ri, rc = icp(src, tgt, rng=0), max_consensus(src, tgt)
    d = ri.translation - rc.translation
    comb = np.hypot(ri.translation_std, rc.translation_std)
    with np.errstate(invalid="ignore"):
        z = np.abs(d) / comb
    print("\nAutzen 2010 -> 2023 (real epochs, Z from ftUS):")
    for r in (ri, rc):
        print(f"  {r.method.split()[0]:14s} {np.array2string(1000 * r.translation, precision=0)} mm "
              f"+- {np.array2string(1000 * r.translation_std, precision=1)} mm  converged={r.converged}")
    if o3d is not None:
        est = run_open3d(src.xyz, tgt.xyz, o3d)
        print(f"  {'open3d':14s} {np.array2string(1000 * est, precision=0)} mm")
    agree = bool(np.all(~np.isfinite(z) | (z <= SIGMAS)))
    print(f"  icp - max_consensus: {np.array2string(1000 * d, precision=0)} mm = "
          f"{np.array2string(z, precision=2)} combined std -> {'agree' if agree and ri.converged else 'DISAGREE'}"
          f"{'' if ri.converged else ' (icp not converged)'}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--realdata", default=None)
    ap.add_argument("--files", default="", help="comma-separated substrings of file names (default: all)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--shifts", default="0,1,2,3", help="indices into SHIFTS")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--no-epochs", action="store_true", help="skip the Autzen 2010 -> 2023 comparison")
    args = ap.parse_args(argv)
    o3d = None
    if not args.no_open3d:
        try:
            import open3d as o3d
        except ImportError:  # pragma: no cover
            print("open3d not installed: labkit rows only")
    root = realdata_root(args.realdata)
    if root is None:
        print("skipped: real development data not found (set LABKIT_REALDATA or --realdata)")
        return
    methods = args.methods.split(",")
    picks = [int(i) for i in args.shifts.split(",")]
    tally = {m: [0, 0, 0] for m in methods}  # ok, miss, confident-wrong
    print(f"{'file':26s} {'shift m':>20s} {'method':14s} {'error mm (+- stated std mm)':^60s} {'verdict':16s} time s")
    for path in als_files(root):
        if args.files and not any(f in path.name for f in args.files.split(",")):
            continue
        try:
            cloud = read_cloud(path)
        except LabkitError as exc:
            print(f"{path.name:26s} skipped: {str(exc).split(';')[0]}")
            continue
        tgt, src0 = halves(cloud, args.seed)
        for i in picks:
            s = SHIFTS[i]
            src = src0.with_xyz(src0.xyz - s)
            head = f"{path.name[:26]:26s} {np.array2string(s, precision=2):>20s} "
            for name in methods:
                t0 = time.perf_counter()
                try:
                    res = run_method(name, src, tgt)
                except LabkitError as exc:
                    print(head + f"{name:14s} refused: {exc}", flush=True)
                    head = " " * len(head)
                    continue
                v, err = verdict(res.translation, res.translation_std, s)
                tally[name][("ok", "miss", "CONFIDENT-WRONG").index(v)] += 1
                conv = "" if res.converged else " not conv."
                print(head + f"{name:14s} {cells(err, res.translation_std):60s} {v:16s} "
                      f"{time.perf_counter() - t0:5.1f}{conv}", flush=True)
                head = " " * len(head)
            if o3d is not None:
                err = run_open3d(src.xyz, tgt.xyz, o3d) - s
                right = "ok" if np.all(np.abs(err) <= RIGHT) else "wrong (no std)"
                print(head + f"{'open3d p2plane':14s} {cells(err):60s} {right:16s}", flush=True)
    print("\ntally (ok / miss / CONFIDENT-WRONG):", {m: tuple(v) for m, v in tally.items()})
    if not args.no_epochs:
        epoch_pair(root, o3d)


if __name__ == "__main__":
    main()
