"""Plots for the Gauss-Helmert sphere adjustment (notebook 01).

Every helper takes an optional ``ax`` / ``axes`` / ``plotter`` and returns it; none calls ``show()``.
"""

from __future__ import annotations

import numpy as np

from ..core.distributions import norm_pdf, norm_ppf
from ._style import CMAP_DIVERGING, COLORS, POINT_SIZE, new_plotter, scalar_bar, show_scale


def _axes(ax, ncols=1, figsize=None):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(1, ncols, figsize=figsize, layout="constrained")
    return ax


def plot_convergence(fit, ax=None):
    """max|dx| per iteration (log scale) with the tolerance line; the Hauptprobe in the title."""
    ax = _axes(ax)
    it = np.arange(1, fit.iterations + 1)
    steps = np.abs(fit.dx_history)
    for j, name in enumerate(["$x_c$", "$y_c$", "$z_c$", "$r$"]):
        if steps[:, j].any():
            ax.semilogy(it, np.maximum(steps[:, j], 1e-18), "o-", ms=4, lw=1, label=f"|d{name}|")
    ax.semilogy(it, steps.max(axis=1), "k--", lw=1.5, label="max |dx|")
    ax.set_xlabel("iteration")
    ax.set_ylabel("increment [m]")
    ax.set_xticks(it)
    check = "passed" if fit.main_check_passed else "FAILED"
    ax.set_title(f"Convergence; main check max|f(l+v, x)| = {fit.main_check:.1e} m ({check})")
    ax.legend(fontsize=8)
    return ax


def plot_residuals(fit, axes=None, bins=50):
    """Histogram of the normal residuals (mm) with the expected normal density, and a QQ plot of w.

    Left: residuals along the surface normal with N(0, s) where s is the mean
    predicted standard deviation sigma0 sqrt(q_i r_i). Right: the w-test
    statistics against standard normal quantiles; points beyond the critical
    value are marked.
    """
    axes = _axes(axes, ncols=2, figsize=(11, 4))
    ax_h, ax_q = axes
    e = fit.normal_residuals * 1e3
    ax_h.hist(e, bins=bins, density=True, color=COLORS["inlier"], alpha=0.7, label="residuals")
    w = fit.w_test[np.isfinite(fit.w_test)]
    if len(w):
        # w uses the a priori sigma0 (rescale to the estimated one); Pope's tau already uses the estimated
        scale = np.nanmedian(np.abs(e[np.isfinite(fit.w_test)] / w)) * (
            fit.sigma0 / fit.sigma0_apriori if getattr(fit, "sigma_known", True) else 1.0)
        grid = np.linspace(e.min(), e.max(), 200)
        ax_h.plot(grid, norm_pdf(grid, scale), color=COLORS["reference"], label=f"N(0, {scale:.2f} mm)")
    ax_h.set_xlabel("residual along the normal [mm]  (+ outside)")
    ax_h.set_ylabel("density")
    ax_h.set_title("Residuals")
    ax_h.legend(fontsize=8)

    if len(w):
        theo = norm_ppf((np.arange(1, len(w) + 1) - 0.5) / len(w))
        order = np.sort(w)
        bad = np.abs(order) > fit.w_critical
        ax_q.plot(theo[~bad], order[~bad], ".", color=COLORS["inlier"], ms=3, label="w")
        ax_q.plot(theo[bad], order[bad], "o", color=COLORS["outlier"], ms=5, label=f"|w| > {fit.w_critical:.2f}")
        lim = [theo.min(), theo.max()]
        ax_q.plot(lim, lim, "--", color=COLORS["reference"], lw=1, label="N(0, 1)")
    ax_q.set_xlabel("standard normal quantile")
    ax_q.set_ylabel("w-test statistic")
    ax_q.set_title("QQ plot of Baarda's w")
    ax_q.legend(fontsize=8)
    return axes


def plot_confidence_ellipsoid(fit, level=0.95, truth=None, axes=None):
    """The centre's confidence ellipsoid projected onto the xy, xz and yz planes, in mm.

    The projection of an ellipsoid is drawn from the 2x2 block of its
    covariance with the same quantile, so the outline is the shadow of the 3D
    ellipsoid. ``truth`` (a known centre) is marked if given.
    """
    ell = fit.confidence_ellipsoid(level)
    axes = _axes(axes, ncols=3, figsize=(12, 4))
    t = np.linspace(0, 2 * np.pi, 200)
    for ax, (i, j) in zip(axes, [(0, 1), (0, 2), (1, 2)]):
        C = ell.covariance[np.ix_([i, j], [i, j])]
        lam, vec = np.linalg.eigh(C)
        circle = np.stack([np.cos(t), np.sin(t)])
        outline = vec @ (np.sqrt(np.clip(lam, 0, None) * ell.quantile)[:, None] * circle) * 1e3
        ax.plot(outline[0], outline[1], color=COLORS["sphere"], label=f"{level:.0%} ellipsoid (shadow)")
        ax.plot(0, 0, "+", color=COLORS["sphere"], ms=10, label="adjusted centre")
        if truth is not None:
            d = (np.asarray(truth, dtype=np.float64)[:3] - ell.center) * 1e3
            ax.plot(d[i], d[j], "x", color=COLORS["outlier"], ms=8, label="true centre")
        names = "xyz"
        ax.set_xlabel(f"d{names[i]} [mm]")
        ax.set_ylabel(f"d{names[j]} [mm]")
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(fontsize=8)
    axes[1].set_title(f"Centre: {level:.0%} confidence ellipsoid, semi-axes "
                      + ", ".join(f"{a * 1e3:.3f}" for a in ell.semi_axes) + " mm")
    return axes


def plot_sphere_residuals(points, fit, plotter=None, clim_mm=None, show_sphere=True, view_from=None):
    """pyvista scene: the adjusted sphere (translucent) and the points coloured by residual (mm).

    Parameters
    ----------
    points : ndarray (n, 3)
        The adjusted points, in the frame of ``fit``.
    fit : SphereFit
    clim_mm : float, optional
        Symmetric colour limit in mm (default: 3 sigma of the residuals).
    view_from : array_like (3,), optional
        Look from about this direction (e.g. the scanner station), turned 40 degrees
        sideways so that the edge of the scanned cap shows, at 6 radii from the centre.
    """
    import pyvista as pv

    plotter = new_plotter(plotter)
    origin = fit.center  # render near the origin: UTM coordinates strain float32 graphics
    cloud = pv.PolyData(np.asarray(points, dtype=np.float64) - origin)
    cloud["residual [mm]"] = fit.normal_residuals * 1e3
    lim = clim_mm if clim_mm is not None else 3 * np.std(fit.normal_residuals) * 1e3
    plotter.add_mesh(cloud, scalars="residual [mm]", cmap=CMAP_DIVERGING, clim=[-lim, lim],
                     point_size=POINT_SIZE + 2, render_points_as_spheres=True,
                     scalar_bar_args=scalar_bar("residual [mm]"))
    if show_sphere:
        sphere = pv.Sphere(radius=fit.radius, center=(0.0, 0.0, 0.0), theta_resolution=60, phi_resolution=60)
        plotter.add_mesh(sphere, color=COLORS["sphere"], opacity=0.25)
    show_scale(plotter, frame="from the centre")
    if view_from is not None:
        d = np.asarray(view_from, dtype=np.float64) - origin
        plotter.camera_position = [tuple(6 * fit.radius * d / np.linalg.norm(d)), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)]
        plotter.camera.azimuth = 40.0
        plotter.camera.elevation = 15.0
    return plotter


def add_confidence_ellipsoid(plotter, fit, level=0.95, exaggeration=100.0, origin=None):
    """Add the centre's confidence ellipsoid, scaled by ``exaggeration``, to a pyvista plotter.

    ``origin`` is the point subtracted for rendering (default: the adjusted
    centre, as in :func:`plot_sphere_residuals`).
    """
    import pyvista as pv

    ell = fit.confidence_ellipsoid(level)
    origin = fit.center if origin is None else np.asarray(origin, dtype=np.float64)
    unit = pv.Sphere(radius=1.0, theta_resolution=40, phi_resolution=40)
    M = ell.axes * (ell.semi_axes * exaggeration)  # columns: scaled semi-axes
    unit.points = unit.points @ M.T + (ell.center - origin)
    plotter.add_mesh(unit, color=COLORS["outlier"], opacity=0.6,
                     label=f"{level:.0%} ellipsoid x{exaggeration:g}")
    return plotter
