"""Shift fields over tiles: coherent areas at survey scale (the registration study, step 6; notebook 08).

A survey is cut into square tiles (e.g. 100 m); every tile is registered on its
own, giving one shift per tile (the *shift field*). Neighbouring tiles whose
shifts differ by more than their combined uncertainty do not move together;
tiles linked by agreeing neighbours, each fitting its area's common shift, form
*coherent areas* (the tests and their correction: :mod:`labkit.tiles.coherent`).

A tile is ``ok`` only when its registration converged and its data determine
every component of its shift; otherwise it is ``undetermined`` (it gives the
components it determines, the others are NaN / empty in the CSV), ``not
converged`` (no shift at all), ``too few points`` or ``failed``
(:data:`STATUSES`, :func:`tile_status`). A tile that disagrees with most of its
tested neighbours is flagged (:attr:`NeighbourTest.disagreeing`).

The per-tile work runs on Dask: one ``dask.delayed`` task per tile, computed by
a local scheduler, a ``distributed.LocalCluster`` started for the run, a running
cluster named by its address (``tcp://HOST:PORT``) or any Client passed in. With
a ``results`` folder every finished tile is written at once as one JSON file, and
a rerun reads those back instead of computing them (resume after a crash).
Tiles of LAS/LAZ files are read lazily inside their task (only the files whose
header extent meets the tile, filtered by the tile's box while reading), so a
survey of hundreds of files never has to fit in memory.

Every option is checked before any file is opened, and a grid of more than
:data:`MAX_TILES` tiles (a size typed in centimetres, say) is refused with the
count and a size that fits, instead of running on for hours.

Modules
-------
:mod:`~labkit.tiles.grid` (``Tile``, ``tile_grid``, ``write_tiles``),
:mod:`~labkit.tiles.survey` (the files of an epoch and their header extents, or
points in memory, cut per tile), :mod:`~labkit.tiles.register` (``register_tile``,
``register_tiles``), :mod:`~labkit.tiles.field` (``TileShift``, ``ShiftField``,
``neighbour_test``), :mod:`~labkit.tiles.schedule` (Dask schedulers and clusters)
and :mod:`~labkit.tiles.store` (one JSON per finished tile, for resuming).

Equation numbers refer to ``notebooks/08-shift-field-over-tiles.ipynb``.
"""

from __future__ import annotations

from .coherent import CORRECTIONS
from ..io import LAS_SUFFIXES
from .field import STATUSES, NeighbourTest, ShiftField, TileShift, neighbour_test, tile_status
from .grid import MAX_TILES, Tile, tile_grid, write_tiles
from .register import register_tile, register_tiles
from .schedule import SCHEDULERS, check_scheduler

__all__ = ["CORRECTIONS", "LAS_SUFFIXES", "MAX_TILES", "SCHEDULERS", "STATUSES", "NeighbourTest", "ShiftField", "Tile",
           "TileShift", "check_scheduler", "neighbour_test", "register_tile", "register_tiles", "tile_grid",
           "tile_status", "write_tiles"]
