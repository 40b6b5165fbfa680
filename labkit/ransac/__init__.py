"""RANSAC detection of a sphere in a cluttered point cloud (notebook 02).

Section 2 of the exercise sheet: draw minimal samples of s = 4 points that are not
coplanar, compute the sphere through each, count the points whose orthogonal
distance satisfies d_i^2 < t^2 (eqs. 25-26), stop after the adaptive number
of samples N of eq. (27), and refit the best sphere in the Gauss-Helmert model
on all its inliers. Added for real scans: a radius range or nominal radius,
MSAC scoring, local optimization (LO-RANSAC), preliminary scoring on a random
reduction of the cloud, local sampling for tiny spheres in large scenes, and a
final data-snooping pass with Baarda's w-test.

Added for ring-structured (multi-beam) and cluttered real scans: every
hypothesis that would become the best is verified on the full cloud
(:class:`~labkit.ransac.verify.Verifier`: free space inside the sphere, shell
contrast, plane pieces, cap spread, and from the scanner station: facing side,
scan lines, points behind the sphere); a rejected one is skipped and the search
continues. The final inliers come from a robust band k sigma_hat around the
refit, not from the search threshold t, so the stated precision holds for any t.

One module per step, in the order of a detection:

- :mod:`~labkit.ransac.config`: the tuning constants and the run configuration;
- :mod:`~labkit.ransac.iterations`: the required number of samples N (eq. 27);
- :mod:`~labkit.ransac.hypotheses`: spheres through samples, scores (eqs. 25-26), LO;
- :mod:`~labkit.ransac.sampling`: uniform and local minimal samples;
- :mod:`~labkit.ransac.search`: the batched adaptive search and its replay;
- :mod:`~labkit.ransac.verify`: is a candidate a sphere cap the scanner saw?
- :mod:`~labkit.ransac.refit`: robust band, Gauss-Helmert refit, data snooping;
- :mod:`~labkit.ransac.result` and :mod:`~labkit.ransac.detect`: ``RansacResult``
  and the public :func:`ransac_sphere`;
- :mod:`~labkit.ransac.proposals` and :mod:`~labkit.ransac.multi`: every sphere
  of a size in a scan, :func:`find_spheres` (candidate centres from normals,
  RANSAC around each, or detect-remove-repeat).
"""

from __future__ import annotations

from .config import S
from .detect import ransac_sphere
from .iterations import required_iterations
from .multi import find_spheres
from .result import RansacResult

__all__ = ["RansacResult", "S", "find_spheres", "ransac_sphere", "required_iterations"]
