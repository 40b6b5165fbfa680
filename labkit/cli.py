"""Command line: ``labkit demo``, ``labkit sphere FILE``, ...

Each sub-command is a small function taking the parsed arguments; errors from
bad input are printed as one clear line with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import LabkitError


def _cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(Path(args.out), quick=args.quick)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="labkit", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main job on built-in synthetic data")
    demo.add_argument("--out", default="labkit-demo", help="folder for the PNG figures (default: %(default)s)")
    demo.add_argument("--quick", action="store_true", help="smaller data, for smoke tests")
    demo.set_defaults(func=_cmd_demo)
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


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
