"""Interactive explorers for the notebooks (ipywidgets).

Building a widget never displays anything: the notebook shows it by making it
the last expression of a cell. Figures are rendered with matplotlib's Agg
canvas into an ``Image`` widget, so the explorers also build and update in a
headless run (CI), where no front end is attached.
"""

from __future__ import annotations

import io

import numpy as np

from .core.checks import as_rng, choice
from .sphere.ghm import gauss_helmert_model
from .tiles.coherent import CORRECTIONS
from .targets.helmert import helmert
from .plotting.compare import plot_shift_field
from .plotting.consensus import PLANES, plot_consensus_slice
from .plotting.ransac import plot_adaptive_trace, plot_section
from .plotting.registration import plot_correspondences
from .plotting.sphere import plot_confidence_ellipsoid
from .ransac import ransac_sphere
from .tiles import neighbour_test
from .transforms import make_transform, rotation_from_angles

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
    box.add_class("labkit-ransac-explorer")  # a handle for the browser test and for styling

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

    plane = widgets.ToggleButtons(options=list(PLANES), value="XY", description="slice")
    slider = widgets.IntSlider(description="cell", continuous_update=False)
    label = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([plane, slider, label]), figure])
    box.add_class("labkit-consensus-slices")

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


def sphere_cap_points(n=500, cap_deg=60.0, noise=0.001, radius=0.0725, rng=0):
    """Points on a spherical cap seen from +x, with isotropic Gaussian noise (notebook 01).

    The cap holds every surface point whose normal lies within ``cap_deg`` of
    the direction to the station (+x); its area is sampled uniformly. The
    centre is the origin. Returns the (n, 3) points.
    """
    gen = as_rng(rng)
    # uniform on the cap: cos(angle from +x) uniform in [cos(cap), 1]
    c = gen.uniform(np.cos(np.radians(cap_deg)), 1.0, n)
    phi = gen.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1.0 - c**2)
    unit = np.column_stack([c, s * np.cos(phi), s * np.sin(phi)])
    return radius * unit + gen.normal(0.0, noise, (n, 3))


def sphere_cap_explorer(noise=0.001, cap_deg=60.0, n=500, radius=0.0725, rng=0):
    """Sliders for the noise and the visible cap of a scanned sphere (notebook 01).

    Each change simulates ``n`` points on the cap (same seed), adjusts them in
    the Gauss-Helmert model with the true noise as a priori sigma, and shows
    the standard deviations, the centre's 95 % ellipsoid, and a section of the
    cap. A small cap leaves the centre poorly determined along the line of
    sight (x), where centre and radius are correlated.

    Returns
    -------
    ipywidgets.VBox
        With attributes ``noise_slider`` (mm), ``cap_slider`` (deg), ``report``
        (HTML), ``figure`` (Image), ``last_fit`` and ``update()``.
    """
    import ipywidgets as widgets

    noise_slider = widgets.FloatSlider(value=noise * 1e3, min=0.1, max=5.0, step=0.1, description="noise (mm)",
                                       continuous_update=False)
    cap_slider = widgets.FloatSlider(value=cap_deg, min=10.0, max=90.0, step=5.0, description="cap (deg)",
                                     continuous_update=False)
    report = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([noise_slider, cap_slider]), report, figure])
    box.add_class("labkit-cap-explorer")

    def update(*_):
        sigma = noise_slider.value * 1e-3
        pts = sphere_cap_points(n, cap_slider.value, sigma, radius, rng)
        fit = gauss_helmert_model(pts, sigma=sigma)
        box.last_fit = fit
        report.value = _cap_html(fit, cap_slider.value)
        figure.value = _png(_cap_figure(pts, fit, radius))

    noise_slider.observe(update, names="value")
    cap_slider.observe(update, names="value")
    box.noise_slider, box.cap_slider, box.report, box.figure, box.update = (noise_slider, cap_slider, report,
                                                                           figure, update)
    update()
    return box


def _cap_html(fit, cap_deg):
    std = fit.std * 1e3
    axes = fit.confidence_ellipsoid(0.95).semi_axes * 1e3
    return (f"<p><b>cap {cap_deg:.0f} deg, {fit.n} points:</b> std x<sub>c</sub>, y<sub>c</sub>, z<sub>c</sub>, r = "
            + ", ".join(f"{s:.3f}" for s in std) + " mm; 95 % ellipsoid semi-axes "
            + ", ".join(f"{a:.3f}" for a in axes) + f" mm; correlation r-x<sub>c</sub> "
            f"{fit.Sigma_xx[0, 3] / (fit.std[0] * fit.std[3]):+.2f}</p>")


def _cap_figure(pts, fit, radius):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 3.6), layout="constrained")
    ax0, *axes = fig.subplots(1, 4)
    near = np.abs(pts[:, 2]) < 0.2 * radius
    t = np.linspace(0, 2 * np.pi, 200)
    ax0.plot(radius * np.cos(t) * 1e3, radius * np.sin(t) * 1e3, color="0.6", lw=1, label="true sphere")
    ax0.plot(pts[near, 0] * 1e3, pts[near, 1] * 1e3, ".", ms=3, label="points |z| < 0.2 r")
    ax0.plot(80, 0, ">", color="k", ms=8, label="to the station")
    ax0.set_aspect("equal")
    ax0.set_xlabel("x [mm]")
    ax0.set_ylabel("y [mm]")
    ax0.legend(fontsize=7, loc="lower left")
    ax0.set_title("section z = 0")
    plot_confidence_ellipsoid(fit, level=0.95, truth=np.zeros(3), axes=axes)
    return fig


def normals_k_explorer(points, true_normals=None, k=20, k_max=80):
    """A slider for the neighbourhood size k of the PCA normals and local noise (notebook 04).

    Each change recomputes :func:`labkit.local_pca` with the new k and shows
    the local noise (eq. 5) and, when ``true_normals`` are given, the angle
    error of the normals. Small k: noisy normals; large k: smoothed across
    edges and curvature.

    Returns
    -------
    ipywidgets.VBox
        With attributes ``k_slider``, ``report`` (HTML), ``figure`` (Image),
        ``last_pca`` and ``update()``.
    """
    import ipywidgets as widgets

    from .features import local_pca

    pts = np.asarray(points, dtype=np.float64)
    truth = None if true_normals is None else np.asarray(true_normals, dtype=np.float64)
    k_slider = widgets.IntSlider(value=k, min=4, max=k_max, step=1, description="k", continuous_update=False)
    report = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([k_slider, report, figure])
    box.add_class("labkit-k-explorer")

    def update(*_):
        pca = local_pca(pts, k=k_slider.value)
        box.last_pca = pca
        err = None if truth is None else np.degrees(np.arccos(np.clip(np.abs(np.sum(pca.normals * truth, axis=1)), 0, 1)))
        report.value = (f"<p><b>k = {k_slider.value}:</b> median local noise {np.median(pca.noise) * 1e3:.2f} mm"
                        + ("" if err is None else f"; normal error median {np.median(err):.2f} deg, "
                           f"95 % {np.percentile(err, 95):.2f} deg") + "</p>")
        figure.value = _png(_k_figure(pca, err, k_slider.value))

    k_slider.observe(update, names="value")
    box.k_slider, box.report, box.figure, box.update = k_slider, report, figure, update
    update()
    return box


def _k_figure(pca, err, k):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.4), layout="constrained")
    axes = fig.subplots(1, 2 if err is not None else 1, squeeze=False)[0]
    axes[0].hist(pca.noise * 1e3, bins=60, color="#1b9e77")
    axes[0].set_xlabel("local noise along the normal (mm)")
    axes[0].set_ylabel("points")
    axes[0].set_title(f"local noise, k = {k}")
    if err is not None:
        axes[1].hist(err, bins=np.linspace(0, max(5.0, np.percentile(err, 99)), 60), color="#7570b3")
        axes[1].set_xlabel("angle error of the normal (deg)")
        axes[1].set_title(f"normal error, k = {k}")
    return fig


_ALPHA_OPTIONS = (0.001, 0.01, 0.05, 0.1, 0.2)


def neighbour_test_explorer(field, alpha=0.05, extra_std=0.0, max_extra_mm=20.0, correction="holm"):
    """Sliders for the significance level and the extra standard deviation of the neighbour test (notebook 08).

    Each change reruns :func:`labkit.neighbour_test` on ``field`` and redraws
    the shift field with the disagreeing borders and the coherent areas. A
    smaller alpha or a larger extra standard deviation accepts more pairs; the
    ``correction`` menu (holm, fdr, none) chooses the control of the many tests.

    Returns
    -------
    ipywidgets.VBox
        With attributes ``alpha_slider``, ``extra_slider`` (mm), ``correction_menu``,
        ``report`` (HTML), ``figure`` (Image), ``last_test`` and ``update()``.
    """
    import ipywidgets as widgets

    a0 = min(_ALPHA_OPTIONS, key=lambda v: abs(np.log(v) - np.log(alpha)))
    alpha_slider = widgets.SelectionSlider(options=_ALPHA_OPTIONS, value=a0, description="alpha",
                                           continuous_update=False)
    extra_slider = widgets.FloatSlider(value=extra_std * 1e3, min=0.0, max=max_extra_mm, step=0.5,
                                       description="s_e (mm)", continuous_update=False)
    correction_menu = widgets.Dropdown(options=CORRECTIONS, value=choice(correction, CORRECTIONS, "correction"),
                                       description="correction")
    report = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([alpha_slider, extra_slider, correction_menu]), report, figure])
    box.add_class("labkit-neighbour-explorer")

    def update(*_):
        test = neighbour_test(field, alpha_slider.value, extra_std=extra_slider.value * 1e-3,
                              correction=correction_menu.value)
        box.last_test = test
        report.value = (f"<p><b>alpha = {alpha_slider.value:g}, s<sub>e</sub> = {extra_slider.value:.1f} mm:</b> "
                        f"{int((~test.agree).sum())} of {len(test.agree)} neighbour pairs disagree; "
                        f"{test.n_areas} coherent area(s)</p>")
        figure.value = _png(_field_figure(field, test))

    alpha_slider.observe(update, names="value")
    extra_slider.observe(update, names="value")
    correction_menu.observe(update, names="value")
    box.alpha_slider, box.extra_slider, box.report, box.figure, box.update = (alpha_slider, extra_slider, report,
                                                                             figure, update)
    box.correction_menu = correction_menu
    update()
    return box


def _field_figure(field, test):
    from matplotlib.figure import Figure


    fig = Figure(figsize=(7, 5.5), layout="constrained")
    plot_shift_field(field, test=test, ax=fig.subplots())
    return fig


def matching_gates_explorer(source, target, max_distance=1.0, max_angle_deg=30.0, max_noise=None, truth=None,
                            run_icp=True, icp_kwargs=None, **match_kwargs):
    """Sliders for the matching gates of ICP (notebook 05, eq. 5.5).

    Each change calls :func:`labkit.match` with the distance gate ``max_distance``
    (eq. 5.1), the normal-angle gate ``max_angle_deg`` and the local-noise gate
    ``max_noise``, shows how many pairs each rule rejects (map in XY and XZ), and,
    with ``run_icp``, registers with :func:`labkit.icp` under the same gates and
    reports the shift (and its error against ``truth``, the true translation).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
    max_distance : float
        Initial distance gate in metres (slider 0.1 .. 3 m).
    max_angle_deg : float or None
        Initial normal-angle gate in degrees; 90 (or None) switches it off.
    max_noise : float or None
        Initial local-noise gate in metres; 0 (or None) switches it off.
    truth : array_like (3,), optional
        True translation, to report the error of the ICP shift.
    run_icp : bool
        Also run ICP with the gates (a second or so per change on 5000 pairs).
    icp_kwargs : dict, optional
        Further options of :func:`labkit.icp` only (e.g. ``reject_sigma=None``).
    **match_kwargs
        Passed to both :func:`labkit.match` and :func:`labkit.icp` (e.g. ``sample``, ``rng``).

    Returns
    -------
    ipywidgets.VBox
        With attributes ``distance_slider`` (m), ``angle_slider`` (deg),
        ``noise_slider`` (cm), ``report`` (HTML), ``figure`` (Image),
        ``last_match``, ``last_icp`` (None without ``run_icp``), ``gates()`` and ``update()``.
    """
    import ipywidgets as widgets

    from .registration import icp, match

    d_slider = widgets.FloatSlider(value=float(max_distance), min=0.1, max=3.0, step=0.1, description="d_max (m)",
                                   continuous_update=False)
    a_slider = widgets.FloatSlider(value=90.0 if max_angle_deg is None else float(max_angle_deg), min=5.0, max=90.0,
                                   step=5.0, description="angle (deg)", continuous_update=False)
    n_slider = widgets.FloatSlider(value=0.0 if max_noise is None else float(max_noise) * 100, min=0.0, max=20.0,
                                   step=0.5, description="noise (cm)", continuous_update=False)
    report = widgets.HTML()
    figure = widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([d_slider, a_slider, n_slider]), report, figure])
    box.add_class("labkit-gates-explorer")

    def gates():
        """The current slider values as keyword arguments of match/icp (90 deg and 0 cm: gate off)."""
        return dict(max_distance=d_slider.value,
                    max_angle_deg=None if a_slider.value >= 90.0 else a_slider.value,
                    max_noise=None if n_slider.value <= 0.0 else n_slider.value / 100)

    def update(*_):
        kw = {**match_kwargs, **gates()}
        corr = match(source, target, **kw)
        result = icp(source, target, **kw, **(icp_kwargs or {})) if run_icp else None
        box.last_match, box.last_icp = corr, result
        report.value = _gates_html(corr, result, truth, kw)
        figure.value = _png(_gates_figure(corr))

    for s in (d_slider, a_slider, n_slider):
        s.observe(update, names="value")
    box.distance_slider, box.angle_slider, box.noise_slider = d_slider, a_slider, n_slider
    box.report, box.figure, box.gates, box.update = report, figure, gates, update
    update()
    return box


def _gates_html(corr, result, truth, kw):
    from .registration.matching.match import RULES

    counts = np.bincount(corr.rule, minlength=len(RULES))
    rows = "".join(f"<td>{RULES[c]}: {counts[c]}</td>" for c in range(len(RULES)) if counts[c])
    off = [k for k in ("max_angle_deg", "max_noise") if kw[k] is None]
    text = (f"<p><b>{corr.n_accepted} of {len(corr)} pairs accepted</b> (d_max {kw['max_distance']:.1f} m"
            + (f"; off: {', '.join(off)}" if off else "") + ")</p><table><tr>" + rows + "</tr></table>")
    if result is not None:
        t = np.asarray(result.translation) * 1e3
        text += "<p>ICP shift (mm): " + ", ".join(f"{v:+.1f}" for v in t)
        if truth is not None:
            e = t - np.asarray(truth, dtype=np.float64) * 1e3
            text += "; error vs truth (mm): " + ", ".join(f"{v:+.1f}" for v in e)
        text += f"; {result.iterations} iterations</p>"
    return text


def _gates_figure(corr):
    from matplotlib.figure import Figure


    fig = Figure(figsize=(12, 4.6), layout="constrained")
    ax0, ax1 = fig.subplots(1, 2)
    plot_correspondences(corr, ax=ax0, view="xy")
    plot_correspondences(corr, ax=ax1, view="xz")
    ax1.set_aspect("auto")
    ax0.set_title("pairs by the rule that rejected them (XY)")
    ax1.set_title("the same, side view (XZ)")
    return fig


def target_line_points(n=4, offset=1.0, length=20.0, rng=0):
    """``n`` target centres along a ``length`` m line (x) with lateral offsets of about ``offset`` m (y, z).

    ``offset=0`` puts them exactly on the line. The offsets alternate in sign with random sizes (seeded).

    Examples
    --------
    >>> from labkit.widgets import target_line_points
    >>> (target_line_points(3, 0.0)[:, 1:] + 0.0).tolist()
    [[0.0, 1.5], [0.0, 1.5], [0.0, 1.5]]
    """
    gen = as_rng(rng)
    x = np.linspace(-length / 2, length / 2, n)
    side = np.where(np.arange(n) % 2 == 0, 1.0, -1.0) * gen.uniform(0.5, 1.0, n)
    return np.column_stack([x, offset * side, 1.5 + 0.3 * offset * gen.uniform(-1, 1, n)])


def target_geometry_explorer(n_targets=4, offset=1.0, noise=0.001, rng=0):
    """Sliders for the number of targets and their offset from a line: what the transformation can determine.

    Each change simulates the targets (:func:`target_line_points`) in two scans related by a known rigid
    transformation, with ``noise`` (m) on every centre, adjusts :func:`labkit.helmert` and shows the standard
    deviations, or the directions it cannot determine (two targets, or targets on one line).

    Returns
    -------
    ipywidgets.VBox
        With ``n_slider``, ``offset_slider``, ``report`` (HTML), ``figure`` (Image), ``last_fit``, ``update()``.
    """
    import ipywidgets as widgets

    n_slider = widgets.IntSlider(value=n_targets, min=2, max=8, description="targets", continuous_update=False)
    offset_slider = widgets.FloatSlider(value=offset, min=0.0, max=5.0, step=0.05, description="offset (m)",
                                        continuous_update=False)
    report, figure = widgets.HTML(), widgets.Image(format="png")
    box = widgets.VBox([widgets.HBox([n_slider, offset_slider]), report, figure])
    T = make_transform(rotation_from_angles(0.01, -0.02, 0.8), [3.0, -1.0, 0.2])

    def update(*_):
        gen = as_rng(rng)
        p = target_line_points(n_slider.value, offset_slider.value, rng=rng)
        q = p @ T[:3, :3].T + T[:3, 3] + gen.normal(0, noise, p.shape)
        fit = helmert(p + gen.normal(0, noise, p.shape), q, source_cov=noise, target_cov=noise)
        box.last_fit = fit
        report.value = _geometry_html(fit)
        figure.value = _png(_geometry_figure(p))

    n_slider.observe(update, names="value")
    offset_slider.observe(update, names="value")
    box.n_slider, box.offset_slider, box.report, box.figure, box.update = n_slider, offset_slider, report, figure, update
    update()
    return box


def _geometry_html(fit):
    if fit.undetermined:
        return "<p><b>Not determined:</b> " + "; ".join(fit.undetermined) + "</p>"
    sd = fit.std
    return ("<p>std rx, ry, rz = " + ", ".join(f"{np.degrees(v) * 3600:.1f}" for v in sd[:3])
            + " arcsec; tx, ty, tz = " + ", ".join(f"{v * 1e3:.2f}" for v in sd[3:6]) + " mm</p>")


def _geometry_figure(p):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 2.6), layout="constrained")
    ax = fig.subplots()
    ax.axhline(0.0, color="0.7", lw=1)
    ax.plot(p[:, 0], p[:, 1], "o", ms=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("offset y (m)")
    ax.set_ylim(-6, 6)
    return fig
