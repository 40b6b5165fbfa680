"""Ready-made registration methods by name: ICP variants, maximum consensus, and consensus then ICP.

For :func:`labkit.registration.compare.compare_methods`, the tiles and the command line: each name
gives a picklable callable ``(source, target) -> RegistrationResult``.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np

from ..core.checks import as_points, choice
from ..core.errors import EmptyRegionError
from ..core.masks import STABLE_CLASSES
from ..neighbours.sampling import median_spacing
from .agreement import disagreement_covariance
from .shift import shift_at, shift_covariance

__all__ = ["METHODS", "standard_methods"]


METHODS = ("icp", "icp-point", "icp-huber", "icp-tukey", "icp-classes", "consensus", "consensus+icp")


def standard_methods(names=("icp", "icp-huber", "consensus"), *, dof: str = "translation", extent: float = 1.0,
                     max_points: int | None = 5000, rng=0, reach: float | None = None,
                     max_iterations: int | None = None) -> dict:
    """Ready-made registration methods by name, for comparisons of methods, tiles and the command line.

    ``icp`` (point to plane), ``icp-point`` (point to point), ``icp-huber`` and
    ``icp-tukey`` (robust weights) with ``dof``; ``icp-classes`` (point to plane on
    the stable classes :data:`STABLE_CLASSES` of both epochs only - ground, roofs,
    roads - so that grown vegetation and crowns cannot pull it; the registration study's step 4,
    "Nutzen nur von best. Klassen"); ``consensus`` (maximum consensus,
    a translation within +-``extent`` m, on at most ``max_points`` source points spread
    evenly); ``consensus+icp`` (consensus, then a Tukey ICP with ``dof`` from there: the
    route for shifts larger than ICP's matching distance; with no pair within the gate there, the gate is
    twice the target's point spacing when that is wider, the precision limit stays; X, Y that ICP leaves undetermined
    are filled from the height models where those fix them, :func:`labkit.registration.height_model.fill_held_axes`
    (matched once: ICP takes the match max_consensus made for its own held axes);
    an ICP that disagrees with its start states a covariance that covers the disagreement,
    :func:`labkit.registration.agreement.disagreement_covariance`). ``reach`` (m, optional) is passed to the ICP
    methods: a reach beyond the matching distance runs ICP's coarse-to-fine pyramid first.
    ``max_iterations`` (optional) is passed to every ICP run (default: ICP's own).
    The callables are picklable (for Dask workers in other processes).

    Examples
    --------
    >>> from labkit.registration.compare import standard_methods
    >>> methods = standard_methods(("icp", "consensus"), dof="translation")
    >>> sorted(methods), callable(methods["icp"])
    (['consensus', 'icp'], True)
    """
    choice(dof, ("translation", "rigid"), "dof")
    out = {}
    for name in names:
        choice(name, METHODS, "method")
        out[name] = partial(_standard, name=name, dof=dof, extent=float(extent), max_points=max_points, rng=rng,
                            reach=reach, **({} if max_iterations is None else {"max_iterations": max_iterations}))
    return out


def _standard(source, target, *, name, dof, extent, max_points, rng, progress=False, reach=None, **icp_options):
    from . import icp, max_consensus  # (numba: loaded when a registration runs)

    if name.startswith("icp"):
        kind = name.partition("-")[2]
        metric = "point_to_point" if kind == "point" else "point_to_plane"
        classes = STABLE_CLASSES if kind == "classes" else None
        return icp(source, target, dof=dof, metric=metric, robust=kind if kind in ("huber", "tukey") else None,
                   classes=classes, rng=rng, progress=progress, reach=reach, **icp_options)
    result = max_consensus(source, target, extent=extent, max_points=max_points)  # an even subset votes
    if name == "consensus":
        return result
    hm = True if result.height_model is None else result.height_model  # the consensus's match: not made twice
    run = partial(icp, source, target, dof=dof, robust="tukey", initial=result.matrix, rng=rng, progress=progress,
                  height_model=hm)
    try:
        refined = run(**icp_options)
    except EmptyRegionError:  # no pair within the gate at the consensus start: points too sparse for the gate?
        gate = 2 * median_spacing(as_points(target, name="target"), distinct=True)
        md = icp_options.get("max_distance", 1.0)  # the precision limit stays that of the caller's gate
        if not gate > md:  # dense clouds that do not overlap: refused
            raise
        refined = run(**dict(icp_options, max_distance=gate, max_std=icp_options.get("max_std") or 0.1 * md))
    bb = result.history[0]  # the branch-and-bound outcome: how far the start is certified
    c = as_points(source, name="source").mean(axis=0)  # ICP that walked away from its start: covered
    d = shift_at(refined.matrix, c) - shift_at(result.matrix, c)
    f, extra, T, k = disagreement_covariance(d, np.zeros(3), shift_covariance(refined, c), shift_covariance(result, c))
    if f > 1:  # d d^T: the shift's translation parameters take it (d(shift)/dt = I at any point)
        E = np.eye(len(refined.parameter_names))[:, [refined.parameter_names.index(n) for n in ("tx", "ty", "tz")]]
        refined = replace(refined, covariance=f * refined.covariance + E @ extra @ E.T)
    start = (f"started at max_consensus: consensus {bb.lower:.0f}, certified gap {bb.gap:.0f}, {bb.reason}, "
             f"shift {np.array2string(result.translation, precision=4)} m; ICP moved it by "
             f"{np.array2string(d * 1e3, precision=1)} mm, T = {T:.1f} / {k}"
             + (f": covariance x {f:.2f}" if f > 1 else "") + (" + (1 - k/T) d d^T" if extra.any() else ""))
    return replace(refined, method=f"max_consensus + {refined.method}",
                   runtime_s=result.runtime_s + refined.runtime_s,
                   message="; ".join(m for m in (refined.message, start) if m))
