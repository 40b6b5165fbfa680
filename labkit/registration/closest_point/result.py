"""The result of ICP: covariance, message and the consistency test between groups (eq. 5.11-5.17)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...core.masks import STABLE_CLASSES
from ...core.order import median
from ...core.threads import side_by_side
from .adjustment import NAMES, design
from .covariance import block_cells
from ..consistency import cell_labels, family_level, group_consistency, normal_equations
from ..result import RegistrationResult

#: Groups of the consistency test by the classes (ASPRS) of a correspondence's two points, in order of
#: precedence (vegetation at either end makes it 'vegetation'); the rest is 'other'.
CLASS_GROUPS = (("vegetation", (3, 4, 5)), ("buildings", (6,)), ("ground/road", (2, 11)))


def icp_result(R, t, origin, adj, history, converged, matcher, opts, runtime):
    deg = adj.degeneracy
    cov = adj.sigma0**2 * adj.Qxx  # (eq. 5.11)
    cell = xy = None  # the block cells of the final pairs (eq. 5.13), shared by the covariance and the group test
    if adj.block_cov is not None or opts.consistency_alpha is not None:
        rows = np.flatnonzero(adj.corr.accepted)
        xy = np.take(adj.corr.source_xyz, rows, axis=0)[:, :2] - opts.origin[:2]  # (by index: faster than the mask)
        cell = cell_labels(block_cells(xy, opts.block_size))
    # the group test and the block covariance (independent) side by side; the test's groupings too
    test, block = side_by_side(
        (lambda: None if opts.consistency_alpha is None else consistency_test(adj, matcher, opts, cell, xy),),
        (lambda: None if adj.block_cov is None else adj.block_cov(cell),),
    )
    if block is not None and np.isfinite(np.diag(block)).any():
        cov = block  # (eq. 5.13)
    cov = cov + adj.held_cov  # prior of held rotations (eq. 5.15); inf stays inf
    cov = resolution_floor(cov, adj)
    undetermined = deg.undetermined_axes
    msg = "converged" if converged else f"not converged after {len(history)} iterations (last step {history[-1].step:.2e} m)"
    if undetermined:
        msg += (
            f"; UNDETERMINED: {', '.join(undetermined)} - the data do not constrain these components, "
            "they are held (at their initial value, or where the iteration was when a held shift's prior "
            "left them too imprecise) and their standard deviation is inf"
        )
    rotations = [n for n in deg.undetermined_parameters if n.startswith("r")]
    if rotations:
        msg += (
            f"; rotations {', '.join(rotations)} undetermined (held at their initial value, see the degeneracy "
            "report): the other parameters are conditional on that value"
            + (
                f", their covariance includes a prior std of {np.degrees(opts.held_rotation_std):g} deg for it"
                if opts.held_rotation_std > 0
                else " and so is their covariance (held_rotation_std_deg=0)"
            )
        )
    elif not deg.well_posed:
        msg += "; some directions are weak (see the degeneracy report)"
    if opts.metric == "point_to_point" and (undetermined or not converged):
        msg += (
            "; point_to_point: the offsets between the two samplings along the surface carry no "
            "information about the shift (only the components along the normals do), consider "
            "metric='point_to_plane'"
        )
    if test is not None and not test.agree:  # the groups' spread enters the stated precision (eq. 5.17)
        free = deg.parameter_determined
        S = np.where([n.startswith("r") for n in NAMES[opts.dof]], opts.L, 1.0)[free]
        before = translation_std(cov, opts)
        cov = cov.copy()
        cov[np.ix_(free, free)] += test.between / np.outer(S, S)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(np.isfinite(before), translation_std(cov, opts) / before, 1.0)
        test = replace(test, std_ratio=ratio)
        msg += "; " + disagreement_text(test, matcher.options["classes"])
    n_used = adj.corr.n_accepted
    if len(adj.corr) < adj.corr.n_source:  # the shift from a sample of the source (sample=)
        msg += (f"; pairs from a sample of {len(adj.corr):,} of {adj.corr.n_source:,} source points "
                f"(sample={opts.sample!r}), {n_used:,} used")
    return RegistrationResult(
        translation=t.copy(), rotation=R.copy(), origin=origin, covariance=cov,
        parameter_names=NAMES[opts.dof], sigma0=adj.sigma0, n_used=n_used,
        share_used=n_used / max(len(adj.corr), 1), converged=converged, iterations=len(history),
        degeneracy=deg, method=f"icp ({opts.dof}, {opts.metric}, robust={opts.robust}, surface={matcher.options.get('surface', 'plane')})",
        history=tuple(history), runtime_s=runtime, message=msg, correspondences=adj.corr,
        consistency=test,
    )  # fmt: skip


#: Smallest residual standard deviation (m) a result may claim: two coordinates rounded to 1 mm (the usual
#: LAS scale) differ by 0.41 mm rms. Identical clouds give residuals of exactly zero, but their shift is not
#: known to zero: the floor keeps a stated precision from being exactly 0.
RESOLUTION = 0.0005


def resolution_floor(cov, adj):
    """``cov`` with every finite variance at least RESOLUTION^2 times the unit-weight cofactor (eq. 5.11)."""
    ok = adj.corr.accepted
    pbar = float(np.mean(adj.corr.weight[ok])) if ok.any() else np.nan
    floor = RESOLUTION**2 * pbar * np.diag(adj.Qxx)
    diag = np.diag(cov)
    raise_ = np.isfinite(floor) & np.isfinite(diag) & (diag < floor)
    if not raise_.any():
        return cov
    cov = cov.copy()
    cov[raise_, raise_] = floor[raise_]
    return cov


def consistency_test(adj, matcher, opts, cell=None, xy=None):
    """Model test of the final correspondences: one transformation for every group? (eq. 5.16)

    Three groupings are tested where the data allow them: by class (when both clouds carry two or more
    of the groups of :data:`CLASS_GROUPS`), by terciles of the local noise (vegetation is rough) and by
    the four spatial quadrants (a changed or mis-modelled part of the area). The result reports the
    grouping that disagrees with the largest spread between its groups (that spread enters the
    covariance, eq. 5.17), or the first tested grouping when all agree. The groupings share the level:
    each is tested at ``consistency_alpha`` / k (:func:`~labkit.registration.consistency.family_level`),
    so that agreeing groups are reported as disagreeing in about ``consistency_alpha`` of the cases.
    ``cell``: the block cell label of every accepted pair (:func:`~labkit.registration.consistency.cell_labels`),
    when the caller has them (the block covariance uses the same), and ``xy`` the accepted pairs' source
    positions in the local frame; default: made here.
    """
    corr = adj.corr
    ok = corr.accepted
    A, l, P = design(corr, None, None, opts)
    free = adj.degeneracy.parameter_determined
    A = A[:, :, free]  # held parameters stay out of the test
    if xy is None:
        xy = np.take(corr.source_xyz, np.flatnonzero(ok), axis=0)[:, :2] - opts.origin[:2]  # (by index: faster)
    cells = cell_labels(block_cells(xy, opts.block_size)) if cell is None else cell
    normal = normal_equations(A, P, l)  # N and n of all rows: the same for every grouping
    names_free = [n for n, f in zip(NAMES[opts.dof], free) if f]
    translation = [names_free.index(n) for n in ("tx", "ty", "tz") if n in names_free]

    def tested(labels, names, grouping):
        return group_consistency(
            A, l, P, labels, names, cells, translation=translation, rel_threshold=opts.rel_threshold,
            alpha=opts.consistency_alpha, grouping=grouping, normal=normal,
        )  # fmt: skip

    # the groupings' tests (independent) on the free cores
    tests = [t for t in side_by_side(*[(tested, *g) for g in _groupings(corr, ok, xy, matcher)]) if t is not None]
    if not tests:
        return None
    tests = family_level(tests, opts.consistency_alpha)
    rejecting = [t for t in tests if not t.agree]
    test = max(rejecting, key=lambda t: float(np.trace(t.between))) if rejecting else tests[0]
    if len(translation) < 3:  # report offsets on all three axes (NaN where held)
        full = np.full((len(test.groups), 3), np.nan)
        axes = [k for k, n in enumerate(("tx", "ty", "tz")) if n in names_free]
        off, std = full.copy(), full.copy()
        off[:, axes], std[:, axes] = test.offset, test.offset_std
        test = replace(test, offset=off, offset_std=std)
    return test


def _groupings(corr, ok, xy, matcher):
    """(labels, names, grouping) of the tests: classes, local-noise terciles, spatial quadrants."""
    rows = np.flatnonzero(ok)
    if matcher.target_class is not None and matcher.source_class is not None:
        # a correspondence belongs to the first group that either of its points belongs to: a
        # source point on regrowth matched to old ground counts as vegetation
        cls_t = matcher.target_class[corr.target_index[ok]]
        cls_s = matcher.source_class[rows]
        labels = np.full(len(rows), len(CLASS_GROUPS))
        for g, (_, codes) in reversed(list(enumerate(CLASS_GROUPS))):
            labels[np.isin(cls_t, codes) | np.isin(cls_s, codes)] = g
        if len(np.unique(labels)) > 1:
            yield labels, [n for n, _ in CLASS_GROUPS] + ["other"], "class"
    sigma = matcher.source_sigma[rows]
    if len(sigma) and np.ptp(sigma) > 0:  # terciles of the source point's a priori sigma: vegetation is rough
        yield (np.searchsorted(np.quantile(sigma, [1 / 3, 2 / 3]), sigma, side="right"),
               ["smooth third", "middle third", "rough third"], "local noise")
    if len(xy):
        above = (xy > [median(xy[:, 0]), median(xy[:, 1])]).astype(int)  # np.median(xy, axis=0): the same
        yield above[:, 0] + 2 * above[:, 1], ["block SW", "block SE", "block NW", "block NE"], "block"


def translation_std(cov, opts):
    idx = [NAMES[opts.dof].index(n) for n in ("tx", "ty", "tz")]
    return np.sqrt(np.clip(np.diag(cov)[idx], 0, None))


def disagreement_text(test, classes):
    """Warning text when the groups disagree."""
    g = int(np.argmax(test.contribution))
    off = [f"d{a} {1000 * o:+.0f} mm" for a, o in zip("XYZ", test.offset[g]) if np.isfinite(o)]
    if test.consistent:
        return (
            f"the {test.grouping} groups differ ('{test.worst}': {', '.join(off) or 'see the report'} from the "
            f"result, p = {test.p_value:.1g}), but the shift hardly depends on it (std widened by at most "
            f"{np.nanmax(test.std_ratio):.2f})"
        )
    text = (
        f"INCONSISTENT: the {test.grouping} groups disagree (T = {test.statistic:.0f}, dof = {test.dof}, "
        f"p = {test.p_value:.1g}); '{test.worst}' differs most ({', '.join(off) or 'see the report'} from the "
        f"result): changes between the epochs suspected, the covariance includes the spread between "
        "the groups"
    )
    if test.grouping == "class" and classes is None:
        return text + f"; consider classes={STABLE_CLASSES} (ground, buildings, roads)"
    return text + "; consider robust='tukey', classes= of stable surfaces, or leaving out the changed area"
