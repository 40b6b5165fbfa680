"""``labkit demo --quick``: every step runs, prints its summary and writes its figures."""

import csv

import numpy as np
import pytest

from labkit import demo
from labkit.cli.main import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EXPECTED = {
    "sphere_ransac_trace.png", "sphere_ransac_inliers.png", "sphere_convergence.png", "sphere_residuals.png",
    "sphere_ellipsoid.png", "sphere_residuals_3d.png",
    "registration_xyz_als-als.png", "registration_demolished_changes.png", "registration_xz_als-dim.png",
    "comparison.csv", "comparison_components.png", "comparison_arrows.png", "comparison_errors.png",
}


def test_demo_steps_are_the_three_parts():
    titles = [title for title, _ in demo._steps()]
    assert len(titles) == 3
    assert "RANSAC" in titles[0] and "ICP" in titles[1] and "Comparison" in titles[2]


@pytest.mark.slow
def test_demo_quick_writes_figures_and_table(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    for heading in ("RANSAC sphere detection", "Sphere adjustment (Gauss-Helmert model)", "Against the truth",
                    "Comparison: 3 methods x 3 regions x 3 cases", "Demo finished"):
        assert heading in text
    names = {p.name for p in out.iterdir()}
    assert names == EXPECTED  # and no temporary files left behind
    for name in EXPECTED - {"comparison.csv"}:
        data = (out / name).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 10_000, name
    rows = list(csv.DictReader((out / "comparison.csv").open()))
    assert len(rows) == 9
    # ICP recovers the true shift on the constrained axes to about a centimetre even in the quick setting
    for r in rows:
        if r["method"] == "icp":
            assert float(r["error_norm_constrained"]) < 0.02, r
            assert np.isfinite(float(r["dx"]))


def test_a_failing_step_leaves_nothing_new(tmp_path, monkeypatch, capsys):
    """Figures of earlier steps do not stay behind when a later step fails; an existing folder keeps its files."""
    from labkit.core.errors import LabkitError

    def first(out, quick):
        return [demo._save(_figure(), out / "first.png")]

    def second(out, quick):
        raise LabkitError("step two failed")

    monkeypatch.setattr(demo, "_steps", lambda: [("one", first), ("two", second)])
    assert main(["demo", "--out", str(tmp_path / "new" / "demo")]) == 2
    assert "step two failed" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "old.txt").write_text("keep")
    assert main(["demo", "--out", str(tmp_path)]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.txt"]
    # and when every step succeeds, the files arrive together
    monkeypatch.setattr(demo, "_steps", lambda: [("one", first)])
    assert main(["demo", "--out", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["first.png", "old.txt"]
    assert (tmp_path / "first.png").read_bytes()[:8] == PNG_MAGIC


def _figure():
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    return fig
