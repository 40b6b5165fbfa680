"""What every synthetic scan of a sphere target has: its points, which of them lie on the sphere, and their share."""

from __future__ import annotations

import numpy as np

from ..core.report import ReportMixin


class SphereScanMixin(ReportMixin):
    """``n``, ``sphere_points`` and ``outlier_ratio`` of a scene with ``points`` (n, 3) and ``is_sphere`` (n,)."""

    @property
    def n(self) -> int:
        return self.points.shape[0]

    @property
    def sphere_points(self) -> np.ndarray:
        """The points scanned on the sphere, (m, 3)."""
        return self.points[self.is_sphere]

    @property
    def outlier_ratio(self) -> float:
        """Share of points that are not on the sphere (0 for an empty scene)."""
        return float(1.0 - self.is_sphere.mean()) if self.n else 0.0
