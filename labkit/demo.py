"""``labkit demo``: the main job on built-in synthetic data.

Three steps, each printing a summary and writing its figures into the output
folder: (a) a sphere target on a tripod found by RANSAC and adjusted in the
Gauss-Helmert model; (b) registration of three synthetic ALS regions (stable,
with a change, ALS against dense image matching) by ICP and by maximum
consensus; (c) the comparison of those transformations with the truth.
"""

from __future__ import annotations

import time
from functools import partial
from pathlib import Path

import numpy as np

from .core.outputs import save_figure, save_render, staged_folder, staged_outputs
from .sphere.ghm import gauss_helmert_model
from .registration.compare import compare_methods, standard_methods, synthetic_cases
from .change.distances import point_to_plane_distance
from .core.errors import LabkitError
from .notebook import setup_headless
from .plotting import compare as PC
from .plotting import ransac as PR
from .plotting import screenshot
from .plotting import sphere as PS
from .plotting.compare import plot_distance_cloud
from .ransac import ransac_sphere
from .synthetic import sphere_on_tripod

SEED = 2026
# (region, case): a stable village, a village with a demolished building, halls seen by image matching
REGIONS = (("xyz", "als-als"), ("demolished", "changes"), ("xz", "als-dim"))
METHODS = ("icp", "icp-tukey", "consensus")


def _steps():
    """The demo steps in order: (title, callable(out_dir, quick) -> list of written files)."""
    shared: dict = {}  # registration results, handed from step (b) to the comparison (c)
    return [
        ("Sphere target on a tripod: RANSAC, then the Gauss-Helmert adjustment", _sphere_step),
        ("Registration of three ALS regions: ICP and maximum consensus", partial(_registration_step, shared=shared)),
        ("Comparison with the true transformations", partial(_comparison_step, shared=shared)),
    ]


def run_demo(out_dir: Path, quick: bool = False) -> list[Path]:
    """Run every demo step; return the paths of the figures written.

    The figures are written into a staging folder and moved into ``out_dir``
    together at the end: a step that fails leaves nothing new behind.

    Examples
    --------
    The whole demo takes a minute (``tests/test_demo.py`` runs it), so it is not run here:

    >>> from labkit.demo import run_demo
    >>> files = run_demo("labkit-demo", quick=True)  # doctest: +SKIP
    """
    setup_headless()
    out_dir = Path(out_dir)
    names: list[str] = []
    start = time.perf_counter()
    with staged_folder(out_dir) as work:
        for title, step in _steps():
            print(f"\n### {title}\n")
            t0 = time.perf_counter()
            names += [Path(p).name for p in step(work, quick)]
            print(f"({title}: {time.perf_counter() - t0:.1f} s)")
    written = [out_dir / name for name in names]
    print(f"\nDemo finished in {time.perf_counter() - start:.1f} s. Files written to {out_dir.resolve()}:")
    for path in written:
        print(f"  {path.name}")
    return written


# --------------------------------------------------------------------------- (a) sphere
def _sphere_step(out: Path, quick: bool) -> list[Path]:
    # A TLS scan in UTM-sized coordinates with 1 mm noise per coordinate
    scene = sphere_on_tripod(n_sphere=600 if quick else 2000, noise=0.001, utm=True, rng=SEED)
    print(f"Scene: {scene.n} points, {scene.outlier_ratio:.0%} of them not on the sphere "
          f"(tripod legs, base plate, ground, clutter); true radius {1000 * scene.sphere[3]:.1f} mm")
    # Detection: RANSAC with t = 3 sigma, radii of common targets
    found = ransac_sphere(scene.points, 0.003, rng=SEED, radius_range=(0.05, 0.10))
    print()
    print(found.summary())
    if not found.found:
        print("No sphere found; the adjustment is skipped.")
        return []
    hit = found.inliers & scene.is_sphere
    print(f"\nInliers on the true sphere: {hit.sum()} of {found.n_inliers} "
          f"(the scan has {scene.is_sphere.sum()} sphere points; the others touch the sphere at the adapter)")
    # Adjustment: Gauss-Helmert model on the inliers with the known a priori sigma of the scanner
    pts = scene.points[found.inliers]
    fit = gauss_helmert_model(pts, sigma=scene.noise)
    print()
    print(fit.summary())
    err, std = (fit.x - scene.sphere) * 1000, fit.std * 1000
    print("\nAgainst the truth: centre error [" + ", ".join(f"{e:+.3f}" for e in err[:3])
          + f"] mm, radius error {err[3]:+.3f} mm; |error| / std = "
          + ", ".join(f"{abs(e) / s:.1f}" for e, s in zip(err, std)))

    files = []
    fig_ax = PR.plot_adaptive_trace(found)
    files.append(_save(fig_ax.figure, out / "sphere_ransac_trace.png"))
    files.append(_save(PR.render_inliers(scene.points, found, close_up=6.0), out / "sphere_ransac_inliers.png"))
    files.append(_save(PS.plot_convergence(fit).figure, out / "sphere_convergence.png"))
    files.append(_save(PS.plot_residuals(fit)[0].figure, out / "sphere_residuals.png"))
    files.append(_save(PS.plot_confidence_ellipsoid(fit, truth=scene.sphere)[0].figure, out / "sphere_ellipsoid.png"))
    files.append(_save(PS.plot_sphere_residuals(pts, fit, view_from=scene.station), out / "sphere_residuals_3d.png"))
    return files


# --------------------------------------------------------------------------- (b) registration
def _registration_step(out: Path, quick: bool, shared: dict) -> list[Path]:
    from .features import normals  # (numba: loaded when needed)

    size, density = ((30.0, 30.0), 4.0) if quick else ((60.0, 60.0), 8.0)
    pairs = {}
    for region, case in REGIONS:
        pairs.update(synthetic_cases([region], [case], size=size, density=density, dim_density=2 * density,
                                     rng=SEED))
    methods = standard_methods(METHODS, dof="translation", extent=1.0, max_points=800 if quick else 2000, rng=SEED)
    results = {}
    files = []
    for (region, case), pair in pairs.items():
        axes = "".join(a for a, c in zip("XYZ", pair.constrained) if c)
        print(f"{region} ({case}): source {pair.source.name} {len(pair.source)} points, target "
              f"{pair.target.name} {len(pair.target)} points; constrained axes {axes}; true shift "
              "[" + ", ".join(f"{v:+.3f}" for v in pair.translation) + "] m")
        nrm = normals(pair.target, k=10)
        dists = {"before": _distances(pair, None, nrm)}
        for name, method in methods.items():
            try:
                res = method(pair.source, pair.target)
            except LabkitError as exc:
                print(f"  {name:10s} failed: {exc}")
                results[(id(pair.source), name)] = exc
                continue
            results[(id(pair.source), name)] = res
            dists[name] = _distances(pair, res, nrm)
            print("  " + _result_line(name, res, pair.translation, dists["before"], dists[name]))
        files.append(_distance_panels(pair, dists, out / f"registration_{region}_{case}.png"))
        print()
    shared.update(pairs=pairs, results=results)
    return files


def _distances(pair, result, nrm) -> np.ndarray:
    return point_to_plane_distance(pair.source, pair.target, nrm, transform=None if result is None else result)


def _result_line(name, res, truth, before, after) -> str:
    err = (np.asarray(res.translation) - truth) * 1000
    std = np.asarray(res.translation_std) * 1000
    und = "" if res.degeneracy is None or not res.degeneracy.undetermined_axes else \
        f"; undetermined {''.join(res.degeneracy.undetermined_axes)}"
    med_before, med_after = (1000 * np.nanmedian(np.abs(d)) for d in (before, after))  # NaN: no usable normal
    return (f"{name:10s} shift [" + ", ".join(f"{v:+.4f}" for v in res.translation) + "] m, std ["
            + ", ".join(f"{s:.1f}" for s in std) + "] mm, error [" + ", ".join(f"{e:+.1f}" for e in err)
            + f"] mm; median |d| {med_before:.0f} -> {med_after:.0f} mm; {res.runtime_s:.2f} s{und}")


def _distance_panels(pair, dists, path: Path) -> Path:
    """The source coloured by its point-to-plane distance: before and after each method (pyvista renders)."""
    import matplotlib.pyplot as plt

    a = max(2.5 * float(np.nanmedian(np.abs(dists["before"]))), 0.05)
    ncols = 2 if len(dists) > 2 else len(dists)
    nrows = -(-len(dists) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6.0 * ncols, 4.6 * nrows), layout="constrained", squeeze=False)
    for ax in axes.flat[len(dists):]:
        ax.set_axis_off()
    for ax, (label, d) in zip(axes.flat, dists.items()):
        p = plot_distance_cloud(pair.source, d, clim=(-a, a), title="distance (m)")
        p.camera.zoom(1.1)  # (the labelled axes stay in view)
        ax.imshow(screenshot(p))
        p.close()
        ax.set_axis_off()
        ax.set_title(f"{label}: median |d| {1000 * np.nanmedian(np.abs(d)):.0f} mm")
    fig.suptitle(f"{pair.region} ({pair.source.name} -> {pair.target.name}): point-to-plane distance, "
                 f"colours clipped at +-{a:.2f} m")
    return _save(fig, path)


# --------------------------------------------------------------------------- (c) comparison
def _comparison_step(out: Path, quick: bool, shared: dict) -> list[Path]:
    if not shared:
        print("No registration results to compare.")
        return []
    pairs, results = shared["pairs"], shared["results"]
    # The methods of step (b), replayed from their results (runtimes are the measured ones)
    replay = {name: partial(_replay, results=results, name=name) for name in METHODS}
    table = compare_methods(pairs, replay)
    print(table.summary())
    print()
    print(table.text())
    print("\nError on the constrained axes (mm):")
    print(table.pivot())
    with staged_outputs(out) as stage:  # (staged: the final file gets the usual permissions)
        table.to_csv(stage("comparison.csv"))
    files = list(stage.written)
    region, case = REGIONS[1]
    rows = table.select(region=region, case=case).rows
    files.append(_save(PC.plot_transformation_components(rows)[0].figure, out / "comparison_components.png"))
    files.append(_save(PC.plot_transformation_arrows(rows, exaggerate=20).figure, out / "comparison_arrows.png"))
    files.append(_save(PC.plot_error_overview(table).figure, out / "comparison_errors.png"))
    return files


def _replay(source, target, *, results, name):
    res = results[(id(source), name)]
    if isinstance(res, Exception):
        raise res
    return res


# --------------------------------------------------------------------------- output
def _save(figure_or_plotter, path: Path) -> Path:
    """Write a matplotlib figure or a pyvista plotter to ``path`` atomically and close it."""
    save = save_render if hasattr(figure_or_plotter, "screenshot") else save_figure
    with staged_outputs(path.parent) as stage:
        save(figure_or_plotter, stage(path.name))
    return path
