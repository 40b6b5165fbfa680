"""Figures of ``labkit change``, ``register``, ``tiles`` and the demo: every length axis names its unit.

A top view names its origin (``x - 194490 m``). With ``LABKIT_ARTIFACTS`` set, each figure is also
saved there as a PNG for a person to look at.
"""

import os
import re
from pathlib import Path

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
LENGTH = re.compile(r"^(x|y|z|d[xyz]|t[xyz])\b|distance|shift|residual|increment|lod\b|level of detection|error|"
                    r"height|radius", re.IGNORECASE)
UNIT = re.compile(r"\b(m|mm|cm|deg|arcsec)\b")
MAP = re.compile(r"^[xy] - \d+ \(?m\)?$|^[xy] \(m\)$")


def _labels(fig):
    """(axes, x label, y label) of every visible 2-D axes, colour bars included."""
    return [(ax, ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes if ax.axison and ax.name == "rectilinear"]


def check_figure(fig, name, *, top_view=False, save=True):
    """Every label naming a length carries a unit; a top view names its origin; saved for inspection."""
    artefacts = os.environ.get("LABKIT_ARTIFACTS")
    if artefacts and save:
        Path(artefacts).mkdir(parents=True, exist_ok=True)
        fig.savefig(Path(artefacts) / f"figure_{name}.png", dpi=90)
    missing = [(name, label) for _, xl, yl in _labels(fig) for label in (xl, yl)
               if label and LENGTH.search(label) and not UNIT.search(label)]
    assert missing == []
    if top_view:
        maps = [(xl, yl) for ax, xl, yl in _labels(fig) if ax.get_aspect() == 1.0]
        assert maps and all(MAP.match(xl) and MAP.match(yl) for xl, yl in maps), maps
    colorbars = [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert all(UNIT.search(c) or "(1)" in c or "consensus" in c for c in colorbars), colorbars


def test_the_checker_refuses_a_length_without_unit():
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.set_xlabel("x (local)")
    with pytest.raises(AssertionError):
        check_figure(fig, "bad", save=False)
    plt.close(fig)


@pytest.mark.skipif(not (REAL / "epochs").exists(), reason="data/real not shipped")
def test_change_figure_on_autzen():
    import matplotlib.pyplot as plt

    from labkit import m3c2, m3c2_parameters, read_cloud
    from labkit.plotting.change import plot_change_figure, plot_distance_vs_lod

    a, b = (read_cloud(REAL / "epochs" / f"autzen-bmx-{y}.las") for y in (2010, 2023))
    p = m3c2_parameters(a, b)
    result = m3c2(a, b, normal_radius=p.normal_radius, cylinder_radius=p.cylinder_radius, max_depth=p.max_depth,
                  registration_covariance=np.eye(3) * 0.05**2)
    fig = plot_change_figure(result, "Autzen 2023 - 2010")
    check_figure(fig, "change", top_view=True)
    lod_bar = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"][1]
    hi = lod_bar.get_ylim()[1]
    assert hi <= np.quantile(result.lod[np.isfinite(result.lod)], 0.98) + 1e-9  # robust limits, not the maximum
    plt.close(fig)
    ax = plot_distance_vs_lod(result)
    check_figure(ax.figure, "change_distance_vs_lod")
    plt.close(ax.figure)


@pytest.mark.skipif(not (REAL / "epochs").exists(), reason="data/real not shipped")
def test_register_figure_on_autzen(tmp_path, monkeypatch):
    import labkit.cli.main as cli

    seen = []

    def keep(fig, path):
        seen.append(fig)
        return Path(path)

    monkeypatch.setattr(cli, "save_figure", keep)
    a, b = (str(REAL / "epochs" / f"autzen-bmx-{y}.las") for y in (2023, 2010))
    assert cli.main(["register", a, b, "--out", str(tmp_path), "--quiet"]) == 0
    assert len(seen) == 1
    check_figure(seen[0], "register", top_view=True)


def test_tiles_figure():
    import matplotlib.pyplot as plt

    from labkit.plotting.compare import plot_shift_field
    from labkit.tiles import ShiftField, Tile, TileShift, neighbour_test

    tiles = tuple(TileShift(Tile(r, c, (687000.0 + 100 * c, 6232900.0 + 100 * r, 687100.0 + 100 * c,
                                        6233000.0 + 100 * r)),
                            np.array([0.01 * c, 0.002 * r, 0.0]), np.eye(3) * 1e-6, np.ones(3, bool),
                            900, 950, 800, 1.0, True, 0.1, "ok") for r in range(2) for c in range(3))
    field = ShiftField(tiles, 100.0)
    ax = plot_shift_field(field, test=neighbour_test(field))
    check_figure(ax.figure, "tiles", top_view=True)
    plt.close(ax.figure)


@pytest.mark.slow
def test_demo_sphere_figures(tmp_path, monkeypatch):
    from labkit import demo

    seen = []
    original = demo.save_figure

    def keep(fig, path):
        seen.append((Path(path).stem, fig.axes and [(ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes]))
        check_figure(fig, f"demo_{Path(path).stem.split('.')[1] if '.' in Path(path).stem else Path(path).stem}")
        return original(fig, path)

    monkeypatch.setattr(demo, "save_figure", keep)
    demo._sphere_step(tmp_path, quick=True)
    assert len(seen) >= 3


def test_demo_renders_have_labelled_axes():
    """The 3-D renders of the demo show x, y, z axes with ticks whose titles name the unit and the origin."""
    from labkit import gauss_helmert_model, ransac_sphere
    from labkit.synthetic import sphere_on_tripod
    from labkit.plotting.compare import plot_distance_cloud
    from labkit.plotting.ransac import render_inliers
    from labkit.plotting.sphere import plot_sphere_residuals

    rng = np.random.default_rng(2)
    xyz = rng.uniform(0, 40, (2000, 3)) * [1, 1, 0.2] + [600_000.0, 5_400_000.0, 300.0]
    scene = sphere_on_tripod(n_sphere=300, outlier_ratio=0.5, rng=10)
    found = ransac_sphere(scene.points, 0.003, rng=0)
    fit = gauss_helmert_model(scene.points[found.inliers], sigma=scene.noise)
    renders = {"distance": plot_distance_cloud(xyz, rng.normal(0, 0.05, len(xyz))),
               "inliers": render_inliers(scene.points, found, close_up=6.0),
               "residuals": plot_sphere_residuals(scene.points[found.inliers], fit)}
    assert renders["distance"].renderer.cube_axes_actor.GetXTitle() == "x - 600020 (m)"
    for name, plotter in renders.items():
        axes = plotter.renderer.cube_axes_actor
        titles = [axes.GetXTitle(), axes.GetYTitle(), axes.GetZTitle()]
        assert all(re.fullmatch(r"[xyz]( - \d+| from the centre)? \(m\)", t) for t in titles), (name, titles)
        assert axes.GetVisibility() and plotter.screenshot(return_img=True).std() > 0
        plotter.close()
