"""The in-memory point cloud: coordinates plus named per-point attributes.

Attribute names follow laspy's dimension names (``classification``,
``intensity``, ``return_number``, ``number_of_returns``, ``gps_time``,
``point_source_id``, ...), so a cloud read from LAS keeps its meaning.

Units
-----
Every cloud carries :class:`Units`: the units of its file's CRS and whether the
coordinates were converted to metres when read. Metric steps (normals, ICP,
consensus, spheres, distances, tiles) take their thresholds in metres; they
call :meth:`PointCloud.require_metric` (through ``labkit.core.checks.as_points``)
and refuse a cloud whose coordinates are known to be in degrees or in feet.
A cloud whose units are not stated anywhere (no CRS) is accepted as metres.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .core.checks import as_points
from .core.errors import LabkitError
from .core.arrays import extent, rows
from .core.units import Units, UnitsError, units_from_crs_text


def _crs_text(crs) -> str | None:
    """The CRS as text: WKT or ``EPSG:code`` kept, an int taken as an EPSG code, a pyproj CRS as its code or WKT."""
    if crs is None or isinstance(crs, str):
        return crs.strip() or None if isinstance(crs, str) else None
    if isinstance(crs, numbers.Integral) and not isinstance(crs, (bool, np.bool_)):
        if not 1024 <= int(crs) <= 999999:
            raise LabkitError(f"crs={crs} is not an EPSG code")
        return f"EPSG:{int(crs)}"
    if type(crs).__name__ == "CRS" and hasattr(crs, "to_wkt"):  # pyproj.CRS
        code = crs.to_epsg(min_confidence=100)
        return f"EPSG:{code}" if code else crs.to_wkt()
    raise LabkitError(f"crs must be WKT, 'EPSG:code', an EPSG code (int) or a pyproj.CRS, got {type(crs).__name__}")


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Coordinates ``xyz`` (n, 3) float64 with per-point attributes by name.

    The arrays are stored read-only; methods return new clouds.

    Parameters
    ----------
    xyz : array_like, shape (n, 3)
        Coordinates in the file's (often UTM) frame; metres unless ``units`` says otherwise.
    attributes : dict of str -> ndarray, optional
        One array of length n per attribute.
    crs : str, optional
        Coordinate reference system as WKT or ``EPSG:nnnn`` when known.
    name : str, optional
        A label used in reports and plots.
    units : Units, optional
        Units of the coordinates and of the file (set by :func:`labkit.io.read_cloud`).
        By default they are derived from ``crs`` with the coordinates taken in
        the CRS's own units; without a CRS they are unknown (taken as metres).
    layout : labkit.io.las_layout.LasLayout, optional
        The LAS file layout the cloud was read from (version, point format,
        scales, offsets, extra-bytes types, VLRs). :func:`labkit.io.write_cloud`
        writes the cloud back in it, so that only the coordinates change.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> cloud = PointCloud(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 5]]), {"classification": np.array([2, 2, 6])},
    ...                    crs="EPSG:25832", name="demo")
    >>> len(cloud), cloud["classification"].tolist(), cloud.crs
    (3, [2, 2, 6], 'EPSG:25832')
    >>> cloud.subset(cloud["classification"] == 2).xyz.tolist()
    [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    """

    xyz: np.ndarray
    attributes: dict = field(default_factory=dict)
    crs: str | None = None
    name: str = ""
    units: Units | None = None
    layout: object = field(default=None, repr=False)

    def __post_init__(self):
        xyz = np.array(as_points(self.xyz, min_points=0, name="xyz"), dtype=np.float64, copy=True)
        xyz.flags.writeable = False
        object.__setattr__(self, "crs", _crs_text(self.crs))
        if self.name is None:
            object.__setattr__(self, "name", "")
        if not isinstance(self.name, str):
            raise LabkitError(f"name must be a str, got {type(self.name).__name__}")
        if not isinstance(self.attributes, Mapping):
            raise LabkitError(f"attributes must be a dict of name -> array (one value per point), "
                              f"got {type(self.attributes).__name__}")
        attrs = {}
        for key, values in dict(self.attributes).items():
            if not isinstance(key, str) or not key:
                raise LabkitError(f"attribute names must be non-empty str, got {key!r}")
            if np.iscomplexobj(values):
                raise LabkitError(f"attribute {key!r} holds complex values; point attributes are real")
            arr = np.array(values, copy=True)
            if arr.shape[:1] != (xyz.shape[0],):
                raise LabkitError(
                    f"attribute {key!r} has {arr.shape[:1] or 'no'} values, expected one per point ({xyz.shape[0]})"
                )
            arr.flags.writeable = False
            attrs[key] = arr
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "attributes", attrs)
        units = self.units
        if units is None:

            units = units_from_crs_text(self.crs)
        elif not isinstance(units, Units):
            raise LabkitError(f"units must be a labkit.core.units.Units, got {type(units).__name__}")
        object.__setattr__(self, "units", units)

    @classmethod
    def _adopt(cls, xyz: np.ndarray, attributes: dict, **fields) -> "PointCloud":
        """A cloud that takes over freshly made arrays without copying them (readers only).

        The caller gives the arrays up: they are made read-only here and must not
        be used elsewhere. Saves one copy of the whole cloud when reading.
        """
        if not (isinstance(xyz, np.ndarray) and xyz.dtype == np.float64 and xyz.ndim == 2 and xyz.shape[1] == 3
                and all(isinstance(v, np.ndarray) and v.shape[:1] == xyz.shape[:1] for v in attributes.values())):
            return cls(xyz, attributes, **fields)
        cloud = cls(np.empty((0, 3)), {}, **fields)
        xyz.flags.writeable = False
        for v in attributes.values():
            v.flags.writeable = False
        object.__setattr__(cloud, "xyz", xyz)
        object.__setattr__(cloud, "attributes", dict(attributes))
        return cloud

    @classmethod
    def concatenate(cls, clouds, *, name: str = "", crs: str | None = None, units=None) -> "PointCloud":
        """The points of several clouds in one, with the attributes all of them have (in the first one's order).

        CRS and units are not compared here: :func:`labkit.regions.merge` and
        :func:`labkit.io.read_clouds` refuse clouds that differ, each by its own rule
        (files must agree exactly; a cloud without a CRS may join others in memory),
        and pass the ``crs`` and ``units`` of the result.

        Examples
        --------
        >>> import numpy as np
        >>> from labkit.cloud import PointCloud
        >>> a = PointCloud(np.zeros((2, 3)), {"intensity": np.array([1, 2]), "flag": np.array([0, 1])})
        >>> b = PointCloud(np.ones((1, 3)), {"intensity": np.array([3])})
        >>> both = PointCloud.concatenate([a, b], name="ab")
        >>> len(both), both["intensity"].tolist(), sorted(both.attributes)
        (3, [1, 2, 3], ['intensity'])
        """
        first = clouds[0]
        common = [k for k in first.attributes if all(k in c.attributes for c in clouds[1:])]
        xyz = np.concatenate([c.xyz for c in clouds])
        attrs = {k: np.concatenate([c.attributes[k] for c in clouds]) for k in common}  # dtypes promoted alike
        return cls._adopt(xyz, attrs, crs=crs, name=name, units=units)

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
        attrs = {k: rows(v, sel) for k, v in self.attributes.items()}
        return PointCloud(rows(self.xyz, sel), attrs, crs=self.crs, name=self.name, units=self.units,
                          layout=self.layout)

    def with_xyz(self, xyz) -> "PointCloud":
        """A new cloud with other coordinates and the same attributes (e.g. after a transform)."""
        return PointCloud(xyz, self.attributes, crs=self.crs, name=self.name, units=self.units,
                          layout=self.layout)

    def with_attributes(self, **attributes) -> "PointCloud":
        """A new cloud with attributes added or replaced."""
        return PointCloud(self.xyz, {**self.attributes, **attributes}, crs=self.crs, name=self.name,
                          units=self.units, layout=self.layout)

    def require_metric(self, what: str = "this step") -> None:
        """Raise :class:`UnitsError` when the coordinates are known not to be metres (degrees, feet)."""
        self.units.require_metric(what, name=f"cloud {self.name!r}" if self.name else "the cloud")

    @property
    def bounds(self) -> np.ndarray:
        """Array [[xmin, ymin, zmin], [xmax, ymax, zmax]]."""
        if len(self) == 0:
            raise LabkitError("an empty cloud has no bounds")
        return np.vstack(extent(self.xyz))
