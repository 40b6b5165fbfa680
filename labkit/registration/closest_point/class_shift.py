"""The shift of one class against a registration: a matching and a translation step (eq. 5.7, 5.13).

The check of the classes a registration left out
(:func:`labkit.registration.selection.check_other_classes`) asks one question per class: do its points
sit where the result puts them? At the result's transformation the class's pairs are matched once and
one weighted adjustment of a translation (3 parameters, eq. 5.7) on them gives the class's own shift
against the result, with the covariance ICP states (block sandwich eq. 5.13, held axes inf, eq. 5.12):
under "the class did not move" a test of that step against zero. Only where the step lies beyond
:data:`SIGMAS` of its standard deviation (the class moved) is the class matched again from there, up to
:data:`MAX_STEPS` times: in sparse vegetation lifted by 0.3 m the first linear step reaches 0.2 m (the
nearest neighbours at that offset are partly other leaves). ICP run to convergence on every class
cost several times the registration itself on a classified ALS file, and on vegetation that did not
move it drifted (two halves of one scan: class 5 stated 32 +- 7 mm off).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ...core.checks import as_points
from ...core.frame import local_origin
from ...transforms import check_transform
from ..matching.match import prepare
from ..result import RegistrationResult
from .adjustment import IcpSettings, adjust, default_max_std, held_shift_std
from .information import TiltVariance
from .result import icp_result

#: Matchings at most; another one follows a step beyond SIGMAS of its standard deviation on some axis.
MAX_STEPS = 5
#: A step larger than this many standard deviations moved the class off the given transformation.
SIGMAS = 3.0


def class_shift(source, target, *, initial, options, metric="point_to_plane", robust=None, reject_sigma=3.0,
                rel_threshold=1e-2, max_std=None, held_rotation_std_deg=0.02, covariance="block", block_size=2.0,
                min_correspondences=20, rng=None, **ignored) -> RegistrationResult:
    """``initial`` followed by translation steps of ``source`` onto ``target`` (module docstring), with covariance.

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        One class of each cloud.
    initial : ndarray (4, 4)
        The registration's transformation (caller's frame); it is kept, only a shift is added.
    options : MatchOptions
        The registration's matching options.
    metric, robust, reject_sigma, rel_threshold, max_std, held_rotation_std_deg, covariance, block_size,
    min_correspondences, rng
        As in :func:`labkit.registration.icp` (its other keywords are ignored).

    Returns
    -------
    RegistrationResult
        Rotation of ``initial``, its translation plus the steps; covariance of the shift from the last
        matching (inf on an axis the class does not determine); ``iterations``: the matchings.

    Raises
    ------
    EmptyRegionError
        Too few pairs within the gates.

    References
    ----------
    .. [1] Notebook 05, eqs. 5.7, 5.12-5.13; the registration study, step 4 (classes).

    Examples
    --------
    >>> from labkit.registration import MatchOptions
    >>> from labkit.synthetic import wavy_pair
    >>> roofs, old_roofs = wavy_pair(300, shift=(0, 0, 0), noise=0.001)  # one class in two epochs, in place
    >>> lifted = roofs + [0.0, 0.0, 0.05]  # the class rose by 5 cm (the registration: the identity)
    >>> res = class_shift(lifted, old_roofs, initial=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    ...                   options=MatchOptions())
    >>> import numpy as np
    >>> bool(np.allclose(res.translation, [0.0, 0.0, -0.05], atol=0.005)), res.iterations > 1  # 5 cm: matched again
    (True, True)
    """
    t_start = time.perf_counter()
    src_xyz = as_points(source, min_points=3, name="source")
    tgt_xyz = as_points(target, min_points=3, name="target")
    origin = local_origin(tgt_xyz)
    T = check_transform(initial)
    R, t = T[:3, :3].copy(), T[:3, :3] @ origin + T[:3, 3] - origin  # the local frame: t_l = R o + t0 - o
    matcher = prepare(source, target, options=options, rng=rng, origin=origin, points=(src_xyz, tgt_xyz))
    opts = IcpSettings(
        origin=origin, dof="translation", metric=metric, robust=robust, reject_sigma=reject_sigma,
        L=max(float(np.sqrt((matcher.source**2).sum(axis=1).mean())), 1.0), rel_threshold=rel_threshold,
        min_correspondences=min_correspondences, covariance=covariance, block_size=block_size,
        held_rotation_std=np.radians(held_rotation_std_deg), consistency_alpha=None,
        max_std=default_max_std(max_std, matcher.options["max_distance"]),
        held_shift_std=held_shift_std(matcher.options["max_distance"]), tilt=TiltVariance(matcher),
        sample=options.sample,
    )  # fmt: skip
    for step in range(1, MAX_STEPS + 1):  # the robust measures of ICP's last stage
        adj = adjust(matcher(R, t), R, t, opts)
        t = t + adj.dx
        res = icp_result(R, t, origin, adj, (), True, matcher, opts, time.perf_counter() - t_start)
        with np.errstate(invalid="ignore"):
            off = np.abs(adj.dx) > SIGMAS * res.translation_std  # inf std: never off
        if not off.any():
            break
    text = "one matching" if step == 1 else f"{step} matchings"
    return replace(res, iterations=step, method=f"translation steps from the given transformation ({metric})",
                   message=f"{text} from the given transformation, the last step within {SIGMAS:g} std")
