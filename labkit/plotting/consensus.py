"""Plots of the consensus cube (notebook 06): slices, profiles, top cells, branch and bound."""

from __future__ import annotations

import numpy as np

from ..registration.consensus.result import PeakShape
from ._style import CMAP_SEQUENTIAL, COLORS, new_plotter, scalar_bar

PLANES = {"XY": (0, 1, 2), "XZ": (0, 2, 1), "YZ": (1, 2, 0)}


def _slice(cube, plane, index):
    """2D array (first axis, second axis) of the cube at ``index`` along the third axis."""
    a, b, c = PLANES[plane]
    sl = [slice(None)] * 3
    sl[c] = index
    arr = cube.counts[tuple(sl)]
    return arr if a < b else arr.T


def plot_consensus_slice(cube, plane="XY", index=None, *, truth=None, ax=None, vmax=None, colorbar=True):
    """One slice of the cube through the peak (or through ``index`` along the normal axis).

    Parameters
    ----------
    cube : ConsensusCube
    plane : {'XY', 'XZ', 'YZ'}
    index : int, optional
        Cell index along the third axis; default: through the highest cell.
    truth : (3,) float, optional
        Known translation: a cross where the slice passes through it; where it does
        not, a hollow circle at its projection, labelled with the distance off the slice.
    ax : matplotlib Axes, optional
    vmax : float, optional
        Colour scale maximum (default: the cube's maximum, so slices compare).
    """
    import matplotlib.pyplot as plt

    a, b, c = PLANES[plane]
    k = cube.peak_index[c] if index is None else int(index)
    ax = ax or plt.subplots()[1]
    ext = [cube.axes[a][0], cube.axes[a][-1], cube.axes[b][0], cube.axes[b][-1]]
    half = cube.step / 2
    ext = [ext[0] - half, ext[1] + half, ext[2] - half, ext[3] + half]
    im = ax.imshow(_slice(cube, plane, k).T, origin="lower", extent=ext, cmap=CMAP_SEQUENTIAL,
                   vmin=0, vmax=vmax or cube.best_count, aspect="equal", interpolation="nearest")
    peak = cube.argmax_translation
    ax.plot(peak[a], peak[b], "o", mfc="none", mec="white", ms=10, label="highest cell")
    if truth is not None:
        off = float(truth[c]) - cube.axes[c][k]
        if abs(off) <= half:
            ax.plot(truth[a], truth[b], "x", color=COLORS["outlier"], ms=10, mew=2, label="truth")
        else:  # the truth lies off this slice: mark its projection, hollow, and say how far off
            ax.plot(truth[a], truth[b], "o", mfc="none", mec=COLORS["outlier"], ms=9, mew=1.5,
                    label=f"truth, projected ({off * 100:+.1f} cm in t{'xyz'[c]})")
    ax.set_xlabel(f"t{plane[0].lower()} (m)")
    ax.set_ylabel(f"t{plane[1].lower()} (m)")
    ax.set_title(f"{plane} at t{'xyz'[c]} = {cube.axes[c][k]:+.3f} m")
    ax.grid(False)
    if colorbar:
        ax.figure.colorbar(im, ax=ax, shrink=0.8, label="consensus")
    return ax


def plot_consensus_slices(cube, *, truth=None, axes=None, title=None):
    """The three slices XY, XZ, YZ through the highest cell, on one colour scale.

    Returns the array of three Axes.
    """
    import matplotlib.pyplot as plt

    if axes is None:
        _, axes = plt.subplots(1, 3, figsize=(14, 4.2), layout="constrained")
    for ax, plane in zip(axes, PLANES):
        plot_consensus_slice(cube, plane, truth=truth, ax=ax, colorbar=plane == "YZ")
        ax.legend(loc="lower left", fontsize=7)
    if title:
        axes[0].figure.suptitle(title)
    return axes


def plot_consensus_profiles(cube, *, truth=None, ax=None, label=None, relative=True, styles=("-", "--", ":")):
    """Profiles of the consensus along X, Y and Z through the highest cell.

    With ``relative`` the counts are divided by the peak, which makes cubes of
    different criteria comparable (point-to-point vs point-to-plane).
    """
    import matplotlib.pyplot as plt

    ax = ax or plt.subplots()[1]
    i, j, k = cube.peak_index
    lines = (cube.counts[:, j, k], cube.counts[i, :, k], cube.counts[i, j, :])
    scale = cube.best_count if relative and cube.best_count > 0 else 1.0
    for axis, (name, y, ls) in enumerate(zip("XYZ", lines, styles)):
        ref = 0.0 if truth is None else truth[axis]
        ax.plot(cube.axes[axis] - ref, y / scale, ls, label=f"{label + ': ' if label else ''}along {name}")
    ax.set_xlabel("translation minus truth (m)" if truth is not None else "translation (m)")
    ax.set_ylabel("consensus / peak" if relative else "consensus")
    ax.legend(fontsize=8)
    return ax


def plot_consensus_top_cells(cube, quantile=0.999, *, truth=None, ax=None, max_cells=20000):
    """3D scatter (matplotlib) of the cells above a quantile of the counts, coloured by count."""
    import matplotlib.pyplot as plt

    if ax is None:
        ax = plt.figure(figsize=(6, 5)).add_subplot(projection="3d")
    level = np.quantile(cube.counts, quantile)
    idx = np.argwhere(cube.counts >= level)
    if len(idx) > max_cells:  # keep the highest ones
        order = np.argsort(cube.counts[tuple(idx.T)])[::-1][:max_cells]
        idx = idx[order]
    xyz = np.column_stack([cube.axes[d][idx[:, d]] for d in range(3)])
    sc = ax.scatter(*xyz.T, c=cube.counts[tuple(idx.T)], cmap=CMAP_SEQUENTIAL, s=6, depthshade=False)
    if truth is not None:
        ax.scatter(*np.asarray(truth)[:, None], marker="x", color=COLORS["outlier"], s=80, label="truth")
        ax.legend(fontsize=8)
    from matplotlib.ticker import MaxNLocator

    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(4))
    ax.set_xlabel("tx (m)", labelpad=8)
    ax.set_ylabel("ty (m)", labelpad=8)
    ax.set_zlabel("tz (m)", labelpad=8)
    ax.set_title(f"cells >= {100 * quantile:g} % quantile ({len(idx)} cells)\n{describe_peak(cube.peak)}",
                 fontsize=10)
    # the colour bar in its own axes at the left edge: beside the 3D box it would cover the tz label
    fig = ax.figure
    box = ax.get_position()
    cax = fig.add_axes([max(box.x0 - 0.06, 0.01), box.y0 + 0.2 * box.height, 0.02, 0.6 * box.height])
    fig.colorbar(sc, cax=cax, label="consensus (points)", ticks=MaxNLocator(5, integer=True))
    cax.yaxis.set_label_position("left")
    cax.yaxis.set_ticks_position("left")
    return ax


def plot_consensus_volume(cube, quantile=0.999, *, truth=None, plotter=None, font_size=20):
    """pyvista view of the cells above a quantile (off screen by default); returns the plotter.

    The camera frames the top cells (two grid steps around them), not the whole search box, so the
    peak fills the view; the axes are labelled in metres of translation, and the colour bar, the
    axis labels and the title are set in ``font_size`` points of a 1000 x 760 render - large enough
    to read when the render is shown at the width of a notebook (:func:`labkit.plotting.show_render`).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.plotting.consensus import plot_consensus_volume
    >>> from labkit.registration import consensus_cube
    >>> from labkit.synthetic import wavy_surface
    >>> rng = np.random.default_rng(1)
    >>> target, source = wavy_surface(1500, rng), wavy_surface(300, rng) - [0.05, 0.02, 0.03]
    >>> cube = consensus_cube(source[::2], target, extent=0.06, step=0.02, eps=0.01, center=[0.04, 0.02, 0.04],
    ...                       use_numba=False)
    >>> plotter = plot_consensus_volume(cube, 0.9, truth=[0.05, 0.02, 0.03])
    >>> list(plotter.window_size)
    [1000, 760]
    >>> plotter.close()
    """
    import pyvista as pv

    plotter = new_plotter(plotter, window_size=(1000, 760))
    grid = pv.ImageData(dimensions=np.array(cube.counts.shape) + 1, spacing=(cube.step,) * 3,
                        origin=[a[0] - cube.step / 2 for a in cube.axes])
    grid.cell_data["consensus"] = cube.counts.ravel(order="F").astype(float)
    top = grid.threshold(float(np.quantile(cube.counts, quantile)), scalars="consensus")
    plotter.add_mesh(top, scalars="consensus", cmap=CMAP_SEQUENTIAL, show_edges=True, edge_color="#666666",
                     line_width=0.5,
                     scalar_bar_args=scalar_bar("consensus\n(points)", fmt="%.0f", n_labels=4, position_x=0.84,
                                                width=0.07, title_font_size=font_size,
                                                label_font_size=font_size - 2, color="black"))
    # the frame: the top cells and two grid steps around them (and the truth, if given)
    lo = np.array(top.bounds[::2]) - 2 * cube.step
    hi = np.array(top.bounds[1::2]) + 2 * cube.step
    if truth is not None:
        truth = np.asarray(truth, dtype=float)
        plotter.add_mesh(pv.Sphere(radius=0.4 * cube.step, center=truth), color=COLORS["outlier"], label="truth")
        lo, hi = np.minimum(lo, truth - cube.step), np.maximum(hi, truth + cube.step)
    frame = pv.Box(bounds=np.ravel(np.column_stack([lo, hi])))
    plotter.add_mesh(frame.outline(), color=COLORS["reference"])
    plotter.show_bounds(mesh=frame, xtitle="tx (m)", ytitle="ty (m)", ztitle="tz (m)", fmt="%.2f",
                        font_size=font_size - 2, color="black", grid=False, location="outer", n_xlabels=3,
                        n_ylabels=3, n_zlabels=3)
    plotter.add_text(f"cells above the {100 * quantile:g} % quantile\n{describe_peak(cube.peak)}",
                     font_size=max(font_size // 2, 8), color="black")
    plotter.set_background("white")
    plotter.reset_camera(bounds=np.ravel(np.column_stack([lo, hi])))
    plotter.camera.zoom(0.85)
    return plotter


def _span(cube) -> float:
    return float(max(a[-1] - a[0] for a in cube.axes))


def describe_peak(peak) -> str:
    """The shape of a consensus peak in words (see :meth:`labkit.registration.consensus.cube.PeakShape.describe`).

    Works on anything with ``kind``, ``directions`` and ``free``; used in titles instead of raw eigenvector
    components.
    """
    return PeakShape.describe(peak)



def plot_bnb_summary(results, labels, *, ax=None):
    """Bar chart of lower and certified upper bounds of several branch-and-bound runs."""
    import matplotlib.pyplot as plt

    ax = ax or plt.subplots()[1]
    bbs = [r.history[0] for r in results]
    x = np.arange(len(bbs))
    ax.bar(x - 0.2, [b.lower for b in bbs], 0.4, label="consensus found (lower bound)", color=COLORS["inlier"])
    ax.bar(x + 0.2, [b.upper for b in bbs], 0.4, label="certified upper bound", color=COLORS["rejected"])
    ax.set_xticks(x, labels)
    ax.set_ylabel("consensus")
    ax.legend(fontsize=8)
    return ax
