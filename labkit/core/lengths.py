"""Lengths as text: a unit and a number of decimals that fit the standard deviation.

``length_text(0.00012, 0.00004)`` gives ``"0.12 +- 0.04 mm"``, never ``"0.0001 +- 0.0000 m"``:
the standard deviation is shown with two significant digits and the value with the same
decimals; millimetres where the value and its standard deviation are below 10 cm.
"""

from __future__ import annotations

import math


def length_unit(value: float, std: float | None = None) -> tuple[str, float]:
    """``("mm", 1000.0)`` or ``("m", 1.0)``: the unit to print a length (and its std) in."""
    sizes = [abs(value)] + ([abs(std)] if std is not None and math.isfinite(std) else [])
    big = max(sizes) if all(math.isfinite(s) for s in sizes) else math.inf
    return ("mm", 1000.0) if 0 < big < 0.1 else ("m", 1.0)


def length_text(value: float, std: float | None = None, *, sign: bool = False, unit: str | None = None) -> str:
    """A length in metres as text with its unit, e.g. ``"3.10 m"``, ``"+12.3 +- 1.4 mm"``.

    Examples
    --------
    >>> from labkit.core.lengths import length_text
    >>> length_text(0.00012, 0.00004), length_text(3.1), length_text(-0.2972, 0.0663, sign=True)
    ('0.120 +- 0.040 mm', '3.100 m', '-0.297 +- 0.066 m')
    >>> length_text(0.0, float("inf")), length_text(0.0044)
    ('0.000 +- inf m (not determined)', '4.4 mm')
    >>> length_text(73.00012, 0.00004)
    '73.000120 +- 0.000040 m'

    """
    value, std = float(value), None if std is None else float(std)
    name, f = (unit, {"mm": 1000.0, "m": 1.0, "cm": 100.0}[unit]) if unit else length_unit(value, std)
    if std is not None and math.isfinite(std) and std > 0:
        decimals = max(0, 1 - math.floor(math.log10(std * f)))
    else:
        decimals = 1 if name == "mm" else 3
    v = f"{value * f:+.{decimals}f}" if sign else f"{value * f:.{decimals}f}"
    if std is None:
        return f"{v} {name}"
    if not math.isfinite(std):
        return f"{v} +- inf {name} (not determined)"
    return f"{v} +- {std * f:.{decimals}f} {name}"
