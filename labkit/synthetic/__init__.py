"""Reproducible synthetic point clouds with known truth.

- ``sphere_on_tripod``: a TLS sphere target on a tripod with base, ground and clutter.
- ``room_scene``: a small sphere in a scanned room (walls, floor, furniture).
- ``multibeam_room``: a sphere in a room scanned by a 16-beam lidar (rings, occlusion).
- ``als_epochs``: two airborne laser scanning epochs of a named test region.
- ``wavy_surface``: a smooth surface sloping in X and Y (the registration examples' test object).
- ``wavy_pair``: two samplings of it, one moved (source, target): the registration examples.
- ``flat_floor``: the plane z = 0 with noise in z (the normals examples).
- ``sphere_points``: points on a sphere with noise (the sphere-fit examples).
- ``target_stations``: TLS panoramas of sphere targets in a yard from several stations with known poses.
- ``tile_row``: a row of small point-cloud files in a fresh folder (the file examples).
"""

from __future__ import annotations

from ..core.lazy import lazy_attribute

_EXPORTS = {
    "sphere_on_tripod": "labkit.synthetic.tripod",
    "TripodScene": "labkit.synthetic.tripod",
    "room_scene": "labkit.synthetic.room",
    "multibeam_room": "labkit.synthetic.multibeam",
    "MultibeamScene": "labkit.synthetic.multibeam",
    "als_scene": "labkit.synthetic.als",
    "als_epochs": "labkit.synthetic.als",
    "EpochPair": "labkit.synthetic.als",
    "REGIONS": "labkit.synthetic.als",
    "SPARSE_REGIONS": "labkit.synthetic.als",
    "wavy_surface": "labkit.synthetic.wavy",
    "wavy_pair": "labkit.synthetic.wavy",
    "flat_floor": "labkit.synthetic.wavy",
    "sphere_points": "labkit.synthetic.wavy",
    "tile_row": "labkit.synthetic.files",
    "target_stations": "labkit.synthetic.stations",
    "TargetStations": "labkit.synthetic.stations",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    return lazy_attribute(__name__, _EXPORTS, globals(), name)
