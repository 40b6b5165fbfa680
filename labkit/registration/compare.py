"""Comparing transformations with references (the registration study, step 5; notebook 07).

The table method x region x case: the shift of every method at the centre of
the region, its error against the reference, and whether that error lies
inside the uncertainty the method states for itself (plus the reference's).
Here the comparison itself; beside it, and re-exported here: the table
(:mod:`labkit.registration.table`), the epoch pairs (:mod:`labkit.registration.pairs`),
the ready-made methods (:mod:`labkit.registration.methods`), the shift at a point
(:mod:`labkit.registration.shift`), the references (:mod:`labkit.registration.references`)
and the distances (:mod:`labkit.change.distances`).

Equation numbers refer to ``notebooks/07-comparing-transformations.ipynb``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from ..core.checks import as_points, probability
from ..core.distributions import chi2_ppf
from ..core.masks import STABLE_CLASSES  # noqa: F401  (re-exported)
from ..core.stats import chi2_test
from ..change.distances import (  # noqa: F401  (re-exported)
    DistanceChange, as_matrix, check_overlap, cloud_to_cloud, distances_before_after, point_to_plane_distance,
)
from ..core.errors import LabkitError
from .methods import METHODS, standard_methods  # noqa: F401  (re-exported)
from .pairs import CASES, CHANGE_REGIONS, FilePair, load_pairs, synthetic_cases  # noqa: F401  (re-exported)
from .references import (  # noqa: F401  (re-exported)
    Reference, average_references, load_references, manual_reference, reference_from_pairs, reference_from_targets, save_references, truth_reference,
)
from .shift import shift_at, shift_covariance  # noqa: F401  (re-exported)
from .table import COLUMNS, ComparisonRow, ComparisonTable  # noqa: F401  (re-exported)

AXES = ("X", "Y", "Z")


def compare_methods(pairs, methods, *, references=None, alpha: float = 0.05) -> ComparisonTable:
    """Run every method on every epoch pair and compare with the references (notebook 07).

    Parameters
    ----------
    pairs : mapping or sequence
        Epoch pairs with attributes ``source`` and ``target`` (e.g.
        :class:`labkit.synthetic.EpochPair`), optional ``truth`` (4x4),
        ``region``, ``case`` and ``constrained`` (3 bools: which axes the data
        determine). A mapping's key labels the pair: ``(region, case)`` or a region name.
    methods : mapping of str -> callable(source, target) -> RegistrationResult
        E.g. ``{"icp": partial(icp, dof="translation"), "consensus": max_consensus}``.
    references : mapping (region, case) -> Reference, optional
        From :func:`load_references`; pairs without one use their ``truth``.
    alpha : float
        Level of the chi-square test of eq. 6.

    Returns
    -------
    ComparisonTable
        One row per method and pair. A method that raises a labkit error gets
        a row with NaN numbers and the error in ``message``.

    References
    ----------
    .. [1] Notebook 07, section 4, eqs. 5-6; the registration study, step 5 (compare the transformations visually
       and quantitatively).
    .. [2] P. J. Besl, N. D. McKay (1992): ICP, doi:10.1109/34.121791.
    .. [3] Y. Chen, G. Medioni (1992): point-to-plane registration, Image and Vision Computing 10(3).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.compare import compare_methods, standard_methods, synthetic_cases
    >>> pairs = synthetic_cases(regions=["xyz"], cases=("als-als",), size=(30.0, 30.0), density=4.0, rng=0)
    >>> table = compare_methods(pairs, standard_methods(["icp"], max_points=2000))
    >>> len(table.rows), table.rows[0].method
    (1, 'icp')
    >>> bool(np.linalg.norm(table.rows[0].error[:3]) < 0.02)
    True
    """
    alpha = probability(alpha, "alpha")
    if not isinstance(methods, Mapping) or not methods:
        raise LabkitError("methods must be a non-empty mapping name -> callable(source, target)")
    rows = []
    for (region, case), pair in _labelled(pairs):
        check_overlap(pair.source, pair.target, name=f"source and target of region {region!r} ({case})")
        ref = _reference_for(pair, region, case, references)
        for name, method in methods.items():
            result, runtime, error = _run(method, pair)
            rows.append(_row(name, region, case, pair, ref, result, runtime, error, alpha))
    return ComparisonTable(tuple(rows), alpha)


def _labelled(pairs):
    items = pairs.items() if isinstance(pairs, Mapping) else ((None, p) for p in pairs)
    for key, pair in items:
        if not (hasattr(pair, "source") and hasattr(pair, "target")):
            raise LabkitError(f"each pair needs .source and .target, got {type(pair).__name__}")
        region = getattr(pair, "region", "") or ""
        case = getattr(pair, "case", "") or ""
        if isinstance(key, tuple) and len(key) == 2:
            region, case = map(str, key)
        elif key is not None:
            region = str(key)
        yield (region, case), pair


def _reference_for(pair, region, case, references):
    if references is not None and (region, case) in references:
        return references[(region, case)]
    if getattr(pair, "truth", None) is not None:
        return truth_reference(pair.truth, region=region, case=case)
    raise LabkitError(f"no reference for region {region!r}, case {case!r}: give references= or pairs with .truth")


def _run(method, pair):
    t0 = time.perf_counter()
    try:
        result = method(pair.source, pair.target)
    except (LabkitError, np.linalg.LinAlgError) as exc:
        return None, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}"
    wall = time.perf_counter() - t0
    runtime = getattr(result, "runtime_s", float("nan"))
    return result, (runtime if np.isfinite(runtime) else wall), ""


def _row(name, region, case, pair, ref, result, runtime, error, alpha) -> ComparisonRow:
    src = as_points(pair.source, name="source")
    c = src.mean(axis=0)
    r_shift = shift_at(ref.matrix, c)
    mask = _constrained_axes(pair)
    labels = "".join(a for a, m in zip(AXES, mask) if m)
    ref_std = ref.std
    if result is None:
        nan = float("nan")
        return ComparisonRow(name, region, case, *[nan] * 6, *r_shift, *ref_std, nan, nan, nan, nan, nan, labels,
                             "", nan, 0, nan, False, nan, 0, 0.0, False, runtime, error)
    T = as_matrix(result)
    shift = shift_at(T, c)  # (eq. 5)
    Sigma_m = shift_covariance(result, c)
    e = shift - r_shift
    missed = mask & ~np.isfinite(np.diag(Sigma_m))  # constrained by the data, undetermined by the method
    test = mask & ~missed
    chi2, p = chi2_test(e[test], (Sigma_m + ref.covariance)[np.ix_(test, test)])  # (eq. 6)
    inside = bool(np.isfinite(chi2) and chi2 <= chi2_ppf(1 - alpha, test.sum()) and not missed.any())
    dR = T[:3, :3] @ ref.rotation.T
    rot_err = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) * 3600
    return ComparisonRow(
        name, region, case, *shift, *np.sqrt(np.clip(np.diag(Sigma_m), 0, None)), *r_shift, *ref_std, *e,
        float(np.linalg.norm(e)), float(np.linalg.norm(e[mask])), labels,
        "".join(a for a, m in zip(AXES, missed) if m), chi2, int(test.sum()), p, inside,
        float(rot_err), int(getattr(result, "n_used", 0)), float(getattr(result, "share_used", np.nan)),
        bool(getattr(result, "converged", False)), float(runtime), str(getattr(result, "message", "")),
        consistent=bool(getattr(result, "consistent", True)),
    )


def _constrained_axes(pair) -> np.ndarray:
    """The axes to test: those the pair's known geometry (``constrained``) determines, else all three.

    Never the method's own verdict: a method that calls an axis undetermined is still tested on it
    (and counted as having missed it) unless the pair says that the data leave that axis free. A
    reference (truth, manual, targets) is finite on every axis, so it determines all three.
    """
    c = getattr(pair, "constrained", None)
    return np.ones(3, bool) if c is None else np.asarray(c, dtype=bool).reshape(3)
