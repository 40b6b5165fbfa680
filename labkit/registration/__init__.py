"""Registration of point clouds: ICP and maximum consensus.

Every method returns a :class:`RegistrationResult` mapping source onto target.

One module per concept: the ICP loop (:mod:`.icp_loop`) with its robust weights, adjustment,
covariance and stopping rules in the ``_icp_*`` modules next to it; the matching
(:mod:`.matching`); the coarse-to-fine pyramid (:mod:`.pyramid`); the consensus searches
(:mod:`.consensus`), their records (:mod:`.consensus_result`) and branch and bound (:mod:`.bnb`).
``labkit.registration.icp`` is always the function (no module carries that name).
"""

from __future__ import annotations

from .._lazy import lazy_attribute
from .consistency import Consistency, group_consistency
from .degeneracy import Degeneracy, degeneracy_report
from .result import RegistrationResult

_EXPORTS = {
    "match": "labkit.registration.matching",
    "Correspondences": "labkit.registration.matching",
    "MatchOptions": "labkit.registration.options",
    "icp": "labkit.registration.icp_loop",
    "IterationRecord": "labkit.registration.icp_loop",
    "consensus_cube": "labkit.registration.consensus",
    "consensus_inputs": "labkit.registration.consensus",
    "max_consensus": "labkit.registration.consensus",
    "ConsensusCube": "labkit.registration.consensus_result",
    "PeakShape": "labkit.registration.consensus_result",
}

__all__ = ["Consistency", "Degeneracy", "RegistrationResult", "degeneracy_report", "group_consistency",
           *sorted(_EXPORTS)]


def __getattr__(name: str):
    return lazy_attribute(__name__, _EXPORTS, globals(), name)
