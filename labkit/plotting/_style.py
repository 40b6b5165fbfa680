"""Colours, sizes and the off-screen pyvista plotter shared by all plots."""

from __future__ import annotations

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
