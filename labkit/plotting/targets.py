"""Figures of target-based registration (notebook 11): the network in plan, std ratios, test statistics."""

from __future__ import annotations

import numpy as np

from ._style import COLORS


def _ax(ax, figsize=(7, 5)):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=figsize, layout="constrained")
    return ax


def plot_network(net, ax=None, truth=None):
    """Plan view of a registered network: stations (scan origins), targets, and which station saw which.

    ``net`` is a :class:`labkit.targets.register.TargetNetwork`; ``truth`` optional (k, 4, 4) true poses in the
    reference frame (drawn as crosses). Excluded observations are dashed red.
    """
    ax = _ax(ax)
    tab = net.table
    for s, M in enumerate(net.matrices):
        if not np.isfinite(M).all():
            continue
        st = M[:3, 3]
        for r in np.flatnonzero((tab.scan == s) & (tab.target >= 0)):
            c = M[:3, :3] @ tab.center[r] + st
            bad = tab.status[r] == "excluded"
            ax.plot([st[0], c[0]], [st[1], c[1]], ls="--" if bad else "-", lw=1.5 if bad else 0.6,
                    color=COLORS["outlier"] if bad else "0.7", zorder=1)
        ax.plot(*st[:2], "^", ms=10, color=COLORS["source"], zorder=3)
        ax.annotate(f"scan {s}", st[:2], textcoords="offset points", xytext=(6, 6))
    ax.plot(*net.targets[:, :2].T, "o", ms=8, color=COLORS["sphere"], zorder=2, label="targets")
    for g, X in enumerate(net.targets):
        ax.annotate(str(g), X[:2], textcoords="offset points", xytext=(5, -12), color=COLORS["sphere"])
    if truth is not None:
        ax.plot(*np.asarray(truth)[:, :2, 3].T, "x", color="k", ms=8, label="true stations")
    ax.set_aspect("equal")
    ax.set_xlabel("x in the reference frame (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best")
    return ax


def plot_std_ratios(ratios, names=("rx", "ry", "rz", "tx", "ty", "tz"), ax=None, labels=None):
    """Bars of empirical spread / stated std per parameter (one group per row of ``ratios``), band 0.8-1.25."""
    ax = _ax(ax, (7, 3.5))
    ratios = np.atleast_2d(ratios)
    k = len(ratios)
    width = 0.8 / k
    for i, r in enumerate(ratios):
        ax.bar(np.arange(len(r)) + (i - (k - 1) / 2) * width, r, width,
               label=None if labels is None else labels[i])
    ax.axhspan(0.8, 1.25, color="0.9", zorder=0, label="0.8 - 1.25")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks(np.arange(len(names)), names)
    ax.set_ylabel("Monte Carlo spread / stated std")
    ax.legend(loc="lower right", fontsize="small")
    return ax


def plot_target_tests(net, ax=None):
    """The test statistic of every observed centre (as a standard normal value) with the critical value."""
    ax = _ax(ax, (8, 3.5))
    tab = net.table
    used = np.isfinite(tab.test)
    x = np.arange(used.sum())
    bad = tab.status[used] == "excluded"
    ax.bar(x[~bad], tab.test[used][~bad], color=COLORS["inlier"], label="used")
    ax.bar(x[bad], tab.test[used][bad], color=COLORS["outlier"], label="left out")
    ax.axhline(net.w_critical, color="k", ls="--", lw=1, label=f"critical value {net.w_critical:.2f}")
    ax.set_xticks(x, [f"{s}/{t}" for s, t in zip(tab.scan[used], tab.target[used])], rotation=90, fontsize=7)
    ax.set_xlabel("scan / target")
    ax.set_ylabel("test (normal quantile)")
    ax.legend(fontsize="small")
    return ax
