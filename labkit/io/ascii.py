"""ASCII clouds (``.xyz .txt .csv .asc``): reading with or without a header line, and writing."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np

from ..core.errors import CloudFileError, LabkitError
from ..core.progress import progress_steps
from .chunks import ChunkCollector
from .common import SCAN_ANGLE_STEP, STANDARD_DTYPES, canonical_name, require_classification
from .filter import ReadFilter


def read_ascii(path: Path, flt: ReadFilter, keep, chunk_size: int, progress: bool):
    size = path.stat().st_size
    with open(path, encoding="utf-8-sig", errors="strict") as f:  # -sig: a byte-order mark is no data
        first, skipped = _first_line(f, path)
        delimiter = "," if "," in first else ";" if ";" in first else None
        first = first.lstrip("#").strip() if first.startswith("#") else first.split("#")[0].strip()  # "# x y z"
        trailing = delimiter is not None and first.endswith(delimiter)  # "1,2,3," (some exporters)
        if trailing:
            first = first.rstrip(delimiter).rstrip()
        tokens = [t.strip() for t in (first.split(delimiter) if delimiter else first.split())]
        header = not all(_is_number(t) for t in tokens)
        columns = _column_names(tokens, header, path)
        ix = [columns.index(c) for c in ("x", "y", "z")]
        extra = [(i, c) for i, c in enumerate(columns) if c not in ("x", "y", "z") and wanted_column(c, keep)]
        require_classification(flt, columns, path)
        lines = f if header else itertools.chain([first], f)
        gather, row = ChunkCollector(None), skipped
        with progress_steps(progress, size, f"reading {path.name}", "B") as step:
            step(len(first.encode()) + 1 if header else 0)
            while True:
                block = list(itertools.islice(lines, chunk_size))
                if not block:
                    break
                if trailing:
                    block = [line.rstrip().rstrip(delimiter) for line in block]
                data = _parse_block(block, delimiter, len(columns), path, row)
                row += len(block)
                xyz = data[:, ix]
                cls = data[:, columns.index("classification")] if flt.classes is not None else None
                mask = flt.mask(xyz, cls)
                sel = slice(None) if mask is None else mask
                gather.add(xyz[sel], {c: data[sel, i] for i, c in extra})
                step(sum(len(s) for s in block))
    xyz, attrs = gather.result()
    return xyz, text_columns(attrs, path), None


def _first_line(f, path: Path) -> tuple[str, int]:
    """The first non-blank line (header or data) and the number of lines consumed."""
    for count, line in enumerate(f, start=1):
        if line.strip() and not _comment(line):
            return line.strip(), count - (0 if _looks_header(line) else 1)
    raise CloudFileError(f"{path} is empty (no lines with data)")


def _comment(line: str) -> bool:
    """A '#' line that is no header naming x, y and z (e.g. '# exported by ...')."""
    text = line.strip()
    if not text.startswith("#"):
        return False
    names = {canonical_name(t) for t in re.split(r"[,;\s]+", text.lstrip("#").strip()) if t}
    return not {"x", "y", "z"} <= names


def _looks_header(line: str) -> bool:
    tokens = re.split(r"[,;\s]+", line.strip())
    return not all(_is_number(t) for t in tokens if t)


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _column_names(tokens: list[str], header: bool, path: Path) -> list[str]:
    if not header:
        if len(tokens) < 3:
            raise CloudFileError(f"{path}: expected at least 3 columns (x y z), found {len(tokens)}")
        return ["x", "y", "z"] + [f"column_{i}" for i in range(3, len(tokens))]
    names = [canonical_name(t) for t in tokens]
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise CloudFileError(f"{path}: the header line names no column {', '.join(missing)} (found {tokens})")
    if len(set(names)) != len(names):
        raise CloudFileError(f"{path}: the header line repeats a column name ({tokens})")
    return names


def _parse_block(block: list[str], delimiter, ncol: int, path: Path, row: int) -> np.ndarray:
    try:
        data = np.loadtxt(block, delimiter=delimiter, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as exc:
        raise CloudFileError(f"{path}: cannot parse lines {row + 1}-{row + len(block)}: {exc}") from None
    if data.shape[1] != ncol:
        raise CloudFileError(f"{path}: expected {ncol} columns near line {row + 1}, found {data.shape[1]}")
    return data


def text_columns(attrs: dict, path: Path) -> dict:
    """Typed text columns; a scan-angle column in fractional degrees (PDAL's
    ``ScanAngleRank`` of LAS 1.4 data) becomes ``scan_angle`` in 0.006-degree units."""
    out = {}
    for name, values in attrs.items():
        if name == "scan_angle_rank" and "scan_angle" not in attrs and _fractional_degrees(values):
            steps = np.rint(values / SCAN_ANGLE_STEP)
            if np.abs(steps * SCAN_ANGLE_STEP - values).max() <= 1e-6 * max(1.0, np.abs(values).max()):
                out["scan_angle"] = steps.astype(np.int16)  # LAS 1.4 units of 0.006 degrees, exact
            else:
                out["scan_angle_degrees"] = values  # finer than the LAS field: kept as degrees
            continue
        out[name] = _text_dtype(name, values, path)
    return out


SCAN_ANGLE_NAMES = {"scan_angle_rank", "scan_angle", "scan_angle_degrees"}  # one text column, three names


def wanted_column(column: str, keep) -> bool:
    """Is a text column asked for? A scan-angle column answers to each name it may be read under."""
    if keep is None or column in keep:
        return True
    return column == "scan_angle_rank" and bool(keep & SCAN_ANGLE_NAMES)


def _fractional_degrees(values: np.ndarray) -> bool:
    """Finite angles within +-180 degrees that are not all whole numbers."""
    return bool(values.size and np.isfinite(values).all() and np.abs(values).max() <= 180.0
                and not np.array_equal(values, np.round(values)))


def _text_dtype(name: str, values: np.ndarray, path: Path) -> np.ndarray:
    """Known dimensions get laspy's dtype, other integral columns int64, the rest float64."""
    finite = np.isfinite(values).all()
    integral = finite and np.array_equal(values, np.round(values))
    target = STANDARD_DTYPES.get(name)
    if target is not None and np.issubdtype(target, np.integer):
        info = np.iinfo(target)
        if not integral or (values.size and (values.min() < info.min or values.max() > info.max)):
            raise CloudFileError(f"{path}: column {name!r} must hold integers in {info.min}..{info.max}")
        return values.astype(target)
    if target is None and integral and values.size and np.abs(values).max() < 2**53:
        return values.astype(np.int64)
    return values


def write_ascii(cloud: PointCloud, tmp: Path, delimiter: str, scales: np.ndarray, chunk_size: int,
                 progress=False, label: str = "") -> None:
    names = list(cloud.attributes)
    decimals = [max(0, int(np.ceil(-np.log10(s) - 1e-9))) for s in scales]
    fmts = [f"%.{d}f" for d in decimals]
    for name in names:
        kind = cloud[name].dtype.kind
        if kind not in "biuf" or cloud[name].ndim != 1:
            raise LabkitError(f"attribute {name!r} ({cloud[name].dtype}) cannot be written as a text column")
        fmts.append("%d" if kind in "biu" else "%.15g")
    with open(tmp, "w", encoding="utf-8", newline="\n") as f, \
            progress_steps(progress, len(cloud), f"writing {label or tmp.name}", "pts") as step:
        f.write(delimiter.join(["x", "y", "z"] + names) + "\n")
        for start in range(0, len(cloud), chunk_size):
            sl = slice(start, start + chunk_size)
            cols = [cloud.xyz[sl, j] for j in range(3)] + [cloud[n][sl] for n in names]
            table = np.empty((len(cols[0]), len(cols)), dtype=object)
            for j, col in enumerate(cols):
                table[:, j] = col
            np.savetxt(f, table, fmt=fmts, delimiter=delimiter)
            step(len(table))
