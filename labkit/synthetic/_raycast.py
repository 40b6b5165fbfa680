"""First hits of rays from one origin on simple solids: floor, ceiling, walls, spheres, vertical cylinders, boxes.

Every function takes the ray origin ``o`` (3,) and unit directions ``D`` (n, 3)
in the world frame and returns the range t (n,) to the first hit, ``inf``
where the ray misses.
"""

from __future__ import annotations

import numpy as np


def ground_hits(o, D):
    """Range to the ground plane z = 0 (seen from above)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / D[:, 2]
    return np.where((D[:, 2] < 0) & (t > 0), t, np.inf)


def ceiling_hits(o, D, height):
    """Range to the ceiling z = ``height`` (seen from below)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (height - o[2]) / D[:, 2]
    return np.where((D[:, 2] > 0) & (t > 0), t, np.inf)


def wall_hits(o, D, half_x, half_y, height):
    """Range to the inside of four walls x = +-half_x, y = +-half_y, from z = 0 up to ``height``."""
    lim = np.array([half_x, half_y])
    with np.errstate(divide="ignore", invalid="ignore"):
        T = np.where(D[:, :2] > 0, (lim - o[:2]) / D[:, :2], np.where(D[:, :2] < 0, (-lim - o[:2]) / D[:, :2], np.inf))
    t = T.min(axis=1)
    z = o[2] + t * D[:, 2]
    return np.where(np.isfinite(t) & (z >= 0) & (z <= height), t, np.inf)


def sphere_hits(o, D, c, r):
    """Range to the near side of the sphere (c, r)."""
    oc = o - c
    b = D @ oc
    disc = b * b - (oc @ oc - r * r)
    out = np.full(len(D), np.inf)
    hit = np.flatnonzero(disc > 0)  # (few rays: the rest skip the square root)
    t = -b[hit] - np.sqrt(disc[hit])
    out[hit[t > 0]] = t[t > 0]
    return out


def cylinder_hits(o, D, xy, r, z0, z1):
    """Range to the side of the vertical cylinder of radius r about (x, y) between z0 and z1."""
    oc = o[:2] - xy
    b = D[:, :2] @ oc
    out = np.full(len(D), np.inf)
    hit = np.flatnonzero(b < 0)  # (only rays heading towards the axis can hit the side from outside)
    Dh = D[hit]
    a = Dh[:, 0] ** 2 + Dh[:, 1] ** 2
    disc = b[hit] ** 2 - a * (oc @ oc - r * r)
    keep = disc > 0
    hit, Dh, a, disc = hit[keep], Dh[keep], a[keep], disc[keep]
    t = (-b[hit] - np.sqrt(disc)) / a
    z = o[2] + t * Dh[:, 2]
    ok = (t > 0) & (z >= z0) & (z <= z1)
    out[hit[ok]] = t[ok]
    return out


def box_hits(o, D, centre, size, yaw):
    """Range to a box of ``size`` (3,) centred at ``centre``, turned by ``yaw`` (rad) about z (slab method)."""
    c, s = np.cos(yaw), np.sin(yaw)
    Rt = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box
    ob = Rt @ (o - centre)
    Db = D @ Rt.T
    half = 0.5 * np.asarray(size, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - ob) / Db, (half - ob) / Db
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    near = np.fmax(np.fmax(lo[:, 0], lo[:, 1]), lo[:, 2])  # (fmax/fmin skip the NaN of 0 / 0)
    far = np.fmin(np.fmin(hi[:, 0], hi[:, 1]), hi[:, 2])
    return np.where((near <= far) & (near > 0), near, np.inf)


def first_hits(o, D, solids):
    """Range and index of the first of ``solids`` (callables (o, D) -> t) each ray hits; -1 where none."""
    t = np.full(len(D), np.inf)
    which = np.full(len(D), -1, dtype=np.int64)
    for k, solid in enumerate(solids):
        t_k = solid(o, D)
        nearer = t_k < t
        t[nearer], which[nearer] = t_k[nearer], k
    return t, which
