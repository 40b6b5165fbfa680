"""What every reader and writer shares: the suffixes, the types of the LAS dimensions, the
spellings of column names, and the checks of paths and arguments."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..core.errors import CloudFileError, LabkitError

LAS_SUFFIXES = (".las", ".laz")
ASCII_SUFFIXES = (".xyz", ".txt", ".csv", ".asc")
NUMPY_SUFFIXES = (".npy", ".npz")
PLY_SUFFIXES = (".ply",)
UNIT_CHOICES = ("m", "native")
SCAN_ANGLE_STEP = 0.006  # degrees per unit of the LAS 1.4 scan_angle field
DEFAULT_CHUNK = 1_000_000
INT32_MAX = 2**31 - 1

# laspy dtypes of the standard dimensions that can arrive as text or npz columns
STANDARD_DTYPES = {
    "intensity": np.uint16,
    "return_number": np.uint8,
    "number_of_returns": np.uint8,
    "classification": np.uint8,
    "scan_direction_flag": np.uint8,
    "edge_of_flight_line": np.uint8,
    "synthetic": np.uint8,
    "key_point": np.uint8,
    "withheld": np.uint8,
    "overlap": np.uint8,
    "scanner_channel": np.uint8,
    "scan_angle_rank": np.int8,
    "scan_angle": np.int16,
    "user_data": np.uint8,
    "point_source_id": np.uint16,
    "gps_time": np.float64,
    "red": np.uint16,
    "green": np.uint16,
    "blue": np.uint16,
    "nir": np.uint16,
}
# spellings found in ASCII headers (CloudCompare, LAStools, PDAL) -> laspy name
_ALIASES = {
    "class": "classification",
    "classification": "classification",
    "intensity": "intensity",
    "returnnumber": "return_number",
    "numberofreturns": "number_of_returns",
    "gpstime": "gps_time",
    "pointsourceid": "point_source_id",
    "userdata": "user_data",
    "scanangle": "scan_angle",
    "scananglerank": "scan_angle_rank",
    "scanchannel": "scanner_channel",
    "scannerchannel": "scanner_channel",
    "scandirectionflag": "scan_direction_flag",
    "edgeofflightline": "edge_of_flight_line",
    "keypoint": "key_point",
    "scalarintensity": "intensity",
    "scalarclassification": "classification",
    "r": "red",
    "g": "green",
    "b": "blue",
}


def canonical_name(token: str) -> str:
    """Header spelling -> laspy-style name ('//X' -> 'x', 'GpsTime' -> 'gps_time')."""
    word = token.strip().lstrip("/#").strip().strip('"').strip("'")
    squeezed = re.sub(r"[^0-9a-z]", "", word.lower())
    if squeezed in ("x", "y", "z"):
        return squeezed
    if squeezed in _ALIASES:
        return _ALIASES[squeezed]
    return re.sub(r"[^0-9a-z]+", "_", word.lower()).strip("_") or "column"


def attribute_names(attributes) -> set | None:
    """The attribute selection as a set of names; a bare string is one name."""
    if attributes is None:
        return None
    if isinstance(attributes, str):
        return {attributes}
    try:
        names = list(attributes)
    except TypeError:
        raise LabkitError(f"attributes must be a name or a sequence of names, got {attributes!r}") from None
    bad = [a for a in names if not isinstance(a, str)]
    if bad:
        raise LabkitError(f"attributes must be names (str), got {bad[0]!r}")
    return set(names)


def existing_file(path) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise CloudFileError(f"a point-cloud file path (str or Path) is needed, got {type(path).__name__}")
    if isinstance(path, str) and not path.strip():
        raise CloudFileError("a point-cloud file path is needed, got an empty string")
    path = Path(path)
    if not path.exists():
        raise CloudFileError(f"point-cloud file not found: {path}")
    if not path.is_file():
        raise CloudFileError(f"not a file: {path}")
    if not os.access(path, os.R_OK):
        raise CloudFileError(f"no permission to read {path}")
    return path


def unsupported_format(path: Path) -> str:
    known = " ".join(LAS_SUFFIXES + ASCII_SUFFIXES + NUMPY_SUFFIXES + PLY_SUFFIXES)
    return f"unsupported point-cloud format {path.suffix!r} of {path}; known suffixes: {known}"


def require_classification(flt: ReadFilter, names, path: Path) -> None:
    if flt.classes is not None and "classification" not in names:
        raise CloudFileError(f"{path} has no classification, so it cannot be filtered by class")
