"""Registration of point clouds: ICP and maximum consensus.

Every method returns a :class:`RegistrationResult` mapping source onto target.

One package per method: the ICP (:mod:`.closest_point`: the loop, its robust weights, adjustment,
covariance, stopping rules and the coarse-to-fine pyramid), the correspondences (:mod:`.matching`) and
maximum consensus (:mod:`.consensus`: the cube, its records and branch and bound). Beside them what every
method shares: the result, options, degeneracy, consistency, point selection and verdict, the registration
file, references and the comparison of methods.
``labkit.registration.icp`` is always the function (no module carries that name).
"""

from __future__ import annotations

from ..core.lazy import lazy_attribute
from .consistency import Consistency, group_consistency
from .degeneracy import Degeneracy, degeneracy_report
from .result import RegistrationResult

_EXPORTS = {
    "match": "labkit.registration.matching.match",
    "Correspondences": "labkit.registration.matching.match",
    "MatchOptions": "labkit.registration.options",
    "icp": "labkit.registration.closest_point.loop",
    "IterationRecord": "labkit.registration.closest_point.loop",
    "consensus_cube": "labkit.registration.consensus.cube",
    "consensus_inputs": "labkit.registration.consensus.cube",
    "max_consensus": "labkit.registration.consensus.cube",
    "ConsensusCube": "labkit.registration.consensus.result",
    "PeakShape": "labkit.registration.consensus.result",
}

__all__ = ["Consistency", "Degeneracy", "RegistrationResult", "degeneracy_report", "group_consistency",
           *sorted(_EXPORTS)]


def __getattr__(name: str):
    return lazy_attribute(__name__, _EXPORTS, globals(), name)
