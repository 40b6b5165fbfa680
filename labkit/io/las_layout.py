"""The layout of a LAS/LAZ file a cloud was read from, so that writing it back changes only the coordinates.

A cloud read from LAS keeps a :class:`LasLayout`: a copy of the file's header
(LAS version, point format with its extra-bytes definitions, scales, offsets,
global encoding, VLRs and EVLRs). :func:`labkit.io.write_cloud` builds the new
header from it: the same version and point format, every VLR (CRS included),
the extra bytes with their own types, scales and offsets, and the input's scale
(or a finer one) with its offsets where the new coordinates fit them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.arrays import extent
from .common import INT32_MAX

_CRS_VLRS = ("GeoKeyDirectoryVlr", "GeoDoubleParamsVlr", "GeoAsciiParamsVlr", "WktCoordinateSystemVlr")


@dataclass(frozen=True, eq=False)
class LasLayout:
    """What a LAS/LAZ file holds besides its points (kept on the cloud read from it).

    Parameters
    ----------
    header : laspy.LasHeader
        A private copy of the file's header.
    crs : str or None
        The CRS text the cloud was given on reading (the VLRs are copied only while the
        cloud keeps this CRS).
    """

    header: object
    crs: str | None = None

    @classmethod
    def of(cls, header, crs) -> "LasLayout":
        return cls(header.copy(), crs)

    @property
    def version(self) -> str:
        return f"{self.header.version.major}.{self.header.version.minor}"

    @property
    def point_format(self) -> int:
        return int(self.header.point_format.id)

    @property
    def scales(self) -> np.ndarray:
        return np.asarray(self.header.scales, dtype=np.float64)

    @property
    def offsets(self) -> np.ndarray:
        return np.asarray(self.header.offsets, dtype=np.float64)

    @property
    def extra_names(self) -> tuple:
        return tuple(self.header.point_format.extra_dimension_names)

    def fits(self, attrs: dict, standard_names) -> bool:
        """The layout's point format can hold these attributes (no standard dimension it lacks)."""
        dims = set(self.header.point_format.dimension_names)
        return all(name in dims or name not in standard_names for name in attrs)

    def header_for(self, attrs: dict, crs, scales) -> object:
        """A fresh header in this layout for a cloud with these attributes, CRS and scales.

        Extra dimensions the cloud no longer has are dropped; the CRS records are kept
        only while the cloud's CRS is the one read (else the caller writes the new one).
        """
        header = self.header.copy()
        header.partial_reset()
        gone = [n for n in header.point_format.extra_dimension_names if n not in attrs]
        if gone:
            header.remove_extra_dims(gone)
        if crs != self.crs:
            for name in _CRS_VLRS:
                for rec in header.vlrs.get(name):
                    header.vlrs.remove(rec)
            if header.evlrs is not None:
                header.evlrs = [r for r in header.evlrs if type(r).__name__ not in _CRS_VLRS]
            if header.version.minor >= 4:
                header.global_encoding.wkt = False
        header.scales = np.asarray(scales, dtype=np.float64)
        return header

    def offsets_for(self, xyz: np.ndarray, scales) -> np.ndarray | None:
        """The file's offsets when the coordinates still fit the int32 range with them, else None."""
        if len(xyz) == 0:
            return self.offsets
        q = (np.vstack(extent(xyz)) - self.offsets) / np.asarray(scales)
        return self.offsets if np.abs(q).max() <= 0.9 * INT32_MAX else None
