"""Distances between two epochs, before and after a transformation (seed 003, step 5).

Cloud to cloud: the distance from each point of one epoch to its nearest
neighbour in the other. Point to plane: the signed distance to the tangent
plane of that neighbour, which is what a shift of a surface changes.

Equation numbers refer to ``notebooks/07-comparing-transformations.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ._checks import as_points
from ._frame import local_origin, reduce
from ._report import ReportMixin
from .errors import EmptyRegionError, LabkitError
from .transforms import apply_transform, check_transform


def as_matrix(transform) -> np.ndarray:
    """A 4x4 matrix from a RegistrationResult, a Reference, or an array (checked)."""
    T = getattr(transform, "matrix", transform)
    return check_transform(T)


def check_overlap(source, target, *, name: str = "source and target") -> None:
    """Raise :class:`EmptyRegionError` unless some source points lie inside the target's xy extent."""
    src, tgt = as_points(source, name="source"), as_points(target, name="target")
    lo, hi = tgt[:, :2].min(axis=0), tgt[:, :2].max(axis=0)
    inside = ((src[:, :2] >= lo) & (src[:, :2] <= hi)).all(axis=1)
    if not inside.any():
        s_lo, s_hi = src[:, :2].min(axis=0), src[:, :2].max(axis=0)
        raise EmptyRegionError(
            f"{name} do not overlap: source spans x {s_lo[0]:.1f}..{s_hi[0]:.1f}, y {s_lo[1]:.1f}..{s_hi[1]:.1f}; "
            f"target spans x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}"
        )


def cloud_to_cloud(source, target, transform=None) -> np.ndarray:
    """Distance from each source point (after ``transform``) to its nearest target point, shape (n,)."""
    src, tgt = _prepared(source, target, transform)
    origin = local_origin(tgt)
    dist, _ = cKDTree(reduce(tgt, origin)).query(reduce(src, origin), k=1, workers=-1)
    return dist


def point_to_plane_distance(source, target, target_normals=None, *, k: int = 10, transform=None) -> np.ndarray:
    """Signed distance from each source point to the tangent plane of its nearest target point.

    d_i = n_j . (p_i - q_j) (eq. 4), with q_j the nearest target point and n_j its
    unit normal (``target_normals`` or PCA normals of ``k`` neighbours). Positive
    means the source point lies above (on the normal side of) the target surface.
    """
    src, tgt = _prepared(source, target, transform)
    if target_normals is None:
        from .features import normals

        nrm = normals(tgt, k=k)
    else:
        nrm = np.asarray(target_normals, dtype=float)
        if nrm.shape != tgt.shape:
            raise LabkitError(f"target_normals must have shape {tgt.shape}, got {nrm.shape}")
    origin = local_origin(tgt)
    q, p = reduce(tgt, origin), reduce(src, origin)
    _, j = cKDTree(q).query(p, k=1, workers=-1)
    return np.einsum("ij,ij->i", nrm[j], p - q[j])  # (eq. 4)


@dataclass(frozen=True, eq=False, repr=False)
class DistanceChange(ReportMixin):
    """Distances of the source to the target before and after a transformation."""

    before: np.ndarray
    after: np.ndarray
    kind: str

    def stats(self, which: str = "after") -> dict:
        """Median |d|, RMS, mean, 95 % quantile of |d| (m)."""
        d = self.before if which == "before" else self.after
        a = np.abs(d)
        return {"median_abs": float(np.median(a)), "rms": float(np.sqrt(np.mean(d**2))),
                "mean": float(np.mean(d)), "q95_abs": float(np.quantile(a, 0.95))}

    def _report(self):
        rows = []
        for which in ("before", "after"):
            s = self.stats(which)
            rows.append((which, f"median |d| {s['median_abs']:.4f} m, RMS {s['rms']:.4f} m, "
                                f"mean {s['mean']:+.4f} m, 95% |d| {s['q95_abs']:.4f} m"))
        return f"Distances ({self.kind}, {len(self.after)} points)", [("", rows)]


def distances_before_after(source, target, transform, *, kind: str = "point_to_plane", k: int = 10,
                           target_normals=None) -> DistanceChange:
    """Distances of ``source`` to ``target`` without and with ``transform`` (4x4, result or reference)."""
    T = as_matrix(transform)
    if kind == "point_to_plane":
        if target_normals is None:
            from .features import normals

            target_normals = normals(as_points(target, min_points=3), k=k)
        f = lambda tr: point_to_plane_distance(source, target, target_normals, transform=tr)  # noqa: E731
    elif kind == "cloud_to_cloud":
        f = lambda tr: cloud_to_cloud(source, target, transform=tr)  # noqa: E731
    else:
        raise LabkitError(f"kind must be 'point_to_plane' or 'cloud_to_cloud', got {kind!r}")
    return DistanceChange(f(None), f(T), kind)


def _prepared(source, target, transform):
    src = as_points(source, name="source")
    tgt = as_points(target, name="target")
    if transform is not None:
        src = apply_transform(as_matrix(transform), src)
    check_overlap(src, tgt)
    return src, tgt
