"""Command line: ``labkit demo``, ``sphere``, ``register``, ``compare`` and ``tiles``.

Each sub-command is a small function taking the parsed arguments. Bad input
(a missing or corrupt file, an invalid option) ends with one clear line on
stderr and exit status 2; ``labkit sphere`` exits with 1 when no sphere is
found. Output files are staged next to their destination and renamed only when
every file of the command has been written, so a failure leaves nothing
half-written.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

import numpy as np

from ._atomic import temporary_path
from .errors import LabkitError

LAS_SUFFIXES = (".las", ".laz")
PLOT_POINTS = 150_000  # at most this many points in a top-view figure


# --------------------------------------------------------------------------- sub-commands
def _cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(Path(args.out), quick=args.quick)
    return 0


def _cmd_sphere(args) -> int:
    from .io import read_cloud
    from .ransac import ransac_sphere

    cloud = read_cloud(args.file)
    print(f"{args.file}: {len(cloud)} points")
    result = ransac_sphere(cloud.xyz, args.threshold, p=args.p, rng=args.seed,
                           radius_range=None if args.radius_range is None else tuple(args.radius_range),
                           nominal_radius=args.radius, hold_radius=args.hold_radius, sigma=args.sigma)
    print()
    print(result.summary())
    if not result.found:
        print(f"\nlabkit sphere: no sphere found in {args.file}: {result.reason}", file=sys.stderr)
        return 1
    print()
    print(result.fit.summary())
    return 0


def _cmd_register(args) -> int:
    from .compare import standard_methods
    from .distances import distances_before_after
    from .io import read_cloud, write_cloud

    if args.method == "consensus" and args.dof == "rigid":
        raise LabkitError("--method consensus estimates a translation only; use --dof translation, "
                          "or --method consensus+icp / icp for a rigid transformation")
    source, target = read_cloud(args.source), read_cloud(args.target)
    print(f"source {args.source}: {len(source)} points; target {args.target}: {len(target)} points")
    method = standard_methods([args.method], dof=args.dof, extent=args.extent, max_points=args.max_points,
                              rng=args.seed)[args.method]
    result = method(source, target)
    print()
    print(result.summary())
    print()
    print(_rotation_text(result))
    change = distances_before_after(source, target, result)
    print()
    print(change.summary())

    # Outputs: the transformed source (LAS/LAZ, attributes kept) and a distance-coloured top view
    moved = source.with_xyz(result.apply(source.xyz))
    suffix = Path(args.source).suffix.lower() if Path(args.source).suffix.lower() in LAS_SUFFIXES else ".laz"
    stem = Path(args.source).stem
    fig = _distance_figure(source, change, f"{stem} -> {Path(args.target).stem} ({result.method})", args.seed)
    with staged_outputs(args.out) as stage:
        write_cloud(moved, stage(f"{stem}_registered{suffix}"))
        save_figure(fig, stage(f"{stem}_distances.png"))
    print()
    for path in stage.written:
        print(f"wrote {path}")
    return 0


def _cmd_compare(args) -> int:
    from .compare import compare_methods, load_pairs, standard_methods
    from .references import load_references

    pairs = load_pairs(args.pairs)
    refs = load_references(args.references) if args.references else {}
    missing = [f"{r} ({c})" for (r, c), pair in pairs.items() if (r, c) not in refs and pair.truth is None]
    if missing:
        raise LabkitError(f"no reference for {', '.join(missing)}: pass --references REF.json with an entry "
                          "(region, case) for every pair, or give the pair a 'truth' in the pair file")
    methods = standard_methods(args.methods, dof=args.dof, extent=args.extent, max_points=args.max_points,
                               rng=args.seed)
    table = compare_methods(pairs, methods, references=refs, alpha=args.alpha)
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
    from .compare import standard_methods
    from .plotting.compare import plot_shift_field
    from .tiles import neighbour_test, register_tiles

    method = standard_methods([args.method], dof=args.dof, extent=args.extent, max_points=args.max_points,
                              rng=args.seed)[args.method]
    field = register_tiles([Path(p) for p in args.source], [Path(p) for p in args.target], method,
                           size=args.size, buffer=args.buffer, min_points=args.min_points,
                           scheduler=args.scheduler, progress=sys.stdout.isatty())
    test = neighbour_test(field, args.alpha, extra_std=args.extra_std)
    print(field.summary())
    print()
    print(test.summary())
    _print_tiles(field, test)
    ax = plot_shift_field(field, test=test)
    with staged_outputs(args.out) as stage:
        field.to_csv(stage("shift_field.csv"))
        save_figure(ax.figure, stage("shift_field.png"))
    print()
    for path in stage.written:
        print(f"wrote {path}")
    return 0


# --------------------------------------------------------------------------- text and figures
def _rotation_text(result) -> str:
    """The 4x4 matrix and, for a rigid result, the angles with standard deviations (arcsec)."""
    from .transforms import angles_from_rotation

    lines = ["4x4 transformation (source -> target, caller's frame):",
             np.array2string(result.matrix, precision=6, suppress_small=True, max_line_width=120)]
    names = tuple(result.parameter_names)
    if "rx" in names:
        lines.append("(its last column includes the rotation about the frame's origin; dX, dY, dZ above are the "
                     "shift about " + "[" + ", ".join(f"{v:.3f}" for v in result.origin) + "])")
        ang = np.degrees(angles_from_rotation(result.rotation)) * 3600
        std = np.degrees(result.std[[names.index(n) for n in ("rx", "ry", "rz")]]) * 3600
        lines.append("rotation (arcsec): " + ", ".join(f"{n} {a:+.2f} +- {s:.2f}"
                                                       for n, a, s in zip(("rx", "ry", "rz"), ang, std)))
    else:
        lines.append("rotation: none estimated (translation only)")
    return "\n".join(lines)


def _print_tiles(field, test) -> None:
    print("\n  row col        dX        dY        dZ   sX (mm) sY (mm) sZ (mm)  area  status")
    for i, (t, s) in enumerate(zip(field.tiles, field.std)):
        if t.ok:
            print(f"  {t.tile.row:3d} {t.tile.col:3d} "
                  + " ".join(f"{v:+9.4f}" if np.isfinite(sd) else f"{'undet.':>9s}" for v, sd in zip(t.translation, s))
                  + " " + " ".join(f"{1000 * v:7.1f}" for v in s) + f"  {test.areas[i]:4d}  ok")
        else:
            print(f"  {t.tile.row:3d} {t.tile.col:3d} " + " " * 60 + f"  {t.status}: {t.message}")
    if len(test.pairs) and test.agree.mean() < 0.5 and test.extra_std == 0:
        print("\nMost neighbours disagree. The formal standard deviations of a registration ignore systematic "
              "effects;\nan extra standard deviation per tile (e.g. --extra-std 0.005) makes the test realistic.")


def _distance_figure(source, change, title, seed):
    """Top views of the source coloured by its point-to-plane distance, before and after (same colour scale)."""
    import matplotlib.pyplot as plt

    from .plotting.compare import plot_distance_map, symmetric_limits

    n = len(source)
    sel = np.sort(np.random.default_rng(seed).choice(n, PLOT_POINTS, replace=False)) if n > PLOT_POINTS else slice(None)
    # colour scale: a few times the typical misfit before, so that the shift shows and changes saturate
    a = 2.5 * float(np.median(np.abs(change.before)))
    clim = (-a, a) if a > 0 else symmetric_limits(change.before)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2), layout="constrained")
    for ax, d, label in zip(axes, (change.before, change.after), ("before", "after")):
        s = change.stats(label)
        plot_distance_map(source.xyz[sel], d[sel], ax=ax, clim=clim, title="point-to-plane distance (m), clipped")
        ax.set_title(f"{label}: median |d| {1000 * s['median_abs']:.1f} mm")
    fig.suptitle(title)
    return fig


def save_figure(fig, path) -> Path:
    """Save a matplotlib figure as PNG (to ``path``, which should be a staged path) and close it."""
    import matplotlib.pyplot as plt

    try:
        fig.savefig(path, format="png", dpi=110)
    finally:
        plt.close(fig)
    return Path(path)


def save_render(plotter, path) -> Path:
    """Render a pyvista plotter off screen into a PNG and close it."""
    try:
        plotter.screenshot(str(path))
    finally:
        plotter.close()
    return Path(path)


class _Stage:
    """Hands out temporary paths next to their destinations; :meth:`commit` renames them all."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.pending: list[tuple[Path, Path]] = []
        self.written: list[Path] = []

    def __call__(self, name: str) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        final = self.folder / name
        tmp = temporary_path(final)
        self.pending.append((tmp, final))
        return tmp

    def commit(self) -> None:
        for tmp, final in self.pending:
            os.replace(tmp, final)
            self.written.append(final)
        self.pending = []

    def discard(self) -> None:
        for tmp, _ in self.pending:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        self.pending = []


@contextlib.contextmanager
def staged_outputs(folder):
    """``with staged_outputs(dir) as stage: write(stage("a.laz")) ...``: all files appear together or none."""
    stage = _Stage(Path(folder))
    try:
        yield stage
        stage.commit()
    except BaseException:
        stage.discard()
        raise


# --------------------------------------------------------------------------- parser
def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _add_method_options(p) -> None:
    p.add_argument("--dof", choices=("translation", "rigid"), default="translation",
                   help="estimate a translation or a rigid transformation (default: %(default)s)")
    p.add_argument("--extent", type=_positive_float, default=1.0,
                   help="consensus: search a translation within +-EXTENT m (default: %(default)s)")
    p.add_argument("--max-points", type=int, default=5000,
                   help="consensus: at most this many source points vote, spread evenly in space; the "
                        "search stops after a time budget with the best translation and its certified gap "
                        "(default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")


def build_parser() -> argparse.ArgumentParser:
    from .compare import METHODS

    parser = argparse.ArgumentParser(
        prog="labkit", description="labkit: robust adjustment of 3D point clouds for engineering geodesy.",
        epilog="Run 'labkit COMMAND --help' for the options of a command; 'labkit demo' needs no input files.")
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main job on built-in synthetic data")
    demo.add_argument("--out", default="labkit-demo", help="folder for the PNG figures (default: %(default)s)")
    demo.add_argument("--quick", action="store_true", help="smaller data, for smoke tests")
    demo.set_defaults(func=_cmd_demo)

    sphere = sub.add_parser("sphere", help="find a sphere target by RANSAC and adjust it (Gauss-Helmert)",
                            description="Detect a sphere in a point cloud (ASCII xyz, LAS/LAZ, npy/npz) with "
                                        "RANSAC and adjust it in the Gauss-Helmert model.")
    sphere.add_argument("file", help="point-cloud file")
    sphere.add_argument("--threshold", type=_positive_float, default=0.003,
                        help="inlier threshold t in m (about 2-3 x the noise; default: %(default)s)")
    sphere.add_argument("--radius-range", type=_positive_float, nargs=2, metavar=("MIN", "MAX"),
                        help="admissible radii in m")
    sphere.add_argument("--radius", type=_positive_float, help="nominal radius of the target in m")
    sphere.add_argument("--hold-radius", action="store_true", help="hold the radius at --radius in the adjustment")
    sphere.add_argument("--sigma", type=_positive_float,
                        help="a priori standard deviation of the coordinates in m (default: estimated robustly)")
    sphere.add_argument("--p", type=float, default=0.99, help="RANSAC success probability (default: %(default)s)")
    sphere.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    sphere.set_defaults(func=_cmd_sphere)

    reg = sub.add_parser("register", help="register SOURCE onto TARGET (ICP or maximum consensus)",
                         description="Register SOURCE onto TARGET; print the transformation with standard "
                                     "deviations and the degeneracy report; write the transformed source and "
                                     "a distance-coloured PNG.")
    reg.add_argument("source", help="point cloud to move (e.g. the later epoch)")
    reg.add_argument("target", help="reference point cloud")
    reg.add_argument("--method", choices=METHODS, default="icp",
                     help="registration method; icp is point to plane (converges from shifts within its "
                          "matching distance), consensus a translation by maximum consensus searched globally "
                          "within +-EXTENT, consensus+icp that search followed by ICP: the route for large "
                          "shifts (default: %(default)s)")
    _add_method_options(reg)
    reg.add_argument("--out", default=".", help="output folder (default: the current folder)")
    reg.set_defaults(func=_cmd_register)

    cmp_ = sub.add_parser("compare", help="compare registration methods with references; write a CSV table",
                          description="Run registration methods on the epoch pairs of a JSON file and compare "
                                      "them with reference transformations.")
    cmp_.add_argument("pairs", help="JSON list of epoch pairs (see labkit.compare.load_pairs)")
    cmp_.add_argument("--methods", nargs="+", choices=METHODS, default=["icp", "icp-tukey", "consensus"],
                      metavar="METHOD", help=f"methods among {', '.join(METHODS)} (default: %(default)s)")
    cmp_.add_argument("--references", help="JSON reference file (see labkit.references.load_references)")
    cmp_.add_argument("--alpha", type=float, default=0.05, help="test level (default: %(default)s)")
    _add_method_options(cmp_)
    cmp_.add_argument("--out", default="comparison.csv", help="CSV file to write (default: %(default)s)")
    cmp_.set_defaults(func=_cmd_compare)

    tiles = sub.add_parser("tiles", help="register tile by tile and test neighbouring tiles (shift field)",
                           description="Cut two surveys into square tiles, register every tile, test whether "
                                       "neighbouring tiles agree; write the shift field as PNG and CSV.")
    tiles.add_argument("source", nargs="+", help="point-cloud file(s) of the epoch to move")
    tiles.add_argument("--target", nargs="+", required=True, help="point-cloud file(s) of the reference epoch")
    tiles.add_argument("--size", type=_positive_float, default=100.0, help="tile edge in m (default: %(default)s)")
    tiles.add_argument("--buffer", type=float, default=0.0, help="margin read around each tile in m")
    tiles.add_argument("--min-points", type=int, default=200, help="fewer points: tile skipped (default: %(default)s)")
    tiles.add_argument("--method", choices=METHODS, default="icp", help="registration per tile (default: %(default)s)")
    tiles.add_argument("--alpha", type=float, default=0.05, help="test level (default: %(default)s)")
    tiles.add_argument("--extra-std", type=float, default=0.0, help="extra std per tile in m for the neighbour test")
    tiles.add_argument("--scheduler", choices=("threads", "processes", "sync", "serial"), default="threads",
                       help="Dask scheduler (default: %(default)s)")
    _add_method_options(tiles)
    tiles.add_argument("--out", default=".", help="output folder (default: the current folder)")
    tiles.set_defaults(func=_cmd_tiles)
    return parser


def _version() -> str:
    from . import __version__

    return f"labkit {__version__}"


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except LabkitError as exc:
        print(f"labkit {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. an output folder that cannot be created or written
        print(f"labkit {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
