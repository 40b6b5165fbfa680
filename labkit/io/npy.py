"""NumPy clouds: ``.npy`` (plain or structured arrays) and ``.npz`` (xyz, attributes, CRS, units)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..core.checks import check_precision
from ..core.units import units_from_crs_text
from ..cloud import PointCloud
from ..core.units import Units
from ..core.errors import CloudFileError, LabkitError
from .chunks import ChunkCollector
from .common import canonical_name, require_classification
from .filter import ReadFilter
from .las import to_metres


def read_numpy(path: Path, flt: ReadFilter, keep, chunk_size: int, units: str):
    if path.suffix.lower() == ".npy":
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
        xyz, attrs = _split_npy(arr, path)
        crs = None
    else:
        with np.load(path, allow_pickle=False) as z:
            xyz, attrs, crs = _split_npz(z, path)
    check_precision(xyz, f"the coordinates in {path.name}")
    found = units_from_crs_text(crs)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            if "units" in z.files:
                found = _units_from_json(str(z["units"]), path)
    found, factors = to_metres(found, units, path)
    attrs = {k: v for k, v in attrs.items() if keep is None or k in keep}
    require_classification(flt, attrs, path)
    gather = ChunkCollector(None)
    for start in range(0, len(xyz), chunk_size):
        part = np.array(xyz[start : start + chunk_size], dtype=np.float64)
        if factors is not None:
            part *= factors
        cls = np.asarray(attrs["classification"][start : start + chunk_size]) if flt.classes is not None else None
        mask = flt.mask(part, cls)
        sel = slice(None) if mask is None else mask
        gather.add(part[sel], {k: np.asarray(v[start : start + chunk_size])[sel] for k, v in attrs.items()})
    out_xyz, out_attrs = gather.result()
    return out_xyz, out_attrs, crs, found


def _split_npy(arr: np.ndarray, path: Path):
    if arr.dtype.names:
        names = {n.lower(): n for n in arr.dtype.names}
        if not all(c in names for c in "xyz"):
            raise CloudFileError(f"{path}: a structured array needs fields x, y, z (has {arr.dtype.names})")
        xyz = np.column_stack([arr[names[c]] for c in "xyz"])
        attrs = {canonical_name(n): arr[n] for n in arr.dtype.names if n.lower() not in "xyz"}
        return xyz, attrs
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise CloudFileError(f"{path}: expected a numeric (n, 3+) array, got shape {arr.shape} of {arr.dtype}")
    return arr[:, :3], {f"column_{i}": arr[:, i] for i in range(3, arr.shape[1])}


def _split_npz(z, path: Path):
    keys = set(z.files)
    if "xyz" in keys:
        xyz = z["xyz"]
        used = {"xyz"}
    elif {"x", "y", "z"} <= keys:
        xyz = np.column_stack([z[c] for c in "xyz"])
        used = {"x", "y", "z"}
    else:
        raise CloudFileError(f"{path}: an .npz cloud needs an 'xyz' array or 'x', 'y', 'z' arrays (has {sorted(keys)})")
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CloudFileError(f"{path}: 'xyz' must have shape (n, 3), got {xyz.shape}")
    crs = str(z["crs"]) if "crs" in keys and z["crs"].size else None
    attrs = {}
    for k in sorted(keys - used - {"crs", "name", "units"}):
        v = z[k]
        if v.ndim != 1 or len(v) != len(xyz):
            raise CloudFileError(f"{path}: array {k!r} has shape {v.shape}, expected ({len(xyz)},)")
        attrs[k] = v
    return xyz, attrs, crs


def _units_from_json(text: str, path: Path) -> Units:
    try:
        fields = json.loads(text)
        return Units(**{k: v for k, v in fields.items() if k != "converted"})
    except (ValueError, TypeError) as exc:
        raise CloudFileError(f"{path}: unreadable 'units' entry: {exc}") from None


def write_npz(cloud: PointCloud, tmp: Path) -> None:
    reserved = sorted({"xyz", "x", "y", "z", "crs", "name", "units"} & set(cloud.attributes))
    if reserved:
        raise LabkitError(f"attribute name(s) {reserved} are reserved in an .npz cloud file: rename them")
    arrays = {"xyz": cloud.xyz, **cloud.attributes}
    if cloud.crs:
        arrays["crs"] = np.array(cloud.crs)
    if cloud.units.known:
        arrays["units"] = np.array(json.dumps(dataclasses.asdict(cloud.units)))
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
