"""The read filter: a box, a polygon and ASPRS classes, applied to every chunk while reading."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core import masks


@dataclass(frozen=True)
class ReadFilter:
    """The spatial and class filter applied to every chunk while reading."""

    box: np.ndarray | None = None
    rings: list | None = None
    classes: np.ndarray | None = None

    @classmethod
    def build(cls, bbox, polygon, classes) -> "ReadFilter":
        return cls(
            box=None if bbox is None else masks.as_bbox(bbox),
            rings=None if polygon is None else masks.as_rings(polygon),
            classes=None if classes is None else masks.as_classes(classes),
        )

    @property
    def active(self) -> bool:
        return self.box is not None or self.rings is not None or self.classes is not None

    def describe(self) -> str:
        parts = []
        if self.box is not None:
            parts.append(f"box {self.box.ravel().tolist()}")
        if self.rings is not None:
            parts.append(f"polygon with {sum(len(r) for r in self.rings)} vertices")
        if self.classes is not None:
            parts.append(f"classes {self.classes.tolist()}")
        return " and ".join(parts) or "no filter"

    def xy_bounds(self) -> np.ndarray | None:
        """[[xmin, ymin], [xmax, ymax]] of the spatial filter, for a quick header test."""
        boxes = []
        if self.box is not None:
            boxes.append(self.box[:, :2])
        if self.rings is not None:
            v = np.vstack(self.rings)
            boxes.append(np.array([v.min(axis=0), v.max(axis=0)]))
        if not boxes:
            return None
        return np.array([np.max([b[0] for b in boxes], axis=0), np.min([b[1] for b in boxes], axis=0)])

    def mask(self, xyz: np.ndarray, classification) -> np.ndarray | None:
        """Boolean mask of kept points, or None when nothing is filtered."""
        if not self.active:
            return None
        keep = np.ones(len(xyz), dtype=bool)
        if self.classes is not None:
            keep &= masks.class_mask(classification, self.classes)
        if self.box is not None:
            keep &= masks.box_mask(xyz, self.box)
        if self.rings is not None and keep.any():
            idx = np.flatnonzero(keep)
            keep[idx] = masks.polygon_mask(xyz[idx], self.rings)
        return keep
