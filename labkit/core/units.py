"""Coordinate units from a CRS description: WKT (OGC/ESRI WKT1, WKT2), EPSG codes and GeoTIFF keys.

pyproj reads the CRS (the well-kept library for it): the units of the
horizontal and the vertical coordinate system come from its axes, EPSG codes
(``EPSG:2277``, a ProjectedCSType GeoKey) are looked up in its database. A
small bracket parser remains for WKT that PROJ refuses (abridged WKT1 without
a datum, as some LAS writers store): it finds the unit nodes that belong to the
horizontal and the vertical coordinate system.

Rules (documented in :func:`labkit.io.read_cloud`)
-------------------------------------------------
- Projected, engineering and geocentric CRS: the unit of their axes; geographic
  CRS: the angle unit (degrees); a 3D geographic CRS also gives the height unit.
- Compound CRS: horizontal from the first component, vertical from the vertical
  one. A bound CRS (a CRS with its datum transformation): its source CRS.
- A vertical unit that is not stated is taken equal to the horizontal linear
  unit (a note says so); for geographic CRS it stays unknown.
- GeoTIFF keys: ProjLinearUnitsGeoKey 3076 (or ProjLinearUnitSizeGeoKey 3077
  for a user-defined unit), GeogAngularUnitsGeoKey 2054, VerticalUnitsGeoKey
  4099, with EPSG unit codes 9001 m, 9002 ft, 9003 ftUS, ... Without a unit key
  the unit of the ProjectedCSType / VerticalCSType code (from the EPSG
  database) is used; when 3076 says otherwise the keys contradict themselves
  and the conflict is recorded.
- Both WKT and GeoKeys present: the LAS 1.4 global-encoding WKT bit decides,
  as the LAS specification says (bit set: WKT; not set: GeoTIFF keys); a LAS
  1.0-1.3 file uses its GeoKeys. A source that names no unit leaves the
  decision to the other one. Differing units are recorded as a conflict.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass

import numpy as np

from .errors import LabkitError


class UnitsError(LabkitError):
    """The coordinates are not in metres (degrees of longitude/latitude, feet) where metres are needed."""


_SHORT = {"metre": "m", "US survey foot": "ftUS", "foot": "ft", "degree": "deg", "radian": "rad",
          "grad": "gon", "kilometre": "km", "unknown": "?"}
_ANGULAR = ("degree", "radian", "grad")


@dataclass(frozen=True)
class Units:
    """Units of a cloud's file and of its coordinates.

    Parameters
    ----------
    horizontal, vertical : str
        Unit of X/Y and of Z in the file's CRS (``"metre"``, ``"US survey foot"``,
        ``"foot"``, ``"degree"``, ... or ``"unknown"`` when the file states none).
    horizontal_to_metre, vertical_to_metre : float or None
        Metres per file unit (1200/3937 for the US survey foot, 0.3048 for the
        international foot); None for angles and unknown units.
    converted : bool
        True when the coordinates were converted from the file's units to metres
        (``read_cloud(units="m")``); then ``xyz`` is in metres on all axes.
    source : str
        Where the units come from: ``"WKT"``, ``"GeoKeys"`` or ``"none"``.
    conflict : str or None
        WKT and GeoKeys (or the GeoKeys among themselves) disagree: what each
        says and which one was used.
    note : str
        Assumptions made (e.g. an unstated vertical unit taken equal to the horizontal one).
    """

    horizontal: str = "unknown"
    vertical: str = "unknown"
    horizontal_to_metre: float | None = None
    vertical_to_metre: float | None = None
    converted: bool = False
    source: str = "none"
    conflict: str | None = None
    note: str = ""

    @property
    def angular(self) -> bool:
        """X/Y are longitude/latitude angles."""
        return self.horizontal in _ANGULAR or self.horizontal.startswith("angle unit")

    @property
    def angle_text(self) -> str:
        """``degrees of longitude/latitude`` (or the angle unit's name) for messages."""
        if self.horizontal in _ANGULAR:
            return f"{self.horizontal}s of longitude/latitude"
        return f"longitude/latitude ({self.horizontal})"

    @property
    def coordinates(self) -> tuple[str, str]:
        """Units of ``xyz`` as held now: (X/Y unit, Z unit)."""
        return ("metre", "metre") if self.converted else (self.horizontal, self.vertical)

    @property
    def is_metric(self) -> bool:
        """The coordinates are known to be in metres on every axis."""
        return self.coordinates == ("metre", "metre")

    @property
    def known(self) -> bool:
        return self.horizontal != "unknown"

    @property
    def factors(self) -> "np.ndarray | None":
        """Metres per file unit for x, y, z, or None when not convertible."""
        if self.horizontal_to_metre is None or self.vertical_to_metre is None:
            return None
        h, v = self.horizontal_to_metre, self.vertical_to_metre
        return np.array([h, h, v])

    def axis_labels(self, native: bool = False) -> tuple[str, str, str]:
        """Short unit labels of x, y, z (``m``, ``ftUS``, ``ft``, ``deg``, ``?``) now or in the file."""
        h, v = (self.horizontal, self.vertical) if native else self.coordinates
        h, v = _SHORT.get(h, h), _SHORT.get(v, v)
        return h, h, v

    def label(self, native: bool = False) -> str:
        """``"m"`` or ``"m (x, y), ftUS (z)"``; ``"units not stated"`` when unknown."""
        h, _, v = self.axis_labels(native)
        if h == "?" and v == "?":
            return "units not stated"
        return h if h == v else f"{h} (x, y), {v} (z)"

    def describe(self) -> str:
        """One line for reports: file units, conversion, source, conflict."""
        if not self.known:
            return "not stated in the file (taken as metres)"
        text = f"file: X/Y {self.horizontal}, Z {self.vertical} (from {self.source})"
        if self.converted:
            text += "; converted to metres"
        if self.conflict:
            text += f"; CONFLICT: {self.conflict}"
        return text

    def require_metric(self, what: str = "this step", name: str = "the cloud") -> None:
        """Raise :class:`UnitsError` unless the coordinates may be taken as metres."""
        if self.angular:
            raise UnitsError(
                f"{name} is in {self.angle_text}; {what} needs metric coordinates: "
                "project it to a metric CRS (e.g. UTM) first"
            )
        h, v = self.coordinates
        bad = [u for u in (h, v) if u not in ("metre", "unknown")]
        if bad:
            raise UnitsError(
                f"{name} has coordinates in {self.label()} ({self.describe()}); {what} takes its distances in "
                "metres: read the file with read_cloud(path) (units='m', the default) to convert"
            )


US_FOOT = 1200.0 / 3937.0
FOOT = 0.3048
DEGREE = math.pi / 180.0

# EPSG unit-of-measure codes -> (name, factor to metre or radian, kind)
EPSG_UNITS = {
    9001: ("metre", 1.0, "length"),
    9002: ("foot", FOOT, "length"),
    9003: ("US survey foot", US_FOOT, "length"),
    9005: ("Clarke's foot", 0.3047972654, "length"),
    9036: ("kilometre", 1000.0, "length"),
    9101: ("radian", 1.0, "angle"),
    9102: ("degree", DEGREE, "angle"),
    9105: ("grad", math.pi / 200.0, "angle"),
    9122: ("degree", DEGREE, "angle"),
}

_ALIASES = {"meter": "metre", "metre": "metre", "m": "metre", "degree": "degree", "radian": "radian"}


# ============================================================================ unit names
def unit_name(factor: float, kind: str, label: str = "") -> str:
    """Canonical name from the conversion factor (to metre or radian)."""
    if kind == "angle":
        for name, f in (("degree", DEGREE), ("radian", 1.0), ("grad", math.pi / 200.0)):
            if math.isclose(factor, f, rel_tol=1e-8):
                return name
        return f"angle unit {label!r} of {factor:g} rad"
    for name, f in (("metre", 1.0), ("US survey foot", US_FOOT), ("foot", FOOT), ("kilometre", 1000.0)):
        if math.isclose(factor, f, rel_tol=1e-9):
            return name
    return label or f"length unit of {factor:g} m"


# ============================================================================ WKT parser
class _Node:
    __slots__ = ("key", "args")

    def __init__(self, key: str):
        self.key, self.args = key.upper(), []

    def nodes(self, *keys):
        return [a for a in self.args if isinstance(a, _Node) and (not keys or a.key in keys)]

    def first(self, *keys):
        found = self.nodes(*keys)
        return found[0] if found else None

    def name(self) -> str:
        return self.args[0] if self.args and isinstance(self.args[0], str) else ""


_TOKEN = re.compile(r'\s*(?:(?P<str>"(?:[^"]|"")*")|(?P<word>[A-Za-z_][A-Za-z0-9_]*)|(?P<num>[-+]?[0-9.][0-9.eE+-]*)|(?P<open>[\[(])|(?P<close>[\])])|(?P<comma>,))')


def parse_wkt(text: str) -> _Node | None:
    """A tree of WKT nodes, or None when the text is not WKT."""
    text = (text or "").strip().rstrip("\x00").strip()
    pos, stack, root, key = 0, [], None, None
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            return None
        pos = m.end()
        kind = m.lastgroup
        if kind == "word":
            word, nxt = m.group("word"), text[pos:].lstrip()[:1]
            if nxt and nxt in "[(":
                key = word
            elif stack:  # enumeration value such as EAST or Cartesian
                stack[-1].args.append(word)
            else:
                return None
        elif kind == "open":
            if key is None:
                return None
            node = _Node(key)
            key = None
            if stack:
                stack[-1].args.append(node)
            elif root is None:
                root = node
            else:
                return None
            stack.append(node)
        elif kind == "close":
            if not stack:
                return None
            stack.pop()
        elif kind == "str" and stack:
            stack[-1].args.append(m.group("str")[1:-1].replace('""', '"'))
        elif kind == "num" and stack:
            try:
                stack[-1].args.append(float(m.group("num")))
            except ValueError:
                return None
        elif kind == "comma":
            continue
        else:
            return None
        if root is not None and not stack:
            break
    return root if root is not None and not stack else None


_HORIZONTAL_LINEAR = ("PROJCS", "PROJCRS", "PROJECTEDCRS", "GEOCCS", "LOCAL_CS", "ENGCRS", "ENGINEERINGCRS")
_GEOGRAPHIC = ("GEOGCS", "GEOGCRS", "GEOGRAPHICCRS", "GEODCRS", "GEODETICCRS")
_VERTICAL = ("VERT_CS", "VERTCRS", "VERTICALCRS")
_COMPOUND = ("COMPD_CS", "COMPOUNDCRS")
_UNIT_KEYS = ("UNIT", "LENGTHUNIT", "ANGLEUNIT")


def _unit_of(node: _Node, default_kind: str):
    """(name, factor, kind) of the unit that belongs to this CRS node, or None."""
    for holder in [node] + node.nodes("AXIS") + [c for c in node.nodes("CS")]:
        for u in holder.nodes(*_UNIT_KEYS):
            numbers = [a for a in u.args if isinstance(a, float)]
            if not numbers or numbers[0] <= 0:
                continue
            kind = "angle" if u.key == "ANGLEUNIT" else "length" if u.key == "LENGTHUNIT" else default_kind
            return unit_name(numbers[0], kind, u.name()), numbers[0], kind
    return None


def _crs_units(node: _Node):
    """(horizontal, vertical) units of one CRS node; compound CRS are searched part by part."""
    if node.key in _VERTICAL:
        return None, _unit_of(node, "length")
    if node.key in _HORIZONTAL_LINEAR:
        return _unit_of(node, "length"), None
    if node.key in _GEOGRAPHIC:
        unit = _unit_of(node, "angle")
        if unit is None and node.key in ("GEOGCRS", "GEOGRAPHICCRS"):
            unit = ("degree", DEGREE, "angle")  # WKT2 geographic CRS without a stated unit
        return unit, None
    horizontal, vertical = None, None
    for part in node.nodes():  # COMPD_CS / COMPOUNDCRS
        h, v = _crs_units(part)
        horizontal, vertical = horizontal or h, vertical or v
    return horizontal, vertical


def units_from_wkt(text: str):
    """(horizontal, vertical) as (name, factor, kind) or None each; None when the text is no CRS.

    pyproj reads the WKT; the bracket parser only takes WKT that PROJ refuses.
    """
    crs = pyproj_crs(text) if text and text.lstrip()[:1].isalpha() and "[" in text else None
    if crs is not None:
        return units_of_crs(crs)
    root = parse_wkt(text)
    if root is not None and root.key == "BOUNDCRS":  # a CRS with its datum transformation: the source CRS
        source = root.first("SOURCECRS")
        root = source.nodes()[0] if source is not None and source.nodes() else None
    if root is None or root.key not in _COMPOUND + _VERTICAL + _HORIZONTAL_LINEAR + _GEOGRAPHIC:
        return None
    return _crs_units(root)


# ============================================================================ pyproj
_CANONICAL = {"metre": 1.0, "US survey foot": US_FOOT, "foot": FOOT, "kilometre": 1000.0,
              "degree": DEGREE, "radian": 1.0, "grad": math.pi / 200.0}


def _unit(factor: float, kind: str, label: str = ""):
    """(name, factor, kind) with the defining factor for the units labkit knows by name."""
    name = unit_name(factor, kind, label)
    return name, _CANONICAL.get(name, factor), kind


@functools.lru_cache(maxsize=256)
def pyproj_crs(text: str):
    """The pyproj CRS of a WKT text or ``EPSG:code`` (``EPSG:h+v`` for a compound), or None."""
    import pyproj

    text = (text or "").strip().rstrip("\x00").strip()
    if not text:
        return None
    try:
        if re.fullmatch(r"EPSG:\d+(\+\d+)?", text, flags=re.IGNORECASE):
            return pyproj.CRS.from_user_input(text.upper())
        return pyproj.CRS.from_wkt(text)
    except (pyproj.exceptions.CRSError, ValueError, TypeError):
        return None


def units_of_crs(crs):
    """(horizontal, vertical) as (name, factor, kind) or None each, from a pyproj CRS's axes."""
    if crs.is_bound:
        crs = crs.source_crs
    if crs.is_compound:
        horizontal, vertical = None, None
        for part in crs.sub_crs_list:
            h, v = units_of_crs(part)
            horizontal, vertical = horizontal or h, vertical or v
        return horizontal, vertical
    axes = [a for a in crs.axis_info if a.unit_conversion_factor and a.unit_conversion_factor > 0]
    if not axes:
        return None, None
    if crs.is_vertical:
        return None, _unit(axes[0].unit_conversion_factor, "length", axes[0].unit_name)
    kind = "angle" if crs.is_geographic else "length"
    horizontal = _unit(axes[0].unit_conversion_factor, kind, axes[0].unit_name)
    vertical = None
    if len(axes) >= 3:  # a 3D geographic CRS (ellipsoidal height) or a geocentric one
        vertical = _unit(axes[2].unit_conversion_factor, "length", axes[2].unit_name)
    return horizontal, vertical


@functools.lru_cache(maxsize=256)
def _epsg_units(code: int):
    """(horizontal, vertical) units of an EPSG CRS code from pyproj's database; (None, None) when unknown."""
    crs = pyproj_crs(f"EPSG:{code}")
    return (None, None) if crs is None else units_of_crs(crs)


# ============================================================================ GeoTIFF keys
def units_from_geokeys(keys: dict, doubles=()):
    """(horizontal, vertical, notes) from GeoKey id -> (location, count, value).

    ``horizontal``/``vertical`` are (name, factor, kind) or None.
    """
    notes = []

    def value(key):
        loc, _count, val = keys[key]
        if loc == 0:
            return int(val)
        if loc == 34736 and 0 <= val < len(doubles):
            return float(doubles[val])
        return None

    def code_unit(key, kind):
        if key not in keys:
            return None
        code = value(key)
        if code in EPSG_UNITS and EPSG_UNITS[code][2] == kind:
            name, f, k = EPSG_UNITS[code]
            return name, f, k
        if code == 32767 and key == 3076 and 3077 in keys and value(3077):
            f = value(3077)
            return unit_name(f, "length"), f, "length"
        notes.append(f"GeoKey {key} names unit code {code}, which labkit does not know")
        name = f"angle unit code {code}" if kind == "angle" else f"unit code {code}"
        return name, None, kind  # stated but not convertible: never taken for metres

    model = value(1024) if 1024 in keys else (1 if 3072 in keys else 2 if 2048 in keys else None)
    horizontal = None
    if model == 1:
        horizontal = code_unit(3076, "length")
        pcs = value(3072) if 3072 in keys else None
        implied = _epsg_units(pcs)[0] if pcs is not None and 1024 <= pcs <= 32766 else None
        if horizontal is None and implied is not None:
            horizontal = implied
            notes.append(f"{implied[0]} implied by the projected CRS EPSG:{pcs} (no ProjLinearUnitsGeoKey)")
        elif horizontal is not None and implied is not None and horizontal[0] != implied[0]:
            notes.append(
                f"GeoKeys contradict themselves: ProjectedCSType EPSG:{pcs} is a {implied[0]} CRS but "
                f"ProjLinearUnitsGeoKey says {horizontal[0]}"
            )
    elif model == 2:
        horizontal = code_unit(2054, "angle") or ("degree", DEGREE, "angle")
    elif model == 3:
        horizontal = code_unit(3076, "length") or ("metre", 1.0, "length")
    vertical = code_unit(4099, "length")
    vcs = value(4096) if 4096 in keys else None
    if vertical is None and vcs is not None and 1024 <= vcs <= 32766:
        vertical = _epsg_units(vcs)[1]
    return horizontal, vertical, notes


# ============================================================================ decision
def _describe(h, v) -> str:
    return f"X/Y in {h[0] if h else 'unstated units'}, Z in {v[0] if v else 'unstated units'}"


def _complete(hv):
    """(h, v, filled): an unstated vertical unit is taken equal to the horizontal linear unit."""
    h, v = hv
    if v is None and h is not None and h[2] == "length":
        return h, h, True
    return h, v, False


def decide_units(wkt_text: str | None, geokeys: dict | None, doubles=(), *, wkt_bit: bool = False,
                 las14: bool = False) -> Units:
    """Units of a LAS file from its WKT and/or GeoKeys (see the module notes for the rule)."""
    from_wkt = units_from_wkt(wkt_text) if wkt_text else None
    from_keys = units_from_geokeys(geokeys, doubles) if geokeys else None
    key_notes = from_keys[2] if from_keys else []
    wkt_hv = _complete(from_wkt) if from_wkt and from_wkt[0] else None
    key_hv = _complete(from_keys[:2]) if from_keys and from_keys[0] else None
    wkt_first = bool(las14 and wkt_bit) or from_keys is None
    order = [("WKT", wkt_hv), ("GeoKeys", key_hv)] if wkt_first else [("GeoKeys", key_hv), ("WKT", wkt_hv)]
    chosen = next(((src, hv) for src, hv in order if hv is not None), None)
    conflicts = [n for n in key_notes if "contradict" in n]
    notes = [n for n in key_notes if "contradict" not in n] if chosen and chosen[0] == "GeoKeys" else []
    if wkt_hv is not None and key_hv is not None:
        both_vertical = from_wkt[1] is not None and from_keys[1] is not None  # compare only stated Z units
        if wkt_hv[0][0] != key_hv[0][0] or (both_vertical and from_wkt[1][0] != from_keys[1][0]):
            conflicts.append(f"WKT says {_describe(*from_wkt)}; GeoKeys say {_describe(*from_keys[:2])}")
    if chosen is None:
        return Units(note="; ".join(notes))
    source, (h, v, filled) = chosen
    if filled:
        notes.append("vertical unit not stated; taken equal to the horizontal unit")
    if conflicts:
        why = ("the LAS 1.4 WKT bit is set" if source == "WKT" and las14 and wkt_bit
               else "without the LAS 1.4 WKT bit the GeoKeys govern" if source == "GeoKeys"
               else f"only the {source} names units")
        conflicts.append(f"used the {source} ({why})")
    return Units(
        horizontal=h[0], vertical=v[0] if v else "unknown",
        horizontal_to_metre=h[1] if h[2] == "length" else None,
        vertical_to_metre=v[1] if v and v[2] == "length" else None,
        source=source, conflict="; ".join(conflicts) or None, note="; ".join(notes),
    )


def units_from_crs_text(crs: str | None) -> Units:
    """Units implied by a cloud's CRS text (WKT or ``EPSG:h[+v]``)."""
    if not crs:
        return Units()
    m = re.fullmatch(r"\s*EPSG:(\d+)(?:\+(\d+))?\s*", crs, flags=re.IGNORECASE)
    if m is not None:
        code = int(m.group(1))
        crs_obj = pyproj_crs(f"EPSG:{code}")
        if crs_obj is not None and crs_obj.is_geographic:
            keys = {1024: (0, 1, 2), 2048: (0, 1, code)}
        else:
            keys = {1024: (0, 1, 1), 3072: (0, 1, code)}
        if m.group(2):
            keys[4096] = (0, 1, int(m.group(2)))
        return decide_units(None, keys)
    return decide_units(crs, None)
