"""A smooth wavy surface: the small test object of the registration examples.

Its slopes run in X and in Y, so a registration of two samplings determines every
direction of the shift (a plane would leave the shift along it free).
"""

from __future__ import annotations

import numpy as np

from ..core.checks import as_rng, count, non_negative, positive


def wavy_surface(n: int, rng=None, *, noise: float = 0.002, size: float = 6.0) -> np.ndarray:
    """Sample ``z = 0.5 sin(2x) + 0.5 cos(2y)`` at ``n`` random places of a square, with noise.

    Parameters
    ----------
    n : int
        Number of points (>= 1).
    rng : int or numpy.random.Generator, optional
        Seed or generator; a generator is drawn from (not copied), so two calls with one
        generator give two independent samplings of the same surface.
    noise : float
        Standard deviation (m) of the isotropic Gaussian noise added to x, y and z; 0 adds
        none and draws nothing.
    size : float
        Edge of the square ``[0, size]^2`` (m) in which x and y are drawn uniformly.

    Returns
    -------
    ndarray (n, 3)
        The sampled points (m).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_surface
    >>> rng = np.random.default_rng(1)
    >>> target = wavy_surface(1500, rng)
    >>> source = wavy_surface(300, rng) - [0.05, 0.02, 0.03]  # another sampling, moved
    >>> target.shape, source.shape
    ((1500, 3), (300, 3))
    >>> exact = wavy_surface(4, 0, noise=0.0)  # on the surface itself
    >>> bool(np.allclose(exact[:, 2], 0.5 * np.sin(2 * exact[:, 0]) + 0.5 * np.cos(2 * exact[:, 1])))
    True
    """
    n = count(n, "n")
    noise = non_negative(noise, "noise")
    size = positive(size, "size")
    rng = as_rng(rng)
    xy = rng.uniform(0, size, (n, 2))
    points = np.column_stack([xy, 0.5 * np.sin(2 * xy[:, 0]) + 0.5 * np.cos(2 * xy[:, 1])])
    if noise > 0:
        points = points + rng.normal(0, noise, (n, 3))
    return points
