"""The notebook explorers (labkit.widgets) and the consensus plot helpers, headless.

Each explorer is checked against the plain labkit call it wraps (an independent route to the same numbers),
and a slider change must change what it shows. The browser side is in tests/test_browser.py.
"""

from __future__ import annotations

import numpy as np
import pytest

import labkit
from labkit.plotting.consensus import describe_peak, plot_consensus_slice

pytest.importorskip("ipywidgets")
from labkit import widgets  # noqa: E402


def test_sphere_cap_points_lie_on_the_requested_cap():
    pts = widgets.sphere_cap_points(n=4000, cap_deg=30.0, noise=0.0, radius=0.1, rng=3)
    r = np.linalg.norm(pts, axis=1)
    assert np.allclose(r, 0.1)
    angle = np.degrees(np.arccos(pts[:, 0] / r))
    assert angle.max() <= 30.0 + 1e-9 and angle.max() > 29.0
    # uniform over the cap's area: cos(angle) uniform in [cos 30, 1], mean at the midpoint
    assert abs(np.mean(np.cos(np.radians(angle))) - (1 + np.cos(np.radians(30))) / 2) < 0.005


def test_sphere_cap_explorer_std_matches_monte_carlo():
    box = widgets.sphere_cap_explorer(noise=0.001, cap_deg=40.0, n=300, rng=0)
    stated = box.last_fit.std
    xs = [labkit.gauss_helmert_model(widgets.sphere_cap_points(300, 40.0, 0.001, rng=s), sigma=0.001).x
          for s in range(1, 201)]
    ratio = stated / np.std(xs, axis=0, ddof=1)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio


def test_sphere_cap_explorer_small_cap_widens_the_line_of_sight():
    box = widgets.sphere_cap_explorer(noise=0.001, cap_deg=80.0, n=400, rng=1)
    wide, img = box.last_fit.std.copy(), box.figure.value
    box.cap_slider.value = 20.0
    narrow = box.last_fit.std
    assert narrow[0] > 3 * wide[0]          # x: the line of sight
    assert box.figure.value != img and "cap 20 deg" in box.report.value


def test_normals_k_explorer_equals_local_pca():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 10, (3000, 2))
    pts = np.column_stack([xy, rng.normal(0, 0.01, 3000)])
    box = widgets.normals_k_explorer(pts, np.tile([0.0, 0.0, 1.0], (3000, 1)), k=12)
    box.k_slider.value = 30
    direct = labkit.local_pca(pts, k=30)
    assert np.allclose(box.last_pca.noise, direct.noise)
    assert f"{np.median(direct.noise) * 1e3:.2f} mm" in box.report.value


def test_neighbour_test_explorer_follows_the_sliders():
    field = _small_field()
    box = widgets.neighbour_test_explorer(field, alpha=0.05, extra_std=0.0)
    strict = int((~box.last_test.agree).sum())
    assert strict == int((~labkit.neighbour_test(field, 0.05).agree).sum())
    box.extra_slider.value = 20.0
    loose = int((~box.last_test.agree).sum())
    assert loose <= strict and box.last_test.extra_std == pytest.approx(0.02)
    box.correction_menu.value = "none"
    assert box.last_test.correction == "none"
    assert int((~box.last_test.agree).sum()) == int((~labkit.neighbour_test(field, box.alpha_slider.value,
                                                                         extra_std=0.02, correction="none").agree).sum())


def _small_field():
    from labkit.synthetic import als_epochs

    pair = als_epochs("xyz", size=(60.0, 40.0), density=2.0, rng=5)
    method = labkit.registration.compare.standard_methods(["icp-classes"])["icp-classes"]
    return labkit.register_tiles(pair.source, pair.target, method, size=20.0)


class _Peak:
    def __init__(self, kind, directions, free):
        self.kind, self.directions, self.free = kind, np.asarray(directions, float), np.asarray(free)


def test_describe_peak_in_words():
    assert describe_peak(_Peak("point", np.eye(3), [False] * 3)) == "point: all three directions determined"
    assert describe_peak(_Peak("ridge", np.eye(3)[:, [0, 2, 1]], [False, False, True])) == "ridge: free along ty"
    tilted = np.array([np.cos(np.radians(5)), np.sin(np.radians(5)), 0.0])
    d = np.column_stack([[0, 0, 1.0], [0, 1.0, 0], tilted])
    assert describe_peak(_Peak("ridge", d, [False, False, True])) == "ridge: free along tx (within 5 deg)"
    plane = np.column_stack([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]])
    assert describe_peak(_Peak("plane", plane, [False, True, True])) == "plane: free in the plane normal to tz"
    oblique = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    text = describe_peak(_Peak("ridge", np.column_stack([[0, 0, 1.0], [-oblique[1], oblique[0], 0], oblique]),
                               [False, False, True]))
    assert "azimuth 45 deg, elevation 0 deg" in text


def test_slice_marks_a_projected_truth():
    import matplotlib.pyplot as plt
    from labkit.synthetic import als_epochs

    pair = als_epochs("xyz", size=(20.0, 20.0), density=4.0, rng=2)
    cube = labkit.consensus_cube(pair.source, pair.target, extent=0.3, step=0.03)
    truth = pair.truth[:3, 3]
    k_truth = int(np.argmin(np.abs(cube.axes[2] - truth[2])))
    far = (k_truth + 5) % len(cube.axes[2])
    ax = plot_consensus_slice(cube, "XY", far, truth=truth)
    labels = ax.get_legend_handles_labels()[1]
    assert any(lab.startswith("truth, projected") for lab in labels), labels
    off = truth[2] - cube.axes[2][far]
    assert any(f"{off * 100:+.1f} cm in tz" in lab for lab in labels)
    ax2 = plot_consensus_slice(cube, "XY", k_truth, truth=truth)
    assert "truth" in ax2.get_legend_handles_labels()[1]
    plt.close("all")


def test_matching_gates_explorer_equals_match_and_icp():
    from labkit.synthetic import als_epochs

    pair = als_epochs("trees_felled", size=(30.0, 30.0), density=4.0, rng=3)
    kw = dict(sample=("normal_space", 1500), rng=0)
    box = widgets.matching_gates_explorer(pair.source, pair.target, max_distance=2.0, max_angle_deg=None,
                                          truth=pair.translation, icp_kwargs=dict(reject_sigma=None), **kw)
    loose = labkit.match(pair.source, pair.target, max_distance=2.0, max_angle_deg=None, **kw)
    assert np.array_equal(box.last_match.rule, loose.rule)
    direct = labkit.icp(pair.source, pair.target, max_distance=2.0, max_angle_deg=None, reject_sigma=None, **kw)
    assert np.allclose(box.last_icp.translation, direct.translation)
    img, n_loose = box.figure.value, box.last_match.n_accepted
    # a tight distance gate and a noise gate reject more pairs, each under its own rule
    box.distance_slider.value = 0.3
    box.noise_slider.value = 5.0
    tight = labkit.match(pair.source, pair.target, max_distance=0.3, max_angle_deg=None, max_noise=0.05, **kw)
    assert box.gates() == dict(max_distance=0.3, max_angle_deg=None, max_noise=0.05)
    assert np.array_equal(box.last_match.rule, tight.rule)
    assert box.last_match.n_accepted < n_loose and box.figure.value != img
    assert f"{tight.n_accepted} of {len(tight)} pairs accepted" in box.report.value


def test_target_geometry_explorer_names_what_two_or_collinear_targets_leave_open():
    from labkit.widgets import target_geometry_explorer, target_line_points

    box = target_geometry_explorer(n_targets=4, offset=2.0)
    assert box.last_fit.undetermined == () and "arcsec" in box.report.value
    spread = box.last_fit.std[0]
    box.offset_slider.value = 0.2  # closer to the line: the rotation about it is weaker
    assert box.last_fit.std[0] > 5 * spread
    box.n_slider.value = 2
    assert "rotation about the line" in box.report.value and np.isinf(box.last_fit.std[0])
    assert np.allclose(target_line_points(4, 0.0)[:, 1], 0.0)
