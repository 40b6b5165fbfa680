"""Results per tile on disk: one JSON file per finished tile, read back by a rerun with the same options (resume)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_write_text
from ..core.checks import as_points
from .field import TileShift, tile_status
from .grid import Tile
from .survey import _Files


def _run_key(method, min_points, classes, size, buffer, src, tgt) -> dict:
    """What a stored tile result depends on besides its tile: options and a fingerprint of the input."""
    key = {"method": _method_text(method), "min_points": int(min_points),
           "classes": None if classes is None else list(classes), "size": float(size), "buffer": float(buffer),
           "source": _fingerprint(src), "target": _fingerprint(tgt)}
    return json.loads(json.dumps(key))  # as it reads back from a file


def _method_text(method) -> str:
    if isinstance(method, partial):
        func = getattr(method.func, "__module__", "") + "." + getattr(method.func, "__qualname__", "")
        return f"{func}{sorted((k, repr(v)) for k, v in method.keywords.items())}"
    return getattr(method, "__module__", "") + "." + getattr(method, "__qualname__", type(method).__name__)


def _fingerprint(data) -> list:
    if isinstance(data, _Files):
        return [[str(Path(p).resolve()), Path(p).stat().st_size, Path(p).stat().st_mtime_ns] for p in data.paths]
    xyz = as_points(data, name="survey cloud")
    return [len(xyz), float(np.sum(xyz, dtype=np.float64)), float(np.sum(xyz * xyz, dtype=np.float64))]


@dataclass(frozen=True)
class _TileStore:
    """One JSON per tile in ``folder``; a file counts only if it was written with the same ``key``."""

    folder: str
    key: dict

    def path(self, tile: Tile) -> Path:
        return Path(self.folder) / f"tile_{tile.row}_{tile.col}.json"

    def load(self, tile: Tile) -> "TileShift | None":
        path = self.path(tile)
        try:
            rec = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None  # missing or cut short: compute again
        same_tile = rec.get("tile") == _tile_json(tile)
        return _shift_from_json(rec, tile) if rec.get("key") == self.key and same_tile else None

    def save(self, shift: "TileShift") -> None:
        Path(self.folder).mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path(shift.tile), json.dumps(dict(_shift_json(shift), key=self.key), indent=1))


def _run_and_save(tile, source, target, *, run, store):
    """Register one tile and write its JSON at once (a crash later loses nothing finished)."""
    shift = run(tile, source, target)
    store.save(shift)
    return shift


def _tile_json(tile: Tile) -> dict:
    return {"row": int(tile.row), "col": int(tile.col), "bounds": [float(v) for v in tile.bounds],
            "buffer": float(tile.buffer)}


def _shift_json(s: "TileShift") -> dict:
    return {"tile": _tile_json(s.tile), "translation": s.translation.tolist(), "covariance": s.covariance.tolist(),
            "axis_determined": [bool(v) for v in s.axis_determined], "n_source": int(s.n_source),
            "n_target": int(s.n_target), "n_used": int(s.n_used), "sigma0": float(s.sigma0),
            "converged": bool(s.converged), "runtime_s": float(s.runtime_s), "status": s.status,
            "message": s.message}


def _shift_from_json(rec: dict, tile: Tile) -> "TileShift":
    cov, determined, converged = np.array(rec["covariance"], float), np.array(rec["axis_determined"], bool), \
        bool(rec["converged"])
    status = str(rec["status"])
    if status in ("ok", "undetermined", "not converged"):  # the verdict follows the numbers, whoever wrote them
        determined = determined & np.isfinite(np.diag(cov))
        status = tile_status(converged, determined)
    return TileShift(tile, np.array(rec["translation"], float), cov, determined, int(rec["n_source"]),
                     int(rec["n_target"]), int(rec["n_used"]), float(rec["sigma0"]), converged,
                     float(rec["runtime_s"]), status, str(rec["message"]))


