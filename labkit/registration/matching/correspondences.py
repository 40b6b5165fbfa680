"""The table of correspondences that :func:`labkit.registration.match` returns (private module).

One row per sampled source point, with the rule that rejected it (:data:`RULES`) and its weight;
re-exported by :mod:`labkit.registration.matching`, where it is documented.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...core.report import ReportMixin, fmt

#: Row labels; code 0 is an accepted correspondence. 'degenerate': the source or target point has
#: no normal (its neighbourhood is a point or a line); it is applied with the normal angle.
RULES = ("accepted", "class", "noise", "distance", "normal_angle", "duplicate", "outlier", "degenerate")
_CODE = {name: code for code, name in enumerate(RULES)}
#: Floor for a point's standard deviation in the weights (m), keeps weights finite.
MIN_SIGMA = 0.005


@dataclass(frozen=True, eq=False)
class Correspondences(ReportMixin):
    """Source-to-target correspondences with their rejection rule and weight.

    One row per sampled source point. Rows that a rule rejected keep their
    values (NaN where nothing was computed, target index -1 when no neighbour
    was searched) so they can be plotted.

    Attributes
    ----------
    source_index : ndarray of int (m,)
        Row of the source cloud.
    target_index : ndarray of int (m,)
        Row of the nearest target point (-1 when excluded before the search).
    source_xyz : ndarray (m, 3)
        Source points after the current transformation, caller's frame.
    d : ndarray (m, 3)
        Difference vectors q_j - p_i (dx, dy, dz) in metres.
    plane_distance : ndarray (m,)
        Signed point-to-plane distance n_j . (q_j - p_i) (eq. 5.2), metres.
    normal_angle : ndarray (m,)
        Angle between the source and target normals in degrees (orientation-free;
        NaN without source normals).
    target_normal : ndarray (m, 3)
        Unit normal of the target point (NaN where not computed).
    weight : ndarray (m,)
        Weight p_i of the correspondence (0 for rejected rows).
    rule : ndarray of int8 (m,)
        Code into :data:`RULES`: 0 accepted, otherwise the first rule that rejected it.
    n_source : int
        Points in the source cloud before sampling.

    Examples
    --------
    >>> from labkit.registration import icp
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(300, noise=0.001)  # slopes in X and Y, 1 mm noise
    >>> res = icp(source, target, dof="translation", select="all")
    >>> corr = res.correspondences  # the pairs of the final adjustment (or: labkit.registration.match)
    >>> len(corr) == 300, corr.n_accepted == res.n_used, bool(abs(corr.plane_distance[corr.accepted]).max() < 0.03)
    (True, True, True)
    """

    source_index: np.ndarray
    target_index: np.ndarray
    source_xyz: np.ndarray
    d: np.ndarray
    plane_distance: np.ndarray
    normal_angle: np.ndarray
    target_normal: np.ndarray
    weight: np.ndarray
    rule: np.ndarray
    n_source: int
    settings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.rule)

    @property
    def accepted(self) -> np.ndarray:
        """Boolean mask of the rows that no rule rejected."""
        return self.rule == 0

    @property
    def n_accepted(self) -> int:
        return int(self.accepted.sum())

    @property
    def distance(self) -> np.ndarray:
        """Point-to-point distance |q_j - p_i| (eq. 5.1), metres."""
        return np.linalg.norm(self.d, axis=1)

    @property
    def dx(self) -> np.ndarray:
        return self.d[:, 0]

    @property
    def dy(self) -> np.ndarray:
        return self.d[:, 1]

    @property
    def dz(self) -> np.ndarray:
        return self.d[:, 2]

    @property
    def rejected(self) -> tuple:
        """(rule, count) pairs for every rejection rule, including zero counts."""
        counts = np.bincount(self.rule, minlength=len(RULES))
        thinned = (("sampling", self.n_source - len(self.rule)),)
        return thinned + tuple((name, int(c)) for name, c in zip(RULES[1:], counts[1:]))

    def with_outliers(self, mask) -> "Correspondences":
        """A copy in which the accepted rows selected by ``mask`` are marked 'outlier' (weight 0)."""
        mask = np.asarray(mask, dtype=bool) & self.accepted
        rule = self.rule.copy()
        rule[mask] = _CODE["outlier"]
        weight = np.where(mask, 0.0, self.weight)
        return _replace(self, rule=rule, weight=weight)

    def with_weights(self, weight) -> "Correspondences":
        """A copy with other weights (e.g. robust IRLS weights); rejected rows stay at 0."""
        weight = np.where(self.accepted, np.asarray(weight, dtype=np.float64), 0.0)
        return _replace(self, weight=weight)

    def with_robust_weights(self, rows, weights, outliers=None) -> "Correspondences":
        """``with_outliers(...).with_weights(...)`` in one copy: the rows ``outliers`` (accepted rows; None: none)
        marked 'outlier', the accepted rows ``rows`` weighted by ``weights``, 0 elsewhere (``weights`` is 0 where
        a row of ``rows`` became an outlier)."""
        rule = self.rule
        if outliers is not None and len(outliers):
            rule = rule.copy()
            rule[outliers] = _CODE["outlier"]
        weight = np.zeros(len(self))
        weight[rows] = weights
        return _replace(self, rule=rule, weight=weight)

    def table(self) -> np.ndarray:
        """All rows as a numpy structured array (no pandas needed)."""
        dtype = [
            ("source_index", "i8"), ("target_index", "i8"),
            ("dx", "f8"), ("dy", "f8"), ("dz", "f8"), ("distance", "f8"),
            ("plane_distance", "f8"), ("normal_angle", "f8"), ("weight", "f8"), ("rule", "U12"),
        ]  # fmt: skip
        out = np.empty(len(self), dtype=dtype)
        out["source_index"], out["target_index"] = self.source_index, self.target_index
        out["dx"], out["dy"], out["dz"] = self.d.T
        out["distance"], out["plane_distance"] = self.distance, self.plane_distance
        out["normal_angle"], out["weight"] = self.normal_angle, self.weight
        out["rule"] = np.asarray(RULES)[self.rule]
        return out

    def _report(self):
        ok = self.accepted
        counts = [(f"rejected by {name}", str(c)) for name, c in self.rejected]
        rows = [("source points", str(self.n_source)), ("candidates (after sampling)", str(len(self)))]
        rows += counts + [("accepted", f"{ok.sum()} ({100 * ok.mean() if len(self) else 0:.1f} %)")]
        if ok.any():
            pd = self.plane_distance[ok]
            rows += [
                ("median |point-to-plane|", fmt(np.median(np.abs(pd)), 4, "m")),
                ("median point-to-point", fmt(np.median(self.distance[ok]), 4, "m")),
                ("weights min / median / max", fmt(np.percentile(self.weight[ok], [0, 50, 100]), 3)),
            ]
        return "Correspondences", [("", rows)]


def _replace(corr: Correspondences, **changes) -> Correspondences:
    values = {name: getattr(corr, name) for name in corr.__dataclass_fields__}
    values.update(changes)
    return Correspondences(**values)
