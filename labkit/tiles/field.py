"""The shift field: one shift per tile, and the test whether neighbouring tiles shift alike (notebook 08, eqs. 2-7)."""

from __future__ import annotations

import csv
import io
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_write_text
from ..core.checks import choice, flag, non_negative, probability
from ..core.report import ReportMixin
from .coherent import CORRECTIONS, NeighbourTest, neighbour_areas
from ..core.errors import LabkitError
from .grid import Tile

__all__ = ["NeighbourTest", "ShiftField", "TileShift", "neighbour_test", "tile_status"]

#: Verdicts of a tile: registered and every component determined; registered but some component not
#: determined by the data; the method did not converge; not registered (too few points, or the method failed).
STATUSES = ("ok", "undetermined", "not converged", "too few points", "failed")


def tile_status(converged: bool, determined) -> str:
    """The verdict of a registered tile: ``'not converged'``, ``'undetermined'`` (some component) or ``'ok'``.

    A tile is ``'ok'`` only when its method converged and the data determine every
    component of its shift; a tile whose data determine none is ``'undetermined'`` too
    (:attr:`TileShift.usable` tells whether any component is left).

    References
    ----------
    .. [1] Notebook 08, section 3 (what "undetermined" and "not converged" mean for a tile).

    Examples
    --------
    >>> from labkit.tiles import tile_status
    >>> tile_status(True, [True, True, True]), tile_status(True, [False, False, True]), tile_status(False, [1, 1, 1])
    ('ok', 'undetermined', 'not converged')
    """
    if not bool(converged):
        return "not converged"
    return "ok" if bool(np.all(determined)) else "undetermined"


@dataclass(frozen=True, eq=False)
class TileShift:
    """The registration of one tile, reduced to what the shift field needs.

    ``translation`` is the shift at the centroid of the tile's source points
    (eq. 1) with its 3x3 ``covariance``; ``axis_determined`` says which of its
    components the data determine (the others are held by the method: their
    value means nothing). ``status`` is one of :data:`STATUSES`: ``"ok"`` (converged,
    every component determined), ``"undetermined"`` (converged, some component not
    determined), ``"not converged"``, ``"too few points"`` or ``"failed"`` (then the
    numbers are NaN); ``message`` says why.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.tiles import Tile, TileShift
    >>> tile = Tile(0, 0, (0.0, 0.0, 100.0, 100.0))
    >>> s = TileShift(tile, np.array([0.01, 0.0, 0.0]), np.eye(3) * 1e-6, np.ones(3, bool),
    ...               900, 950, 800, 1.0, True, 0.1, "ok")
    >>> s.ok, s.translation.tolist()
    (True, [0.01, 0.0, 0.0])
    """

    tile: Tile
    translation: np.ndarray
    covariance: np.ndarray
    axis_determined: np.ndarray
    n_source: int
    n_target: int
    n_used: int
    sigma0: float
    converged: bool
    runtime_s: float
    status: str
    message: str = ""

    @property
    def ok(self) -> bool:
        """Converged, and every component determined (with a finite standard deviation)."""
        return self.verdict == "ok"

    @property
    def usable(self) -> bool:
        """Converged with at least one determined component: the tile enters the neighbour test."""
        return self.status in STATUSES[:3] and bool(self.converged) and bool(self.determined.any())

    @property
    def verdict(self) -> str:
        """The status as the numbers say it (:func:`tile_status` for a registered tile, else ``status``)."""
        return tile_status(self.converged, self.determined) if self.status in STATUSES[:3] else self.status

    @property
    def determined(self) -> np.ndarray:
        """(3,) bool: components the data determine, with a finite standard deviation (none if not converged)."""
        var = np.diag(np.asarray(self.covariance, dtype=float))
        return np.asarray(self.axis_determined, bool) & np.isfinite(var) & bool(self.converged)


@dataclass(frozen=True, eq=False, repr=False)
class ShiftField(ReportMixin):
    """The shift of every tile of a survey (from :func:`register_tiles`).

    Examples
    --------
    Two tiles; the second (a flat field) determines only Z:

    >>> import numpy as np
    >>> from labkit.tiles import ShiftField, TileShift, tile_grid
    >>> a, b = tile_grid((0, 0, 199, 99), 100.0)
    >>> field = ShiftField((TileShift(a, np.array([0.02, 0.01, 0.03]), np.eye(3) * 4e-6, np.ones(3, bool),
    ...                               900, 900, 800, 1.0, True, 0.1, "ok"),
    ...                     TileShift(b, np.array([0.0, 0.0, 0.03]), np.eye(3) * 4e-6, np.array([False, False, True]),
    ...                               900, 900, 800, 1.0, True, 0.1, "undetermined")), 100.0)
    >>> field.centres.tolist(), field.std[0].tolist()
    ([[50.0, 50.0], [150.0, 50.0]], [0.002, 0.002, 0.002])
    >>> field.determined_translations.tolist()  # what the data do not determine is NaN
    [[0.02, 0.01, 0.03], [nan, nan, 0.03]]
    >>> field.ok.tolist(), field.usable.tolist()  # ok: every component determined
    ([True, False], [True, True])
    """

    tiles: tuple
    size: float
    method: str = ""
    n_reused: int = 0  # tiles read back from an earlier run's results (register_tiles(results=...))

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def ok(self) -> np.ndarray:
        """(n,) bool: tiles that converged with every component determined."""
        return np.array([t.ok for t in self.tiles], bool)

    @property
    def usable(self) -> np.ndarray:
        """(n,) bool: tiles that converged with at least one component determined (neighbour-tested)."""
        return np.array([t.usable for t in self.tiles], bool)

    @property
    def status(self) -> np.ndarray:
        """(n,) str: the verdict of every tile (:data:`STATUSES`, :attr:`TileShift.verdict`)."""
        return np.array([t.verdict for t in self.tiles], dtype=object)

    @property
    def centres(self) -> np.ndarray:
        return np.array([t.tile.centre for t in self.tiles]).reshape(-1, 2)

    @property
    def translations(self) -> np.ndarray:
        return np.array([t.translation for t in self.tiles]).reshape(-1, 3)

    @property
    def covariances(self) -> np.ndarray:
        return np.array([t.covariance for t in self.tiles]).reshape(-1, 3, 3)

    @property
    def determined(self) -> np.ndarray:
        """(n, 3) bool: which components of each tile's shift are usable: converged, determined by the data."""
        return np.array([t.determined & t.usable for t in self.tiles], bool).reshape(-1, 3)

    @property
    def determined_translations(self) -> np.ndarray:
        """The translations, NaN where a component is not determined (held by the method) or not converged."""
        return np.where(self.determined, self.translations, np.nan)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.einsum("nii->ni", self.covariances), 0, None))

    def neighbour_test(self, alpha: float = 0.05, *, extra_std: float = 0.0, diagonal: bool = False,
                       correction: str = "holm") -> NeighbourTest:
        """Test whether neighbouring tiles shift alike and find the coherent areas; see :func:`neighbour_test`."""
        return neighbour_test(self, alpha, extra_std=extra_std, diagonal=diagonal, correction=correction)

    def to_csv(self, path, test=None) -> Path:
        """One line per tile: index, bounds, shift, standard deviations, counts, status (atomic write).

        A component the tile's data do not determine, and every component of a tile that
        did not converge, is an empty cell (never the value the method held or stopped at);
        ``determined`` names the determined axes (e.g. ``Z``). With ``test`` (the
        :class:`NeighbourTest` of this field) more columns follow: the tile's coherent
        ``area`` (-1: no shift), the p-value of its test against the area's common shift
        (``tile_p``, eq. 7), ``area_dx, area_dy, area_dz``, that common shift, the neighbour
        pairs tested and disagreeing, and ``flag`` = ``disagrees with neighbours`` for a
        tile that disagrees with most of its tested neighbours.
        """
        if test is not None and len(test.areas) != len(self.tiles):
            raise LabkitError(f"the neighbour test has {len(test.areas)} tiles, the field {len(self.tiles)}")
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        head = ["row", "col", "xmin", "ymin", "xmax", "ymax", "dx", "dy", "dz", "sx", "sy", "sz", "determined",
                "n_source", "n_target", "n_used", "sigma0", "converged", "runtime_s", "status", "message"]
        w.writerow(head + (["area", "tile_p", "area_dx", "area_dy", "area_dz", "neighbours_tested",
                            "neighbours_disagree", "flag"] if test is not None else []))
        det = self.determined
        shown_t = np.where(det, self.translations, np.nan)
        shown_s = np.where(det, self.std, np.nan)
        for i, t in enumerate(self.tiles):
            row = [t.tile.row, t.tile.col, *t.tile.bounds, *_cells(shown_t[i]), *_cells(shown_s[i]),
                   "".join(a for a, d in zip("XYZ", det[i]) if d), t.n_source, t.n_target, t.n_used,
                   *_cells([t.sigma0]), t.converged, f"{t.runtime_s:.3f}", t.verdict, t.message]
            if test is not None:
                a = int(test.areas[i])
                common = test.area_shift[a] if a >= 0 else np.full(3, np.nan)
                row += [a, *_cells([test.tile_p_value[i]]), *_cells(common), int(test.neighbours_tested[i]),
                        int(test.neighbours_disagree[i]), "disagrees with neighbours" if test.disagreeing[i] else ""]
            w.writerow(row)
        return atomic_write_text(path, buf.getvalue())

    def _report(self):
        usable = self.usable
        tr = self.determined_translations[usable]  # undetermined components do not enter the statistics
        rows = [("tiles", f"{len(self)} of {self.size:g} m; {int(self.ok.sum())} ok (converged, X, Y, Z determined)"),
                ("method", self.method or "?")]
        if usable.any():
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an axis no tile determines gives nan
                med, spread = np.nanmedian(tr, axis=0), np.nanstd(tr, axis=0)
            rows += [("median shift", "[" + ", ".join("  undet." if np.isnan(v) else f"{v:+.4f}" for v in med)
                      + "] m"),
                     ("spread (std) of shifts", "[" + ", ".join("-" if np.isnan(v) else f"{v:.4f}" for v in spread)
                      + "] m")]
        status = self.status
        n_undet = int((status == "undetermined").sum())
        if n_undet:
            per_axis = (~self.determined[status == "undetermined"]).sum(axis=0)
            rows.append(("undetermined", f"{n_undet} tiles (not determined: "
                         + ", ".join(f"{a} in {k}" for a, k in zip("XYZ", per_axis)) + "; empty in the CSV)"))
        for name in STATUSES[2:]:
            n = int((status == name).sum())
            if n:
                rows.append((name, f"{n} tiles" + (" (no shift given)" if name == "not converged" else "")))
        return "Shift field", [("", rows)]


def _cells(values) -> list:
    """CSV cells: numbers with 6 significant digits; NaN or inf (nothing to state) as an empty cell."""
    return [f"{v:.6g}" if np.isfinite(v) else "" for v in np.asarray(values, dtype=float)]


def neighbour_test(field: ShiftField, alpha: float = 0.05, *, extra_std: float = 0.0, diagonal: bool = False,
                   correction: str = "holm") -> NeighbourTest:
    """Do neighbouring tiles agree within their uncertainty, and which areas move as one? (notebook 08, eqs. 2-7)

    For tiles i, j sharing an edge (or a corner with ``diagonal``) the
    difference d = t_i - t_j has covariance C = Sigma_i + Sigma_j + 2 s^2 I
    (eq. 2; s = ``extra_std``, an uncertainty per tile beyond the formal one,
    e.g. for systematic effects the covariance of ICP does not see). On the
    axes both tiles determine, T = d^T C^-1 d is chi-square distributed with as
    many degrees of freedom (eq. 3). Tiles linked by agreeing pairs are a first
    guess of the coherent areas; each tile is then tested against its area's
    common weighted shift (eqs. 5, 6), and an area with a tile that disagrees
    is split, so that a chain of small steps is not one area (see
    :mod:`labkit.tiles.coherent`).

    Parameters
    ----------
    field : ShiftField
    alpha : float
        Level of the tests; with ``correction='holm'`` the family-wise level: the
        chance that a survey whose tiles all shift alike shows any disagreeing
        border or more than one area.
    extra_std : float
        Extra standard deviation per tile (m).
    diagonal : bool
        Also test tiles that share only a corner.
    correction : {'holm', 'fdr', 'none'}
        Control of the many tests (about three per tile) (eq. 7). ``'holm'`` (default)
        keeps the family-wise error at alpha under any dependence (pairs sharing a
        tile are correlated): a flagged border is then evidence about the survey,
        not the expected few percent of false alarms among hundreds of borders -
        without correction a stable survey of 100 tiles shows about ten. ``'fdr'``
        (Benjamini-Hochberg) bounds the expected share of false alarms among the
        flagged ones instead; it finds more where much has moved (a campaign after
        a landslide). ``'none'`` tests each pair at alpha (as notebook 08 does first).

    Returns
    -------
    NeighbourTest

    References
    ----------
    .. [1] Notebook 08, section 4, eqs. 2-7.
    .. [2] Holm (1979) and Benjamini and Hochberg (1995), cited in full at
       :func:`labkit.core.stats.adjusted_p_values`, which applies the correction.

    Examples
    --------
    Three tiles in a row with 1 mm std; the third moved 5 cm more:

    >>> import numpy as np
    >>> from labkit.tiles import ShiftField, TileShift, neighbour_test, tile_grid
    >>> grid = tile_grid((0, 0, 299, 99), 100.0)
    >>> field = ShiftField(tuple(TileShift(t, np.array([dx, 0.0, 0.0]), np.eye(3) * 1e-6, np.ones(3, bool),
    ...                                    900, 900, 800, 1.0, True, 0.1, "ok")
    ...                          for t, dx in zip(grid, [0.010, 0.011, 0.060])), 100.0)
    >>> test = neighbour_test(field, alpha=0.05)
    >>> test.agree.tolist(), test.areas.tolist(), test.n_areas
    ([True, False], [0, 0, 1], 2)
    >>> neighbour_test(field, extra_std=0.05).n_areas  # 5 cm more uncertainty per tile: one area
    1
    """
    alpha = probability(alpha, "alpha")
    extra_std = non_negative(extra_std, "extra_std")
    diagonal = flag(diagonal, "diagonal")
    correction = choice(correction, CORRECTIONS, "correction")
    if not isinstance(field, ShiftField):
        raise LabkitError(f"neighbour_test needs a ShiftField (from register_tiles), got {type(field).__name__}")
    return neighbour_areas(_neighbour_pairs(field, diagonal), field.translations, field.covariances,
                           field.determined, field.usable, alpha=alpha, extra_std=extra_std, correction=correction)


def _neighbour_pairs(field: ShiftField, diagonal: bool) -> np.ndarray:
    index = {(s.tile.row, s.tile.col): n for n, s in enumerate(field.tiles) if s.usable}
    steps = [(0, 1), (1, 0)] + ([(1, 1), (1, -1)] if diagonal else [])
    pairs = [(n, index[(r + dr, c + dc)]) for (r, c), n in index.items() for dr, dc in steps
             if (r + dr, c + dc) in index]
    return np.array(sorted(pairs), int).reshape(-1, 2)
