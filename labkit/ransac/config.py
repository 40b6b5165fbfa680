"""Tuning constants of the RANSAC sphere detection and the configuration of one run."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

S = 4  # minimal sample size of a sphere
FIRST_BATCH = 128
MIN_BATCH = 64
CELLS_PER_BATCH = 4_000_000  # hypotheses x points scored at once (about 32 MB)
LO_STEPS = 4
SNOOP_ROUNDS = 10
START_STEPS = 3  # Gauss-Newton steps of the orthogonal fit that give the Gauss-Helmert refit its initial values
PLANE_RATIO = 3.0  # a sphere must fit its inliers clearly better than a plane
BAND_K = 3.0  # final inliers: |d| < k sigma_hat (robust scale), whatever the search threshold t
INTERIOR_SHARE = 0.1  # points clearly inside a solid sphere, per inlier (true spheres: ~0)
SHADOW_SHARE = 0.1  # points behind the sphere seen from the station, per inlier (true spheres: ~0)
BACKFACE_SHARE = 0.2  # inliers on the side turned away from the station (true spheres: ~0)
CONTRAST = 5.0  # inliers on the shell per point in the shell just outside it, t..3t (true spheres: > 14,
# spheres fitted to a cylinder or to pieces of planes: 2-3)
TWO_PLANES_SHARE = 0.9  # inliers on one or two planes: plane pieces cut by the sphere
TWO_PLANES_POINTS = 1024  # the share is counted on an even subsample of at most this many inliers
MIN_LEVELS = 3  # a cap spans at least three scan lines (elevation levels) seen from the station
MIN_SPREAD = 0.01  # smallest variance of the inliers' normals across the cap (units of 1; a ring: ~0)
LOCAL_REACH = 1.0  # local sampling: the other three points lie within LOCAL_REACH r_max + t of the first
LOCAL_MAX_SHARE = 0.25  # 'auto' samples locally only where a neighbourhood holds less of the working set
LOCAL_MAX_PAIRS = 8_000_000  # ... and the neighbour pairs stay affordable
FINAL_ATTEMPTS = 3  # searches per working set when the final refit of the best fails its checks
VERIFY_PER_BATCH = 16  # candidates verified per batch at most (the best-scoring ones)
VERIFY_MAX = 400  # candidates verified per search at most
SHAPE_POINTS = 8192  # polishing, scale and shape checks of a candidate: an even subsample of about this many
# points of the ball around it (the counts of the checks take every point)
COARSE_POINTS = 65_536  # the coarse interior test runs first on an even subsample of about this many points
COARSE_CLEAR = 100  # ... and rejects there only with this many points deep inside and twice the limit


@dataclass(frozen=True)
class Config:
    """The checked arguments of one :func:`~labkit.ransac.ransac_sphere` call (see its parameters)."""

    threshold: float
    p: float
    r_min: float
    r_max: float
    known: bool  # r_max given by the caller (radius range or nominal radius)
    scoring: str
    minimal_solver: str
    sampling: str
    max_iterations: int
    local_optimization: bool
    min_inliers: int
    snooping: bool
    sigma: object
    alpha: float
    hold_radius: float | None  # the nominal radius to hold in the refit, or None
    station: np.ndarray | None = None  # scanner position (input frame), or None
