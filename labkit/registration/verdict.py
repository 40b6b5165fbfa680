"""When a registration result must not be used: the verdict behind ``labkit register``'s exit status 4.

A registration that did not converge, or whose data determine none of the shift
components, is not a result with a large uncertainty but no result: the command
line says why in one line, what to try, writes nothing and exits with
:data:`EXIT_NOT_CONVERGED`. The Python API keeps the flags on the result
(``converged``, ``degeneracy``); this module only reads them.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EXIT_NOT_CONVERGED", "register_verdict"]

#: Exit status of ``labkit register`` when the registration did not converge or determines no component.
EXIT_NOT_CONVERGED = 4


def register_verdict(result) -> str | None:
    """Why a registration result must not be used (one line with what to try), or None when it may.

    Not usable: the method did not converge, or the data determine none of the shift
    components (dX, dY, dZ all held, std inf). A result that determines some components
    (e.g. only dZ on flat ground) is usable; its summary names the undetermined ones.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.verdict import register_verdict
    >>> from labkit.registration import RegistrationResult
    >>> res = RegistrationResult(np.zeros(3), np.eye(3), np.zeros(3), np.eye(3) * 1e-6, ("tx", "ty", "tz"),
    ...                          1.0, 500, 1.0, False, 50, method="icp", message="not converged after 50 iterations")
    >>> register_verdict(res).split(";")[0]
    'not converged: icp stopped: not converged after 50 iterations'
    """
    method = (getattr(result, "method", "") or "the method").split(" (")[0]
    if not result.converged:
        message = " ".join(str(getattr(result, "message", "")).split())
        stop = message.split(";")[0] or f"after {result.iterations} iterations"
        if "consensus" in method and "icp" not in method:
            advice = "try a smaller --extent or fewer --max-points (the search ran out of budget)"
        else:
            advice = (f"try --max-iterations {max(2 * int(result.iterations), 100)}; if the shift may exceed the "
                      "1 m matching distance, --reach R or --method consensus+icp")
        return f"not converged: {method} stopped: {stop}; {advice}"
    std = np.asarray(result.translation_std, dtype=float)
    deg = getattr(result, "degeneracy", None)
    determined = np.isfinite(std) & (np.ones(3, bool) if deg is None else np.asarray(deg.axis_determined, bool))
    if not determined.any():
        return ("not usable: the data determine none of dX, dY, dZ (all held, std inf): the overlap is too "
                "small or featureless; try a larger overlap, or the whole survey rather than a part")
    return None
