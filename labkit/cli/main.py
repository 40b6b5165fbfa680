"""Command line: ``labkit demo``, ``sphere``, ``register``, ``compare``, ``tiles``, ``change`` and ``targets``.

Each sub-command is a small function taking the parsed arguments. Bad input
(a missing or corrupt file, an invalid option or number) ends with exactly one
line on stderr and exit status 2, never a traceback; ``labkit sphere`` exits
with 1 when no sphere is found; ``labkit register`` exits with 4 when the
registration did not converge or determines no component (one line says why
and what to try); an unexpected internal error prints one line
and exits with 3 (``LABKIT_TRACEBACK=1`` shows the traceback).

Output files are staged next to their destination and moved into place only
when every file of the command has been written; if moving one fails, those
already moved are rolled back (files they replaced are restored) and folders
the command created are removed, so a failure leaves nothing new behind.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from .. import __version__
from . import targets as _cli_targets
from ..registration import compare
from ..core.crs import check_same_crs
from ..core.checks import count, finite, non_negative, positive, probability
from .change import change_parameters, frame_text, held_priors, registration_for
from .output import _distance_figure, _print_tiles, _rotation_text
from ..core.outputs import save_figure, staged_outputs
from ..neighbours.treecache import forget as forget_tree
from ..cloud import PointCloud
from ..demo import run_demo
from ..change.distances import distances_before_after
from ..core.errors import LabkitError
from ..io.geotiff import change_geotiff, shift_field_geotiff
from ..io import LAS_SUFFIXES, cloud_info, read_cloud, write_cloud
from ..io.write import write_moved
from ..plotting.change import plot_change_figure
from ..plotting.compare import plot_shift_field
from ..core.progress import from_cli
from ..ransac import ransac_sphere
from ..ransac.threshold import estimate_threshold
from ..registration.references import load_references
from ..registration.file import save_registration
from ..tiles import MAX_TILES, check_scheduler, neighbour_test, register_tiles
from ..registration.verdict import EXIT_NOT_CONVERGED, register_verdict

# --------------------------------------------------------------------------- sub-commands
def _cmd_demo(args) -> int:
    run_demo(Path(args.out), quick=args.quick)
    return 0


def _cmd_sphere(args) -> int:
    if args.station is not None and args.no_station:
        raise LabkitError("--station X Y Z and --no-station contradict each other: give one of them")
    if args.hold_radius and args.radius is None:
        raise LabkitError("--hold-radius holds the radius at --radius R: give --radius as well")
    xyz = read_cloud(args.file).xyz  # (a missing or corrupt file is reported first)
    print(f"{args.file}: {len(xyz)} points")
    station, why = _sphere_station(xyz, args.station, args.no_station)
    print(f"station: {why}")
    if args.radius_range is None and args.radius is None:
        # a sphere of unknown size competes with every round object and needs uniform sampling: refuse
        raise LabkitError("labkit sphere needs the size of the target: --radius-range MIN MAX or --radius R "
                          "(in m; e.g. --radius-range 0.1 0.2 for a 0.145 m target)")
    estimate = estimate_threshold(xyz, rng=args.seed)
    threshold = estimate.threshold if args.threshold is None else args.threshold
    print(f"inlier {estimate.text()} (estimated from the data; --threshold overrides)" if args.threshold is None
          else f"threshold: {1000 * threshold:g} mm (given; the data's noise suggests {estimate.text()})")
    result = ransac_sphere(xyz, threshold, p=args.p, rng=args.seed,
                           radius_range=None if args.radius_range is None else tuple(args.radius_range),
                           nominal_radius=args.radius, hold_radius=args.hold_radius, sigma=args.sigma,
                           station=station)
    print()
    print(result.summary())
    if not result.found:
        hint = (f"; tried with threshold {1000 * threshold:g} mm: try --threshold {2 * threshold:g} (m) if the "
                "noise is larger than the estimate" if args.threshold is None else
                f"; tried with --threshold {threshold:g} m: try --threshold {max(estimate.threshold, 2 * threshold):g}")
        print(f"\nlabkit sphere: no sphere found in {args.file}: {result.reason}{hint}", file=sys.stderr)
        return 1
    print()
    print(result.fit.summary())
    return 0


def _sphere_station(xyz, given, off):
    """The scanner position for the visibility checks, and a line saying which and why.

    Default: the origin when the file looks scanner-centred (the origin inside the bounding box and no
    point within 0.25 m of it, the blind zone around a scanner); otherwise no station.
    """
    if off:
        return None, "not used (--no-station): no visibility checks"
    if given is not None:
        return np.asarray(given, dtype=np.float64), f"{given[0]:g} {given[1]:g} {given[2]:g} (given)"
    inside = bool(np.all(xyz.min(axis=0) < 0) and np.all(xyz.max(axis=0) > 0))
    if inside and float(np.min(np.einsum("ij,ij->i", xyz, xyz))) > 0.25**2:
        return np.zeros(3), "0 0 0 (the file looks scanner-centred: points all round the origin, none within 0.25 m)"
    return None, ("not used: the file does not look scanner-centred (give --station X Y Z for the visibility "
                  "checks)")


def _cmd_register(args) -> int:

    _method_options(args, [args.method])
    _check_dof([args.method], args.dof)
    _check_max_iterations(args.method, args.max_iterations)
    progress = from_cli(args.quiet, args.progress)  # on stderr: reading, ICP iterations, distances, writing
    # ICP reads only the classification: the moved source is written from its file (write_moved)
    source = read_cloud(args.source, attributes=_registration_attributes(args.source), progress=progress)
    target = read_cloud(args.target, attributes=_registration_attributes(args.target), progress=progress)
    print(f"source {args.source}: {len(source)} points; target {args.target}: {len(target)} points")
    check_same_crs(source, target, "labkit register")
    method = compare.standard_methods([args.method], dof=args.dof, extent=args.extent, max_points=args.max_points,
                                      rng=args.seed, reach=args.reach,
                                      max_iterations=args.max_iterations)[args.method]
    result = method(source, target, progress=progress)
    print()
    print(result.summary())
    print()
    print(_rotation_text(result))
    why = register_verdict(result)
    if why is not None:  # not converged, or no component determined: a verdict, not a result to apply
        print(f"labkit register: {why}; nothing written", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    change = distances_before_after(source, target, result, progress=progress)  # reuses ICP's target tree
    forget_tree()  # then frees it before the moved cloud is written
    print()
    print(change.summary())
    print(f"\ncoordinates of the 4x4 and the outputs: {frame_text(source)}")

    # Outputs: the transformed source (LAS/LAZ, attributes kept) and a distance-coloured top view
    suffix = Path(args.source).suffix.lower() if Path(args.source).suffix.lower() in LAS_SUFFIXES else ".laz"
    stem = Path(args.source).stem
    fig = _distance_figure(source, change, f"{stem} -> {Path(args.target).stem} ({result.method})\n"
                                           f"{frame_text(source)}", args.seed)
    with staged_outputs(args.out) as stage:
        _write_moved(args.source, source, result, stage(f"{stem}_registered{suffix}"), progress)
        save_figure(fig, stage(f"{stem}_distances.png"))
        save_registration(stage("registration.json"), result, crs=source.crs,
                          inputs={"source": str(Path(args.source).resolve()), "target": str(Path(args.target).resolve())})
    print()
    for path in stage.written:
        print(f"wrote {path}")
    return 0


def _registration_attributes(path):
    """Attributes a registration reads: the classification of a LAS/LAZ file (all of them from other formats,
    whose moved cloud is written from memory)."""
    if Path(path).suffix.lower() not in LAS_SUFFIXES:
        return None
    return ["classification"] if "classification" in cloud_info(path).dimensions else []


def _write_moved(path, source, result, out, progress) -> None:
    """The moved source: from its LAS/LAZ file chunk by chunk (all attributes), else from the cloud in memory."""
    if Path(path).suffix.lower() in LAS_SUFFIXES and write_moved(path, out, result.apply, progress=progress):
        return
    if Path(path).suffix.lower() in LAS_SUFFIXES:  # new offsets needed: the cloud with all its attributes
        source = read_cloud(path, progress=progress)
    write_cloud(source.with_xyz(result.apply(source.xyz)), out, progress=progress)


def _cmd_compare(args) -> int:

    _method_options(args, args.methods, "--methods")
    _check_dof(args.methods, args.dof)
    pairs = compare.load_pairs(args.pairs)
    refs = load_references(args.references) if args.references else {}
    missing = [f"{r} ({c})" for (r, c), pair in pairs.items() if (r, c) not in refs and pair.truth is None]
    if missing:
        raise LabkitError(f"no reference for {', '.join(missing)}: pass --references REF.json with an entry "
                          "(region, case) for every pair, or give the pair a 'truth' in the pair file")
    methods = compare.standard_methods(args.methods, dof=args.dof, extent=args.extent, max_points=args.max_points,
                               rng=args.seed)
    table = compare.compare_methods(pairs, methods, references=refs, alpha=args.alpha)
    print(table.summary())
    print()
    print(table.text())
    print("\nError on the constrained axes (mm):")
    print(table.pivot())
    with staged_outputs(Path(args.out).parent) as stage:
        table.to_csv(stage(Path(args.out).name))
    print(f"\nwrote {stage.written[0]}")
    return 0


def _cmd_tiles(args) -> int:

    _method_options(args, [args.method])
    _check_dof([args.method], args.dof)
    _check_max_iterations(args.method, args.max_iterations)
    method = compare.standard_methods([args.method], dof=args.dof, extent=args.extent, max_points=args.max_points,
                              rng=args.seed, max_iterations=args.max_iterations)[args.method]
    scheduler = args.scheduler or default_scheduler()
    results = Path(args.results) if args.results else Path(args.out) / "tiles"
    field = register_tiles(list(args.source), list(args.target), method,
                           size=args.size, buffer=args.buffer, min_points=args.min_points,
                           scheduler=scheduler, progress=from_cli(args.quiet, args.progress), results=results,
                           max_tiles=MAX_TILES if args.max_tiles is None else args.max_tiles)
    test = neighbour_test(field, args.alpha, extra_std=args.extra_std, correction=args.correction)
    print(field.summary())
    print()
    print(test.summary())
    _print_tiles(field, test)
    print(f"\ntiles: {len(field) - field.n_reused} computed, {field.n_reused} read back from {results} "
          f"(scheduler: {scheduler})")
    ax = plot_shift_field(field, test=test)
    with staged_outputs(args.out) as stage:
        field.to_csv(stage("shift_field.csv"), test)
        save_figure(ax.figure, stage("shift_field.png"))
        shift_field_geotiff(field, stage("shift_field.tif"), list(args.source))
    print()
    for path in stage.written:
        print(f"wrote {path}")
    return 0


def default_scheduler() -> str:
    """``labkit tiles`` runs on a LocalCluster when dask.distributed is installed, else on threads.

    Examples
    --------
    >>> from labkit.cli.main import default_scheduler
    >>> default_scheduler() in ("cluster", "threads")
    True
    """
    import importlib.util

    return "cluster" if importlib.util.find_spec("distributed") is not None else "threads"


def _scheduler_option(text: str) -> str:
    try:
        return check_scheduler(text)
    except LabkitError:
        raise argparse.ArgumentTypeError(
            f"expected threads, processes, sync, serial, cluster or tcp://HOST:PORT, got {text!r}") from None


def _cmd_change(args) -> int:
    """M3C2 change REFERENCE -> COMPARED with a LoD carrying the registration's covariance."""
    from ..change.m3c2 import load_registration, m3c2  # (numba, about 0.5 s: loaded when needed)

    _method_options(args, [args.register] if args.register else [], "--register")
    if args.held_rotation_std is not None and not (args.register or args.registration):
        raise LabkitError("--held-rotation-std applies to a registration's undetermined rotations only: give "
                          "--register METHOD or --registration RESULT.json, or drop it")
    args.held_rotation_std = 0.02 if args.held_rotation_std is None else args.held_rotation_std
    ref, cmp_ = read_cloud(args.reference), read_cloud(args.compared)
    print(f"reference {args.reference}: {len(ref)} points; compared {args.compared}: {len(cmp_)} points")
    check_same_crs(ref, cmp_, "labkit change", ("reference", "compared"))
    registration = None
    if args.registration:
        registration = registration_for(load_registration(args.registration), args, ref.crs)
    elif args.register:
        method = compare.standard_methods([args.register], dof=args.dof, extent=args.extent, max_points=args.max_points,
                                  rng=args.seed)[args.register]
        registration = method(cmp_, ref)
        print()
        print(registration.summary())
    moved = cmp_.xyz if registration is None else registration.apply(cmp_.xyz)
    held = held_priors(registration, args)
    normal_radius, cylinder_radius, max_depth = change_parameters(ref.xyz, moved, args)
    result = m3c2(ref, moved, args.spacing, normal_radius=normal_radius, cylinder_radius=cylinder_radius,
                  max_depth=max_depth, registration_covariance=registration, alpha=args.alpha, quantile=args.quantile,
                  progress=sys.stderr.isatty(), held_std=held)
    print()
    print(result.summary())
    stem = f"{Path(args.reference).stem}_{Path(args.compared).stem}_m3c2"
    suffix = Path(args.reference).suffix.lower() if Path(args.reference).suffix.lower() in LAS_SUFFIXES else ".laz"
    cores = result.to_cloud()
    cores = PointCloud(cores.xyz, cores.attributes, crs=ref.crs, units=ref.units, name=stem)  # in the file's units
    fig = plot_change_figure(result, f"M3C2 {Path(args.compared).stem} - {Path(args.reference).stem}\n"
                                     f"{frame_text(ref)}")
    with staged_outputs(args.out) as stage:
        write_cloud(cores, stage(stem + suffix), scale=None)
        write_cloud(cores, stage(stem + ".csv"), scale=None)
        save_figure(fig, stage(stem + ".png"))
        change_geotiff(result, stage(stem + ".tif"), crs=ref.crs, units=ref.units, extent=ref.bounds)
    print()
    for path in stage.written:
        print(f"wrote {path}")
    return 0


def _check_dof(methods, dof: str) -> None:
    """Maximum consensus estimates a translation only: refuse ``--dof rigid`` rather than ignore it."""
    if "consensus" in methods and dof == "rigid":
        raise LabkitError("--method consensus estimates a translation only; use --dof translation, "
                          "or --method consensus+icp / icp for a rigid transformation")


def _check_max_iterations(method: str, max_iterations) -> None:
    """``--max-iterations`` bounds ICP; refuse it with ``--method consensus`` rather than ignore it."""
    if max_iterations is not None and method == "consensus":
        raise LabkitError("--max-iterations applies to the icp methods (icp*, consensus+icp); --method consensus "
                          "stops at its own search budget")


# --------------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr (exit status 2), without the usage block."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see '{self.prog} --help')\n")


def _option_type(check, expected: str, convert=float):
    """An argparse type: ``convert`` the text, then run the shared validator ``check``."""

    def parse(text: str):
        try:
            value = convert(text)
            return check(value, "value")
        except (ValueError, LabkitError):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None

    parse.__name__ = expected  # argparse names the type in some messages
    return parse


_positive_float = _option_type(positive, "a positive number")
_non_negative_float = _option_type(non_negative, "a number >= 0")
_probability = _option_type(probability, "a number between 0 and 1")
_count = _option_type(count, "a whole number >= 1", int)
_finite_float = _option_type(finite, "a finite number")
_seed = _option_type(lambda v, name: count(v, name, minimum=0), "a whole number >= 0", int)


_METHOD_DEFAULTS = {"dof": "translation", "extent": 1.0, "max_points": 5000, "seed": 0}


def _add_method_options(p) -> None:
    # defaults None: an option given for a method it does not apply to is refused (_method_options)
    p.add_argument("--dof", choices=("translation", "rigid"), default=None,
                   help="estimate a translation or a rigid transformation (default: translation)")
    p.add_argument("--extent", type=_positive_float, default=None,
                   help="consensus methods only: search a translation within +-EXTENT m (default: 1.0)")
    p.add_argument("--max-points", type=_count, default=None,
                   help="consensus methods only: at most this many source points vote, spread evenly in space; "
                        "the search stops after a time budget with the best translation and its certified gap "
                        "(default: 5000)")
    p.add_argument("--seed", type=_seed, default=None, help="random seed (default: 0)")


def _method_options(args, methods, option: str = "--method") -> None:
    """Refuse a method option that none of the chosen methods uses; then fill in the defaults.

    ``methods`` empty: no registration runs (``labkit change`` without ``--register``).
    """
    given = {"--dof": args.dof, "--extent": args.extent, "--max-points": args.max_points, "--seed": args.seed,
             "--reach": getattr(args, "reach", None)}
    used = {"--dof", "--seed"} if methods else set()
    if any(m.startswith("consensus") for m in methods):
        used |= {"--extent", "--max-points"}
    if any(m.startswith("icp") for m in methods):
        used.add("--reach")
    for name, value in given.items():
        if value is not None and name not in used:
            chosen = f"{option} {' '.join(methods)}" if methods else "no registration (give --register METHOD)"
            applies = {"--extent": "consensus methods", "--max-points": "consensus methods",
                       "--reach": "the icp methods", "--dof": "a registration", "--seed": "a registration"}[name]
            raise LabkitError(f"{name} applies to {applies} only, not to {chosen}: drop it")
    for key, default in _METHOD_DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, default)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``labkit``: one sub-command per job, each checking its numbers with labkit's validators.

    Examples
    --------
    >>> from labkit.cli.main import build_parser
    >>> args = build_parser().parse_args(["sphere", "scan.laz", "--radius-range", "0.1", "0.2"])
    >>> args.command, args.file, args.radius_range
    ('sphere', 'scan.laz', [0.1, 0.2])
    """
    parser = _Parser(
        prog="labkit", description="labkit: robust adjustment of 3D point clouds for engineering geodesy.",
        epilog="Run 'labkit COMMAND --help' for the options of a command; 'labkit demo' needs no input files.")
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main job on built-in synthetic data")
    demo.add_argument("--out", default="labkit-demo", help="folder for the PNG figures (default: %(default)s)")
    demo.add_argument("--quick", action="store_true", help="smaller data, for smoke tests")
    demo.set_defaults(func=_cmd_demo)

    sphere = sub.add_parser("sphere", help="find a sphere target by RANSAC and adjust it (Gauss-Helmert)",
                            description="Detect a sphere in a point cloud (ASCII xyz, LAS/LAZ, npy/npz, PLY) with "
                                        "RANSAC and adjust it in the Gauss-Helmert model.")
    sphere.add_argument("file", help="point-cloud file")
    sphere.add_argument("--threshold", type=_positive_float, default=None,
                        help="inlier threshold t in m (about 2-3 x the noise; default: 3 x the noise estimated "
                             "from 8-point neighbourhoods, see labkit.ransac.threshold)")
    sphere.add_argument("--radius-range", type=_positive_float, nargs=2, metavar=("MIN", "MAX"),
                        help="admissible radii in m (this or --radius is required)")
    sphere.add_argument("--radius", type=_positive_float, help="nominal radius of the target in m")
    sphere.add_argument("--hold-radius", action="store_true", help="hold the radius at --radius in the adjustment")
    sphere.add_argument("--sigma", type=_positive_float,
                        help="a priori standard deviation of the coordinates in m (default: estimated robustly)")
    sphere.add_argument("--p", type=_probability, default=0.99,
                        help="RANSAC success probability (default: %(default)s)")
    sphere.add_argument("--seed", type=_seed, default=0, help="random seed (default: %(default)s)")
    sphere.add_argument("--station", type=_finite_float, nargs=3, metavar=("X", "Y", "Z"),
                        help="scanner position in m for the visibility checks (default: the origin when the file "
                             "looks scanner-centred, otherwise none)")
    sphere.add_argument("--no-station", action="store_true", help="skip the visibility checks")
    sphere.set_defaults(func=_cmd_sphere)

    reg = sub.add_parser("register", help="register SOURCE onto TARGET (ICP or maximum consensus)",
                         description="Register SOURCE onto TARGET; print the transformation with standard "
                                     "deviations and the degeneracy report; write the transformed source and "
                                     "a distance-coloured PNG.",
                         epilog="Exit status: 0 done; 2 bad input; 3 internal error; 4 the registration did not "
                                "converge or determines none of dX, dY, dZ (one line on stderr says why and what "
                                "to try; nothing is written).")
    reg.add_argument("source", help="point cloud to move (e.g. the later epoch)")
    reg.add_argument("target", help="reference point cloud")
    reg.add_argument("--method", choices=compare.METHODS, default="icp",
                     help="registration method; icp is point to plane (converges from shifts within its "
                          "matching distance), consensus a translation by maximum consensus searched globally "
                          "within +-EXTENT, consensus+icp that search followed by ICP: the route for large "
                          "shifts (default: %(default)s)")
    _add_method_options(reg)
    reg.add_argument("--reach", type=_positive_float, default=None,
                     help="icp methods: largest expected shift in m; beyond the 1 m matching distance a "
                          "coarse-to-fine pyramid (voxel levels, wider gates) runs first (default: none)")
    reg.add_argument("--max-iterations", type=_count, default=None, metavar="N",
                     help="icp methods: stop after N iterations (default: ICP's own, 50); a run that stops "
                          "before converging exits with status 4")
    reg.add_argument("--out", default=".", help="output folder (default: the current folder)")
    shown = reg.add_mutually_exclusive_group()
    shown.add_argument("--quiet", action="store_true",
                       help="no progress on stderr (reading, ICP iterations, distances, writing)")
    shown.add_argument("--progress", action="store_true",
                       help="progress on stderr even when it is not a terminal (default: only on a terminal)")
    reg.set_defaults(func=_cmd_register)

    cmp_ = sub.add_parser("compare", help="compare registration methods with references; write a CSV table",
                          description="Run registration methods on the epoch pairs of a JSON file and compare "
                                      "them with reference transformations.")
    cmp_.add_argument("pairs", help="JSON list of epoch pairs (see labkit.registration.compare.load_pairs)")
    cmp_.add_argument("--methods", nargs="+", choices=compare.METHODS, default=["icp", "icp-tukey", "consensus"],
                      metavar="METHOD", help=f"methods among {', '.join(compare.METHODS)} (default: %(default)s)")
    cmp_.add_argument("--references", help="JSON reference file (see labkit.registration.references.load_references)")
    cmp_.add_argument("--alpha", type=_probability, default=0.05, help="test level (default: %(default)s)")
    _add_method_options(cmp_)
    cmp_.add_argument("--out", default="comparison.csv", help="CSV file to write (default: %(default)s)")
    cmp_.set_defaults(func=_cmd_compare)

    tiles = sub.add_parser("tiles", help="register tile by tile and test neighbouring tiles (shift field)",
                           description="Cut two surveys into square tiles, register every tile, test whether "
                                       "neighbouring tiles agree; write the shift field as PNG and CSV. A tile is "
                                       "'ok' only when its registration converged and its data determine dX, dY "
                                       "and dZ; 'undetermined' tiles give only the components they determine "
                                       "(the others are empty in the CSV), 'not converged' tiles none.")
    tiles.add_argument("source", nargs="+",
                       help="point-cloud files, folders of LAS/LAZ tiles or globs ('2016/*.laz') of the epoch to move")
    tiles.add_argument("--target", nargs="+", required=True,
                       help="files, folders or globs of the reference epoch")
    tiles.add_argument("--size", type=_positive_float, default=100.0, help="tile edge in m (default: %(default)s)")
    tiles.add_argument("--buffer", type=_non_negative_float, default=0.0, help="margin read around each tile in m")
    tiles.add_argument("--max-tiles", type=_count, default=None,
                       help="refuse grids of more tiles (default: labkit.tiles.MAX_TILES)")
    tiles.add_argument("--min-points", type=_count, default=200,
                       help="fewer points: tile skipped (default: %(default)s)")
    tiles.add_argument("--method", choices=compare.METHODS, default="icp", help="registration per tile (default: %(default)s)")
    tiles.add_argument("--max-iterations", type=_count, default=None, metavar="N",
                       help="icp methods: stop after N iterations (default: ICP's own, 50); a tile that stops "
                            "before converging is 'not converged' and gives no shift")
    tiles.add_argument("--alpha", type=_probability, default=0.05, help="test level (default: %(default)s)")
    tiles.add_argument("--extra-std", type=_non_negative_float, default=0.0,
                       help="extra std per tile in m for the neighbour test")
    tiles.add_argument("--correction", choices=("holm", "fdr", "none"), default="holm",
                       help="control of the many tests: holm keeps the chance of any false alarm in a stable survey "
                            "at alpha, fdr the share of false alarms among the flagged, none tests each at alpha "
                            "(default: %(default)s)")
    tiles.add_argument("--scheduler", type=_scheduler_option, default=None, metavar="SCHEDULER",
                       help="where the tiles run: cluster (a dask LocalCluster, one worker process per core; the "
                            "default when dask.distributed is installed), tcp://HOST:PORT (a running Dask "
                            "scheduler), threads (default without distributed), processes, sync or serial")
    tiles.add_argument("--results", metavar="DIR",
                       help="folder for one JSON per finished tile; a rerun reads finished tiles back instead of "
                            "computing them (default: OUT/tiles)")
    shown = tiles.add_mutually_exclusive_group()
    shown.add_argument("--quiet", action="store_true", help="no progress on stderr")
    shown.add_argument("--progress", action="store_true",
                       help="progress on stderr even when it is not a terminal (default: only on a terminal)")
    _add_method_options(tiles)
    tiles.add_argument("--out", default=".", help="output folder (default: the current folder)")
    tiles.set_defaults(func=_cmd_tiles)

    change = sub.add_parser("change", help="M3C2 change between two epochs with a level of detection",
                            description="M3C2 distances from REFERENCE to COMPARED at core points, with a level of "
                                        "detection that carries the registration's covariance; writes the core "
                                        "points (LAS/LAZ with distance, lod, significant), a CSV, a GeoTIFF "
                                        "and a PNG map of significant change.")
    change.add_argument("reference", help="reference epoch (point-cloud file)")
    change.add_argument("compared", help="compared (later) epoch")
    how = change.add_mutually_exclusive_group()
    how.add_argument("--registration", metavar="REGISTRATION.json",
                     help="registration file (labkit register --out R writes R/registration.json; "
                          "labkit.save_registration; or {'matrix': 4x4, 'covariance': 3x3}) of COMPARED onto "
                          "REFERENCE, or of REFERENCE onto COMPARED as its inputs say (then inverted); applied, "
                          "its covariance enters the LoD")
    how.add_argument("--register", choices=compare.METHODS, metavar="METHOD",
                     help=f"register COMPARED onto REFERENCE first ({', '.join(compare.METHODS)}) and use its covariance")
    change.add_argument("--normal-radius", type=_positive_float, nargs="+",
                        help="PCA radius for the normals in m; several: the most planar per core point (default: "
                             "max(cylinder radius, 12.5 x roughness), the normal scale >= 25 x roughness of "
                             "Lague et al. 2013)")
    change.add_argument("--cylinder-radius", type=_positive_float,
                        help="cylinder radius in m (default: median distance to the 30th nearest reference point, "
                             "about 30 points per cylinder)")
    change.add_argument("--max-depth", type=_positive_float,
                        help="cylinder half length along the normal in m (default: max(2 x expected change, "
                             "cylinder radius))")
    change.add_argument("--expected-change", type=_positive_float,
                        help="largest change expected in m, for the default max depth (default: the 99th "
                             "percentile of the cloud-to-cloud distance compared -> reference)")
    change.add_argument("--held-shift-std", type=_non_negative_float, metavar="M",
                        help="prior std in m of a shift component the registration left undetermined (default: "
                             "none, the LoD is infinite where it matters)")
    change.add_argument("--spacing", type=_positive_float,
                        help="core points: one reference point per cube of this edge (default: the cylinder radius)")
    change.add_argument("--alpha", type=_probability, default=0.05,
                        help="test level of the LoD, the false-alarm rate (default: %(default)s)")
    change.add_argument("--quantile", choices=("student", "normal"), default="student",
                        help="LoD quantile: Student t with Welch's degrees of freedom, or the normal z of "
                             "PDAL/CloudCompare (default: %(default)s)")
    change.add_argument("--held-rotation-std", type=_non_negative_float, default=None, metavar="DEG",
                        help="prior std (deg) of a rotation the registration left undetermined, as ICP's "
                             "held_rotation_std_deg (default: 0.02)")
    _add_method_options(change)
    change.add_argument("--out", default=".", help="output folder (default: the current folder)")
    change.set_defaults(func=_cmd_change)

    _cli_targets.add_parser(sub, _positive_float, _seed)
    return parser


def _version() -> str:
    return f"labkit {__version__}"


def _one_line(text) -> str:
    return " ".join(str(text).split())


def main(argv=None) -> int:
    """Run ``labkit`` with the arguments ``argv`` (default: the command line); return the exit status.

    0: done; 1: ``labkit sphere`` found no sphere; 2: bad input (one line on stderr); 3: an internal error;
    4: ``labkit register``'s registration did not converge or determines no component (:data:`EXIT_NOT_CONVERGED`).

    Examples
    --------
    >>> from labkit.cli.main import main
    >>> main(["sphere", "no-such-file.laz", "--radius", "0.1"])
    2
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with warnings.catch_warnings(record=True) as caught:  # one line each, and none after an error
            warnings.simplefilter("default")
            code = args.func(args)
        for text in dict.fromkeys(f"{w.category.__name__}: {_one_line(w.message)}" for w in caught):
            print(f"labkit {args.command}: warning: {text}", file=sys.stderr)
        return code
    except (LabkitError, OSError) as exc:  # bad input, or an output folder that cannot be written
        print(f"labkit {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"labkit {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug, not bad input: one line unless the traceback is asked for
        if os.environ.get("LABKIT_TRACEBACK"):
            raise
        print(f"labkit {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)} "
              "(please report; LABKIT_TRACEBACK=1 shows the traceback)", file=sys.stderr)
        return 3


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
