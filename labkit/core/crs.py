"""Do two inputs share a coordinate reference system? Compared through pyproj.

One call at the entry of every computation that takes two clouds (ICP, maximum
consensus, cloud-to-cloud and point-to-plane distances, M3C2, tiles, the
command line): :func:`check_same_crs`. Two different CRS raise
:class:`labkit.core.errors.CrsMismatchError` naming both; a CRS on one side only is
noted (:class:`labkit.core.errors.CrsNote` warning, printed by the command line) and
the clouds are taken to be in one frame; no CRS on either side passes silently.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from .units import pyproj_crs, units_from_crs_text
from .errors import CrsMismatchError, CrsNote, LabkitError
from ..io import LAS_SUFFIXES, cloud_files, cloud_info

#: what a result and its files say when the input stated no CRS (a warning alone would be lost)
NO_CRS = "no CRS in the input: coordinates in an unknown frame"


def crs_of(data) -> str | None:
    """The CRS text of a PointCloud, of LAS/LAZ files (headers only) or None (arrays, text files)."""
    crs = getattr(data, "crs", None)
    if isinstance(crs, str) or crs is None and hasattr(data, "xyz"):
        return crs or None
    if isinstance(data, (str, Path)) or (isinstance(data, (list, tuple)) and data
                                         and all(isinstance(p, (str, Path)) for p in data)):
        try:
            paths = [p for p in cloud_files(data) if p.suffix.lower() in LAS_SUFFIXES]
            found = {cloud_info(p).crs for p in paths} - {None}
        except LabkitError:
            return None  # the reader reports a bad file in its own words
        return sorted(found)[0] if found else None
    return None


def _horizontal_vertical(crs):
    if crs.is_bound:
        crs = crs.source_crs
    if crs.is_compound:
        parts = crs.sub_crs_list
        vertical = next((p for p in parts if p.is_vertical), None)
        return parts[0], vertical
    return (None, crs) if crs.is_vertical else (crs, None)


def _same(a, b) -> bool:
    if a is None or b is None:
        return True  # a part only one of them states is not compared
    if a.equals(b, ignore_axis_order=True):
        return True
    ea, eb = a.to_epsg(min_confidence=70), b.to_epsg(min_confidence=70)
    return ea is not None and ea == eb


def same_crs(a: str, b: str) -> bool | None:
    """Whether two CRS texts (WKT or ``EPSG:code``) describe one CRS (parts stated by both compared).

    None when pyproj cannot read one of them and their units agree (not comparable); False when the
    units already differ.

    Examples
    --------
    >>> from labkit.core.crs import same_crs
    >>> import pyproj
    >>> same_crs("EPSG:25832", pyproj.CRS.from_epsg(25832).to_wkt()), same_crs("EPSG:25832", "EPSG:25833")
    (True, False)
    """
    if a.strip() == b.strip():
        return True
    ca, cb = pyproj_crs(a), pyproj_crs(b)
    if ca is None or cb is None:  # not comparable beyond their units
        ua, ub = units_from_crs_text(a), units_from_crs_text(b)
        known = ua.known and ub.known
        return False if known and (ua.horizontal, ua.vertical) != (ub.horizontal, ub.vertical) else None
    (ha, va), (hb, vb) = _horizontal_vertical(ca), _horizontal_vertical(cb)
    local = [c for c in (ha, hb) if c is not None and c.type_name == "Engineering CRS"]
    if local and ha is not None and hb is not None and ha.name != hb.name:
        return None  # local frames (LOCAL_CS, ENGCRS) of other names: PROJ cannot tell whether they agree
    return _same(ha, hb) and _same(va, vb)


def describe_crs(text: str) -> str:
    """``name (EPSG:code)`` of a CRS text, for messages."""
    crs = pyproj_crs(text)
    if crs is None:
        return repr(text if len(text) <= 60 else text[:57] + "...")
    code = crs.to_epsg(min_confidence=70)
    return f"{crs.name} (EPSG:{code})" if code else crs.name


def crs_summary(crs: str | None) -> str:
    """A result's CRS for its summary: ``name (EPSG:code)``, or :data:`NO_CRS` when the input stated none.

    Examples
    --------
    >>> from labkit.core.crs import crs_summary
    >>> crs_summary("EPSG:25832"), crs_summary(None)
    ('ETRS89 / UTM zone 32N (EPSG:25832)', 'no CRS in the input: coordinates in an unknown frame')
    """
    return describe_crs(crs) if crs else NO_CRS


def check_same_crs(a, b, what: str, names=("source", "target")) -> None:
    """Refuse two inputs in different CRS; note (warning) a CRS stated by one input only.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.core.crs import check_same_crs
    >>> from labkit.cloud import PointCloud
    >>> check_same_crs(np.zeros((2, 3)), PointCloud(np.zeros((2, 3))), "icp")  # no CRS anywhere: nothing said
    """
    ca, cb = crs_of(a), crs_of(b)
    if ca is None and cb is None:
        return
    if ca is None or cb is None:
        stated, missing = (names[0], names[1]) if ca else (names[1], names[0])
        warnings.warn(f"{what}: the {missing} states no CRS, the {stated} is in {describe_crs(ca or cb)}; "
                      "both are taken to be in that frame", CrsNote, stacklevel=3)
        return
    same = same_crs(ca, cb)
    if same is None:
        warnings.warn(f"{what}: the CRS of the {names[0]} ({describe_crs(ca)}) and of the {names[1]} "
                      f"({describe_crs(cb)}) cannot be compared (pyproj reads one of them not); both are taken "
                      "to be in one frame", CrsNote, stacklevel=3)
    elif not same:
        raise CrsMismatchError(f"{what}: the {names[0]} is in {describe_crs(ca)} but the {names[1]} in "
                               f"{describe_crs(cb)}; reproject one of them to the other's CRS first")
