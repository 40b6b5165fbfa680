"""Plots for RANSAC sphere detection (notebook 02).

Every helper takes an optional ``ax`` or ``plotter`` and returns it; none calls ``show()``.
"""

from __future__ import annotations

import numpy as np

from ..ransac import required_iterations
from ._style import COLORS, POINT_SIZE, new_plotter, show_scale


def _axes(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots()
    return ax


def plot_required_iterations(ax=None, p_values=(0.9, 0.99, 0.999), s=4, max_ratio=0.9):
    """N(eps, p) of eq. (27) over the outlier ratio eps, one curve per p, log scale."""
    ax = _axes(ax)
    eps = np.linspace(0.0, max_ratio, 181)
    for p in p_values:
        ax.semilogy(eps, required_iterations(eps, p, s), label=f"p = {p}")
    ax.set_xlabel("outlier ratio $\\varepsilon$")
    ax.set_ylabel("required samples $N$ (eq. 27)")
    ax.set_title(f"Samples needed for a minimal sample of s = {s}")
    ax.legend()
    return ax


def plot_adaptive_trace(result, ax=None):
    """The required N after each new best (a falling staircase) against the samples drawn.

    The loop stops where the staircase meets the diagonal N = iteration.
    """
    ax = _axes(ax)
    hist = np.asarray(result.n_required_history)
    if len(hist):
        it, N = hist[:, 0], hist[:, 1]
        end = max(result.iterations, it.max())
        finite = np.isfinite(N)
        ax.step(np.append(it[finite], end), np.append(N[finite], N[finite][-1:]) if finite.any() else [],
                where="post", color=COLORS["sphere"], label="required N after a new best")
        ax.plot(it[finite], N[finite], "o", color=COLORS["sphere"], ms=4)
        top = max(end, N[finite].max() if finite.any() else end)
        ax.plot([1, top], [1, top], "--", color=COLORS["reference"], lw=1, label="samples drawn")
        ax.axvline(result.iterations, color=COLORS["outlier"], lw=1, label=f"stop after {result.iterations}")
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel("valid samples drawn")
    ax.set_ylabel("required N")
    ax.set_title("Adaptive number of samples")
    ax.legend()
    return ax


def plot_section(points, spheres, ax=None, labels=None, width=None, axis=1, inliers=None):
    """A slab through the first sphere's centre, with the circles of one or more spheres.

    Parameters
    ----------
    points : ndarray (n, 3)
    spheres : sequence of array_like (4,)
        Spheres [xc, yc, zc, r]; the slab is centred on the first one.
    labels : sequence of str, optional
        Legend text per sphere.
    width : float, optional
        Slab half-width (default: a third of the first radius).
    axis : int
        Axis normal to the slab (1: the x-z plane).
    inliers : ndarray of bool (n,), optional
        Colour inliers and outliers differently.
    """
    ax = _axes(ax)
    spheres = [np.asarray(s, dtype=np.float64) for s in spheres]
    c0, r0 = spheres[0][:3], spheres[0][3]
    width = r0 / 3 if width is None else width
    h, v = [k for k in range(3) if k != axis]
    pts = np.asarray(points)
    sel = np.abs(pts[:, axis] - c0[axis]) < width
    near = sel & (np.abs(pts[:, h] - c0[h]) < 4 * r0) & (np.abs(pts[:, v] - c0[v]) < 4 * r0)
    if inliers is None:
        ax.plot(pts[near, h], pts[near, v], ".", ms=2, color=COLORS["reference"], label="points in the slab")
    else:
        for mask, key in ((near & inliers, "inlier"), (near & ~inliers, "outlier")):
            ax.plot(pts[mask, h], pts[mask, v], ".", ms=2, color=COLORS[key], label=f"{key}s")
    phi = np.linspace(0, 2 * np.pi, 361)
    labels = labels or [None] * len(spheres)
    for s, lab in zip(spheres, labels):
        rr = np.sqrt(max(s[3] ** 2 - (c0[axis] - s[axis]) ** 2, 0.0))  # circle cut by the slab's mid-plane
        ax.plot(s[h] + rr * np.cos(phi), s[v] + rr * np.sin(phi), lw=1.5, label=lab)
    ax.set_aspect("equal")
    ax.set_xlabel("xyz"[h] + " (m)")
    ax.set_ylabel("xyz"[v] + " (m)")
    ax.legend(fontsize=8, loc="upper right")
    return ax


def render_inliers(points, result, plotter=None, max_points=200_000, show_sphere=True, rng=0,
                   subset=None, close_up=None, view=(1.0, -1.0, 0.7)):
    """Inliers and outliers of a RANSAC result as coloured points, with the adjusted sphere.

    Parameters
    ----------
    points : ndarray (n, 3)
        The points given to :func:`labkit.ransac_sphere`.
    result : RansacResult
    max_points : int
        At most this many points are drawn (a random subset) to keep rendering fast.
    subset : ndarray of bool (n,), optional
        Draw only these points (e.g. without the ceiling of a room).
    close_up : float, optional
        Look at the found sphere from ``close_up`` radii away, along ``view``; the axes then
        span the sphere (its bounding box) rather than the whole scene.
    """
    import pyvista as pv

    plotter = new_plotter(plotter)
    pts = np.asarray(points, dtype=np.float64)
    origin = np.round(pts.mean(axis=0))  # render in a local frame (VTK works in float32)
    keep = np.flatnonzero(np.ones(len(pts), dtype=bool) if subset is None else subset)
    if len(keep) > max_points:
        keep = np.sort(np.random.default_rng(rng).choice(keep, max_points, replace=False))
    inl = result.inliers[keep]
    for mask, key in ((inl, "inlier"), (~inl, "outlier")):
        if mask.any():
            plotter.add_points(pts[keep][mask] - origin, color=COLORS[key], point_size=POINT_SIZE,
                               render_points_as_spheres=True, label=f"{key}s")
    if result.found:
        centre, r = result.fit.x[:3] - origin, float(result.fit.x[3])
        if show_sphere:
            mesh = pv.Sphere(radius=r, center=centre, theta_resolution=48, phi_resolution=48)
            plotter.add_mesh(mesh, color=COLORS["sphere"], opacity=0.25, label="sphere")
        if close_up:
            direction = np.asarray(view, dtype=np.float64) / np.linalg.norm(view)
            plotter.camera_position = [tuple(centre + close_up * r * direction), tuple(centre), (0.0, 0.0, 1.0)]
    plotter.add_legend(bcolor="white", size=(0.24, 0.12), loc="upper right")
    near = None
    if result.found and close_up:
        near = np.repeat(centre, 2) + np.tile([-r, r], 3)
    show_scale(plotter, origin, bounds=near)
    return plotter


def plot_reduction(points, is_sphere, work, draws, *, axes=None):
    """The random reduction of RANSAC's search: which points it keeps, and how many sphere points it holds.

    Left, a top view of the scene below 2.5 m (the ceiling left out) with the reduced working set and
    its sphere points; right, the hypergeometric distribution of the sphere points in a reduction
    (``draws``, e.g. from ``numpy.random.Generator.hypergeometric``) and the count of this one
    (notebook 02, section 9b).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.plotting.ransac import plot_reduction
    >>> rng = np.random.default_rng(0)
    >>> points = rng.uniform(0, 2, (500, 3))
    >>> is_sphere = np.arange(500) < 25
    >>> work = rng.choice(500, 100, replace=False)
    >>> draws = rng.hypergeometric(25, 475, 100, size=1000)
    >>> axes = plot_reduction(points, is_sphere, work, draws)
    >>> axes[1].get_xlabel()
    'sphere points in the reduction'
    """
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
    points, is_sphere, work = np.asarray(points), np.asarray(is_sphere, bool), np.asarray(work)
    below = points[:, 2] < 2.5
    axes[0].scatter(*points[below][:, :2].T, s=0.3, c="0.8", label=f"all {len(points)} points (no ceiling)")
    axes[0].scatter(*points[work][:, :2].T, s=3, c="tab:blue", label=f"reduction to {len(work)}")
    on = work[is_sphere[work]]
    axes[0].scatter(*points[on][:, :2].T, s=14, c=COLORS["outlier"], label=f"{len(on)} sphere points in it")
    axes[0].set_aspect("equal")
    axes[0].set(xlabel="x [m]", ylabel="y [m]", title="top view of the room")
    axes[0].legend(markerscale=3, fontsize=8, loc="upper right")
    draws = np.asarray(draws)
    axes[1].hist(draws, bins=np.arange(draws.min(), draws.max() + 2) - 0.5, density=True, color="0.6",
                 label=f"hypergeometric, {len(draws)} reductions")
    axes[1].axvline(len(on), color=COLORS["outlier"], label="this reduction")
    axes[1].set(xlabel="sphere points in the reduction", ylabel="probability",
                title="how many sphere points a reduction keeps")
    axes[1].legend(fontsize=8)
    return axes


def plot_scan_overview(scan, around, *, half=1.0, axes=None):
    """A scan from above, whole and in a square of ``2 half`` metres around ``around`` (x, y), coloured by z.

    The close-up shows what a multi-beam scanner leaves of a target: rings, not a surface
    (notebook 09, section 1).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.plotting.ransac import plot_scan_overview
    >>> scan = np.random.default_rng(0).uniform(-5, 5, (2000, 3))
    >>> axes = plot_scan_overview(scan, (1.0, 1.0), half=2.0)
    >>> axes[1].get_title()
    '4 m x 4 m around (1, 1)'
    """
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, 2, figsize=(13, 5), layout="constrained")
    scan = np.asarray(scan, dtype=float)
    near = (np.abs(scan[:, :2] - np.asarray(around, dtype=float)) < half).all(axis=1)
    for ax, sel, size in ((axes[0], slice(None), 1), (axes[1], near, 6)):
        sc = ax.scatter(scan[sel, 0], scan[sel, 1], c=scan[sel, 2], s=size, cmap="viridis")
        ax.set_aspect("equal")
        ax.set(xlabel="x (m)", ylabel="y (m)")
    axes[0].figure.colorbar(sc, ax=axes, label="z (m)")
    axes[0].set_title("the whole scan (sensor at 0, 0)")
    axes[1].set_title(f"{2 * half:g} m x {2 * half:g} m around ({around[0]:g}, {around[1]:g})")
    return axes
