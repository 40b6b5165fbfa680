"""Plots for comparing transformations and for shift fields (notebooks 07, 08).

Every helper takes an optional ``ax``/``axes`` or ``plotter`` and returns it; none calls ``show()``.
"""

from __future__ import annotations

import numpy as np

from ..core.checks import as_points
from ..core.frame import local_origin
from ..core.errors import LabkitError
from ..core.masks import ASPRS_NAMES  # noqa: F401  (re-exported: the one table lives in labkit.core.masks)
from .clouds import class_name
from ._style import CMAP_DIVERGING, CMAP_SEQUENTIAL, COLORS, POINT_SIZE, new_plotter, scalar_bar, show_scale

AXES = ("X", "Y", "Z")


def _axes(ax, **kw):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(**kw)
    return ax


def symmetric_limits(values, quantile: float = 0.98) -> tuple:
    """(-a, a) with a the ``quantile`` of |values|: a diverging colour map centred on zero."""
    a = float(np.quantile(np.abs(np.asarray(values)[np.isfinite(values)]), quantile)) if np.size(values) else 1.0
    return (-a, a) if a > 0 else (-1.0, 1.0)


# --------------------------------------------------------------------------- distances
def plot_distance_cloud(points, distances, *, plotter=None, clim=None, title="distance (m)", cmap=CMAP_DIVERGING,
                        point_size=POINT_SIZE, view="iso"):
    """The cloud coloured by its (signed) distances, diverging colour map with a scale bar.

    Coordinates are reduced to a local origin first (VTK renders in float32); the axes name it
    (``x - 600000 (m)``). ``clim`` defaults to symmetric limits at the 98 % quantile of |d|.
    """
    import pyvista as pv

    xyz = as_points(points, name="points")
    d = np.asarray(distances, dtype=float)
    plotter = new_plotter(plotter)
    origin = local_origin(xyz)
    poly = pv.PolyData(xyz - origin)
    poly[title] = d
    clim = symmetric_limits(d) if clim is None else clim
    plotter.add_mesh(poly, scalars=title, cmap=cmap, clim=clim, point_size=point_size,
                     render_points_as_spheres=False, scalar_bar_args=scalar_bar(title, n_labels=5, fmt="%.3f"))
    show_scale(plotter, origin)
    if view == "iso":
        plotter.view_isometric()
    elif view == "top":
        plotter.view_xy()
    return plotter


def plot_distance_map(points, distances, *, ax=None, clim=None, title="distance (m)", cmap=CMAP_DIVERGING, s=1.0,
                      colorbar=True):
    """Top view (matplotlib) of the cloud coloured by distance, with a colour bar; x, y in m from a local origin."""
    xyz = as_points(points, name="points")
    ax = _axes(ax)
    o = local_origin(xyz)
    clim = symmetric_limits(distances) if clim is None else clim
    sc = ax.scatter(xyz[:, 0] - o[0], xyz[:, 1] - o[1], c=distances, s=s, cmap=cmap, vmin=clim[0], vmax=clim[1],
                    rasterized=True)
    if colorbar:
        ax.figure.colorbar(sc, ax=ax, label=title)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x - {o[0]:.0f} (m)")
    ax.set_ylabel(f"y - {o[1]:.0f} (m)")
    return ax


def plot_distance_overview(items, *, clim=(-0.3, 0.3), s=0.4, title=None, cmap=CMAP_DIVERGING):
    """Distance maps of several regions: one column per region, before (top) and after (bottom).

    ``items``: sequence of ``(label, points, before, after)``; one shared colour
    bar. Returns the figure.
    """
    import matplotlib.pyplot as plt

    items = list(items)
    if not items:
        raise LabkitError("plot_distance_overview needs at least one (label, points, before, after)")
    fig, axes = plt.subplots(2, len(items), figsize=(2.3 * len(items) + 1.2, 5.0), squeeze=False)
    for col, (label, points, before, after) in enumerate(items):
        for row, d in enumerate((before, after)):
            ax = plot_distance_map(points, d, ax=axes[row, col], clim=clim, cmap=cmap, s=s, colorbar=False)
            ax.set_xticks([]), ax.set_yticks([]), ax.set_xlabel(""), ax.set_ylabel("")
        axes[0, col].set_title(label, fontsize="small")
    axes[0, 0].set_ylabel("before"), axes[1, 0].set_ylabel("after")
    fig.colorbar(axes[0, 0].collections[0], ax=axes, label="distance (m)", shrink=0.8)
    if title:
        fig.suptitle(title, x=0.02, ha="left")
    return fig


def plot_profile(clouds, start, end, *, width=1.0, ax=None, labels=None, colors=None, s=2.0):
    """A vertical profile: points within ``width``/2 of the xy segment start -> end, as (along, z).

    ``clouds`` is a sequence of (n, 3) arrays or PointClouds (e.g. target,
    source before, source after the transformation).
    """
    ax = _axes(ax, figsize=(9, 3.5))
    a, b = np.asarray(start, float)[:2], np.asarray(end, float)[:2]
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    labels = labels or [getattr(c, "name", "") or f"cloud {i}" for i, c in enumerate(clouds)]
    default = [COLORS["target"], COLORS["source"], COLORS["inlier"], COLORS["sphere"]]
    colors = colors or default
    for i, cloud in enumerate(clouds):
        xyz = as_points(cloud, name="cloud")
        rel = xyz[:, :2] - a
        along = rel @ u
        across = rel @ np.array([-u[1], u[0]])
        sel = (np.abs(across) <= width / 2) & (along >= 0) & (along <= length)
        ax.scatter(along[sel], xyz[sel, 2], s=s, color=colors[i % len(colors)], label=f"{labels[i]} ({sel.sum()})")
    ax.set_xlabel("distance along the profile (m)")
    ax.set_ylabel("height z (m)")
    ax.set_title(f"Profile, {length:.0f} m long, {width:g} m wide")
    ax.legend(markerscale=4, fontsize="small")
    return ax


def plot_class_histograms(distances, classes, *, ax=None, bins=60, limits=None, min_count=20):
    """Histograms of distances per ASPRS class (step lines, densities), with the median of each class."""
    ax = _axes(ax)
    d = np.asarray(distances, dtype=float)
    cls = np.asarray(classes)
    limits = symmetric_limits(d, 0.99) if limits is None else limits
    edges = np.linspace(*limits, bins + 1)
    for code in np.unique(cls):
        sel = cls == code
        if sel.sum() < min_count:
            continue
        name = class_name(code)
        ax.hist(d[sel], bins=edges, density=True, histtype="step", lw=1.5,
                label=f"{name} (n={sel.sum()}, median {np.median(d[sel]):+.3f} m)")
    ax.axvline(0, color=COLORS["reference"], lw=0.8)
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("density")
    ax.legend(fontsize="small")
    return ax


# --------------------------------------------------------------------------- transformation vectors
def plot_transformation_components(rows, *, axes=None, k=2.0, title=None):
    """dX, dY, dZ of every method (estimate +- k sigma) against the reference (line +- k sigma band).

    ``rows`` are the :class:`labkit.registration.compare.ComparisonRow` of one region and
    case (e.g. ``table.select(region=..., case=...)``). Axes the data do not
    constrain are marked; an infinite standard deviation draws no error bar.
    """
    rows = list(rows)
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, 3, figsize=(11, 3.8), layout="constrained")
    x = np.arange(len(rows))
    for i, ax in enumerate(axes):
        ref, ref_s = rows[0].reference[i], rows[0].reference_std[i]
        ax.axhline(ref, color=COLORS["reference"], lw=1.2, label="reference")
        if ref_s > 0:
            ax.axhspan(ref - k * ref_s, ref + k * ref_s, color=COLORS["reference"], alpha=0.15)
        for j, r in enumerate(rows):
            s = r.shift_std[i]
            ok = AXES[i] in r.constrained
            ax.errorbar(j, r.shift[i], yerr=k * s if np.isfinite(s) else None, fmt="o" if ok else "x", capsize=4,
                        color=f"C{j}", mfc=f"C{j}" if ok else "none")
        ax.set_xticks(x, [r.method for r in rows], rotation=30, ha="right")
        ax.set_xlim(-0.6, len(rows) - 0.4)
        constrained = all(AXES[i] in r.constrained for r in rows)
        ax.set_title(f"d{AXES[i]} (m)" + ("" if constrained else "  - not constrained"))
        ax.ticklabel_format(axis="y", useOffset=False)
    axes[0].legend(fontsize="small")
    if title or rows:
        axes[0].figure.suptitle(title or f"Shift at the region centre, +-{k:g} sigma: {rows[0].region} ({rows[0].case})")
    return axes


def plot_transformation_arrows(rows, *, ax=None, title=None, exaggerate=1.0):
    """3D view of the shift vectors of every method (coloured) and the reference (black), from one origin.

    Errors of a few millimetres vanish beside a shift of decimetres: with
    ``exaggerate`` = e each method's arrow ends at reference + e * (shift - reference).
    """
    rows = list(rows)
    if ax is None:
        import matplotlib.pyplot as plt

        ax = plt.figure(figsize=(6, 5.5)).add_subplot(projection="3d")
    ref = rows[0].reference
    vecs = [ref] + [ref + exaggerate * (r.shift - ref) for r in rows]
    for j, (v, label) in enumerate(zip(vecs, ["reference"] + [r.method for r in rows])):
        if not np.isfinite(v).all():
            continue
        color = COLORS["reference"] if j == 0 else f"C{j - 1}"
        ax.quiver(0, 0, 0, *v, color=color, lw=2.5 if j == 0 else 1.5, arrow_length_ratio=0.08, label=label)
    m = max(np.abs(np.array([v for v in vecs if np.isfinite(v).all()])).max(), 1e-3) * 1.1
    for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setter(-m, m)
    ax.set_xlabel("dX (m)")
    ax.set_ylabel("dY (m)")
    ax.set_zlabel("dZ (m)")
    extra = f", errors x {exaggerate:g}" if exaggerate != 1 else ""
    ax.set_title(title or f"Shift vectors: {rows[0].region} ({rows[0].case}{extra})")
    ax.legend(fontsize="small")
    return ax


def plot_error_overview(table, *, ax=None, metric="error_norm_constrained"):
    """Error norm (constrained axes) per region and case, one marker per method; hollow = outside its uncertainty."""
    labels = list(dict.fromkeys((r.region, r.case) for r in table.rows))
    ax = _axes(ax, figsize=(max(8.0, 0.65 * len(labels)), 4))
    for j, m in enumerate(table.methods):
        for r in table.select(method=m).rows:
            x = labels.index((r.region, r.case)) + (j - (len(table.methods) - 1) / 2) * 0.12
            ax.plot(x, getattr(r, metric), "o", color=f"C{j}", mfc=f"C{j}" if r.inside else "none",
                    label=m if r is table.select(method=m).rows[0] else None)
    ax.set_xticks(range(len(labels)), [f"{r}\n{c}" for r, c in labels], fontsize="small")
    ax.set_xlim(-0.5, len(labels) - 0.5)
    ax.set_yscale("log")
    ax.set_ylabel("|error| on constrained axes (m)")
    ax.set_title("Error against the reference (filled: inside the stated uncertainty)")
    ax.legend(fontsize="small")
    return ax


# --------------------------------------------------------------------------- shift field
#: Face colour of a tile by its status (:data:`labkit.tiles.STATUSES`).
TILE_FACES = {"ok": "#ffffff", "undetermined": "#dfe8f3", "not converged": "#f7d9c4", "too few points": "#eeeeee",
              "failed": "#c8c8c8"}
FLAG_COLOR = "#7570b3"  # edge of a tile that disagrees with most of its neighbours


def plot_shift_field(field, *, ax=None, test=None, scale=None, cmap=CMAP_SEQUENTIAL):
    """Arrows of the horizontal shift per tile, coloured by the 3D shift magnitude (mm).

    Each tile's face shows its status (legend below the map): ``ok``, ``undetermined``
    (some component not determined by the tile's data), ``not converged``, ``too few
    points``, ``failed``. Components a tile does not determine are left out: its arrow
    runs along its determined horizontal axis only (a dot when it determines only Z),
    its colour uses the determined components; a tile that did not converge gets no
    arrow. Text in the tiles (the undetermined axes, the area) is drawn only where the
    tiles are large enough on the page to hold it.

    With ``test`` (a :class:`labkit.tiles.NeighbourTest`), borders between
    neighbours that do NOT agree within their uncertainty are drawn in red,
    borders between areas that the area test split (the pair itself agrees)
    dashed, tiles that disagree with most of their neighbours get a thick purple
    edge, and each tile is labelled with its coherent area (``A0``, ``A1``, ...).
    """
    import matplotlib.patches as mpatches
    from matplotlib.colors import Normalize

    ax = _axes(ax, figsize=(7.5, 6.5), layout="constrained")
    c, use = field.centres, field.usable
    det = field.determined
    t = np.where(det, field.translations, 0.0)  # undetermined components drawn as no arrow, not as 0 shift
    o = np.floor(c.min(axis=0) / field.size) * field.size if len(c) else np.zeros(2)
    xy = c - o
    flagged = test.disagreeing if test is not None else np.zeros(len(xy), bool)
    font = _tile_font(ax, xy, field.size)
    for n, (status, (x, y)) in enumerate(zip(field.status, xy)):
        ax.add_patch(mpatches.Rectangle((x - field.size / 2, y - field.size / 2), field.size, field.size,
                                        fc=TILE_FACES.get(status, "#c8c8c8"), ec="#999999", lw=0.6, zorder=0))
        if font and status in ("undetermined", "not converged"):
            free = "".join(a for a, d in zip("XYZ", det[n]) if not d)
            text = f"{free} undet." if status == "undetermined" else "not conv."
            ax.text(x, y - 0.42 * field.size, text, ha="center", va="bottom", fontsize=font, color="#555555",
                    clip_on=True)
    for n in np.flatnonzero(flagged):
        x, y = xy[n]
        ax.add_patch(mpatches.Rectangle((x - field.size / 2, y - field.size / 2), field.size, field.size,
                                        fc="none", ec=FLAG_COLOR, lw=2.5, zorder=3))
    if use.any():
        mag = 1000 * np.linalg.norm(t[use], axis=1)
        lo, hi = float(mag.min()), float(mag.max())
        norm = Normalize(lo, hi) if hi > lo else Normalize(0.0, max(hi, 1.0))
        h = np.linalg.norm(t[use, :2], axis=1).max()
        scale = scale or (h / (0.45 * field.size) if h > 0 else 1.0)
        horizontal = det[use, :2].any(axis=1)
        p, v = xy[use], t[use]
        q = ax.quiver(p[horizontal, 0], p[horizontal, 1], v[horizontal, 0], v[horizontal, 1], mag[horizontal],
                      cmap=cmap, norm=norm, angles="xy", scale_units="xy", scale=scale, width=0.006, pivot="middle",
                      zorder=4)
        ax.scatter(p[~horizontal, 0], p[~horizontal, 1], c=mag[~horizontal], cmap=cmap, norm=norm, s=18, marker="o",
                   edgecolors="k", linewidths=0.4, zorder=4)
        ax.figure.colorbar(q, ax=ax, label="|shift| of the determined components (mm)", shrink=0.8)
        if h > 0:
            ref = 10 ** np.floor(np.log10(h))
            ax.quiverkey(q, 0.7, 1.03, ref, f"{1000 * ref:g} mm horizontal", labelpos="E", coordinates="axes",
                         fontproperties={"size": "small"})  # right of the left-aligned title, inside the axes' width
    if test is not None:
        _draw_disagreement(ax, field, test, xy, font)
    _status_legend(ax, field, flagged, test is not None and not test.agree[test.dof > 0].all())
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel(f"x - {o[0]:.0f} (m)")
    ax.set_ylabel(f"y - {o[1]:.0f} (m)")
    ax.set_title(f"Shift field, {field.size:g} m tiles", loc="left")
    return ax


def _tile_font(ax, xy, size) -> float:
    """Font size (pt) for text inside a tile: about an eighth of the tile's width on the page; 0 if too small."""
    fig = ax.figure
    width_pt = ax.get_position().width * fig.get_figwidth() * 72
    span = max(float(np.ptp(xy[:, 0])) + size, float(np.ptp(xy[:, 1])) + size) if len(xy) else size
    font = min(7.0, width_pt * size / span / 8)
    return font if font >= 4.5 else 0.0


def _status_legend(ax, field, flagged, with_test) -> None:
    import matplotlib.lines as mlines
    import matplotlib.patches as mpatches

    status = field.status
    handles = [mpatches.Patch(fc=face, ec="#999999", label=f"{name} ({int((status == name).sum())})")
               for name, face in TILE_FACES.items() if (status == name).any()]
    if flagged.any():
        handles.append(mpatches.Patch(fc="none", ec=FLAG_COLOR, lw=2.5,
                                      label=f"disagrees with neighbours ({int(flagged.sum())})"))
    if with_test:
        handles.append(mlines.Line2D([], [], color=COLORS["outlier"], lw=3, label="neighbours disagree"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize="small",
              frameon=False)


def _draw_disagreement(ax, field, test, xy, font=7.0):
    half = field.size / 2
    for (i, j), agree in zip(test.pairs, test.agree):
        split = agree and test.areas[i] != test.areas[j]  # the pair agrees, their areas' common shifts do not
        if agree and not split:
            continue
        mid = (xy[i] + xy[j]) / 2
        d = (xy[j] - xy[i]) / np.linalg.norm(xy[j] - xy[i])
        perp = np.array([-d[1], d[0]]) * half
        ax.plot(*np.c_[mid - perp, mid + perp], color=COLORS["outlier"], lw=1.5 if split else 3,
                ls="--" if split else "-", solid_capstyle="butt", zorder=2)
    if not font:
        return
    for n, (x, y) in enumerate(xy):
        if test.areas[n] >= 0:
            ax.text(x - 0.45 * field.size, y + 0.43 * field.size, f"A{test.areas[n]}", fontsize=font, va="top",
                    color="#333333", clip_on=True)


def plot_strips(strips, labels, cloud, *, axes=None):
    """Overlapping strips from above (one colour each) beside the height of the whole cloud.

    ``strips`` and ``cloud`` are PointClouds or (n, 3) arrays; coordinates are shown relative to the
    cloud's minimum corner so that UTM-size numbers stay readable (notebook 09, section 3).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.plotting.compare import plot_strips
    >>> rng = np.random.default_rng(0)
    >>> a, b = rng.uniform(0, 10, (300, 3)), rng.uniform(5, 15, (300, 3))
    >>> axes = plot_strips([a, b], ["1", "2"], np.vstack([a, b]))
    >>> [t.get_text() for t in axes[0].get_legend().get_texts()]
    ['strip 1', 'strip 2']
    """
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, 2, figsize=(13, 5), layout="constrained")
    xyz = np.asarray(getattr(cloud, "xyz", cloud), dtype=float)
    o = xyz.min(axis=0)
    for strip, label in zip(strips, labels):
        axes[0].scatter(*(np.asarray(getattr(strip, "xyz", strip))[:, :2] - o[:2]).T, s=0.5, label=f"strip {label}")
    axes[0].legend(markerscale=10)
    axes[0].set_title("the strips")
    sc = axes[1].scatter(*(xyz[:, :2] - o[:2]).T, c=xyz[:, 2], s=0.5, cmap="terrain")
    axes[1].figure.colorbar(sc, ax=axes[1], label="z (m)")
    axes[1].set_title("height")
    for ax in axes:
        ax.set_aspect("equal")
        ax.set(xlabel=f"x - {o[0]:.0f} (m)", ylabel=f"y - {o[1]:.0f} (m)")
    return axes
