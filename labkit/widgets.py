"""Interactive explorers for the notebooks (ipywidgets).

Building a widget never displays anything: the notebook shows it by making it
the last expression of a cell. Figures are rendered with matplotlib's Agg
canvas into an ``Image`` widget, so the explorers also build and update in a
headless run (CI), where no front end is attached.
"""

from __future__ import annotations

import io

import numpy as np

_P_OPTIONS = (0.5, 0.8, 0.9, 0.95, 0.99, 0.999, 0.9999)


def _png(fig) -> bytes:
    """Render a matplotlib Figure (Agg) to PNG bytes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()


def ransac_explorer(points, threshold=0.003, p=0.99, truth=None, rng=0, **ransac_kwargs):
    """Sliders for the inlier threshold t and the probability p of :func:`labkit.ransac_sphere`.

    Each change reruns the detection with the same seed and shows the result
    summary, the error against ``truth`` (if given), a section through the
    sphere and the adaptive-N trace.

    Parameters
    ----------
    points : array_like (n, 3)
    threshold : float
        Initial t in metres; the slider spans t/10 .. 10 t on a log scale.
    p : float
        Initial probability (snapped to the nearest of 0.5 ... 0.9999).
    truth : array_like (4,), optional
        The true sphere, to report the centre and radius errors.
    rng : int
        Seed used for every run, so only t and p change between runs.
    **ransac_kwargs
        Passed to :func:`labkit.ransac_sphere` (e.g. ``radius_range``).

    Returns
    -------
    ipywidgets.VBox
        With attributes ``threshold_slider``, ``p_slider``, ``report`` (HTML),
        ``figure`` (Image), ``last_result`` and ``update()``.
    """
    import ipywidgets as widgets

    from .ransac import ransac_sphere

    pts = np.asarray(points, dtype=np.float64)
    t_mm = float(threshold) * 1e3
    t_slider = widgets.FloatLogSlider(
        value=t_mm, base=10, min=np.log10(t_mm) - 1, max=np.log10(t_mm) + 1, step=0.05,
        description="t (mm)", continuous_update=False, readout_format=".3g",
    )
    p0 = min(_P_OPTIONS, key=lambda v: abs(v - p))
    p_slider = widgets.SelectionSlider(options=_P_OPTIONS, value=p0, description="p", continuous_update=False)
    report = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([t_slider, p_slider]), report, figure])

    def update(*_):
        result = ransac_sphere(pts, t_slider.value * 1e-3, p=p_slider.value, rng=rng, **ransac_kwargs)
        box.last_result = result
        report.value = _error_html(result, truth) + result._repr_html_()
        figure.value = _png(_explorer_figure(pts, result, truth))

    t_slider.observe(update, names="value")
    p_slider.observe(update, names="value")
    box.threshold_slider, box.p_slider, box.report, box.figure, box.update = t_slider, p_slider, report, figure, update
    update()
    return box


def _error_html(result, truth) -> str:
    if truth is None or not result.found:
        return ""
    truth = np.asarray(truth, dtype=np.float64)
    dc = np.linalg.norm(result.fit.x[:3] - truth[:3]) * 1e3
    dr = (result.fit.x[3] - truth[3]) * 1e3
    return f"<p><b>error vs truth:</b> centre {dc:.3f} mm, radius {dr:+.3f} mm</p>"


def _explorer_figure(pts, result, truth):
    from matplotlib.figure import Figure

    from .plotting.ransac import plot_adaptive_trace, plot_section

    fig = Figure(figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    if result.found:
        spheres, labels = [result.fit.x], ["RANSAC + GHM"]
        if truth is not None:
            spheres, labels = spheres + [truth], labels + ["truth"]
        plot_section(pts, spheres, ax=ax1, labels=labels, inliers=result.inliers)
    else:
        ax1.text(0.5, 0.5, "no sphere found:\n" + result.reason, ha="center", va="center", wrap=True)
        ax1.set_axis_off()
    plot_adaptive_trace(result, ax=ax2)
    fig.tight_layout()
    return fig


def consensus_slices_widget(cube, truth=None):
    """A slider through the slices of a consensus cube (notebook 06).

    Choose the slice orientation (XY, XZ, YZ) and move through the cells along
    the third axis; the colour scale stays that of the whole cube.

    Parameters
    ----------
    cube : labkit.registration.ConsensusCube
    truth : (3,) float, optional
        Known translation, marked in every slice.

    Returns
    -------
    ipywidgets.VBox
        With attributes ``plane`` (ToggleButtons), ``slider`` (IntSlider),
        ``figure`` (Image) and ``update()``.
    """
    import ipywidgets as widgets
    from matplotlib.figure import Figure

    from .plotting.consensus import PLANES, plot_consensus_slice

    plane = widgets.ToggleButtons(options=list(PLANES), value="XY", description="slice")
    slider = widgets.IntSlider(description="cell", continuous_update=False)
    label = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([plane, slider, label]), figure])

    def set_range(*_):
        c = PLANES[plane.value][2]
        slider.max = cube.counts.shape[c] - 1
        slider.value = cube.peak_index[c]

    def update(*_):
        c = PLANES[plane.value][2]
        label.value = f"t{'xyz'[c]} = {cube.axes[c][slider.value]:+.3f} m"
        fig = Figure(figsize=(6, 5))
        plot_consensus_slice(cube, plane.value, slider.value, truth=truth, ax=fig.subplots())
        figure.value = _png(fig)

    plane.observe(set_range, names="value")
    plane.observe(update, names="value")
    slider.observe(update, names="value")
    box.plane, box.slider, box.figure, box.update = plane, slider, figure, update
    set_range()
    update()
    return box
