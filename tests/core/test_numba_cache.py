"""Compiled kernels are cached on disk (labkit.core.numba_cache): a second process loads them instead of compiling."""

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import labkit
from labkit.core import numba_cache as _numba_cache

numba = pytest.importorskip("numba")

ROOT = Path(labkit.__file__).resolve().parents[1]
KERNEL_MODULES = ["labkit.neighbours.eigh3", "labkit.neighbours.kdtree", "labkit.neighbours.kdtree_nn", "labkit.neighbours.kdtree_build", "labkit.neighbours.search", "labkit.change.grid",
                  "labkit.registration.matching.matcher", "labkit.registration.consensus.kernels",
                  "labkit.registration.matching.local_surface"]


def _dispatchers():
    from numba.core.registry import CPUDispatcher

    for name in KERNEL_MODULES:
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == name:
                yield f"{name}.{attr}", value


def test_every_kernel_is_compiled_with_an_on_disk_cache():
    found = dict(_dispatchers())
    assert len(found) >= 10  # the walk finds the kernels
    not_cached = [name for name, d in found.items() if type(d._cache).__name__ == "NullCache"]
    assert not_cached == []


def test_fallback_only_when_no_writable_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(numba.config, "CACHE_DIR", numba.config.CACHE_DIR)
    blocker = tmp_path / "a_file"  # a folder below a regular file cannot be created, whoever runs the test
    blocker.write_text("")
    monkeypatch.setattr(_numba_cache, "fallback_dir", lambda: tmp_path / "fallback")
    # package folder writable: numba's own search succeeds, nothing changes
    assert _numba_cache.ensure_cache_dir(tmp_path / "pkg", blocker / "home") is None
    assert "NUMBA_CACHE_DIR" not in os.environ
    # package read-only, user cache folder writable: nothing changes either
    assert _numba_cache.ensure_cache_dir(blocker / "pkg", tmp_path / "home") is None
    assert "NUMBA_CACHE_DIR" not in os.environ
    # neither writable: numba (already imported here) and child processes are pointed to the fallback
    got = _numba_cache.ensure_cache_dir(blocker / "pkg", blocker / "home")
    assert got == str(tmp_path / "fallback") and os.environ["NUMBA_CACHE_DIR"] == got
    assert numba.config.CACHE_DIR == got and (tmp_path / "fallback").is_dir()
    # a folder the user chose is never overridden
    assert _numba_cache.ensure_cache_dir(blocker / "pkg", blocker / "home") is None


SCRIPT = """
import numpy as np
from labkit import m3c2
from labkit.change import grid as g
rng = np.random.default_rng(0)
a = np.c_[rng.uniform(0, 10, (2000, 2)), rng.normal(0, 0.01, 2000)]
b = a + [0, 0, 0.1]
r = m3c2(a, b, a[:50], normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
hits = sum(sum(k.stats.cache_hits.values()) for k in (g._cylinder_serial, g._ball_serial))
misses = sum(sum(k.stats.cache_misses.values()) for k in (g._cylinder_serial, g._ball_serial))
print(hits, misses, round(float(np.nanmedian(r.distance)), 3))
"""


@pytest.mark.slow
def test_second_process_loads_the_m3c2_kernels_from_the_cache(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(ROOT))

    def run():
        out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True)
        return out.stdout.split()

    first, second = run(), run()
    assert first[:2] == ["0", "2"]  # compiled and written
    assert any(tmp_path.rglob("*.nbi"))
    assert second[:2] == ["2", "0"]  # loaded, nothing compiled
    assert first[2] == second[2] == "0.1"  # the same answer from the loaded machine code
