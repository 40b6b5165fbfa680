"""M3C2 parameters chosen from the data: cylinder radius, normal radius and maximum depth (notebook 10).

The rules follow the guidance of Lague, Brodu and Leroux (2013), which the
CloudCompare M3C2 plugin and py4dgeo's documentation repeat:

- cylinder radius r (half the projection scale d): the cylinder should hold about
  30 points of each epoch, so that the mean and the spread of eq. 3-4 are stable and the
  Student quantile of eq. 5 is close to z. Rule: r = median distance from a reference
  point to its 30th nearest reference neighbour (a sample of at most 5000 points).
- normal radius R (half the normal scale D): D should be 20-25 times the roughness
  sigma of the surface at that scale, so that the normal's orientation error stays
  below about 2 degrees (Lague et al. 2013, sec. 4.2), and the neighbourhood should hold
  at least the cylinder's 30 points. Rule: R = max(r, 12.5 sigma), where sigma is the
  median over the sample of sqrt(lambda_3), the smallest principal standard deviation of
  each point's 30 nearest neighbours; capped at 10 r (then the surface is too rough for
  a plane at any useful scale, which the text says).
- maximum depth h (the cylinder's half length): changes beyond h are not found. Rule:
  h = max(2 E, r) with the expected change E: given (``expected_change``), or the 99th
  percentile of the cloud-to-cloud distance from the compared epoch to the reference.

All lengths are in the clouds' metric coordinates (``read_cloud`` converts feet to metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.checks import as_points
from ..core.frame import local_origin, reduce
from ..core.lengths import length_text
from ..core.report import ReportMixin
from ..core.errors import LabkitError

__all__ = ["M3C2Parameters", "m3c2_parameters"]

K = 30  # points per cylinder and per normal neighbourhood (Lague et al. 2013)
D_OVER_SIGMA = 25.0  # normal scale / roughness
SAMPLE = 5000


@dataclass(frozen=True, eq=False, repr=False)
class M3C2Parameters(ReportMixin):
    """M3C2 parameters and the data they were chosen from (all lengths in m).

    Examples
    --------
    >>> from labkit.change.defaults import M3C2Parameters
    >>> p = M3C2Parameters(1.0, 1.5, 2.0, 0.3, 0.01, 0.4, "measured")
    >>> print(p.lines()[0])
    cylinder radius 1.000 m: the median distance to the 30th nearest reference point (about 30 points per cylinder)
    """

    cylinder_radius: float
    normal_radius: float
    max_depth: float
    spacing: float  # median nearest-neighbour distance of the reference
    roughness: float  # median sqrt(lambda_3) of 30-point neighbourhoods
    expected_change: float
    expected_from: str  # "given" or "measured"
    capped: bool = False

    def lines(self) -> list[str]:
        """One line per parameter: value with unit, and the rule that chose it."""
        r, sig = self.cylinder_radius, self.roughness
        normal = (f"normal radius {length_text(self.normal_radius)}: max(cylinder radius, 12.5 x roughness "
                  f"{length_text(sig)}) so that the normal scale is >= 25 x roughness")
        if self.capped:
            normal += " -- capped at 10 x the cylinder radius: the surface is rough at every useful scale"
        source = ("given (--expected-change)" if self.expected_from == "given" else
                  "measured: 99th percentile of the cloud-to-cloud distance compared -> reference")
        return [
            f"cylinder radius {length_text(r)}: the median distance to the 30th nearest reference point "
            "(about 30 points per cylinder)",
            normal,
            f"max depth {length_text(self.max_depth)}: max(2 x expected change, cylinder radius); expected change "
            f"{length_text(self.expected_change)} {source}",
            f"(reference point spacing {length_text(self.spacing)}, median nearest-neighbour distance)",
        ]

    def _report(self):
        return "M3C2 parameters chosen from the data", [("", [(f"{i + 1}", t) for i, t in enumerate(self.lines())])]


def m3c2_parameters(reference, compared, *, expected_change: float | None = None, rng=0) -> M3C2Parameters:
    """Cylinder radius, normal radius and maximum depth for :func:`labkit.m3c2` from the two epochs.

    Parameters
    ----------
    reference, compared : array_like (n, 3) or PointCloud
        The epochs in one metric frame (the compared one registered).
    expected_change : float, optional
        Largest change expected, in m; default: measured (99th percentile of the
        cloud-to-cloud distance compared -> reference).
    rng : int or numpy.random.Generator
        For the sample of at most 5000 points the statistics are taken on.

    Returns
    -------
    M3C2Parameters

    Raises
    ------
    LabkitError
        Fewer than 31 reference points, or an ``expected_change`` that is not a positive number.

    Notes
    -----
    The rules are given in the module notes: r from the distance to the 30th neighbour, R =
    max(r, 12.5 sigma) capped at 10 r, h = max(2 E, r).

    References
    ----------
    .. [1] Notebook 10, sections 2-3 (eqs. 1-5: normal scale, cylinder, level of detection).
    .. [2] D. Lague, N. Brodu, J. Leroux (2013): Accurate 3D comparison of complex topography with
       terrestrial laser scanner: application to the Rangitikei canyon (N-Z). ISPRS Journal of
       Photogrammetry and Remote Sensing 82, 10-26, sec. 4.2 (normal scale >= 20-25 x roughness,
       about 30 points per projection cylinder).

    Examples
    --------
    A plane with 1 cm noise sampled on a 0.1 m grid, and the same plane 5 cm higher:

    >>> import numpy as np
    >>> from labkit.change.defaults import m3c2_parameters
    >>> rng = np.random.default_rng(0)
    >>> xy = np.stack(np.meshgrid(np.arange(0, 10, 0.1), np.arange(0, 10, 0.1)), -1).reshape(-1, 2)
    >>> a = np.c_[xy, rng.normal(0, 0.01, len(xy))]
    >>> b = np.c_[xy, 0.05 + rng.normal(0, 0.01, len(xy))]
    >>> p = m3c2_parameters(a, b)
    >>> round(p.spacing, 2), round(p.cylinder_radius, 2), round(p.normal_radius, 2), round(p.max_depth, 2)
    (0.1, 0.32, 0.32, 0.32)
    >>> round(m3c2_parameters(a, b, expected_change=0.5).max_depth, 2)
    1.0
    """
    ref = as_points(reference, min_points=K + 1, name="reference")
    cmp_ = as_points(compared, min_points=1, name="compared")
    if expected_change is not None and not (np.isfinite(expected_change) and expected_change > 0):
        raise LabkitError(f"expected_change must be a positive length in m, got {expected_change!r}")
    origin = local_origin(ref)
    ref_l, cmp_l = reduce(ref, origin), reduce(cmp_, origin)
    gen = np.random.default_rng(rng)
    tree = cKDTree(ref_l)
    sample = ref_l[gen.choice(len(ref_l), SAMPLE, replace=False)] if len(ref_l) > SAMPLE else ref_l
    dist, idx = tree.query(sample, k=K + 1, workers=-1)  # itself first
    spacing = float(np.median(dist[:, 1]))
    r = float(np.median(dist[:, K]))
    nb = ref_l[idx]  # (m, K + 1, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    lam = np.linalg.eigvalsh(np.einsum("mki,mkj->mij", centred, centred) / K)
    sigma = float(np.median(np.sqrt(np.clip(lam[:, 0], 0.0, None))))
    R = max(r, 0.5 * D_OVER_SIGMA * sigma)
    capped = R > 10 * r
    R = min(R, 10 * r)
    if expected_change is None:
        probe = cmp_l[gen.choice(len(cmp_l), SAMPLE, replace=False)] if len(cmp_l) > SAMPLE else cmp_l
        E, source = float(np.quantile(tree.query(probe, workers=-1)[0], 0.99)), "measured"
    else:
        E, source = float(expected_change), "given"
    h = max(2 * E, r)
    return M3C2Parameters(r, R, h, spacing, sigma, E, source, capped)
