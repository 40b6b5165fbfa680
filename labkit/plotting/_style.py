"""Colours, sizes and the off-screen pyvista plotter shared by all plots."""

from __future__ import annotations

import numpy as np

from ..notebook import setup_headless

COLORS = {
    "inlier": "#1b9e77",
    "outlier": "#d95f02",
    "sphere": "#7570b3",
    "source": "#e7298a",
    "target": "#66a61e",
    "reference": "#333333",
    "rejected": "#bbbbbb",
}
CMAP_DIVERGING = "RdBu_r"
CMAP_SEQUENTIAL = "viridis"
POINT_SIZE = 4.0
WINDOW_SIZE = (900, 650)


def scalar_bar(title: str, **extra) -> dict:
    """pyvista ``scalar_bar_args``: a vertical bar at the right edge, so the title never
    overlaps the tick labels (as it does on the default horizontal bar)."""
    # a second (empty) title line keeps the title clear of the top tick label of a vertical bar
    title = title if "\n" in title else title + "\n"
    args = {"title": title, "vertical": True, "position_x": 0.86, "position_y": 0.12, "width": 0.06,
            "height": 0.76, "title_font_size": 20, "label_font_size": 17}
    args.update(extra)
    return args


def new_plotter(plotter=None, window_size=WINDOW_SIZE):
    """Return ``plotter`` or a new off-screen ``pyvista.Plotter``.

    Examples
    --------
    >>> from labkit.plotting import new_plotter
    >>> plotter = new_plotter(window_size=(64, 48))  # off screen
    >>> new_plotter(plotter) is plotter, list(plotter.window_size)
    (True, [64, 48])
    >>> plotter.close()
    """
    if plotter is not None:
        return plotter
    setup_headless()
    import pyvista as pv

    return pv.Plotter(off_screen=True, window_size=list(window_size))


def show_scale(plotter, origin=(0.0, 0.0, 0.0), unit="m", frame=None, bounds=None):
    """Labelled x, y, z axes with ticks in ``unit`` around what the plotter shows, and the orientation widget.

    The rendered coordinates are reduced (VTK works in float32): ``origin`` is the point subtracted,
    named in the titles (``x - 600000 (m)``), or ``frame`` names it in words (``x from the centre (m)``).
    ``bounds`` (xmin, xmax, ymin, ymax, zmin, zmax) limits the axes to a part of the scene (a close-up).
    Returns ``plotter``.

    Examples
    --------
    >>> from labkit.plotting import new_plotter, show_scale
    >>> box = (0.0, 40.0, 0.0, 30.0, 0.0, 5.0)  # the reduced extent of the points drawn
    >>> plotter = show_scale(new_plotter(window_size=(64, 48)), origin=(600000.0, 5400000.0, 0.0), bounds=box)
    >>> axes = plotter.renderer.cube_axes_actor
    >>> axes.GetXTitle(), axes.GetZTitle()
    ('x - 600000 (m)', 'z (m)')
    >>> plotter.close()
    """
    def title(axis, o):
        if frame is not None:
            return f"{axis} {frame} ({unit})"
        return f"{axis} ({unit})" if o == 0 else f"{axis} - {o:.0f} ({unit})"

    x, y, z = (title(a, float(o)) for a, o in zip("xyz", origin))
    b = plotter.bounds if bounds is None else bounds
    extent = max(b[1] - b[0], b[3] - b[2], b[5] - b[4], 1e-9)
    decimals = int(np.clip(2 - np.floor(np.log10(extent)), 0, 4))  # about three significant digits
    plotter.show_bounds(bounds=None if bounds is None else list(bounds), xtitle=x, ytitle=y, ztitle=z,
                        grid=False, location="outer", ticks="outside", n_xlabels=3, n_ylabels=3, n_zlabels=3,
                        font_size=12, bold=False, fmt=f"%.{decimals}f",
                        use_3d_text=False)
    plotter.add_axes()
    return plotter


def screenshot(plotter, path=None):
    """Render off screen; write a PNG to ``path`` if given and return the image array.

    Examples
    --------
    >>> import pyvista as pv
    >>> from labkit.plotting import new_plotter, screenshot
    >>> plotter = new_plotter(window_size=(64, 48))
    >>> _ = plotter.add_mesh(pv.Sphere())
    >>> screenshot(plotter).shape
    (48, 64, 3)
    """
    return plotter.screenshot(str(path) if path is not None else None, return_img=True)


def show_render(plotter, ax=None, *, width=10.0):
    """Show an off-screen pyvista render as a matplotlib image at the width of a notebook; returns ``ax``.

    A render placed beside another panel shrinks to half the width and its labels become unreadable:
    give it its own figure (``width`` inches) or a wide ``ax``. The plotter is closed afterwards.

    Examples
    --------
    >>> import pyvista as pv
    >>> from labkit.plotting import new_plotter, show_render
    >>> plotter = new_plotter(window_size=(200, 100))
    >>> _ = plotter.add_mesh(pv.Sphere())
    >>> ax = show_render(plotter)
    >>> ax.images[0].get_array().shape, float(ax.figure.get_figwidth())
    ((100, 200, 3), 10.0)
    """
    import matplotlib.pyplot as plt

    image = screenshot(plotter)
    plotter.close()
    if ax is None:
        h, w = image.shape[:2]
        _, ax = plt.subplots(figsize=(width, width * h / w), layout="constrained")
    ax.imshow(image)
    ax.set_axis_off()
    return ax
