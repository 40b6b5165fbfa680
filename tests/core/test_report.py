"""labkit.core.report: number formatting and the text / HTML reports every result shares."""

from dataclasses import dataclass

import numpy as np

from labkit.core.report import ReportMixin, fmt


@dataclass(frozen=True, repr=False)
class _Result(ReportMixin):
    name: str

    def _report(self):
        return f"Fit of {self.name}", [("", [("points", "12"), ("a longer label", "3.0 m")]),
                                       ("Residuals", [("rms", "<1 mm & more")])]


def test_fmt_scalars_vectors_units_and_non_finite():
    assert fmt(0.123456) == "0.1235" and fmt(2, 1, "m") == "2.0 m"
    assert fmt(np.float32(1.5), 2) == "1.50"
    assert fmt([1, 2.25], 1, "m") == "[1.0, 2.2] m"  # half to even, as Python's format
    assert fmt(np.eye(2), 0) == "[1, 0, 0, 1]"  # any shape: flattened
    assert fmt(np.nan, 3, "m") == "nan m" and fmt(-np.inf) == "-inf"


def test_summary_aligns_the_labels_and_underlines_title_and_headings():
    text = _Result("a sphere").summary()
    assert str(_Result("a sphere")) == text
    assert text.splitlines() == [
        "Fit of a sphere",
        "===============",
        "points          12",
        "a longer label  3.0 m",
        "",
        "Residuals",
        "---------",
        "rms             <1 mm & more",
    ]


def test_repr_is_one_line_and_html_escapes_what_it_shows():
    r = _Result("<b>x</b>")
    assert repr(r) == "<_Result: Fit of <b>x</b>>"
    page = r._repr_html_()
    assert "<b>x</b>" not in page and "&lt;b&gt;x&lt;/b&gt;" in page
    assert "&lt;1 mm &amp; more" in page and page.count("<tr>") == 4  # three rows and one heading
