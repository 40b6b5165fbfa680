"""Plain-text and HTML rendering shared by all result dataclasses.

A result implements ``_report()`` returning ``(title, sections)`` where each
section is ``(heading, rows)`` and each row is ``(label, value_text)``. The
mixin turns that into ``summary()`` (text) and ``_repr_html_()`` (notebooks).
"""

from __future__ import annotations

import html

import numpy as np

Row = tuple[str, str]
Section = tuple[str, list[Row]]


def fmt(value, digits: int = 4, unit: str = "") -> str:
    """Format a number (or a short vector) for a report."""
    suffix = f" {unit}" if unit else ""
    arr = np.asarray(value)
    if arr.ndim == 0:
        v = float(arr)
        if not np.isfinite(v):
            return f"{v}{suffix}"
        return f"{v:.{digits}f}{suffix}"
    return "[" + ", ".join(f"{float(v):.{digits}f}" for v in arr.ravel()) + "]" + suffix


class ReportMixin:
    """Adds ``summary()``, ``__str__`` and ``_repr_html_`` from ``_report()``."""

    def _report(self) -> tuple[str, list[Section]]:  # pragma: no cover - abstract
        raise NotImplementedError

    def summary(self) -> str:
        """A readable multi-line text report of the result."""
        title, sections = self._report()
        width = max([len(label) for _, rows in sections for label, _ in rows] + [10])
        lines = [title, "=" * len(title)]
        for heading, rows in sections:
            if heading:
                lines += ["", heading, "-" * len(heading)]
            lines += [f"{label:<{width}}  {value}" for label, value in rows]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def __repr__(self) -> str:
        # one line; dataclasses using the mixin declare ``repr=False`` so that this one applies
        return f"<{type(self).__name__}: {self._report()[0]}>"

    def _repr_html_(self) -> str:
        title, sections = self._report()
        parts = [f"<div class='labkit-report'><h4>{html.escape(title)}</h4><table>"]
        for heading, rows in sections:
            if heading:
                parts.append(f"<tr><th colspan='2' style='text-align:left'>{html.escape(heading)}</th></tr>")
            for label, value in rows:
                parts.append(
                    f"<tr><td style='text-align:left'>{html.escape(label)}</td>"
                    f"<td style='text-align:left;font-family:monospace'>{html.escape(value)}</td></tr>"
                )
        parts.append("</table></div>")
        return "".join(parts)
