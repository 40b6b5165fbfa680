"""The comparison table: one row per method, region and case (the registration study, step 5; notebook 07).

Each row holds a method's shift at the centre of the region, its error against the reference, and
whether that error lies inside the uncertainty the method states (plus the reference's); the table
exports CSV and renders text. :func:`labkit.registration.compare.compare_methods` fills it.

Equation numbers refer to ``notebooks/07-comparing-transformations.ipynb``.
"""

from __future__ import annotations

import csv
import io
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_write_text
from ..core.errors import LabkitError
from ..core.report import ReportMixin

__all__ = ["COLUMNS", "ComparisonRow", "ComparisonTable"]


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

    Examples
    --------
    >>> from labkit.registration.compare import compare_methods, standard_methods, synthetic_cases
    >>> pairs = synthetic_cases(regions=["xyz"], cases=("als-als",), size=(20.0, 20.0), density=2.0, rng=0)
    >>> row = compare_methods(pairs, standard_methods(["icp"], max_points=2000)).rows[0]
    >>> row.method, row.constrained, row.ok, row.error.shape
    ('icp', 'XYZ', True, (3,))
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


def _cell(fmt_: str, value) -> str:
    if isinstance(value, float) and not np.isfinite(value):
        return "nan"
    return fmt_.format(value)
