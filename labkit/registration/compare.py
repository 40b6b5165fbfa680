"""Comparing transformations with references (the registration study, step 5; notebook 07).

The table method x region x case: the shift of every method at the centre of
the region, its error against the reference, and whether that error lies
inside the uncertainty the method states for itself (plus the reference's).
References live in :mod:`labkit.registration.references`, distances in
:mod:`labkit.change.distances`; both are re-exported here.

Equation numbers refer to ``notebooks/07-comparing-transformations.ipynb``.
"""

from __future__ import annotations

import csv
import io
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from functools import partial
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_write_text
from ..core.checks import as_points, as_rng, choice, probability
from ..core.distributions import chi2_ppf
from ..core.report import ReportMixin
from ..core.stats import chi2_test
from ..change.distances import (
    DistanceChange, as_matrix, check_overlap, cloud_to_cloud, distances_before_after, point_to_plane_distance,
)
from ..core.errors import EmptyRegionError, LabkitError
from ..io import read_cloud
from ..core.masks import STABLE_CLASSES
from ..neighbours.sampling import median_spacing
from ..synthetic import REGIONS, als_epochs
from ..transforms import check_transform, skew
from .agreement import disagreement_covariance
from .references import (
    Reference, average_references, load_references, manual_reference, reference_from_pairs, reference_from_targets, save_references, truth_reference,
)
from .references import _json_entries

AXES = ("X", "Y", "Z")


@dataclass(frozen=True, eq=False)
class ComparisonRow:
    """One method on one region and case. Shifts are at the source centroid (eq. 5), metres.

    ``dx, dy, dz`` estimated shift and ``sx, sy, sz`` its standard deviations;
    ``ref_*`` the reference and its standard deviations; ``ex, ey, ez`` the error
    (estimate - reference); ``error_norm`` over all axes and
    ``error_norm_constrained`` over the axes the data constrain (``constrained``,
    e.g. ``"XZ"``); ``missed`` the constrained axes the method itself calls
    undetermined (infinite variance); ``chi2`` with ``dof`` and ``p_value`` of the
    test of eq. 6 on the remaining axes; ``inside`` True when the error lies inside
    the combined stated uncertainty and no constrained axis was missed;
    ``consistent`` False when the method's own model test found parts of the data
    that disagree (ICP: classes pulling to different shifts, changes suspected; its
    covariance is then widened accordingly, notebook 05).
    """

    method: str
    region: str
    case: str
    dx: float
    dy: float
    dz: float
    sx: float
    sy: float
    sz: float
    ref_dx: float
    ref_dy: float
    ref_dz: float
    ref_sx: float
    ref_sy: float
    ref_sz: float
    ex: float
    ey: float
    ez: float
    error_norm: float
    error_norm_constrained: float
    constrained: str
    missed: str
    chi2: float
    dof: int
    p_value: float
    inside: bool
    rotation_error_arcsec: float
    n_used: int
    share_used: float
    converged: bool
    runtime_s: float
    message: str = ""
    consistent: bool = True

    @property
    def shift(self) -> np.ndarray:
        return np.array([self.dx, self.dy, self.dz])

    @property
    def shift_std(self) -> np.ndarray:
        return np.array([self.sx, self.sy, self.sz])

    @property
    def reference(self) -> np.ndarray:
        return np.array([self.ref_dx, self.ref_dy, self.ref_dz])

    @property
    def reference_std(self) -> np.ndarray:
        return np.array([self.ref_sx, self.ref_sy, self.ref_sz])

    @property
    def error(self) -> np.ndarray:
        return np.array([self.ex, self.ey, self.ez])

    @property
    def ok(self) -> bool:
        """False when the method failed (its numbers are NaN; see ``message``)."""
        return bool(np.isfinite(self.dx))


COLUMNS = tuple(f.name for f in fields(ComparisonRow))
_TEXT_COLUMNS = (("method", "{}"), ("region", "{}"), ("case", "{}"), ("dx", "{:+.4f}"), ("dy", "{:+.4f}"),
                 ("dz", "{:+.4f}"), ("ex", "{:+.4f}"), ("ey", "{:+.4f}"), ("ez", "{:+.4f}"),
                 ("error_norm_constrained", "{:.4f}"), ("constrained", "{}"), ("missed", "{}"), ("inside", "{}"),
                 ("consistent", "{}"), ("converged", "{}"), ("n_used", "{}"), ("runtime_s", "{:.2f}"))


@dataclass(frozen=True, eq=False, repr=False)
class ComparisonTable(ReportMixin):
    """Rows method x region x case with CSV export and a text rendering.

    Examples
    --------
    >>> from labkit.registration.compare import compare_methods, standard_methods, synthetic_cases
    >>> pairs = synthetic_cases(regions=["xyz"], cases=("als-als",), size=(20.0, 20.0), density=2.0, rng=0)
    >>> table = compare_methods(pairs, standard_methods(["icp"], max_points=2000))
    >>> len(table), table.methods, table.cases
    (1, ('icp',), ('als-als',))
    >>> print(table.pivot("converged"))
    region         case          icp
    xyz            als-als      True
    """

    rows: tuple
    alpha: float = 0.05

    def __repr__(self) -> str:
        return self.summary() + "\n\n" + self.text()

    def pivot(self, metric: str = "error_norm_constrained", scale: float = 1000.0, digits: int = 1) -> str:
        """A text matrix: one line per region and case, one column per method (default: error in mm)."""
        if metric not in COLUMNS:
            raise LabkitError(f"metric must be one of the columns {COLUMNS}, got {metric!r}")
        keys = list(dict.fromkeys((r.region, r.case) for r in self.rows))
        cells = {(r.region, r.case, r.method): getattr(r, metric) for r in self.rows}
        width = max([len(m) for m in self.methods] + [8])
        lines = [f"{'region':14s} {'case':8s} " + " ".join(f"{m:>{width}s}" for m in self.methods)]
        for region, case in keys:
            vals = [cells.get((region, case, m)) for m in self.methods]
            txt = ["-" if v is None else (f"{v * scale:.{digits}f}" if isinstance(v, float) else str(v))
                   for v in vals]
            lines.append(f"{region:14s} {case:8s} " + " ".join(f"{t:>{width}s}" for t in txt))
        return "\n".join(lines)

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self):
        return iter(self.rows)

    def __add__(self, other: "ComparisonTable") -> "ComparisonTable":
        """Rows of both tables (e.g. cheap methods on all regions + an expensive one on a few)."""
        if not isinstance(other, ComparisonTable) or other.alpha != self.alpha:
            raise LabkitError("only comparison tables with the same alpha can be joined")
        return ComparisonTable(self.rows + other.rows, self.alpha)

    @property
    def methods(self) -> tuple:
        return tuple(dict.fromkeys(r.method for r in self.rows))

    @property
    def regions(self) -> tuple:
        return tuple(dict.fromkeys(r.region for r in self.rows))

    @property
    def cases(self) -> tuple:
        return tuple(dict.fromkeys(r.case for r in self.rows))

    def select(self, method=None, region=None, case=None) -> "ComparisonTable":
        """The rows matching every given label."""
        keep = [r for r in self.rows if (method is None or r.method == method)
                and (region is None or r.region == region) and (case is None or r.case == case)]
        return ComparisonTable(tuple(keep), self.alpha)

    def to_records(self) -> list:
        """The rows as dictionaries."""
        return [asdict(r) for r in self.rows]

    def to_csv(self, path) -> Path:
        """Write all columns to a CSV file (atomically)."""
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for rec in self.to_records():
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in rec.items()})
        return atomic_write_text(path, buf.getvalue())

    def text(self) -> str:
        """A fixed-width text table of the main columns (m, s)."""
        head = [name for name, _ in _TEXT_COLUMNS]
        body = [[_cell(fmt_, getattr(r, name)) for name, fmt_ in _TEXT_COLUMNS] for r in self.rows]
        width = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(head)]
        line = lambda cells: "  ".join(c.rjust(w) for c, w in zip(cells, width))  # noqa: E731
        return "\n".join([line(head), line(["-" * w for w in width])] + [line(b) for b in body])

    def _report(self):
        rows = []
        for m in self.methods:
            sel = [r for r in self.rows if r.method == m]
            good = [r for r in sel if r.ok]
            med = np.median([r.error_norm_constrained for r in good]) if good else float("nan")
            inside = sum(r.inside for r in good)
            flagged = sum(not r.consistent for r in good)
            rows.append((m, f"{len(good)}/{len(sel)} ran; median error {med:.4f} m (constrained axes); "
                            f"{inside}/{len(sel)} inside stated uncertainty"
                            + (f"; {flagged} flagged inconsistent" if flagged else "")))
        title = f"Comparison: {len(self.methods)} methods x {len(self.regions)} regions x {len(self.cases)} cases"
        return title, [(f"per method (test level alpha = {self.alpha})", rows)]

    def _repr_html_(self) -> str:
        head = "".join(f"<th>{n}</th>" for n, _ in _TEXT_COLUMNS)
        body = "".join("<tr>" + "".join(f"<td>{_cell(f, getattr(r, n))}</td>" for n, f in _TEXT_COLUMNS) + "</tr>"
                       for r in self.rows)
        return super()._repr_html_() + f"<table><tr>{head}</tr>{body}</table>"


CASES = ("als-als", "changes", "als-dim")
CHANGE_REGIONS = ("demolished", "new_building", "trees_felled", "trees_planted")


def synthetic_cases(regions=None, cases=CASES, *, size=(60.0, 60.0), density=10.0, dim_density=None,
                    shift=(0.23, -0.17, 0.11), rotation_deg=None, rng=None) -> dict:
    """The registration study's three cases on synthetic regions: ``{(region, case): EpochPair}``.

    ``"als-als"``: two ALS epochs of the stable regions; ``"changes"``: two ALS
    epochs of the regions with changes (demolished, new building, trees felled
    or planted); ``"als-dim"``: ALS against dense image matching on the stable
    regions. ``regions`` restricts the regions (default: all of
    :data:`labkit.synthetic.REGIONS`).

    References
    ----------
    .. [1] Seed 003, step 5 (ALS/ALS, ALS/ALS with change, ALS/DIM); notebook 07, section 1.

    Examples
    --------
    >>> from labkit.registration.compare import synthetic_cases
    >>> pairs = synthetic_cases(regions=["xyz"], cases=("als-als",), size=(20.0, 20.0), density=2.0, rng=0)
    >>> list(pairs)
    [('xyz', 'als-als')]
    """
    regions = REGIONS if regions is None else tuple(choice(r, REGIONS, "region") for r in regions)
    gen = as_rng(rng)
    out = {}
    for case in cases:
        choice(case, CASES, "case")
        for region in regions:
            if (region in CHANGE_REGIONS) != (case == "changes"):
                continue
            dim = case == "als-dim"
            out[(region, case)] = als_epochs(region, shift=shift, rotation_deg=rotation_deg, size=size,
                                             density=density, source_density=dim_density if dim else None,
                                             dim=dim, rng=gen.spawn(1)[0])
    if not out:
        raise LabkitError(f"no region among {regions} belongs to the cases {cases}")
    return out


METHODS = ("icp", "icp-point", "icp-huber", "icp-tukey", "icp-classes", "consensus", "consensus+icp")


def standard_methods(names=("icp", "icp-huber", "consensus"), *, dof: str = "translation", extent: float = 1.0,
                     max_points: int | None = 5000, rng=0, reach: float | None = None,
                     max_iterations: int | None = None) -> dict:
    """Ready-made registration methods by name, for :func:`compare_methods`, tiles and the command line.

    ``icp`` (point to plane), ``icp-point`` (point to point), ``icp-huber`` and
    ``icp-tukey`` (robust weights) with ``dof``; ``icp-classes`` (point to plane on
    the stable classes :data:`STABLE_CLASSES` of both epochs only - ground, roofs,
    roads - so that grown vegetation and crowns cannot pull it; the registration study's step 4,
    "Nutzen nur von best. Klassen"); ``consensus`` (maximum consensus,
    a translation within +-``extent`` m, on at most ``max_points`` source points spread
    evenly); ``consensus+icp`` (consensus, then a Tukey ICP with ``dof`` from there: the
    route for shifts larger than ICP's matching distance; with no pair within the gate there, the gate is
    twice the target's point spacing when that is wider, the precision limit stays; X, Y that ICP leaves undetermined
    are filled from the height models where those fix them, :func:`labkit.registration.height_model.fill_held_axes`;
    an ICP that disagrees with its start states a covariance that covers the disagreement,
    :func:`labkit.registration.agreement.disagreement_covariance`). ``reach`` (m, optional) is passed to the ICP
    methods: a reach beyond the matching distance runs ICP's coarse-to-fine pyramid first.
    ``max_iterations`` (optional) is passed to every ICP run (default: ICP's own).
    The callables are picklable (for Dask workers in other processes).

    Examples
    --------
    >>> from labkit.registration.compare import standard_methods
    >>> methods = standard_methods(("icp", "consensus"), dof="translation")
    >>> sorted(methods), callable(methods["icp"])
    (['consensus', 'icp'], True)
    """
    choice(dof, ("translation", "rigid"), "dof")
    out = {}
    for name in names:
        choice(name, METHODS, "method")
        out[name] = partial(_standard, name=name, dof=dof, extent=float(extent), max_points=max_points, rng=rng,
                            reach=reach, **({} if max_iterations is None else {"max_iterations": max_iterations}))
    return out


def _standard(source, target, *, name, dof, extent, max_points, rng, progress=False, reach=None, **icp_options):
    from . import icp, max_consensus  # (numba: loaded when a registration runs)

    if name.startswith("icp"):
        kind = name.partition("-")[2]
        metric = "point_to_point" if kind == "point" else "point_to_plane"
        classes = STABLE_CLASSES if kind == "classes" else None
        return icp(source, target, dof=dof, metric=metric, robust=kind if kind in ("huber", "tukey") else None,
                   classes=classes, rng=rng, progress=progress, reach=reach, **icp_options)
    result = max_consensus(source, target, extent=extent, max_points=max_points)  # an even subset votes
    if name == "consensus":
        return result
    run = partial(icp, source, target, dof=dof, robust="tukey", initial=result.matrix, rng=rng, progress=progress)
    try:
        refined = run(**icp_options)
    except EmptyRegionError:  # no pair within the gate at the consensus start: points too sparse for the gate?
        gate = 2 * median_spacing(as_points(target, name="target"), distinct=True)
        md = icp_options.get("max_distance", 1.0)  # the precision limit stays that of the caller's gate
        if not gate > md:  # dense clouds that do not overlap: refused
            raise
        refined = run(**dict(icp_options, max_distance=gate, max_std=icp_options.get("max_std") or 0.1 * md))
    bb = result.history[0]  # the branch-and-bound outcome: how far the start is certified
    c = as_points(source, name="source").mean(axis=0)  # ICP that walked away from its start: covered
    d = shift_at(refined.matrix, c) - shift_at(result.matrix, c)
    f, extra, T, k = disagreement_covariance(d, np.zeros(3), shift_covariance(refined, c), shift_covariance(result, c))
    if f > 1:  # d d^T: the shift's translation parameters take it (d(shift)/dt = I at any point)
        E = np.eye(len(refined.parameter_names))[:, [refined.parameter_names.index(n) for n in ("tx", "ty", "tz")]]
        refined = replace(refined, covariance=f * refined.covariance + E @ extra @ E.T)
    start = (f"started at max_consensus: consensus {bb.lower:.0f}, certified gap {bb.gap:.0f}, {bb.reason}, "
             f"shift {np.array2string(result.translation, precision=4)} m; ICP moved it by "
             f"{np.array2string(d * 1e3, precision=1)} mm, T = {T:.1f} / {k}"
             + (f": covariance x {f:.2f}" if f > 1 else "") + (" + (1 - k/T) d d^T" if extra.any() else ""))
    return replace(refined, method=f"max_consensus + {refined.method}",
                   runtime_s=result.runtime_s + refined.runtime_s,
                   message="; ".join(m for m in (refined.message, start) if m))


@dataclass(frozen=True, eq=False)
class FilePair:
    """Two epochs of one region read from files (see :func:`load_pairs`)."""

    source: object
    target: object
    region: str
    case: str = ""
    constrained: tuple | None = None
    truth: np.ndarray | None = None


def load_pairs(path) -> dict:
    """Read a JSON list of epoch pairs ``{(region, case): FilePair}``.

    Each entry: ``{"region": ..., "case": ..., "source": file, "target": file}``
    with optional ``"constrained": [true, false, true]``, ``"bbox": [xmin,
    ymin, xmax, ymax]`` (crop while reading) and ``"truth"``, a 4x4 matrix
    source -> target (a known transformation, e.g. of synthetic data; used as the
    reference when no other is given). Relative file names are taken relative to
    the JSON file.

    Examples
    --------
    >>> import json, tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.registration.compare import load_pairs
    >>> from labkit.io import write_cloud
    >>> folder = Path(tempfile.mkdtemp())
    >>> for name in ("e1.laz", "e2.laz"):
    ...     _ = write_cloud(PointCloud(np.random.default_rng(0).uniform(0, 10, (50, 3))), folder / name)
    >>> _ = (folder / "pairs.json").write_text(json.dumps(
    ...     [{"region": "tile", "case": "epochs", "source": "e2.laz", "target": "e1.laz"}]))
    >>> pairs = load_pairs(folder / "pairs.json")
    >>> pair = pairs[("tile", "epochs")]
    >>> list(pairs), len(pair.source), len(pair.target)
    ([('tile', 'epochs')], 50, 50)
    """
    path = Path(path)
    entries = _json_entries(path, "pairs", "pair file", "a list of epoch pairs")
    if not isinstance(entries, list):
        raise LabkitError(f"{path} is not a list of epoch pairs (got {type(entries).__name__})")
    out = {}
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not {"region", "source", "target"} <= set(e):
            raise LabkitError(f"{path}: pair {i} needs 'region', 'source' and 'target'")
        if not all(isinstance(e[k], str) for k in ("source", "target")) or not (
                e.get("constrained") is None or isinstance(e["constrained"], list)):
            raise LabkitError(f"{path}: pair {i}: 'source' and 'target' must be file names, 'constrained' a list")
        files = [(path.parent / e[k]) for k in ("source", "target")]
        src, tgt = (read_cloud(f, bbox=e.get("bbox")) for f in files)
        c = e.get("constrained")
        truth = None
        if e.get("truth") is not None:
            try:
                truth = check_transform(np.asarray(e["truth"], dtype=np.float64))
            except (LabkitError, ValueError, TypeError) as exc:
                raise LabkitError(f"{path}: pair {i}: 'truth' must be a 4x4 transformation matrix ({exc})") from None
        out[(str(e["region"]), str(e.get("case", "")))] = FilePair(
            src, tgt, str(e["region"]), str(e.get("case", "")), None if c is None else tuple(map(bool, c)), truth)
    return out


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


def shift_at(T, c) -> np.ndarray:
    """Shift of the point c under T: R c + t - c (eq. 5).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.compare import shift_at
    >>> from labkit.transforms import make_transform, rotation_from_angles
    >>> T = make_transform(rotation_from_angles(0, 0, 0.001), [0.1, 0.0, 0.0])
    >>> shift_at(T, np.zeros(3)).round(6).tolist(), shift_at(T, np.array([100.0, 0, 0])).round(6).tolist()
    ([0.1, 0.0, 0.0], [0.09995, 0.1, 0.0])
    """
    return T[:3, :3] @ c + T[:3, 3] - c


def shift_covariance(result, c) -> np.ndarray:
    """Covariance of the shift at c by propagating the parameter covariance: J Sigma J^T.

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from labkit.registration.compare import shift_covariance
    >>> result = SimpleNamespace(parameter_names=("tx", "ty", "tz", "rz"), origin=np.zeros(3),
    ...                      covariance=np.diag([1e-6, 1e-6, 1e-6, 1e-8]))
    >>> np.sqrt(np.diag(shift_covariance(result, np.array([100.0, 0, 0])))).round(5).tolist()
    [0.001, 0.01005, 0.001]
    """
    names = tuple(getattr(result, "parameter_names", ("tx", "ty", "tz")))
    Sigma = np.asarray(getattr(result, "covariance", np.full((3, 3), np.nan)), dtype=float)
    if Sigma.shape != (len(names), len(names)):
        return np.full((3, 3), np.nan)
    arm = c - np.asarray(getattr(result, "origin", np.zeros(3)), dtype=float)
    # d(shift)/d(angle): a small rotation dtheta moves c by dtheta x arm = -[arm]x dtheta
    dtheta = -skew(arm)
    cols = {"tx": np.eye(3)[:, 0], "ty": np.eye(3)[:, 1], "tz": np.eye(3)[:, 2],
            "rx": dtheta[:, 0], "ry": dtheta[:, 1], "rz": dtheta[:, 2]}
    J = np.column_stack([cols.get(n, np.zeros(3)) for n in names])
    # J Sigma J^T term by term, so that inf/NaN of undetermined parameters stay where J touches them
    terms = np.einsum("ik,kl,jl->ijkl", J, np.nan_to_num(Sigma, nan=0.0, posinf=0.0, neginf=0.0), J)
    bad = ~np.isfinite(Sigma)[None, None] & (J[:, None, :, None] != 0) & (J[None, :, None, :] != 0)
    return np.where(bad.any(axis=(2, 3)), np.inf, terms.sum(axis=(2, 3)))


def _constrained_axes(pair) -> np.ndarray:
    """The axes to test: those the pair's known geometry (``constrained``) determines, else all three.

    Never the method's own verdict: a method that calls an axis undetermined is still tested on it
    (and counted as having missed it) unless the pair says that the data leave that axis free. A
    reference (truth, manual, targets) is finite on every axis, so it determines all three.
    """
    c = getattr(pair, "constrained", None)
    return np.ones(3, bool) if c is None else np.asarray(c, dtype=bool).reshape(3)


def _cell(fmt_: str, value) -> str:
    if isinstance(value, float) and not np.isfinite(value):
        return "nan"
    return fmt_.format(value)
