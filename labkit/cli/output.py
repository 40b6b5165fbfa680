"""Text and figures of the command line: the 4x4 with its angles, the tile table, the distance maps.

Kept apart from :mod:`labkit.cli` so that the command module holds the parser and the sub-commands only.
"""

from __future__ import annotations

import numpy as np

from ..plotting.compare import plot_distance_map, symmetric_limits
from ..transforms import angles_from_rotation

PLOT_POINTS = 150_000  # at most this many points in a top-view figure


def _rotation_text(result, frame: str = "the input's coordinates, m") -> str:
    """The 4x4 matrix and, for a rigid result, the angles with standard deviations (arcsec)."""
    lines = [f"4x4 transformation (source -> target) in {frame}:",
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
    """The tile table: a component the tile does not determine is '-' (empty in the CSV), never a number."""
    print("\n  row col        dX        dY        dZ   sX (mm) sY (mm) sZ (mm)  area  status")
    det, std, flagged = field.determined, field.std, test.disagreeing
    for i, t in enumerate(field.tiles):
        head = f"  {t.tile.row:3d} {t.tile.col:3d} "
        if t.usable:
            shift = " ".join(f"{v:+9.4f}" if d else f"{'-':>9s}" for v, d in zip(t.translation, det[i]))
            sd = " ".join(f"{1000 * v:7.1f}" if d else f"{'-':>7s}" for v, d in zip(std[i], det[i]))
            note = "" if t.ok else " (" + "".join(a for a, d in zip("XYZ", det[i]) if not d) + " not determined)"
            flag = "  DISAGREES with neighbours" if flagged[i] else ""
            print(head + shift + " " + sd + f"  {test.areas[i]:4d}  {t.verdict}{note}{flag}")
        else:
            why = t.message.split(";")[0]
            print(head + " " * 60 + f"  {t.verdict}: {why}")
    tested = test.dof > 0
    if tested.any() and test.agree[tested].mean() < 0.5 and test.extra_std == 0:
        print("\nMost neighbours disagree. The formal standard deviations of a registration ignore systematic "
              "effects;\nan extra standard deviation per tile (e.g. --extra-std 0.005) makes the test realistic.")


def _distance_figure(source, change, title, seed):
    """Top views of the source coloured by its point-to-plane distance, before and after (same colour scale)."""
    import matplotlib.pyplot as plt

    n = len(source)
    sel = np.sort(np.random.default_rng(seed).choice(n, PLOT_POINTS, replace=False)) if n > PLOT_POINTS else slice(None)
    # colour scale: a few times the typical misfit before, so that the shift shows and changes saturate
    a = 2.5 * float(np.nanmedian(np.abs(change.before)))
    clim = (-a, a) if a > 0 else symmetric_limits(change.before[np.isfinite(change.before)])
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2), layout="constrained")
    for ax, d, label in zip(axes, (change.before, change.after), ("before", "after")):
        s = change.stats(label)
        plot_distance_map(source.xyz[sel], d[sel], ax=ax, clim=clim, title="point-to-plane distance (m), clipped")
        ax.set_title(f"{label}: median |d| {1000 * s['median_abs']:.1f} mm")
    fig.suptitle(title)
    return fig
