"""Coordinate units from a CRS description: WKT (OGC/ESRI WKT1, WKT2) and GeoTIFF keys.

No pyproj: a small bracket parser finds the unit nodes that belong to the
horizontal and the vertical coordinate system, and a table of EPSG unit codes
reads the GeoTIFF keys of a LAS file.

Rules (documented in :func:`labkit.io.read_cloud`)
-------------------------------------------------
- WKT1 ``PROJCS``/``GEOCCS``/``VERT_CS``/``LOCAL_CS``: the ``UNIT`` that is a
  direct child of that node (the one inside ``GEOGCS`` is the base CRS's angle).
  ``GEOGCS`` -> its angular unit.
- WKT2 ``PROJCRS``/``VERTCRS``/``ENGCRS``/``GEODCRS``: a ``LENGTHUNIT``/``ANGLEUNIT``/
  ``UNIT`` child of the CRS node or of its ``AXIS`` nodes; ``CONVERSION`` and
  ``BASEGEOGCRS`` are skipped (their units are those of parameters).
- Compound CRS (``COMPD_CS``/``COMPOUNDCRS``): horizontal from the first
  component, vertical from the vertical one. ``BOUNDCRS``: its source CRS.
- A vertical unit that is not stated is taken equal to the horizontal linear
  unit (a note says so); for geographic CRS it stays unknown.
- GeoTIFF keys: ProjLinearUnitsGeoKey 3076 (or ProjLinearUnitSizeGeoKey 3077
  for a user-defined unit), GeogAngularUnitsGeoKey 2054, VerticalUnitsGeoKey
  4099, with EPSG unit codes 9001 m, 9002 ft, 9003 ftUS, ... A projected CRS
  code from a family known to be in metres (UTM, NAD83 state plane in m, ...)
  implies metres when 3076 is absent; when 3076 says otherwise the keys
  contradict themselves and the conflict is recorded.
- Both WKT and GeoKeys present: the LAS 1.4 global-encoding WKT bit decides,
  as the LAS specification says (bit set: WKT; not set: GeoTIFF keys); a LAS
  1.0-1.3 file uses its GeoKeys. A source that names no unit leaves the
  decision to the other one. Differing units are recorded as a conflict.
"""

from __future__ import annotations

import math
import re

from .cloud import Units

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

# EPSG projected CRS codes known to be in metres (used when no unit key says so)
_METRE_CRS_RANGES = (
    (32601, 32660), (32701, 32760),  # WGS 84 / UTM
    (26901, 26923), (26929, 26998), (32100, 32161),  # NAD83 / UTM, NAD83 / state plane (m)
    (25828, 25838), (3040, 3051),  # ETRS89 / UTM
    (28348, 28358), (7846, 7859),  # GDA94 / GDA2020 MGA
    (31466, 31469), (2154, 2154), (27700, 27700), (2180, 2180), (2056, 2056), (3857, 3857),
    (3006, 3006), (2193, 2193), (3035, 3035), (3034, 3034), (21781, 21781),
)

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
    """(horizontal, vertical) as (name, factor, kind) or None each; None when the text is no CRS."""
    root = parse_wkt(text)
    if root is not None and root.key == "BOUNDCRS":  # a CRS with its datum transformation: the source CRS
        source = root.first("SOURCECRS")
        root = source.nodes()[0] if source is not None and source.nodes() else None
    if root is None or root.key not in _COMPOUND + _VERTICAL + _HORIZONTAL_LINEAR + _GEOGRAPHIC:
        return None
    return _crs_units(root)


# ============================================================================ GeoTIFF keys
def _metre_crs(code) -> bool:
    return code is not None and any(lo <= code <= hi for lo, hi in _METRE_CRS_RANGES)


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
        if horizontal is None and _metre_crs(pcs):
            horizontal = ("metre", 1.0, "length")
            notes.append(f"metre implied by the projected CRS EPSG:{pcs} (no ProjLinearUnitsGeoKey)")
        elif horizontal is not None and _metre_crs(pcs) and horizontal[0] != "metre":
            notes.append(
                f"GeoKeys contradict themselves: ProjectedCSType EPSG:{pcs} is a metre CRS but "
                f"ProjLinearUnitsGeoKey says {horizontal[0]}"
            )
    elif model == 2:
        horizontal = code_unit(2054, "angle") or ("degree", DEGREE, "angle")
    elif model == 3:
        horizontal = code_unit(3076, "length") or ("metre", 1.0, "length")
    vertical = code_unit(4099, "length")
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
        if 4000 <= code < 5000:
            keys = {1024: (0, 1, 2), 2048: (0, 1, code)}
        else:
            keys = {1024: (0, 1, 1), 3072: (0, 1, code)}
        return decide_units(None, keys)
    return decide_units(crs, None)
