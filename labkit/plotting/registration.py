"""Plots for ICP registration (notebook 05): correspondences by rule, convergence, shifts vs truth.

Every helper takes an optional ``ax`` / ``axes`` / ``plotter`` and returns it; none calls ``show()``.
"""

from __future__ import annotations

import numpy as np

from ._style import COLORS, POINT_SIZE, new_plotter

#: One colour per rule of :data:`labkit.registration.matching.match.RULES`.
RULE_COLORS = {
    "accepted": COLORS["inlier"],
    "class": "#7570b3",
    "noise": "#66a61e",
    "distance": "#bbbbbb",
    "normal_angle": "#e6ab02",
    "duplicate": "#a6cee3",
    "outlier": COLORS["outlier"],
    "degenerate": "#999999",  # no normal: the neighbourhood is a point or a line
}
_AXES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


def _new_ax(ax, **kw):
    if ax is not None:
        return ax
    import matplotlib.pyplot as plt

    return plt.subplots(**kw)[1]


def plot_correspondences(corr, *, ax=None, view="xy", max_points=30000, rng=0, s=3.0):
    """Sampled source points coloured by the rule that rejected them (accepted in green).

    Parameters
    ----------
    corr : Correspondences
    view : {'xy', 'xz', 'yz'}
        Projection plane.
    max_points : int
        Plot a random subset if there are more rows (the legend counts all).
    """
    from ..registration.matching.match import RULES

    ax = _new_ax(ax, figsize=(6.5, 6.0))
    i, j = _AXES[view]
    xyz = corr.source_xyz - corr.source_xyz.min(axis=0)
    show = np.arange(len(corr))
    if len(show) > max_points:
        show = np.sort(np.random.default_rng(rng).choice(len(show), max_points, replace=False))
    counts = np.bincount(corr.rule, minlength=len(RULES))
    for code in np.argsort(-counts):  # largest group first, small groups on top
        name = RULES[code]
        sel = show[corr.rule[show] == code]
        if counts[code] == 0:
            continue
        ax.scatter(xyz[sel, i], xyz[sel, j], s=s, c=RULE_COLORS[name], label=f"{name} ({counts[code]})", lw=0)
    ax.set_xlabel(f"{view[0]} (m, local)")
    ax.set_ylabel(f"{view[1]} (m, local)")
    if view == "xy":
        ax.set_aspect("equal")
    ax.legend(markerscale=4, fontsize=8, loc="upper right", framealpha=0.85)
    ax.set_title("Correspondences by rule")
    return ax


def plot_correspondences_3d(corr, target=None, *, plotter=None, point_size=POINT_SIZE):
    """3D view (pyvista): source points by rule, the target in light grey."""
    import pyvista as pv

    from ..registration.matching.match import RULES

    plotter = new_plotter(plotter)
    o = corr.source_xyz.min(axis=0)
    if target is not None:
        tgt = getattr(target, "xyz", target)
        plotter.add_mesh(pv.PolyData(np.asarray(tgt) - o), color="#dddddd", point_size=point_size / 2)
    for code, name in enumerate(RULES):
        sel = corr.rule == code
        if sel.any():
            plotter.add_mesh(pv.PolyData(corr.source_xyz[sel] - o), color=RULE_COLORS[name], point_size=point_size, label=name)
    plotter.add_legend(bcolor="white", size=(0.22, 0.25))
    return plotter


def plot_convergence(result, *, truth=None, axes=None):
    """Three panels over the iterations: shift (or its error vs ``truth``, mm), RMS and used, step size.

    Parameters
    ----------
    result : RegistrationResult
        Of :func:`labkit.registration.icp` (history of IterationRecord).
    truth : array_like (3,), optional
        The true shift; the first panel then shows the error in mm.
    axes : sequence of 3 Axes, optional
    """
    if axes is None:
        import matplotlib.pyplot as plt

        axes = plt.subplots(1, 3, figsize=(13, 3.6))[1]
    h = result.history
    it = np.array([r.iteration for r in h])
    t = np.array([r.translation for r in h])
    label = "shift (m)"
    if truth is not None:
        t, label = 1000 * (t - np.asarray(truth, dtype=float)), "error vs truth (mm)"
    for k, (name, c) in enumerate(zip("XYZ", ("#1b9e77", "#d95f02", "#7570b3"))):
        axes[0].plot(it, t[:, k], "o-", color=c, ms=3, label=f"d{name}")
    axes[0].set(xlabel="iteration", ylabel=label, title="Estimate")
    axes[0].legend(fontsize=8)
    axes[1].plot(it, [1000 * r.rms for r in h], "o-", ms=3, color="#333333")
    axes[1].set(xlabel="iteration", ylabel="weighted RMS (mm)", title="Residuals")
    twin = axes[1].twinx()
    twin.plot(it, [r.n_used for r in h], "s--", ms=3, color=COLORS["outlier"])
    twin.set_ylabel("correspondences used", color=COLORS["outlier"])
    twin.grid(False)
    axes[2].semilogy(it, [max(r.step, 1e-12) for r in h], "o-", ms=3, color="#333333")
    axes[2].set(xlabel="iteration", ylabel="update size (m)", title="Step")
    return axes


def plot_shifts(results, *, truth=None, ax=None, sigma=2.0):
    """Estimated shifts of several methods with error bars (``sigma`` x std), against the truth.

    Parameters
    ----------
    results : dict name -> RegistrationResult (or (3,) shift, or (shift, std))
    truth : array_like (3,), optional
        The true shift; plotted as errors in mm when given.
    sigma : float
        Error bars span +- sigma standard deviations. Undetermined components
        (inf std) are drawn as hollow markers with a label; NaN std (no
        uncertainty known, e.g. a shift from another library) gets no error bar.
    """
    ax = _new_ax(ax, figsize=(7.5, 4.2))
    names = list(results)
    width = 0.8 / max(len(names), 1)
    for m, name in enumerate(names):
        shift, std = _shift_and_std(results[name])
        value = shift if truth is None else shift - np.asarray(truth, dtype=float)
        scale = 1.0 if truth is None else 1000.0
        x = np.arange(3) + (m - (len(names) - 1) / 2) * width
        undetermined = np.isinf(std)  # NaN std: no uncertainty given (e.g. a peer library), no error bar
        shown = ~undetermined
        yerr = np.where(np.isnan(std), 0.0, std)[shown]
        ax.errorbar(x[shown], scale * value[shown], yerr=scale * sigma * yerr, fmt="o", capsize=3, label=name)
        if undetermined.any():
            ax.plot(x[undetermined], scale * value[undetermined], "o", mfc="none", color="#888888")
            for xi, vi in zip(x[undetermined], value[undetermined]):
                ax.annotate("undetermined", (xi, scale * vi), fontsize=7, rotation=90, va="bottom", ha="center")
    ax.axhline(0, color=COLORS["reference"], lw=1)
    ax.set_xticks(range(3), ["dX", "dY", "dZ"])
    ax.set_ylabel("shift (m)" if truth is None else "error vs truth (mm)")
    ax.set_title(f"Shifts with +-{sigma:g} sigma")
    ax.legend(fontsize=8)
    return ax


def _shift_and_std(item):
    if hasattr(item, "translation"):
        return np.asarray(item.translation, float), np.asarray(item.translation_std, float)
    if isinstance(item, tuple) and len(item) == 2:
        return np.asarray(item[0], float), np.asarray(item[1], float)
    return np.asarray(item, float), np.full(3, np.nan)


def plot_residuals(corr, *, ax=None, bins=80, limit=None):
    """Histogram of the point-to-plane distances: accepted vs deleted ('outlier') rows, mm."""
    ax = _new_ax(ax)
    pd = 1000 * corr.plane_distance
    acc = corr.accepted
    out = corr.rule == 6  # 'outlier'
    lim = limit or float(np.nanpercentile(np.abs(pd[acc | out]), 99.5)) if (acc | out).any() else 1.0
    edges = np.linspace(-lim, lim, bins + 1)
    ax.hist(np.clip(pd[acc], -lim, lim), edges, color=RULE_COLORS["accepted"], alpha=0.8, label="accepted")
    if out.any():
        ax.hist(np.clip(pd[out], -lim, lim), edges, color=RULE_COLORS["outlier"], alpha=0.8, label="deleted (outlier)")
    ax.set(xlabel="point-to-plane distance (mm)", ylabel="count", title="Residuals of the last iteration")
    ax.legend(fontsize=8)
    return ax


def plot_degeneracy(degeneracy, *, axes=None):
    """The eigen analysis of a registration: precision per eigen-direction and the directions themselves.

    Left, the standard deviation along each eigen-direction v_k of the normal equations (log scale,
    capped at 10 m) against the limit ``max_std`` of notebook 05, eq. 5.12a: green where the direction is
    determined, orange where it is held. Right, the absolute eigenvectors as a table over tx, ty, tz
    (which axes each direction mixes), with the signed components written in.

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from labkit.plotting.registration import plot_degeneracy
    >>> deg = SimpleNamespace(direction_std=np.array([0.5, 0.004, 0.0002]), constrained=np.array([False, True, True]),
    ...                       max_std=0.1, eigenvectors=np.eye(3))
    >>> axes = plot_degeneracy(deg)
    >>> [len(a.patches) for a in axes], len(axes[1].texts)
    ([3, 0], 9)
    """
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, 2, figsize=(12, 4), layout="constrained")
    names = [f"v{k + 1}" for k in range(3)]
    colors = [COLORS["inlier"] if c else COLORS["outlier"] for c in degeneracy.constrained]
    axes[0].bar(range(3), np.minimum(degeneracy.direction_std, 10.0), color=colors)
    axes[0].axhline(degeneracy.max_std, color="k", ls="--", lw=1, label=f"max_std = {degeneracy.max_std} m")
    axes[0].set(yscale="log", xticks=range(3), xticklabels=names, ylabel="std along the direction (m)",
                title="Precision of each eigen-direction (5.12a)")
    axes[0].legend()
    vectors = np.asarray(degeneracy.eigenvectors)
    axes[1].imshow(np.abs(vectors), cmap="Greys", vmin=0, vmax=1)
    axes[1].set(xticks=range(3), xticklabels=names, yticks=range(3), yticklabels=["tx", "ty", "tz"],
                title="|eigenvectors| (columns)")
    axes[1].grid(False)
    for (i, j), v in np.ndenumerate(vectors):  # white on the dark cells, black on the light ones
        axes[1].text(j, i, f"{v:+.2f}", ha="center", va="center", color="white" if abs(v) > 0.5 else "black")
    return axes
