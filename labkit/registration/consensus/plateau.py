"""The centre of the consensus hill along the directions the refinement leaves undetermined (eq. 6.9).

Used by :func:`labkit.registration.max_consensus` for the directions that neither its refinement
nor the height model determine.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import kernels as K
from .inputs import candidate_pairs

#: samples of the consensus profile, its reach and the mirrored window, in box half-widths: on real ALS
#: halves the hill along a held direction falls off over about 2 m either side (a 1 m box), wider than
#: the box, so the profile reaches beyond it and the centre is sought within 1.5 half-widths of the start
N_SAMPLES, REACH, WINDOW = 241, 3.0, 1.5
#: chunk of translations per call of the kernel (its index buffer is chunk x pairs)
CHUNK = 8


def consensus_profile(pb, t, d, s, *, use_numba=None):
    """Consensus C(t + s_i d) at the steps ``s`` along the unit direction ``d`` (eq. 6.5).

    The candidate pairs are gathered anew for the segment, so the profile may reach beyond the
    search box (the flanks of the hill tell where its centre is).

    Parameters
    ----------
    pb : Problem
        The prepared problem of the search (:func:`.inputs.prepare_problem`).
    t, d : ndarray (3,)
        Start and unit direction (m).
    s : ndarray (n,)
        Steps (m), ascending.
    use_numba : bool, optional

    Returns
    -------
    ndarray (n,)
        Consensus (weight sum of the consistent voting points) per step.
    """
    T = np.asarray(t, dtype=np.float64)[None, :] + np.asarray(s, dtype=np.float64)[:, None] * d
    _, src_of, D, nrm = candidate_pairs(pb, T.min(axis=0), T.max(axis=0), pb.radius)
    every = np.arange(len(D), dtype=np.int64)
    out = np.zeros(len(T))
    for i in range(0, len(T), CHUNK):
        _, _, lb, sure = K.children(every, src_of, D, nrm, T[i:i + CHUNK], pb.radius, pb.eps, 0.0, pb.w,
                                    use_numba=use_numba)
        out[i:i + CHUNK] = lb + sure
    return out


def hill_centre(s, counts, window: float) -> float:
    """Centre of symmetry of a consensus profile: the point about which it best matches its mirror image.

    For each candidate centre c at least ``window`` inside the ends of ``s`` (on a grid of half
    the sample spacing), the profile at c + x is compared with the profile at c - x for
    0 <= x <= ``window``; the centre is the c with the least mean squared difference. A profile
    symmetric about s0 has its best match at s0 whatever its shape (flat top, trapezoid, many
    small bumps), and unlike the vertex of a fitted quadratic the match uses the flanks as much
    as the top and does not depend on where the search starts.

    Why not the highest sample: along a direction the local planes do not determine (the ridge
    of parallel gable roofs, a flat town square), the consensus is a broad hill whose top is
    flat within the counting noise; its highest sample lands anywhere on the top (0.4-0.6 m off
    on real ALS halves, a different place for every random half). The hill itself is made of
    plateaus of every surface patch, each centred on the true shift (a patch of slope n stays
    consistent over eps / |n . d| either side), so its centre of symmetry is the better estimate.
    Two checks keep the start (0): the profile must have a maximum (a quadratic fitted to the
    whole profile opens downwards: not a straight slope or a valley; a flat top with a bump near
    the end of a window may not), and the centre must lie on the top, its consensus lower than
    the highest sample by no more than the counting noise (3 sqrt(count), or 1 % for weight sums);
    otherwise the peak is sharp and the symmetry is that of the broad flanks.

    Parameters
    ----------
    s : ndarray (n,)
        Steps (m), ascending, evenly spaced, holding 0.
    counts : ndarray (n,)
        Consensus at the steps.
    window : float
        Half-width (m) of the mirrored part of the profile.

    Returns
    -------
    float
        The centre (m); 0 when the profile has no maximum, is too short for the window, or the
        centre is off the top.

    Examples
    --------
    >>> import numpy as np
    >>> s = np.linspace(-3, 3, 241)
    >>> hill = np.minimum(1000.0, 1300.0 - 200.0 * np.abs(s - 0.4))  # flat top from -1.1 to 1.9
    >>> counts = np.rint(hill + 20.0 * np.exp(-((s + 0.8) / 0.05) ** 2))  # the highest sample: at -0.8
    >>> round(float(s[np.argmax(counts)]), 2), abs(hill_centre(s, counts, 1.5) - 0.4) < 0.1
    (-0.8, True)
    """
    s = np.asarray(s, dtype=np.float64)
    c = np.asarray(counts, dtype=np.float64)
    h = 0.5 * float(np.median(np.diff(s)))
    cand = np.arange(s[0] + window, s[-1] - window + h / 2, h)
    if cand.size == 0 or s.size < 5:
        return 0.0
    x = np.arange(h, window + h / 2, h)
    mismatch = np.mean((np.interp(cand[:, None] + x, s, c) - np.interp(cand[:, None] - x, s, c)) ** 2, axis=1)
    best = np.flatnonzero(mismatch == mismatch.min())
    centre = float(cand[best[len(best) // 2]])  # ties (a straight slope matches nowhere better): the middle one
    a, b, _ = np.polyfit(s - centre, c - c.mean(), 2)
    if a >= -1e-9 * abs(b):  # the profile has no maximum (a straight slope or a valley)
        return 0.0
    top = float(c.max())
    noise = 3.0 * np.sqrt(max(top, 1.0)) if np.allclose(c, np.rint(c)) else 0.01 * abs(top)
    return centre if float(np.interp(centre, s, c)) >= top - noise else 0.0


def centre_held(t, deg, pb, center, ext, box_var, max_std, *, fixed=None, use_numba=None):
    """Move ``t`` along the held directions to the centre of the consensus hill; the other axes stay.

    For each undetermined eigen-direction u of the refinement (the least squares keep the
    branch-and-bound maximum there), the consensus is profiled along u over 3 box half-widths
    to either side and ``t`` moves to the hill's centre (:func:`hill_centre`, the profile mirrored
    over 1.5 box half-widths), clipped to the search box. Only the axes that the held directions leave with a
    standard deviation of at least ``max_std`` move: a determined axis with a small share in u
    keeps its value exactly. The covariance is not changed: the held direction stays reported
    undetermined with the variance of the box.

    Parameters
    ----------
    t : ndarray (3,)
        The refined translation (m).
    deg : DegeneracyReport
        The refinement's degeneracy report (eigen-directions and which are constrained).
    pb : Problem
        The prepared problem of the search.
    center, ext : ndarray (3,)
        Centre and half-widths of the search box (m).
    box_var : float
        Variance (m^2) given to a held direction.
    max_std : float
        Standard deviation (m) below which an axis counts as determined.
    fixed : ndarray of bool (3,), optional
        Axes that must not move whatever their share in the held directions (filled by the
        height model).
    use_numba : bool, optional

    Returns
    -------
    t : ndarray (3,)
        The moved translation (a new array).
    moved : ndarray (3,)
        What moved, per axis (m).
    """
    t0 = np.asarray(t, dtype=np.float64)
    Vu = deg.eigenvectors[:, ~deg.constrained]
    free = np.sqrt(box_var * (Vu**2).sum(axis=1)) >= max_std  # the axes the held directions leave loose
    if fixed is not None:
        free &= ~np.asarray(fixed, dtype=bool)
    out = t0.copy()
    if Vu.shape[1] == 0 or not free.any():
        return out, np.zeros(3)
    half = float(np.max(ext))
    s = np.linspace(-REACH * half, REACH * half, N_SAMPLES)
    for j in range(Vu.shape[1]):
        d = np.where(free, Vu[:, j], 0.0)
        if np.linalg.norm(d) < 0.5:  # this direction lies mostly in determined axes
            continue
        d = d / np.linalg.norm(d)
        counts = consensus_profile(pb, out, d, s, use_numba=use_numba)
        out = np.clip(out + hill_centre(s, counts, WINDOW * half) * d, center - ext, center + ext)
    out = np.where(free, out, t0)
    return out, out - t0


def centre_result(res, pb, center, ext, max_std, fixed=None, *, use_numba=None):
    """The result of :func:`labkit.registration.max_consensus` with its held directions at the hill centre.

    :func:`centre_held` on ``res.translation`` with the box variance of the refinement
    ((2 max(ext))^2 / 12); the covariance and the degeneracy report stay as they are (the held
    directions remain undetermined) and the message says where the held value lies.

    Parameters
    ----------
    res : RegistrationResult
        The refined result (``res.degeneracy`` None: returned unchanged).
    pb : Problem
        The prepared problem of the search.
    center, ext : ndarray (3,)
        Centre and half-widths of the search box (m).
    max_std : float
        The refinement's precision limit (m).
    fixed : ndarray of bool (3,), optional
        Axes that must not move (those the height model filled).
    use_numba : bool, optional

    Returns
    -------
    RegistrationResult
    """
    deg = res.degeneracy
    if deg is None or deg.constrained.all():
        return res
    box_var = float((2 * np.max(ext)) ** 2 / 12)
    t, moved = centre_held(res.translation, deg, pb, np.asarray(center, dtype=np.float64), ext, box_var, max_std,
                           fixed=fixed, use_numba=use_numba)
    if not np.any(moved != 0):
        return res
    note = (f"; held directions: the centre of the consensus hill along them, "
            f"{np.array2string(1000 * moved, precision=0)} mm from the branch-and-bound maximum")
    return replace(res, translation=t, message=res.message + note)
