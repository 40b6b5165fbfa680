"""The benchmark scripts' own helpers: a peer that is not installed leaves its column out, and the busy
processes of ``bench_icp.py --load`` run only inside ``with``."""

import importlib.util
import sys
import time
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_missing_peer_is_left_out(monkeypatch, capsys):
    bench = _load("bench_ransac")
    monkeypatch.setitem(bench.PEER_MODULES, "skimage", "no_such_module_for_labkit_tests")
    methods = {"labkit": len, "pyransac3d": len, "skimage": len}
    kept = bench.installed(methods)
    assert "skimage" not in kept and "labkit" in kept
    assert ("pyransac3d" in kept) == (importlib.util.find_spec("pyransac3d") is not None)
    assert "skipped: skimage" in capsys.readouterr().out


def _state(pid):
    """The process state letter of /proc/<pid>/stat (R running, S sleeping, T stopped)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_busy_processes_run_only_inside_with():
    bench = _load("bench_icp")
    busy = bench.BusyProcesses(1)
    pid = busy.procs[0].pid
    try:
        time.sleep(0.2)
        assert _state(pid) == "T"  # paused until entered
        with busy:
            time.sleep(0.2)
            assert _state(pid) == "R"  # a busy loop: running
        time.sleep(0.2)
        assert _state(pid) == "T"
    finally:
        busy.close()
    assert busy.procs[0].poll() is not None  # ended and reaped
