"""Freed memory kept for reuse (labkit.core.memory): measured in fresh processes, with and without the setting."""

import os
import platform
import subprocess
import sys

import pytest

from labkit.core.memory import KEEP, keep_freed_memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# 150 arrays of 1 MB made and freed; the resident memory before and after, in MB
_PROBE = """
import os, numpy as np
import labkit
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
before = rss()
arrays = [np.ones(1 << 17) for _ in range(150)]  # 1 MB each, written (resident)
del arrays
print(rss() - before)
"""


def _kept_mb(env):
    out = subprocess.run([sys.executable, "-c", _PROBE], env={**os.environ, **env}, capture_output=True, text=True,
                         check=True)
    return float(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_freed_arrays_stay_resident_for_reuse_and_go_back_when_switched_off():
    kept = _kept_mb({"LABKIT_KEEP_FREED_MEMORY": "1"})
    returned = _kept_mb({"LABKIT_KEEP_FREED_MEMORY": "0"})
    assert kept > 120  # the 150 MB freed stay in the process (below the 256 MB kept)
    assert returned < 30  # glibc's defaults: 1 MB arrays are mappings of their own, unmapped when freed
    assert KEEP >= 150 << 20


def test_switch_off_and_repeated_calls(monkeypatch):
    monkeypatch.setenv("LABKIT_KEEP_FREED_MEMORY", "0")
    assert keep_freed_memory() is False
    monkeypatch.delenv("LABKIT_KEEP_FREED_MEMORY")
    assert keep_freed_memory() is GLIBC  # set at import where glibc is there; the same answer again
    assert keep_freed_memory() is GLIBC
