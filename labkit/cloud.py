"""The in-memory point cloud: coordinates plus named per-point attributes.

Attribute names follow laspy's dimension names (``classification``,
``intensity``, ``return_number``, ``number_of_returns``, ``gps_time``,
``point_source_id``, ...), so a cloud read from LAS keeps its meaning.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._checks import as_points
from .errors import LabkitError


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Coordinates ``xyz`` (n, 3) float64 with per-point attributes by name.

    The arrays are stored read-only; methods return new clouds.

    Parameters
    ----------
    xyz : array_like, shape (n, 3)
        Coordinates in the file's (often UTM) frame, metres.
    attributes : dict of str -> ndarray, optional
        One array of length n per attribute.
    crs : str, optional
        Coordinate reference system as WKT or ``EPSG:nnnn`` when known.
    name : str, optional
        A label used in reports and plots.
    """

    xyz: np.ndarray
    attributes: dict = field(default_factory=dict)
    crs: str | None = None
    name: str = ""

    def __post_init__(self):
        xyz = np.array(as_points(self.xyz, min_points=0, name="xyz"), dtype=np.float64, copy=True)
        xyz.flags.writeable = False
        attrs = {}
        for key, values in dict(self.attributes).items():
            arr = np.array(values, copy=True)
            if arr.shape[:1] != (xyz.shape[0],):
                raise LabkitError(
                    f"attribute {key!r} has {arr.shape[:1] or 'no'} values, expected one per point ({xyz.shape[0]})"
                )
            arr.flags.writeable = False
            attrs[key] = arr
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "attributes", attrs)

    def __len__(self) -> int:
        return self.xyz.shape[0]

    def __getitem__(self, key: str) -> np.ndarray:
        try:
            return self.attributes[key]
        except KeyError:
            have = ", ".join(sorted(self.attributes)) or "none"
            raise KeyError(f"attribute {key!r} not in this cloud (has: {have})") from None

    def __contains__(self, key: str) -> bool:
        return key in self.attributes

    def __repr__(self) -> str:
        attrs = ", ".join(sorted(self.attributes))
        label = f" {self.name!r}" if self.name else ""
        return f"PointCloud{label}({len(self)} points; attributes: {attrs or 'none'})"

    def subset(self, mask_or_index) -> "PointCloud":
        """A new cloud with the selected points (boolean mask or integer index)."""
        sel = np.asarray(mask_or_index)
        attrs = {k: v[sel] for k, v in self.attributes.items()}
        return PointCloud(self.xyz[sel], attrs, crs=self.crs, name=self.name)

    def with_xyz(self, xyz) -> "PointCloud":
        """A new cloud with other coordinates and the same attributes (e.g. after a transform)."""
        return PointCloud(xyz, self.attributes, crs=self.crs, name=self.name)

    def with_attributes(self, **attributes) -> "PointCloud":
        """A new cloud with attributes added or replaced."""
        return PointCloud(self.xyz, {**self.attributes, **attributes}, crs=self.crs, name=self.name)

    @property
    def bounds(self) -> np.ndarray:
        """Array [[xmin, ymin, zmin], [xmax, ymax, zmax]]."""
        if len(self) == 0:
            raise LabkitError("an empty cloud has no bounds")
        return np.vstack([self.xyz.min(axis=0), self.xyz.max(axis=0)])
