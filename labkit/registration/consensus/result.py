"""The records of the consensus search: the cube of counts and the shape of its peak (eq. 6.5, 6.9)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ...core.report import ReportMixin, fmt

AXES = ("X", "Y", "Z")


@dataclass(frozen=True, eq=False)
class PeakShape(ReportMixin):
    """Which translation directions the consensus peak determines.

    The cells whose count lies within ``level`` of the peak (relative to the
    peak-to-median contrast) and that are connected to the peak form the *top
    region*; a principal component analysis of their positions tells whether it
    is a point, a ridge (one free direction) or a plane (two free directions).
    The *summit* is the part of the top region within the counting noise of the
    peak (3 sqrt(peak) for counts); its centroid is the best grid estimate of the
    translation, because the consensus of an eps-tolerance is flat-topped and
    its single highest cell wanders over the plateau by chance.

    Attributes
    ----------
    kind : str
        'point', 'ridge', 'plane' or 'flat' (no peak at all: undetermined).
    spreads : ndarray (3,)
        Standard deviations (m) of the top region along its principal directions, ascending.
    directions : ndarray (3, 3)
        The principal directions in the columns, in the order of ``spreads``.
    free : ndarray of bool (3,)
        Per principal direction: spread at least ``free_spread`` (not determined).
    axis_constrained : ndarray of bool (3,)
        Per axis X, Y, Z: the free directions have less than half their weight on it.
    contrast : float
        (peak - median) / peak: near 0 for a consensus that barely distinguishes shifts.
    n_top : int
        Number of cells in the top region.
    free_spread : float
        Threshold (m) on the spread that separates determined from free directions.
    summit : ndarray (3,)
        Centroid (m) of the summit: the cells connected to the peak within the counting noise of it.
    n_summit : int
        Number of cells in the summit.

    Examples
    --------
    >>> from labkit.registration import consensus_cube
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(150)  # wavy surface sampled twice, the source moved by -[0.05, 0.02, 0.03]
    >>> cube = consensus_cube(source, target, extent=0.06, step=0.02, eps=0.01, center=[0.04, 0.02, 0.04],
    ...                       use_numba=False)
    >>> peak = cube.peak  # slopes in X and Y: every direction is determined
    >>> peak.kind, peak.free.tolist(), peak.axis_constrained.tolist()
    ('point', [False, False, False], [True, True, True])
    """

    kind: str
    spreads: np.ndarray
    directions: np.ndarray
    free: np.ndarray
    axis_constrained: np.ndarray
    contrast: float
    n_top: int
    free_spread: float
    summit: np.ndarray
    n_summit: int

    @property
    def constrained_axes(self) -> tuple:
        """Names of the axes the peak determines, e.g. ('X', 'Z')."""
        return tuple(a for a, ok in zip(AXES, self.axis_constrained) if ok)

    def describe(self) -> str:
        """One line in words: the shape and the translation direction(s) it leaves free.

        A free direction within 10 degrees of a coordinate axis is named by that axis ("free along ty"),
        otherwise by its azimuth and elevation; a plane of free directions by its normal.

        Examples
        --------
        >>> import numpy as np
        >>> axes = (np.linspace(-0.1, 0.1, 11),) * 3
        >>> X, Y, Z = np.meshgrid(*axes, indexing="ij")
        >>> peak_shape(np.rint(1000 * np.exp(-(X**2 + Z**2) / 2e-4)), axes, eps=0.01).describe()
        'ridge: free along ty'
        """
        if self.kind == "flat":
            return "flat: no peak, the translation is undetermined"
        free = [np.asarray(self.directions)[:, i] for i in np.flatnonzero(self.free)]
        if not free:
            return f"{self.kind}: all three directions determined"
        if len(free) == 1:
            return f"{self.kind}: free along {_direction_words(free[0])}"
        if len(free) == 2:
            return f"{self.kind}: free in the plane normal to {_direction_words(np.cross(free[0], free[1]))}"
        return f"{self.kind}: free in all directions"

    def _report(self):
        rows = [
            ("shape", self.describe()),
            ("constrained axes", ", ".join(self.constrained_axes) or "none"),
            ("spreads of the top region", fmt(self.spreads, 4, "m")),
            ("contrast (peak - median) / peak", fmt(self.contrast, 3)),
            ("cells in the top region / summit", f"{self.n_top} / {self.n_summit}"),
        ]
        return "Consensus peak", [("", rows)]


def _direction_words(v) -> str:
    """A unit direction in words: the axis it is within 10 degrees of, else azimuth and elevation."""
    v = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    a = int(np.argmax(np.abs(v)))
    angle = float(np.degrees(np.arccos(min(1.0, abs(v[a])))))
    if angle <= 10.0:
        return f"t{'xyz'[a]}" + (f" (within {angle:.0f} deg)" if angle >= 1.0 else "")
    v = v if v[2] >= 0 else -v
    azimuth = float(np.degrees(np.arctan2(v[1], v[0])))
    elevation = float(np.degrees(np.arcsin(np.clip(v[2], -1.0, 1.0))))
    return f"a direction at azimuth {azimuth:.0f} deg, elevation {elevation:.0f} deg"


@dataclass(frozen=True, eq=False)
class ConsensusCube(ReportMixin):
    """The consensus C(t) on a regular grid of translations (eq. 6.5).

    Attributes
    ----------
    counts : ndarray (nx, ny, nz)
        Consensus per cell: number of source points (int) or their weight sum (float).
    axes : tuple of three ndarrays
        Translations (m) along X, Y, Z; ``counts[i, j, k]`` belongs to
        ``(axes[0][i], axes[1][j], axes[2][k])``.
    best_translation : ndarray (3,)
        Centre of the summit of the peak (see :class:`PeakShape`), NaN in every axis the
        peak does not determine.
    argmax_translation : ndarray (3,)
        Translation of the highest cell (the first one on a plateau), without that caution.
    best_count : float
        The highest consensus.
    peak : PeakShape
        Shape of the peak: which directions are constrained.
    metric : str
        'point_to_plane' or 'point_to_point'.
    eps : float
        Distance tolerance (m).
    radius : float
        Search radius (m) around target points (point-to-plane); eps for point-to-point.
    max_angle_deg : float or None
        Largest angle (degrees) between source and target normals.
    n_source, n_pairs : int
        Source points and candidate pairs considered.
    step : float
        Grid step (m).
    kernel : str
        'numba' or 'numpy'.
    runtime_s : float
        Wall-clock time (s).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration import consensus_cube
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(150)  # wavy surface sampled twice, the source moved by -[0.05, 0.02, 0.03]
    >>> cube = consensus_cube(source, target, extent=0.06, step=0.02, eps=0.01, center=[0.04, 0.02, 0.04],
    ...                       use_numba=False)
    >>> cube.counts.shape, [len(a) for a in cube.axes], cube.n_source
    ((7, 7, 7), [7, 7, 7], 150)
    >>> bool(cube.best_count == cube.counts.max()), bool(np.allclose(cube.best_translation, [0.05, 0.02, 0.03], atol=0.02))
    (True, True)
    """

    counts: np.ndarray
    axes: tuple
    best_translation: np.ndarray
    argmax_translation: np.ndarray
    best_count: float
    peak: PeakShape
    metric: str
    eps: float
    radius: float
    max_angle_deg: float | None
    n_source: int
    n_pairs: int
    step: float
    kernel: str
    runtime_s: float

    @property
    def peak_index(self) -> tuple:
        """Index (i, j, k) of the highest cell."""
        return tuple(int(i) for i in np.unravel_index(np.argmax(self.counts), self.counts.shape))

    @property
    def undetermined(self) -> bool:
        """True when the consensus has no peak at all."""
        return self.peak.kind == "flat"

    def count_at(self, translation) -> float:
        """Count of the cell nearest to ``translation`` (3,).

        Examples
        --------
        >>> from labkit.registration import consensus_cube
        >>> from labkit.synthetic import wavy_surface
        >>> target = wavy_surface(1500, 1, noise=0.0)  # slopes in X and Y, no noise
        >>> source = target[::10] - [0.0, 0.0, 0.02]
        >>> cube = consensus_cube(source, target, extent=0.04, step=0.02, eps=0.005, use_numba=False)
        >>> cube.count_at([0.0, 0.0, 0.02]) == cube.best_count == len(source)
        True
        """
        idx = [int(np.clip(np.rint((t - a[0]) / self.step), 0, a.size - 1)) for t, a in zip(translation, self.axes)]
        return float(self.counts[tuple(idx)])

    def _report(self):
        shape = "x".join(str(n) for n in self.counts.shape)
        rows = [
            ("metric", f"{self.metric}, eps = {self.eps:.3f} m"
             + (f", radius = {self.radius:.3f} m" if self.metric == "point_to_plane" else "")
             + (f", max angle = {self.max_angle_deg:.1f} deg" if self.max_angle_deg is not None else "")),
            ("grid", f"{shape} = {self.counts.size:,} translations, step {self.step * 100:.2f} cm"),
            ("range", ", ".join(f"{a}: {ax[0]:+.3f}..{ax[-1]:+.3f} m" for a, ax in zip(AXES, self.axes))),
            ("best translation", fmt(self.best_translation, 4, "m")),
            ("highest cell", fmt(self.argmax_translation, 4, "m")),
            ("best consensus", f"{self.best_count:.6g} of {self.n_source} source points"),
            ("pairs", f"{self.n_pairs:,} (kernel: {self.kernel})"),
            ("runtime", fmt(self.runtime_s, 2, "s")),
        ]
        return "Consensus cube", [("", rows)] + self.peak._report()[1]


def peak_shape(counts, axes, eps: float, level: float = 0.07) -> PeakShape:
    """Shape of the consensus peak: point, ridge, plane or flat (eq. 6.9).

    Parameters
    ----------
    counts : ndarray (nx, ny, nz)
    axes : tuple of three 1D arrays
    eps : float
        Tolerance of the consistency test; a peak narrower than the box by far is "determined".
    level : float
        Top region: counts >= peak - level * (peak - median).

    A principal direction is free when the top region spreads along it by at
    least 14 % of the box width (a top region filling the box has 29 %).

    Examples
    --------
    A peak narrow in X and Z but long in Y (a ridge: Y is not determined):

    >>> import numpy as np
    >>> axes = (np.linspace(-0.1, 0.1, 11),) * 3
    >>> X, Y, Z = np.meshgrid(*axes, indexing="ij")
    >>> counts = np.rint(1000 * np.exp(-(X**2 + Z**2) / (2 * 0.01**2)))
    >>> shape = peak_shape(counts, axes, eps=0.01)
    >>> shape.kind, shape.constrained_axes
    ('ridge', ('X', 'Z'))
    """
    c = np.asarray(counts, dtype=np.float64)
    top, med = c.max(), np.median(c)
    contrast = (top - med) / top if top > 0 else 0.0
    width = np.array([a[-1] - a[0] for a in axes])
    free_spread = max(0.14 * float(width.min()), 1.5 * eps / np.sqrt(3))
    # no peak: the best cells are hardly better than the typical one (counting noise of the peak)
    noise = 3.0 * np.sqrt(max(top, 1.0)) if np.allclose(c, np.rint(c)) else 0.01 * top
    if top <= 0 or top - med <= noise:
        return PeakShape(kind="flat", spreads=np.full(3, np.nan), directions=np.eye(3), free=np.ones(3, bool),
                         axis_constrained=np.zeros(3, bool), contrast=float(contrast), n_top=int(c.size),
                         free_spread=free_spread, summit=np.full(3, np.nan), n_summit=int(c.size))
    # top region and summit: cells connected to the peak above two thresholds
    region = _connected_to_peak(c >= top - max(level * (top - med), noise), c)
    summit = _connected_to_peak(c >= top - noise, c)
    X = np.column_stack([a[i] for a, i in zip(axes, np.nonzero(region))])
    centre = np.array([a[i].mean() for a, i in zip(axes, np.nonzero(summit))])
    # principal directions of the top region (eq. 6.9)
    lam, vec = np.linalg.eigh(np.cov(X.T, bias=True) if len(X) > 1 else np.zeros((3, 3)))
    spreads = np.sqrt(np.clip(lam, 0, None))
    free = spreads >= free_spread
    share = (vec[:, free] ** 2).sum(axis=1)
    kind = ("point", "ridge", "plane", "flat")[int(free.sum())]
    return PeakShape(kind=kind, spreads=spreads, directions=vec, free=free, axis_constrained=share < 0.5,
                     contrast=float(contrast), n_top=int(region.sum()), free_spread=free_spread, summit=centre,
                     n_summit=int(summit.sum()))


def _connected_to_peak(mask, c):
    """The connected part of ``mask`` that holds the highest cell of ``c``."""
    labels, _ = ndimage.label(mask)
    return labels == labels[np.unravel_index(np.argmax(c), c.shape)]
