"""Sphere model helpers against independent constructions."""

import numpy as np
import pytest

from labkit.core.errors import DegenerateGeometryError
from labkit.sphere.model import algebraic_sphere, circumspheres, sphere_residuals


def _on_sphere(rng, n, c, r, noise=0.0):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return c + r * u + noise * rng.normal(size=(n, 3))


def test_circumspheres_pass_through_all_four_points():
    rng = np.random.default_rng(0)
    centers = rng.uniform(-5, 5, size=(200, 3))
    radii = rng.uniform(0.05, 3, size=200)
    samples = np.stack([_on_sphere(rng, 4, c, r) for c, r in zip(centers, radii)])
    c, r, valid = circumspheres(samples)
    assert valid.mean() > 0.95
    dist = np.linalg.norm(samples[valid] - c[valid, None, :], axis=2)
    np.testing.assert_allclose(dist, r[valid, None] * np.ones((1, 4)), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r[valid], radii[valid], rtol=1e-7)


def test_circumspheres_flag_coplanar_and_duplicate_samples():
    flat = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]], dtype=float)
    dup = np.array([[[0, 0, 0], [0, 0, 0], [0, 1, 0], [1, 1, 1]]], dtype=float)
    _, r, valid = circumspheres(np.concatenate([flat, dup]))
    assert not valid.any() and np.isnan(r).all()


def test_algebraic_sphere_exact_and_utm_sized():
    rng = np.random.default_rng(1)
    c = np.array([600123.4, 5400456.7, 312.3])
    pts = _on_sphere(rng, 50, c, 0.0725)
    x = algebraic_sphere(pts)
    np.testing.assert_allclose(x[:3], c, atol=1e-7)
    assert abs(x[3] - 0.0725) < 1e-8
    assert np.abs(sphere_residuals(pts, x)).max() < 1e-7


def test_algebraic_sphere_rejects_planes():
    rng = np.random.default_rng(2)
    plane = np.column_stack([rng.uniform(size=(30, 2)), np.zeros(30)])
    with pytest.raises(DegenerateGeometryError):
        algebraic_sphere(plane)
