"""The correspondence options shared by :func:`~labkit.registration.icp`, ``match`` and ``prepare``.

One frozen :class:`MatchOptions` documents and checks the options of the matching (notebook 05,
section 2) in one place. Every function that matches still takes them as keywords (the notebooks
do); :func:`takes_match_options` folds those keywords and an optional ``options=`` object into one
checked :class:`MatchOptions` before the function body runs, so the body reads ``options.k``
instead of fourteen loose arguments.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import numbers
from collections.abc import Mapping

from ..core.checks import choice, count, flag, non_negative, positive
from ..core.errors import LabkitError

__all__ = ["FIELDS", "SAMPLE_METHODS", "SURFACES", "MatchOptions", "takes_match_options", "with_keywords"]

#: Local surface models of the matching: the PCA plane, a quadric (curved, sparse surfaces) or 'auto'.
SURFACES = ("plane", "quadric", "auto")
#: Methods of ``sample=(method, value)``.
SAMPLE_METHODS = ("random", "voxel", "normal_space")


@dataclasses.dataclass(frozen=True, eq=False)
class MatchOptions:
    """How correspondences are found, gated and weighted (notebook 05, section 2).

    The defaults are those of :func:`labkit.registration.icp`. :func:`labkit.registration.match` and
    ``prepare`` called without ``options`` default to ``sample=None`` and ``surface='plane'`` instead
    (every source point, the PCA plane); given an ``options`` object they use its values. A keyword given
    next to ``options`` overrides that field: ``icp(s, t, options=opts, k=30)``. The consensus searches
    (:func:`~labkit.registration.consensus_cube`, :func:`~labkit.registration.max_consensus`) take the
    options they share under the same names, with their own defaults (``max_angle_deg=None``, ``k=12``,
    ``source_normals``, ``target_normals``).

    Parameters
    ----------
    max_distance : float or None
        Gate on the nearest-neighbour distance in metres (eq. 5.1); None: no gate.
    max_angle_deg : float or None
        Gate on the angle between the source and target normals in degrees (orientation-free); None: no gate.
    classes : sequence of int, optional
        Allowed ASPRS classes (e.g. (2, 6, 11)); others are rejected by rule 'class'. Both clouds need a
        ``classification`` attribute.
    class_sigma : mapping int -> float, optional
        A priori standard deviation per class in metres (roof precise, vegetation not); classes not
        listed get ``default_sigma``.
    default_sigma : float
        A priori standard deviation (m) of the classes missing in ``class_sigma`` (0: only their local
        noise counts).
    noise_weighting : bool
        Add each point's local noise (std along its normal) to its variance, so that the weight is
        p_i = 1 / (sigma_s,i^2 + sigma_t,j^2) (eq. 5.6). Without it and ``class_sigma`` all weights are 1.
    max_noise : float, optional
        Reject points whose local noise (m) exceeds this (rule 'noise'; vegetation).
    sample : None, 'auto', int or (method, value)
        Source points that form pairs. None: all; an int m: m random points; ('random', m),
        ('voxel', edge in m) or ('normal_space', m); 'auto': all up to 300,000 points, a larger source
        thinned to about 100,000 points spread in space and over the normal directions.
    unique : bool
        At most one source point per target point (the closest; the others are rejected as
        'duplicate'), so that no target point's noise enters two residuals.
    k : int
        Neighbours for normals, local noise and the local surface (at least 3, at most the target size).
    target_normals, source_normals : array_like (n, 3), optional
        Given normals, one per point of that cloud; otherwise PCA normals of k neighbours.
    surface : {'auto', 'plane', 'quadric'}
        Local surface model of both clouds from their k neighbours. 'plane': the PCA plane (notebook
        04), right for dense data. 'quadric': h = a u^2 + b uv + c v^2 + d u + e v + f in the PCA frame
        at each target point, for sparse curved ground (ALS at 0.5-1 pts/m^2 on hills), where the
        plane's l3 holds the curvature (its noise, weight and ``max_noise`` are wrong by that much) and
        the point-to-plane residual carries the sagitta between p_i and q_j. With the quadric the noise
        is the spread about it (redundancy k - 6), ``d`` runs from p_i to its foot point on the target's
        quadric shifted to pass through the measured q_j (so that q_j's noise enters one residual only),
        and the target normal is the quadric's at the foot point; needs k >= 10. 'auto': the quadric
        where the median radius of the target's k-neighbourhoods exceeds 1 m (sparse ALS), else the
        plane; the matcher's settings and ICP's ``result.method`` name the choice.

    Raises
    ------
    LabkitError
        For a value outside the ranges above (checked when the object is built).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration import MatchOptions, icp
    >>> from labkit.synthetic import wavy_surface
    >>> target = wavy_surface(1500, 1, noise=0.0)  # slopes in X and Y, no noise
    >>> opts = MatchOptions(max_distance=0.5, max_angle_deg=20.0)
    >>> res = icp(target[::5] + [0.02, -0.01, 0.03], target, options=opts)
    >>> bool(np.allclose(res.translation, [-0.02, 0.01, -0.03], atol=0.002))
    True
    >>> opts.replace(k=12).k, opts.k  # a changed copy; the object itself is frozen
    (12, 20)
    """

    max_distance: float | None = 1.0
    max_angle_deg: float | None = 30.0
    classes: tuple | None = None
    class_sigma: Mapping | None = None
    default_sigma: float = 0.0
    noise_weighting: bool = True
    max_noise: float | None = None
    sample: object = "auto"
    unique: bool = True
    k: int = 20
    target_normals: object = None
    source_normals: object = None
    surface: str = "auto"

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        put("max_distance", _optional(positive, self.max_distance, "max_distance"))
        put("max_angle_deg", _optional(positive, self.max_angle_deg, "max_angle_deg"))
        if self.classes is not None:
            if isinstance(self.classes, (str, bytes)) or not hasattr(self.classes, "__iter__"):
                raise LabkitError(f"classes must be a sequence of class numbers or None, got {self.classes!r}")
            put("classes", tuple(self.classes))
        if self.class_sigma is not None:
            if not isinstance(self.class_sigma, Mapping):
                raise LabkitError(f"class_sigma must be a mapping class -> sigma (m) or None, got {self.class_sigma!r}")
            put("class_sigma", dict(self.class_sigma))  # a copy: later changes of the caller's dict do not leak in
        put("default_sigma", non_negative(self.default_sigma, "default_sigma"))
        put("noise_weighting", flag(self.noise_weighting, "noise_weighting"))
        put("max_noise", _optional(positive, self.max_noise, "max_noise"))
        put("sample", _check_sample(self.sample))
        put("unique", flag(self.unique, "unique"))
        k = count(self.k, "k", minimum=1)
        if k < 3:
            raise LabkitError(f"k must lie between 3 and the number of target points, got {self.k!r}")
        put("k", k)
        choice(self.surface, SURFACES, "surface")
        if self.surface == "quadric" and k < 10:
            raise LabkitError(f"surface='quadric' fits 6 parameters: k must be at least 10, got {k}")

    def replace(self, **changes) -> MatchOptions:
        """A checked copy with ``changes`` applied (field names as keywords)."""
        unknown = set(changes) - set(FIELDS)
        if unknown:
            raise LabkitError(f"MatchOptions has no option {', '.join(sorted(unknown))}; options: {', '.join(FIELDS)}")
        return dataclasses.replace(self, **changes)


#: The names of the matching options, in the order of :class:`MatchOptions`.
FIELDS = tuple(f.name for f in dataclasses.fields(MatchOptions))


def _optional(check, value, name):
    return None if value is None else check(value, name)


def _check_sample(sample):
    """None, 'auto', a whole number > 0 or (method, value) with value > 0; a list becomes a tuple."""
    if sample is None or (isinstance(sample, str) and sample == "auto"):
        return sample
    if isinstance(sample, numbers.Integral) and not isinstance(sample, bool):
        return count(sample, "sample size")
    if isinstance(sample, (tuple, list)) and len(sample) == 2:
        choice(sample[0], SAMPLE_METHODS, "sample method")
        positive(sample[1], "voxel size" if sample[0] == "voxel" else "sample size")
        return tuple(sample)
    raise LabkitError(f"sample must be None, 'auto', an int or (method, value), got {sample!r}")


def takes_match_options(func):
    """Let ``func`` take the matching options as keywords and/or as ``options=MatchOptions(...)``.

    ``func`` declares the option keywords with its own defaults (its public signature) and a keyword
    ``options``; the wrapper takes the keywords actually given out of the call, applies them to
    ``options`` (or to a :class:`MatchOptions` of ``func``'s defaults) and calls ``func`` with the result,
    so that the body reads ``options`` only.

    Examples
    --------
    >>> @takes_match_options
    ... def gate(*, options=None, max_distance=0.5, k=10):
    ...     return options.max_distance, options.k
    >>> gate(), gate(k=30), gate(options=MatchOptions(max_distance=2.0), k=30)  # own defaults, then overrides
    ((0.5, 10), (0.5, 30), (2.0, 30))
    """
    params = inspect.signature(func).parameters
    names = tuple(name for name in FIELDS if name in params)
    base = MatchOptions(**{name: params[name].default for name in names})  # the function's own defaults

    @functools.wraps(func)
    def wrapper(*args, options=None, **kwargs):
        return func(*args, options=with_keywords(options, kwargs, base, names), **kwargs)

    return wrapper


def with_keywords(options, keywords, base=None, names=FIELDS) -> MatchOptions:
    """``options`` (default ``base``, else ``MatchOptions()``) with the matching options found in the dict
    ``keywords`` applied; those entries are removed from ``keywords``.

    Examples
    --------
    >>> rest = {"k": 12, "dof": "rigid"}
    >>> with_keywords(MatchOptions(max_distance=0.3), rest).k, rest  # k moved into the options
    (12, {'dof': 'rigid'})
    """
    if options is not None and not isinstance(options, MatchOptions):
        raise LabkitError(f"options must be a labkit.registration.MatchOptions or None, got {type(options).__name__}")
    given = {name: keywords.pop(name) for name in names if name in keywords}
    opts = options if options is not None else base if base is not None else MatchOptions()
    return opts.replace(**given) if given else opts
