"""labkit: robust adjustment of 3D point clouds for engineering geodesy.

The public names below are imported lazily (PEP 562), so ``import labkit`` is
fast and does not pull in pyvista or laspy until they are needed.
"""

from __future__ import annotations

import importlib

from .core.lazy import lazy_attribute
from .core.memory import keep_freed_memory
from .core.numba_cache import ensure_cache_dir

ensure_cache_dir()  # before any compiled kernel is defined: numba must find a writable cache folder
keep_freed_memory()  # freed work arrays reused by the next call, not handed back to the system (core/memory.py)

__version__ = "0.1.0"

# public name -> module that defines it
_EXPORTS = {
    # errors
    "LabkitError": "labkit.core.errors",
    "DegenerateGeometryError": "labkit.core.errors",
    "EmptyRegionError": "labkit.core.errors",
    "CloudFileError": "labkit.core.errors",
    "precision_tolerance": "labkit.core.checks",
    # data
    "PointCloud": "labkit.cloud",
    "read_cloud": "labkit.io",
    "write_cloud": "labkit.io",
    # sphere
    "gauss_helmert_model": "labkit.sphere.ghm",
    "SphereFit": "labkit.sphere.fit",
    "ransac_sphere": "labkit.ransac",
    "find_spheres": "labkit.ransac",
    # local geometry
    "local_pca": "labkit.features",
    "LocalPCA": "labkit.features",
    "local_noise": "labkit.features",
    "eigen_features": "labkit.features",
    "multiscale_features": "labkit.features",
    "robust_normals": "labkit.features",
    # transforms
    "make_transform": "labkit.transforms",
    "compose": "labkit.transforms",
    "invert": "labkit.transforms",
    "apply_transform": "labkit.transforms",
    # registration
    "RegistrationResult": "labkit.registration",
    "match": "labkit.registration",
    "MatchOptions": "labkit.registration",
    "icp": "labkit.registration",
    "consensus_cube": "labkit.registration",
    "max_consensus": "labkit.registration",
    # comparison and tiles
    "cloud_to_cloud": "labkit.change.distances",
    "point_to_plane_distance": "labkit.change.distances",
    "distances_before_after": "labkit.change.distances",
    "Reference": "labkit.registration.references",
    "truth_reference": "labkit.registration.references",
    "manual_reference": "labkit.registration.references",
    "average_references": "labkit.registration.references",
    "reference_from_targets": "labkit.registration.references",
    "reference_from_pairs": "labkit.registration.references",
    "load_references": "labkit.registration.references",
    "save_references": "labkit.registration.references",
    "compare_methods": "labkit.registration.compare",
    "synthetic_cases": "labkit.registration.compare",
    "ComparisonTable": "labkit.registration.compare",
    "register_tiles": "labkit.tiles",
    "neighbour_test": "labkit.tiles",
    "ShiftField": "labkit.tiles",
    # change between epochs
    "m3c2": "labkit.change.m3c2",
    "M3C2Result": "labkit.change.m3c2",
    "m3c2_parameters": "labkit.change.defaults",
    # target-based registration
    "helmert": "labkit.targets.helmert",
    "HelmertFit": "labkit.targets.helmert",
    "register_targets": "labkit.targets.register",
    "register_scans": "labkit.targets.register",
    "TargetNetwork": "labkit.targets.register",
    # deliverables: the registration file
    "RegistrationFile": "labkit.registration.file",
    "save_registration": "labkit.registration.file",
    "load_registration": "labkit.registration.file",
    # notebooks
    "setup_notebook": "labkit.notebook",
}

#: Sub-modules reachable as attributes (``labkit.registration``) without an explicit import.
_SUBMODULES = {
    "change", "core", "features", "io", "neighbours", "plotting", "ransac", "regions", "registration", "sphere",
    "synthetic", "targets", "tiles", "transforms", "widgets",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    if name in _SUBMODULES:
        value = importlib.import_module(f"labkit.{name}")
        globals()[name] = value
        return value
    return lazy_attribute(__name__, _EXPORTS, globals(), name)


def __dir__():
    return __all__
