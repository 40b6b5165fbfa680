"""Views of whole clouds: coloured by ASPRS class or by height, top views, density maps (notebook 03).

The 3D helpers render with pyvista (off screen by default) and the 2D helpers
with matplotlib. Coordinates are reduced to a local origin before plotting:
VTK renders in float32, which cannot resolve millimetres at 6-7 digit UTM
values, and axis labels like ``x - 600000 m`` read better than ``6.0e5``.
Every helper takes an optional ``plotter`` or ``ax`` and returns it.
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from ..core.errors import LabkitError
from ..core.masks import ASPRS_NAMES, as_bbox, as_rings
from ..regions import density_grid
from ._style import CMAP_SEQUENTIAL, POINT_SIZE, new_plotter, scalar_bar

# ASPRS LAS 1.4 standard classes: name and display colour (close to common viewer palettes)
ASPRS_COLORS = {
    0: "#a0a0a0",  # never classified
    1: "#c8c8c8",  # unclassified
    2: "#a0522d",  # ground
    3: "#b5e61d",  # low vegetation
    4: "#5cb85c",  # medium vegetation
    5: "#1e6b1e",  # high vegetation
    6: "#d7301f",  # building
    7: "#ff00ff",  # low point (noise)
    8: "#ffd700",  # model key point
    9: "#1f78b4",  # water
    10: "#6a3d9a",  # rail
    11: "#4d4d4d",  # road surface
    12: "#fdbf6f",  # overlap
    13: "#e0e000",  # wire guard
    14: "#ffaa00",  # wire conductor
    15: "#8c510a",  # transmission tower
    16: "#b15928",  # wire connector
    17: "#8dd3c7",  # bridge deck
    18: "#ff1493",  # high noise
}
ASPRS_CLASSES = {code: (ASPRS_NAMES[code], color) for code, color in ASPRS_COLORS.items()}
OTHER_CLASS_COLOR = "#000000"


def class_name(code: int) -> str:
    """ASPRS name of a class code ('class 64' for user-defined codes)."""
    return ASPRS_NAMES.get(int(code), f"class {int(code)}")


def class_colors(classification) -> np.ndarray:
    """RGB colours (n, 3) uint8 for ASPRS class codes; unknown codes are black."""
    from matplotlib.colors import to_rgb

    codes = np.asarray(classification).astype(np.int64)
    table = np.zeros((256, 3), dtype=np.uint8)
    table[:] = (np.array(to_rgb(OTHER_CLASS_COLOR)) * 255).round().astype(np.uint8)
    for code, color in ASPRS_COLORS.items():
        table[code] = (np.array(to_rgb(color)) * 255).round().astype(np.uint8)
    return table[np.clip(codes, 0, 255)]


def plot_origin(cloud: PointCloud) -> np.ndarray:
    """The plotting origin: the cloud's minimum rounded down to 100 m (x, y) and 1 m (z)."""
    lo = cloud.xyz.min(axis=0)
    return np.array([np.floor(lo[0] / 100) * 100, np.floor(lo[1] / 100) * 100, np.floor(lo[2])])


def _every(n: int, max_points: int | None) -> slice:
    """A regular stride that keeps at most ``max_points`` (deterministic, keeps the spatial pattern)."""
    if max_points is None or n <= max_points:
        return slice(None)
    return slice(None, None, int(np.ceil(n / max_points)))


def _polydata(cloud: PointCloud, sel, origin):
    import pyvista as pv

    return pv.PolyData(np.ascontiguousarray(cloud.xyz[sel] - origin))


# ----------------------------------------------------------------------------- 3D (pyvista)
def plot_cloud_classes(cloud: PointCloud, *, plotter=None, point_size: float = POINT_SIZE, legend: bool = True,
                       max_points: int | None = 1_000_000, origin=None):
    """3D render of the cloud coloured by ASPRS class, with a legend of the classes present.

    Parameters
    ----------
    cloud : PointCloud with a ``classification`` attribute.
    plotter : pyvista.Plotter, optional (default: a new off-screen plotter).
    max_points : draw at most this many points (a regular stride), None for all.
    origin : (3,) local origin subtracted before rendering; default :func:`plot_origin`.
    """
    if "classification" not in cloud:
        raise LabkitError("plot_cloud_classes needs a 'classification' attribute")
    plotter = new_plotter(plotter)
    origin = plot_origin(cloud) if origin is None else np.asarray(origin, dtype=float)
    sel = _every(len(cloud), max_points)
    mesh = _polydata(cloud, sel, origin)
    mesh["rgb"] = class_colors(cloud["classification"][sel])
    plotter.add_mesh(mesh, scalars="rgb", rgb=True, point_size=point_size, render_points_as_spheres=True)
    if legend:
        present = np.unique(cloud["classification"])
        labels = [[f"{int(c)} {class_name(c)}", ASPRS_COLORS.get(int(c), OTHER_CLASS_COLOR)] for c in present]
        plotter.add_legend(labels=labels, bcolor="white", face="circle", size=(0.24, 0.05 * len(labels) + 0.02))
    plotter.add_axes()
    return plotter


def plot_cloud_height(cloud: PointCloud, *, plotter=None, values=None, title: str = "height z (m)",
                      cmap: str = CMAP_SEQUENTIAL, clim=None, point_size: float = POINT_SIZE,
                      max_points: int | None = 1_000_000, origin=None):
    """3D render coloured by height (or by any per-point ``values``), with a scalar bar.

    ``clim`` defaults to the 1st-99th percentile, so single outliers do not wash the colours out.
    Heights are shown in the file frame (not reduced), so the bar reads true elevations.
    """
    plotter = new_plotter(plotter)
    origin = plot_origin(cloud) if origin is None else np.asarray(origin, dtype=float)
    sel = _every(len(cloud), max_points)
    vals = cloud.xyz[:, 2] if values is None else np.asarray(values, dtype=float)
    if vals.shape != (len(cloud),):
        raise LabkitError(f"values must hold one number per point ({len(cloud)}), got shape {vals.shape}")
    vals = vals[sel]
    mesh = _polydata(cloud, sel, origin)
    mesh[title] = vals
    if clim is None:
        clim = tuple(np.percentile(vals[np.isfinite(vals)], [1, 99]))
    plotter.add_mesh(mesh, scalars=title, cmap=cmap, clim=clim, point_size=point_size,
                     render_points_as_spheres=True, scalar_bar_args=scalar_bar(title))
    plotter.add_axes()
    return plotter


# ----------------------------------------------------------------------------- 2D (matplotlib)
def _axes(ax, **kw):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(**kw)
    return ax


def plot_top_view(cloud: PointCloud, *, by: str = "classification", ax=None, s: float = 0.5,
                  max_points: int | None = 200_000, origin=None, legend: bool = True, cmap: str = CMAP_SEQUENTIAL):
    """Top view (x, y) coloured by class (``by='classification'``), by height (``'z'``) or by an attribute.

    The plotted frame is ``xy - origin`` (default :func:`plot_origin`); the origin is
    stored on the axes as ``ax.labkit_origin`` so that :func:`plot_outline` can draw
    regions in the same frame.
    """
    ax = _axes(ax)
    origin = plot_origin(cloud) if origin is None else np.asarray(origin, dtype=float)
    sel = np.arange(len(cloud))[_every(len(cloud), max_points)]
    sel = sel[np.argsort(cloud.xyz[sel, 2], kind="stable")]  # high points drawn last (roofs over ground)
    xy = cloud.xyz[sel, :2] - origin[:2]
    if by == "classification":
        cls = cloud["classification"][sel]
        ax.scatter(xy[:, 0], xy[:, 1], c=class_colors(cls) / 255.0, s=s, linewidths=0, rasterized=True)
        if legend:
            from matplotlib.lines import Line2D

            handles = [Line2D([], [], ls="", marker="o", color=ASPRS_COLORS.get(int(c), OTHER_CLASS_COLOR),
                              label=f"{int(c)} {class_name(c)}") for c in np.unique(cls)]
            ax.legend(handles=handles, fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:
        vals = cloud.xyz[sel, 2] if by == "z" else np.asarray(cloud[by], dtype=float)[sel]
        pts = ax.scatter(xy[:, 0], xy[:, 1], c=vals, s=s, cmap=cmap, linewidths=0, rasterized=True)
        ax.figure.colorbar(pts, ax=ax, label="z (m)" if by == "z" else by)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x - {origin[0]:.0f} (m)")
    ax.set_ylabel(f"y - {origin[1]:.0f} (m)")
    ax.labkit_origin = origin
    return ax


def plot_outline(*, bbox=None, polygon=None, circle=None, ax=None, label: str | None = None, color="k", **kw):
    """Draw a crop region (box, polygon or circle ``(centre, radius)``) on a top view.

    Uses the origin that :func:`plot_top_view` stored on the axes (zero otherwise).
    """
    ax = _axes(ax)
    o = np.asarray(getattr(ax, "labkit_origin", np.zeros(3)))[:2]
    if sum(v is not None for v in (bbox, polygon, circle)) != 1:
        raise LabkitError("give exactly one of bbox, polygon or circle=(centre, radius)")
    if bbox is not None:
        (x0, y0), (x1, y1) = as_bbox(bbox)[:, :2]
        rings = [np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])]
    elif polygon is not None:
        rings = as_rings(polygon)
    else:
        centre, radius = circle
        t = np.linspace(0, 2 * np.pi, 181)
        rings = [np.column_stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)])]
    for i, ring in enumerate(rings):
        closed = np.vstack([ring, ring[:1]]) - o
        ax.plot(closed[:, 0], closed[:, 1], color=color, lw=1.5, label=label if i == 0 else None, **kw)
    if label:
        x, y = rings[0].max(axis=0) - o
        ax.annotate(label, (x, y), xytext=(2, 2), textcoords="offset points", fontsize="small", color=color)
    return ax


def plot_density(grid, *, ax=None, vmax=None, cmap: str = "magma", origin=None):
    """Map of points per m^2 from a :class:`labkit.regions.DensityGrid` (or a cloud, with 1 m cells)."""
    if isinstance(grid, PointCloud):
        grid = density_grid(grid, 1.0)
    ax = _axes(ax)
    o = np.zeros(2) if origin is None else np.asarray(origin, dtype=float)[:2]
    x0, x1, y0, y1 = grid.extent
    dens = grid.density
    vmax = float(np.percentile(dens[dens > 0], 99)) if vmax is None and (dens > 0).any() else vmax
    im = ax.imshow(dens, origin="lower", extent=(x0 - o[0], x1 - o[0], y0 - o[1], y1 - o[1]), cmap=cmap,
                   vmin=0, vmax=vmax, interpolation="nearest")
    ax.figure.colorbar(im, ax=ax, label=f"points per m$^2$ ({grid.cell:g} m cells)")
    ax.grid(False)
    ax.set_xlabel("x (m)" if origin is None else f"x - {o[0]:.0f} (m)")
    ax.set_ylabel("y (m)" if origin is None else f"y - {o[1]:.0f} (m)")
    return ax


def plot_class_counts(cloud: PointCloud, *, ax=None, area: float | None = None):
    """Bar chart of the points (or, with ``area`` in m^2, the density) per ASPRS class."""
    ax = _axes(ax)
    codes, counts = np.unique(cloud["classification"], return_counts=True)
    values = counts if area is None else counts / float(area)
    colors = [ASPRS_COLORS.get(int(c), OTHER_CLASS_COLOR) for c in codes]
    ax.barh([f"{int(c)} {class_name(c)}" for c in codes], values, color=colors)
    ax.invert_yaxis()
    ax.set_xlabel("points" if area is None else "points per m$^2$")
    return ax
