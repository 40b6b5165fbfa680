"""Geometry shared by the synthetic scenes: unit vectors, an orthonormal basis, a scanned sphere cap."""

from __future__ import annotations

import numpy as np


def unit(v):
    """``v`` scaled to unit length (along the last axis)."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def basis(axis):
    """Two unit vectors perpendicular to ``axis`` (3,) and to each other."""
    a = unit(np.asarray(axis, dtype=np.float64))
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(np.cross(a, helper))
    return e1, np.cross(a, e1)


def sphere_cap(rng, n, centre, radius, station, max_incidence):
    """Points on the cap seen from the station, uniform in the scanner's view.

    A scanner samples on an angular grid, so from afar the points are uniform
    over the projected disc: sin(theta) = sqrt(U) sin(theta_max), with theta the
    angle between the surface normal and the direction to the station, up to
    ``max_incidence`` (rad).
    """
    to_station = station - centre
    dist = np.linalg.norm(to_station)
    u = to_station / dist
    e1, e2 = basis(u)
    theta_max = min(np.arccos(radius / dist), max_incidence)
    sin_t = np.sqrt(rng.random(n)) * np.sin(theta_max)
    cos_t = np.sqrt(1.0 - sin_t**2)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    normal = cos_t[:, None] * u + sin_t[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return centre + radius * normal
