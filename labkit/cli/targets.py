"""``labkit targets SCAN... --radius-range A B``: register scans by their sphere targets (notebook 11).

Prints each scan's transformation with standard deviations and the residual and test of every target,
then writes, per registered scan, a registration file (``labkit change --registration`` reads it) and the
scan moved into the reference frame. The parser and the handler live here to keep ``labkit.cli`` short.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.outputs import staged_outputs
from ..core.errors import LabkitError
from ..io import LAS_SUFFIXES, read_cloud, write_cloud
from ..registration.file import save_registration
from ..targets.register import register_scans


def add_parser(sub, positive_float, seed):
    """The ``targets`` sub-command (option types from ``labkit.cli``)."""
    p = sub.add_parser("targets", help="register scans by their sphere targets (Gauss-Helmert network)",
                       description="Find the sphere targets in every scan, match them by their distances, adjust "
                                   "all scans into the reference scan's frame in one Gauss-Helmert network; print "
                                   "each transformation with standard deviations and every target's residual and "
                                   "test; write one registration file and the registered cloud per scan.")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="point-cloud files, each in its scanner's frame")
    p.add_argument("--radius-range", type=positive_float, nargs=2, metavar=("MIN", "MAX"), required=True,
                   help="admissible target radii in m")
    p.add_argument("--reference", type=seed, default=0, help="index of the reference scan (default: %(default)s)")
    p.add_argument("--scale", action="store_true", help="estimate a scale factor per scan as well")
    p.add_argument("--moved-frames", action="store_true",
                   help="the scans are not in their scanners' frames (no station at the origin for the detection)")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the detection (default: %(default)s)")
    p.add_argument("--out", default=".", help="output folder (default: the current folder)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    """Detect, match, adjust, print, write; 0 when every scan was registered, 1 when one was refused."""
    if len(args.scans) < 2:
        raise LabkitError("give at least two scans")
    if args.reference >= len(args.scans):
        raise LabkitError(f"--reference {args.reference} is out of range for {len(args.scans)} scans")
    clouds = [read_cloud(path) for path in args.scans]
    for path, cloud in zip(args.scans, clouds):
        print(f"{path}: {len(cloud)} points")
    net = register_scans([c.xyz for c in clouds], tuple(args.radius_range), reference=args.reference,
                         scale=args.scale, station_at_origin=not args.moved_frames, rng=args.seed)
    for path, found in zip(args.scans, net.spheres):
        print(f"{path}: {len(found)} spheres found")
    print()
    print(net.summary())
    print()
    print(net.table.summary())

    ref = args.scans[args.reference]
    refused = []
    with staged_outputs(args.out) as stage:
        for i, (path, cloud) in enumerate(zip(args.scans, clouds)):
            M = net.matrices[i]
            names, cov = net.registration_covariance(i)
            if not np.isfinite(M).all() or not np.isfinite(cov).all():
                refused.append((path, "; ".join(net.undetermined[i]) or "not determined"))
                continue
            stem = Path(path).stem
            suffix = Path(path).suffix.lower() if Path(path).suffix.lower() in LAS_SUFFIXES else ".laz"
            save_registration(stage(f"{stem}_registration.json"), matrix=M, covariance=cov, parameter_names=names,
                              origin=np.zeros(3), crs=cloud.crs, inputs={"source": path, "target": ref},
                              method="targets")
            write_cloud(cloud.with_xyz(cloud.xyz @ M[:3, :3].T + M[:3, 3]), stage(f"{stem}_registered{suffix}"))
    print()
    for path in stage.written:
        print(f"wrote {path}")
    for path, why in refused:
        print(f"not registered: {path}: {why}")
    return 1 if refused else 0
