"""Reading and writing point-cloud files (the registration study, step 1: laspy -> numpy -> CSV).

Formats
-------
- LAS / LAZ 1.0-1.4, every point format, via laspy (LAZ through lazrs).
  Coordinates are ``X * scale + offset`` as float64; every other dimension
  (classification, intensity, return_number, number_of_returns, gps_time,
  point_source_id, colours, flags, extra bytes, ...) becomes an attribute under
  laspy's name. The CRS is kept as text: the WKT of the WKT VLR, or
  ``"EPSG:code"`` from the GeoTIFF keys (read with pyproj).
- ASCII ``.xyz .txt .csv .asc``: comma, semicolon or whitespace separated, with
  or without a header line. With a header, x/y/z are found by name and other
  columns become attributes (common spellings such as ``Classification``,
  ``Intensity``, ``GpsTime``, ``//X`` are mapped to laspy's names); without a
  header the first three columns are x, y, z and further ones are kept as
  ``column_3``, ``column_4``, ...
- NumPy ``.npy`` (an (n, >=3) array or a structured array with x, y, z fields)
  and ``.npz`` (``xyz`` or ``x``, ``y``, ``z`` plus one array per attribute).
- PLY ``.ply`` (reading): ASCII and binary little/big endian; the ``vertex``
  element's x, y, z plus every scalar property as an attribute.

Units
-----
The units of a LAS/LAZ file are read from its CRS (WKT and GeoTIFF keys, see
``labkit.core.units`` for the parser and the rule when they contradict each
other). By default (``units="m"``) coordinates in feet (US survey foot
1200/3937 m, international foot 0.3048 m; horizontal and vertical may differ)
are converted to metres, and a file in longitude/latitude degrees is refused
with :class:`labkit.core.units.UnitsError` before any point is read. With
``units="native"`` the coordinates stay as stored and the cloud records its
units, so metric steps refuse it later (:meth:`PointCloud.require_metric`).
Either way ``cloud.units`` says what the file states, whether the
coordinates were converted, and any conflict between WKT and GeoKeys. Writing
a converted cloud to LAS/LAZ/NPZ stores it in its file's units again (the CRS
is written with it), so a file never holds metres under a CRS in feet.

Large files
-----------
Files are read in chunks; a box, polygon or class filter is applied to each
chunk, so only the kept points are ever held in memory. LAZ is decompressed
(and compressed) on all cores by lazrs (``parallel=True``); with a selection of
``attributes`` from a LAS 1.4 file (point formats 6-10) only the layers of
those attributes are decompressed. Without a filter, each chunk's coordinates
``X * scale + offset`` are computed straight into the one preallocated array
the cloud then keeps (no concatenation, no second copy): reading needs the
memory of the cloud plus one chunk. :func:`read_clouds` reads the part of many
files (a folder, a glob) that an area needs: the LAS headers are read first and
files whose extent misses the area are skipped without decompressing a point.
Writing quantizes and writes one chunk at a time. ``progress=True`` reports the
chunks (see :mod:`labkit.core.progress`). Files are written atomically: into a
temporary file in the destination folder, renamed over the destination only
when complete.

Modules
-------
:mod:`~labkit.io.read` (``read_cloud``), :mod:`~labkit.io.write` (``write_cloud``),
:mod:`~labkit.io.many` (``read_clouds``, ``cloud_files``, ``files_in_box``); one
module per format: :mod:`~labkit.io.las` (reading, units, ``cloud_info``),
:mod:`~labkit.io.las_write`, :mod:`~labkit.io.ascii`, :mod:`~labkit.io.npy`,
:mod:`~labkit.io.ply`; and what they share: :mod:`~labkit.io.filter` (the read
filter), :mod:`~labkit.io.chunks` (the chunk collector), :mod:`~labkit.io.common`.
"""

from __future__ import annotations

from .common import ASCII_SUFFIXES, DEFAULT_CHUNK, LAS_SUFFIXES, NUMPY_SUFFIXES, PLY_SUFFIXES
from .las import CloudInfo, cloud_info, las_units, laz_backend
from .many import cloud_files, files_in_box, read_clouds
from .read import read_cloud
from .write import ANGULAR_SCALE, DEFAULT_SCALE, write_cloud

__all__ = ["read_cloud", "read_clouds", "write_cloud", "cloud_info", "CloudInfo", "cloud_files", "files_in_box",
           "LAS_SUFFIXES", "ASCII_SUFFIXES"]
