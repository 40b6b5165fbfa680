"""labkit.core.progress: the one progress mechanism of long work (silent, lines, bar, callback)."""

import re
import sys

import numpy as np
import pytest

from labkit.core import progress as P
from labkit.core.errors import LabkitError
from labkit.core.progress import ProgressEvent, progress_steps


def _run(progress, sizes, total=None, desc="task", unit="pts", **kw):
    with progress_steps(progress, total=total, desc=desc, unit=unit, **kw) as step:
        for n in sizes:
            step(n)
    return step


@pytest.mark.parametrize("off", [False, None])
def test_silent_by_default(capsys, off):
    step = _run(off, [5, 5], total=10)
    out = capsys.readouterr()
    assert out.err == "" and out.out == ""
    assert not step.enabled


def test_callback_gets_every_step_and_a_final_event():
    events = []
    sizes = [3, 0, 7, 2]
    with progress_steps(events.append, total=12, desc="reading", unit="pts") as step:
        for k, n in enumerate(sizes):
            step(n, info=f"chunk {k}")
    assert [e.n for e in events[:-1]] == sizes
    # running sums as an independent count of what was done
    assert [e.done for e in events[:-1]] == [sum(sizes[: k + 1]) for k in range(len(sizes))]
    last = events[-1]
    assert last.finished and last.n == 0 and last.done == sum(sizes) and last.total == 12
    assert [e.info for e in events[:-1]] == [f"chunk {k}" for k in range(len(sizes))]
    assert not any(e.finished for e in events[:-1])
    assert last.fraction == pytest.approx(1.0) and ProgressEvent("x", 1, None, 1).fraction is None


def test_callback_is_closed_when_the_work_fails():
    events = []
    with pytest.raises(RuntimeError):
        with progress_steps(events.append, total=100, desc="icp") as step:
            step(10)
            raise RuntimeError("stop")
    assert events[-1].finished and events[-1].done == 10


def test_lines_one_per_step_without_throttle(capsys):
    _run("lines", [250, 250, 250, 250], total=1000, desc="reading a.laz", interval=0.0)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 4
    pct = [float(re.search(r"(\d+\.\d)%", line).group(1)) for line in lines]
    assert pct == [25.0, 50.0, 75.0, 100.0]
    assert lines[-1].startswith("reading a.laz [") and "(1,000 of 1,000 pts)" in lines[-1]


def test_lines_throttled_keep_the_last(capsys):
    _run("lines", [1] * 500, total=None, desc="normals", interval=3600.0)
    lines = capsys.readouterr().err.splitlines()
    # the first step is shown at once, the rest only at the end
    assert lines == ["normals: 1 pts", "normals: 500 pts"]


def test_lines_carry_the_step_info(capsys):
    with progress_steps("lines", total=3, desc="ICP", unit="it", interval=0.0) as step:
        for k in range(3):
            step(1, info=f"shift {0.1 * k:+.3f} m, {1000 + k:,} pairs")
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1].endswith("shift +0.200 m, 1,002 pairs") and "(3 of 3 it)" in lines[-1]


def test_true_writes_lines_when_stderr_is_not_a_terminal(capsys):
    assert not sys.stderr.isatty()
    _run(True, [10], total=10, desc="writing b.laz")
    err = capsys.readouterr().err
    assert "writing b.laz" in err and "100.0%" in err and "\r" not in err


def test_true_without_tqdm_falls_back_to_lines(capsys, monkeypatch):
    monkeypatch.setattr(P, "_tqdm", lambda: None)
    monkeypatch.setattr(P, "_in_notebook", lambda: True)
    _run(True, [4, 6], total=10, desc="tiles", unit="tiles", interval=0.0)
    assert "(10 of 10 tiles)" in capsys.readouterr().err
    with pytest.raises(LabkitError, match="tqdm"):
        _run("bar", [1])


def test_bar_uses_tqdm_on_stderr(capsys):
    pytest.importorskip("tqdm")
    _run("bar", [400, 600], total=1000, desc="reading c.laz")
    err = capsys.readouterr().err
    assert "reading c.laz" in err and "100%" in err


def test_true_in_a_notebook_uses_tqdm(capsys, monkeypatch):
    pytest.importorskip("tqdm")
    made = []

    class FakeBar:
        def __init__(self, **kw):
            made.append(kw)
            self.n = 0

        def update(self, n):
            self.n += n

        def set_postfix_str(self, text, refresh=True):
            self.text = text

        def close(self):
            made.append(("closed", self.n, getattr(self, "text", "")))

    monkeypatch.setattr(P, "_tqdm", lambda: FakeBar)
    monkeypatch.setattr(P, "_in_notebook", lambda: True)
    with progress_steps(True, total=5, desc="ICP", unit="it") as step:
        step(2, info="pairs 10")
        step(3)
    assert made[0]["total"] == 5 and made[0]["desc"] == "ICP" and made[0]["file"] is sys.stderr
    assert made[-1] == ("closed", 5, "pairs 10")
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("bad", ["yes", 1.5, object()])
def test_bad_progress_values_raise(bad):
    with pytest.raises(LabkitError, match="progress must be"):
        _run(bad, [1])


class _Stream:
    def __init__(self, tty):
        self.tty = tty

    def isatty(self):
        return self.tty


def test_cli_quiet_progress_and_terminal():
    assert P.from_cli(quiet=True, stream=_Stream(True)) is False
    assert P.from_cli(quiet=False, stream=_Stream(True)) is True  # a terminal: shown
    assert P.from_cli(quiet=False, stream=_Stream(False)) is False  # a log or pipe: only errors
    assert P.from_cli(quiet=False, force=True, stream=_Stream(False)) is True  # --progress


# --------------------------------------------------------------------------- library functions report their steps
@pytest.fixture(scope="module")
def small_pair():
    from labkit.synthetic import als_epochs

    return als_epochs("xyz", size=(40.0, 40.0), density=5.0, rng=21)


def _by_desc(events):
    out = {}
    for e in events:
        out.setdefault(e.desc, []).append(e)
    return out


def test_icp_reports_every_iteration_with_shift_and_pairs(small_pair):
    from labkit.registration import icp

    events = []
    res = icp(small_pair.source, small_pair.target, rng=0, progress=events.append)
    steps = [e for e in events if not e.finished]
    assert events[-1].finished and events[-1].desc == "ICP" and events[-1].done == len(res.history)
    assert len(steps) == len(res.history) and [e.done for e in steps] == list(range(1, len(res.history) + 1))
    for e, rec in zip(steps, res.history):  # the text carries that iteration's shift and pair count
        shown = np.array([float(v) for v in re.search(r"shift \(([^)]*)\)", e.info).group(1).split(",")])
        np.testing.assert_allclose(shown, rec.translation, atol=6e-5)
        assert f"{rec.n_used:,} pairs" in e.info
    # silent by default and the same answer with and without a receiver
    again = icp(small_pair.source, small_pair.target, rng=0)
    np.testing.assert_array_equal(again.matrix, res.matrix)


def test_normals_report_every_point_once(small_pair):
    from labkit.features import normals

    events = []
    n1 = normals(small_pair.target, k=10, progress=events.append, chunk_size=2000)
    steps = [e for e in events if not e.finished]
    assert len(steps) >= 2 and sum(e.n for e in steps) == len(small_pair.target)
    assert events[-1].finished and events[-1].done == events[-1].total == len(small_pair.target)
    np.testing.assert_array_equal(n1, normals(small_pair.target, k=10, chunk_size=2000))


def test_distances_report_before_and_after_then_normals(small_pair):
    from labkit.change.distances import distances_before_after

    events = []
    ch = distances_before_after(small_pair.source, small_pair.target, small_pair.truth, progress=events.append)
    groups = _by_desc(events)
    assert set(groups) == {"normals", "distances (point_to_plane)"}
    # the normals only at the target points found as nearest neighbours: after both searches
    assert [e.desc for e in events].index("normals") > [e.desc for e in events].index("distances (point_to_plane)")
    assert groups["normals"][-1].total <= len(small_pair.target)
    dist = [e for e in groups["distances (point_to_plane)"] if not e.finished]
    assert [e.info for e in dist] == ["before", "after"] and dist[-1].done == 2 * len(ch.after)


@pytest.mark.slow
def test_cli_register_shows_progress_on_stderr_unless_quiet(small_pair, tmp_path, capsys):
    from labkit.cli.main import main
    from labkit.io import write_cloud

    src, tgt = write_cloud(small_pair.source, tmp_path / "s.laz"), write_cloud(small_pair.target, tmp_path / "t.laz")
    assert main(["register", str(src), str(tgt), "--out", str(tmp_path / "n")]) == 0
    assert capsys.readouterr().err == ""  # stderr is not a terminal here: no progress unless asked
    assert main(["register", str(src), str(tgt), "--out", str(tmp_path / "o"), "--progress"]) == 0
    err = capsys.readouterr().err
    for what in ("reading s.laz", "reading t.laz", "ICP [", "pairs", "distances (point_to_plane)", "writing"):
        assert what in err, (what, err)
    assert main(["register", str(src), str(tgt), "--out", str(tmp_path / "q"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
