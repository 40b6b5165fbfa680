"""``labkit demo``: the main job on built-in synthetic data.

Each step prints a summary and writes its figures into the output folder.
"""

from __future__ import annotations

import time
from pathlib import Path


def _steps():
    """The demo steps in order: (title, callable(out_dir, quick) -> list of written files)."""
    steps = []
    return steps


def run_demo(out_dir: Path, quick: bool = False) -> list[Path]:
    """Run every demo step; return the paths of the figures written."""
    from .notebook import setup_headless

    setup_headless()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for title, step in _steps():
        print(f"\n### {title}\n")
        t0 = time.perf_counter()
        written += step(out_dir, quick)
        print(f"({title}: {time.perf_counter() - t0:.1f} s)")
    print(f"\nFigures written to {out_dir.resolve()}:")
    for path in written:
        print(f"  {path.name}")
    return written
