"""Plots for local geometry: normals, local noise, eigenvalue features (notebook 04).

Every helper takes an optional ``ax``/``axes`` or ``plotter`` and returns it; none calls ``show()``.
"""

from __future__ import annotations

import numpy as np

from ..core.checks import as_points, as_rng
from ..core.frame import local_origin
from ..core.masks import ASPRS_NAMES
from ._style import CMAP_SEQUENTIAL, COLORS, POINT_SIZE, new_plotter, scalar_bar

FEATURE_LABELS = {
    "linearity": "linearity $(e_1-e_2)/e_1$",
    "planarity": "planarity $(e_2-e_3)/e_1$",
    "scattering": "scattering $e_3/e_1$",
    "omnivariance": "omnivariance $\\sqrt[3]{e_1e_2e_3}$",
    "anisotropy": "anisotropy $(e_1-e_3)/e_1$",
    "eigenentropy": "eigenentropy $-\\sum e_i\\ln e_i$",
    "change_of_curvature": "change of curvature $e_3$",
    "noise": "local noise $\\sigma_n$ [m]",
    "verticality": "verticality $1-|n_z|$",
}


def _axes(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots()
    return ax


def _local(points):
    xyz = as_points(points)
    return xyz - local_origin(xyz)


def plot_normals(points, normals, *, scalars=None, scalar_name="", subsample=1500, length=None,
                 clim=None, cmap=CMAP_SEQUENTIAL, plotter=None, rng=0):
    """Points (optionally coloured by ``scalars``) with normal arrows on a random subsample.

    Parameters
    ----------
    points : (n, 3) array or PointCloud; shown in a local frame (UTM-sized coordinates are reduced).
    normals : (n, 3) unit normals.
    scalars : (n,) values to colour the points (e.g. local noise, verticality), optional.
    subsample : number of arrows drawn.
    length : arrow length in metres; default 2 % of the scene's diagonal.
    """
    import pyvista as pv

    plotter = new_plotter(plotter)
    xyz = _local(points)
    nrm = np.asarray(normals, dtype=np.float64)
    cloud = pv.PolyData(xyz)
    if scalars is not None:
        cloud[scalar_name or "value"] = np.asarray(scalars, dtype=np.float64)
        plotter.add_mesh(cloud, scalars=scalar_name or "value", cmap=cmap, clim=clim, point_size=POINT_SIZE,
                         render_points_as_spheres=True, scalar_bar_args=scalar_bar(scalar_name or "value"))
    else:
        plotter.add_mesh(cloud, color=COLORS["reference"], point_size=POINT_SIZE, render_points_as_spheres=True)
    ok = np.flatnonzero(np.isfinite(nrm).all(axis=1))
    pick = as_rng(rng).choice(ok, min(subsample, len(ok)), replace=False)
    if length is None:
        length = 0.02 * float(np.linalg.norm(np.ptp(xyz, axis=0)))
    arrows = pv.PolyData(xyz[pick])
    arrows["normal"] = nrm[pick]
    glyphs = arrows.glyph(orient="normal", scale=False, factor=length, geom=pv.Arrow(tip_radius=0.15, shaft_radius=0.05))
    plotter.add_mesh(glyphs, color=COLORS["inlier"])
    plotter.add_axes()
    return plotter


def plot_local_noise(points, noise, *, clim=None, plotter=None):
    """Points coloured by local noise sigma_n (eq. 5); colour limits default to the 2nd-98th percentile."""
    import pyvista as pv

    plotter = new_plotter(plotter)
    xyz = _local(points)
    values = np.asarray(noise, dtype=np.float64)
    if clim is None:
        finite = values[np.isfinite(values)]
        clim = tuple(np.percentile(finite, [2, 98])) if len(finite) else None
    cloud = pv.PolyData(xyz)
    cloud["sigma_n [m]"] = values
    plotter.add_mesh(cloud, scalars="sigma_n [m]", cmap="magma", clim=clim, point_size=POINT_SIZE,
                     render_points_as_spheres=True, nan_color=COLORS["rejected"],
                     scalar_bar_args=scalar_bar("sigma_n [m]"))
    plotter.add_axes()
    return plotter


def plot_by_class(values, classes, *, name="noise", bins=60, log=False, range=None, ax=None, min_points=20):
    """Histograms (densities, step lines) of one per-point quantity, one line per ASPRS class.

    ``name`` selects the axis label (a feature name, 'noise' or 'verticality'); ``log`` bins on a log10 axis.
    """
    ax = _axes(ax)
    v = np.asarray(values, dtype=np.float64)
    cls = np.asarray(classes)
    keep = np.isfinite(v) & ((v > 0) if log else True)
    if range is None and keep.any():
        range = tuple(np.percentile(v[keep], [0.5, 99.5]))
    edges = np.geomspace(max(range[0], 1e-12), range[1], bins + 1) if log else np.linspace(*range, bins + 1)
    for code in np.unique(cls[keep]):
        sel = keep & (cls == code)
        if sel.sum() < min_points:
            continue
        label = f"{ASPRS_NAMES.get(int(code), f'class {int(code)}')} (n = {sel.sum()})"
        ax.hist(v[sel], bins=edges, density=True, histtype="step", lw=1.6, label=label)
    if log:
        from matplotlib.ticker import NullFormatter

        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(FEATURE_LABELS.get(name, name))
    ax.set_ylabel("density")
    ax.legend(fontsize="small")
    return ax


def plot_features_by_class(features, classes, *, names=("linearity", "planarity", "scattering"), axes=None, **kw):
    """One :func:`plot_by_class` panel per eigenvalue feature (``features``: EigenFeatures)."""
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.6), constrained_layout=True)
    for name, ax in zip(names, np.atleast_1d(axes)):
        plot_by_class(features[name], classes, name=name, range=(0.0, 1.0) if name != "eigenentropy" else None,
                      ax=ax, **kw)
        ax.set_title(name)
    return axes


def plot_scale_choice(multiscale, classes=None, ax=None):
    """Share of points per chosen scale (least eigenentropy), grouped by class when given."""
    ax = _axes(ax)
    scales = multiscale.scales
    cls = np.zeros(len(multiscale.best), dtype=int) if classes is None else np.asarray(classes)
    codes = np.unique(cls)
    width = 0.8 / len(scales)
    for j, s in enumerate(scales):
        share = [np.mean(multiscale.best[cls == c] == j) for c in codes]
        ax.bar(np.arange(len(codes)) + (j - (len(scales) - 1) / 2) * width, share, width,
               label=f"{multiscale.by} = {s}")
    ax.set_xticks(np.arange(len(codes)))
    ax.set_xticklabels(["all" if classes is None else ASPRS_NAMES.get(int(c), str(c)) for c in codes],
                       rotation=20, ha="right")
    ax.set_ylabel("share of points")
    ax.set_title("scale of least eigenentropy")
    ax.legend(fontsize="small")
    return ax


def plot_angle_errors(estimates, truth, *, labels=None, bins=60, ax=None):
    """Histograms of the angles (degrees) between estimated and true normals, up to sign."""
    ax = _axes(ax)
    truth = np.asarray(truth, dtype=np.float64)
    angles = []
    for est in estimates:
        est = np.asarray(est, dtype=np.float64)
        c = np.abs(np.einsum("ij,ij->i", est, truth)) / np.linalg.norm(est, axis=1) / np.linalg.norm(truth, axis=1)
        angles.append(np.degrees(np.arccos(np.clip(c, 0, 1))))
    top = max(np.percentile(a, 99) for a in angles) * 1.1
    for i, ang in enumerate(angles):
        label = (labels[i] if labels else f"estimate {i}") + f" (median {np.median(ang):.2f} deg)"
        ax.hist(ang, bins=np.linspace(0, top, bins + 1), histtype="step", lw=1.6, density=True, label=label)
    ax.set_xlabel("angle to the true normal [deg]")
    ax.set_ylabel("density")
    ax.legend(fontsize="small")
    return ax
