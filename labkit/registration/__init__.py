"""Registration of point clouds: ICP and maximum consensus.

Every method returns a :class:`RegistrationResult` mapping source onto target.
"""

from __future__ import annotations

import importlib

from .result import Degeneracy, RegistrationResult, degeneracy_report

_EXPORTS = {
    "match": "labkit.registration.matching",
    "Correspondences": "labkit.registration.matching",
    "icp": "labkit.registration.icp",
    "consensus_cube": "labkit.registration.consensus",
    "ConsensusCube": "labkit.registration.consensus",
    "max_consensus": "labkit.registration.consensus",
}

__all__ = ["Degeneracy", "RegistrationResult", "degeneracy_report", *sorted(_EXPORTS)]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'labkit.registration' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
