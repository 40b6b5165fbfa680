"""Chunked reading: the collector that keeps the kept part of each chunk, preallocated when it can."""

from __future__ import annotations

import numpy as np


class ChunkCollector:
    """Collects the kept part of each chunk; preallocates when the final size is known.

    With a known capacity the chunks are written into one array (the memory of
    the cloud plus one chunk, no concatenation); :meth:`slot` hands out the rows
    a chunk of known size fills, so coordinates can be computed straight into them.
    """

    def __init__(self, capacity: int | None):
        self.capacity, self.n = capacity, 0
        self.xyz_parts, self.attr_parts = [], {}
        self.xyz, self.attrs = None, None

    def _allocate(self, attrs: dict) -> None:
        if self.xyz is None:
            self.xyz = np.empty((self.capacity, 3))
        if self.attrs is None:
            self.attrs = {k: np.empty(self.capacity, dtype=v.dtype) for k, v in attrs.items()}

    def slot(self, m: int) -> np.ndarray | None:
        """Rows ``n:n+m`` of the preallocated coordinates (None without a capacity)."""
        if self.capacity is None or self.n + m > self.capacity:
            return None
        if self.xyz is None:
            self.xyz = np.empty((self.capacity, 3))
        return self.xyz[self.n : self.n + m]

    def add(self, xyz: np.ndarray, attrs: dict) -> None:
        m = len(xyz)
        if self.capacity is not None and self.n + m <= self.capacity:
            self._allocate(attrs)
            dest = self.xyz[self.n : self.n + m]
            if not np.shares_memory(dest, xyz):
                dest[:] = xyz
            for k, v in attrs.items():
                self.attrs[k][self.n : self.n + m] = v
        else:
            if self.capacity is not None:  # more points than announced: fall back to gathering parts
                self._spill()
            self.xyz_parts.append(xyz)
            for k, v in attrs.items():
                self.attr_parts.setdefault(k, []).append(v)
        self.n += m

    def _spill(self) -> None:
        if self.xyz is not None:
            self.xyz_parts.append(self.xyz[: self.n])
            for k, v in (self.attrs or {}).items():
                self.attr_parts.setdefault(k, []).append(v[: self.n])
        self.capacity, self.xyz, self.attrs = None, None, None

    def result(self) -> tuple[np.ndarray, dict]:
        if self.capacity is not None and self.xyz is not None:
            xyz, attrs = self.xyz[: self.n], {k: v[: self.n] for k, v in (self.attrs or {}).items()}
            if self.n < 0.9 * self.capacity:  # much was filtered out: give the unused rows back
                xyz, attrs = xyz.copy(), {k: v.copy() for k, v in attrs.items()}
            return xyz, attrs
        xyz = np.concatenate(self.xyz_parts) if self.xyz_parts else np.empty((0, 3))
        self.xyz_parts = []
        attrs = {}
        for k in list(self.attr_parts):
            attrs[k] = np.concatenate(self.attr_parts.pop(k))
        return xyz, attrs
