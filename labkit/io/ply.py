"""PLY files (Stanford polygon format): the header and the vertex element, chunk by chunk.

Only reading is supported: ``format ascii``, ``binary_little_endian`` and
``binary_big_endian``; the ``vertex`` element's scalar properties are returned
as arrays (binary files keep each property's type). Elements before the
vertices are skipped (in binary files they must not hold list properties);
elements after them (faces) are ignored. :func:`labkit.io.read_cloud` maps the
property names to labkit's attribute names and applies its filters.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import CloudFileError
from .ascii import text_columns, wanted_column
from .chunks import ChunkCollector
from .common import canonical_name, require_classification
from .filter import ReadFilter

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


@dataclass(frozen=True)
class Element:
    """One element of the header: name, count and properties."""

    name: str
    count: int
    properties: tuple  # (name, type code) or (name, "list", count type, item type)


def read_header(f, path: Path):
    """(format, elements, byte offset of the data) from an open binary file.

    Examples
    --------
    >>> import io
    >>> from labkit.io.ply import read_header
    >>> f = io.BytesIO(b"ply\\nformat binary_little_endian 1.0\\nelement vertex 2\\nproperty double x\\nend_header\\n")
    >>> fmt, elements, start = read_header(f, "in-memory.ply")
    >>> fmt, elements[0].name, elements[0].count, elements[0].properties, start
    ('binary_little_endian', 'vertex', 2, (('x', 'f8'),), 82)
    """
    if f.readline().strip() != b"ply":
        raise CloudFileError(f"{path} is not a PLY file (no 'ply' magic line)")
    fmt, elements = None, []
    for _ in range(100_000):
        raw = f.readline()
        if not raw:
            raise CloudFileError(f"{path}: the PLY header has no 'end_header' line")
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            if fmt is None:
                raise CloudFileError(f"{path}: the PLY header has no 'format' line")
            return fmt, elements, f.tell()
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
            if fmt not in FORMATS:
                raise CloudFileError(f"{path}: unknown PLY format {fmt!r} (known: {', '.join(FORMATS)})")
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(Element(words[1], int(words[2]), ()))
        elif words[0] == "property" and elements:
            if len(words) == 3 and words[1] in PLY_TYPES:
                prop = (words[2], PLY_TYPES[words[1]])
            elif len(words) == 5 and words[1] == "list" and words[2] in PLY_TYPES and words[3] in PLY_TYPES:
                prop = (words[4], "list", PLY_TYPES[words[2]], PLY_TYPES[words[3]])
            else:
                raise CloudFileError(f"{path}: cannot read the PLY property line {raw.strip()!r}")
            last = elements[-1]
            elements[-1] = Element(last.name, last.count, last.properties + (prop,))
        else:
            raise CloudFileError(f"{path}: unexpected PLY header line {raw.strip()!r}")
    raise CloudFileError(f"{path}: the PLY header is too long")


def ply_vertex_blocks(path: Path, chunk_size: int):
    """(property names, format, iterator of blocks); a block is one array per vertex property.

    The file stays open while the iterator runs.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from labkit.io.ply import ply_vertex_blocks
    >>> path = Path(tempfile.mkdtemp()) / "tri.ply"
    >>> _ = path.write_text("ply\\nformat ascii 1.0\\nelement vertex 3\\nproperty float x\\nproperty float y\\n"
    ...                 "property float z\\nend_header\\n0 0 0\\n1 0 0\\n0 1 0\\n")
    >>> names, fmt, blocks = ply_vertex_blocks(path, chunk_size=2)
    >>> names, fmt, [len(block[0]) for block in blocks]
    (['x', 'y', 'z'], 'ascii', [2, 1])
    """
    f = open(path, "rb")
    try:
        fmt, elements, start = read_header(f, path)
        names = [e.name for e in elements]
        if "vertex" not in names:
            raise CloudFileError(f"{path}: the PLY file has no 'vertex' element (has {names})")
        before, vertex = elements[: names.index("vertex")], elements[names.index("vertex")]
        if any(len(p) != 2 for p in vertex.properties):
            raise CloudFileError(f"{path}: list properties in the PLY vertex element are not supported")
        props = [p[0] for p in vertex.properties]
        if fmt == "ascii":
            lines = itertools.islice(f, sum(e.count for e in before), None)  # one line per earlier item
            blocks = _ascii_blocks(f, lines, vertex.count, len(props), chunk_size, path)
        else:
            if any(len(p) != 2 for e in before for p in e.properties):
                raise CloudFileError(f"{path}: a binary PLY with list properties before its vertices is not supported")
            end = "<" if fmt == "binary_little_endian" else ">"
            skip = sum(e.count * _record(e.properties, end).itemsize for e in before)
            blocks = _binary_blocks(f, start + skip, _record(vertex.properties, end), vertex.count, chunk_size, path)
    except BaseException:
        f.close()
        raise
    return props, fmt, blocks


def _record(properties, end: str) -> np.dtype:
    return np.dtype([(f"p{i}", end + p[1]) for i, p in enumerate(properties)])


def _ascii_blocks(f, lines, count: int, ncol: int, chunk_size: int, path: Path):
    with f:
        done = 0
        while done < count:
            want = min(chunk_size, count - done)
            block = list(itertools.islice(lines, want))
            if len(block) < want:
                raise CloudFileError(f"{path} is truncated: the PLY header announces {count} vertices, "
                                     f"the file holds {done + len(block)}")
            try:
                data = np.loadtxt([b.decode("ascii", errors="replace") for b in block], dtype=np.float64, ndmin=2)
            except ValueError as exc:
                raise CloudFileError(f"{path}: cannot parse lines {done + 1}-{done + want} of the vertices: {exc}") from None
            if data.shape[1] != ncol:
                raise CloudFileError(f"{path}: expected {ncol} vertex properties per line, found {data.shape[1]}")
            done += want
            yield [data[:, j] for j in range(ncol)]


def _binary_blocks(f, offset: int, dtype: np.dtype, count: int, chunk_size: int, path: Path):
    with f:
        size = path.stat().st_size
        if offset + count * dtype.itemsize > size:
            raise CloudFileError(f"{path} is truncated: the PLY header announces {count} vertices "
                                 f"({offset + count * dtype.itemsize} bytes), the file has {size} bytes")
        f.seek(offset)
        for start in range(0, count, chunk_size):
            rec = np.fromfile(f, dtype=dtype, count=min(chunk_size, count - start))
            yield [rec[name].astype(rec.dtype[name].newbyteorder("=")) for name in dtype.names]


def read_ply(path: Path, flt: ReadFilter, keep, chunk_size: int):
    """Vertex x, y, z and scalar properties of an ASCII or binary PLY file (see :func:`ply_vertex_blocks`)."""
    names, fmt, blocks = ply_vertex_blocks(path, chunk_size)
    columns = [canonical_name(n) for n in names]
    if len(set(columns)) != len(columns):
        raise CloudFileError(f"{path}: the PLY vertex element repeats a property ({names})")
    missing = [c for c in "xyz" if c not in columns]
    if missing:
        raise CloudFileError(f"{path}: the PLY vertex element has no property {', '.join(missing)}")
    ix = [columns.index(c) for c in "xyz"]
    extra = [(i, c) for i, c in enumerate(columns) if c not in "xyz" and wanted_column(c, keep)]
    require_classification(flt, columns, path)
    gather = ChunkCollector(None)
    for block in blocks:  # one array per property
        xyz = np.column_stack([block[i].astype(np.float64) for i in ix])
        cls = block[columns.index("classification")] if flt.classes is not None else None
        mask = flt.mask(xyz, cls)
        sel = slice(None) if mask is None else mask
        gather.add(xyz[sel], {c: block[i][sel] for i, c in extra})
    xyz, attrs = gather.result()
    if fmt == "ascii":  # text: typed like the columns of an ASCII file
        attrs = text_columns(attrs, path)
    return xyz, attrs, None
