"""Small test surfaces: a smooth wavy surface (the registration examples), a flat floor and a sphere.

Its slopes run in X and in Y, so a registration of two samplings determines every
direction of the shift (a plane would leave the shift along it free).
"""

from __future__ import annotations

import numpy as np

from ..core.checks import as_rng, count, non_negative, positive
from ..core.errors import LabkitError


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


def wavy_pair(n_source: int = 300, n_target: int = 1500, rng=1, *, shift=(0.05, 0.02, 0.03),
              noise: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """Two samplings of :func:`wavy_surface`, the source moved by ``-shift``: a registration test case.

    The target is drawn first, then the source from the same generator, so the pair equals
    ``wavy_surface(n_target, rng)`` followed by ``wavy_surface(n_source, rng) - shift``.

    Parameters
    ----------
    n_source, n_target : int
        Number of points of each sampling (>= 1).
    rng : int or numpy.random.Generator, optional
        Seed or generator (default 1, as in the registration examples).
    shift : array_like (3,)
        The translation (m) that maps the source back onto the surface: what a registration should find.
    noise : float
        Standard deviation (m) of the noise of both samplings.

    Returns
    -------
    source, target : ndarray (n_source, 3), ndarray (n_target, 3)

    Examples
    --------
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(300)
    >>> source.shape, target.shape
    ((300, 3), (1500, 3))
    """
    rng = as_rng(rng)
    shift = np.asarray(shift, dtype=np.float64)
    if shift.shape != (3,) or not np.all(np.isfinite(shift)):
        raise LabkitError(f"shift must be 3 finite numbers (m), got {shift.tolist()!r}")
    target = wavy_surface(n_target, rng, noise=noise)
    return wavy_surface(n_source, rng, noise=noise) - shift, target


def flat_floor(n: int, rng=None, *, noise: float = 0.001, size: float = 1.0) -> np.ndarray:
    """Sample the plane ``z = 0`` at ``n`` random places of a square, with noise in z only.

    The flat counterpart of :func:`wavy_surface`: its normal is ``(0, 0, 1)`` everywhere and it
    fixes only the height of a registration.

    Parameters
    ----------
    n, rng, size : as in :func:`wavy_surface`
    noise : float
        Standard deviation (m) of the Gaussian noise of z.

    Returns
    -------
    ndarray (n, 3)
        Points (m) of the floor, z being the noise alone.

    Examples
    --------
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # 1 mm noise in z
    >>> floor.shape, bool(abs(floor[:, 2]).max() < 0.005), bool(floor[:, :2].max() <= 1.0)
    ((200, 3), True, True)
    """
    n = count(n, "n")
    noise = non_negative(noise, "noise")
    size = positive(size, "size")
    rng = as_rng(rng)
    return np.column_stack([rng.uniform(0, size, (n, 2)), rng.normal(0, noise, n)])


def sphere_points(n: int, rng=None, *, center=(0.0, 0.0, 0.0), radius: float = 1.0,
                  noise: float = 0.0) -> np.ndarray:
    """Sample a sphere at ``n`` directions drawn uniformly, with isotropic noise: the sphere examples' test object.

    The directions are normalised Gaussian draws; the noise (if any) is drawn after them.

    Parameters
    ----------
    n, rng : as in :func:`wavy_surface`
    center : array_like (3,)
        Centre (m).
    radius : float
        Radius (m), > 0.
    noise : float
        Standard deviation (m) of the Gaussian noise of x, y and z; 0 draws none.

    Returns
    -------
    ndarray (n, 3)
        Points (m) on (or, with noise, near) the sphere.

    Examples
    --------
    >>> from labkit.synthetic import sphere_points
    >>> pts = sphere_points(100, 0, center=[1.0, 2.0, 3.0], radius=0.5)
    >>> bool(abs(((pts - [1.0, 2.0, 3.0]) ** 2).sum(axis=1) - 0.25).max() < 1e-12)
    True
    """
    n = count(n, "n")
    radius = positive(radius, "radius")
    noise = non_negative(noise, "noise")
    center = np.asarray(center, dtype=np.float64)
    if center.shape != (3,) or not np.all(np.isfinite(center)):
        raise LabkitError(f"center must be 3 finite numbers (m), got {center.tolist()!r}")
    rng = as_rng(rng)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    points = center + radius * u
    return points + rng.normal(0.0, noise, (n, 3)) if noise > 0 else points
