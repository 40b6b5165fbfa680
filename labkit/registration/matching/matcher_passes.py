"""The compiled passes of one matching step, each over a range of its rows (private).

:meth:`labkit.registration.matching.matcher._Matcher._compiled_call` runs them over consecutive ranges
on the cores (:func:`labkit.neighbours.kdtree_build.in_runs`): every pass writes disjoint rows, so the numbers do not depend on the
ranges nor on who computed which. The arithmetic is that of ``_Matcher._numpy_call`` (no fastmath).
"""

from __future__ import annotations

import numpy as np

from ...core.jit import compiled
from ...core.threads import cores  # noqa: F401  (the matcher's thread count)

#: Rows below which one thread does a pass alone (waking a worker costs more than it saves).
SERIAL_ROWS = 20_000


def range_cuts(n, threads, per_thread=4):
    """Bounds of consecutive ranges covering ``0..n``: ``per_thread`` ranges per thread (a late thread is
    balanced by the others), one range for few rows or one thread."""
    if threads <= 1 or n < SERIAL_ROWS:
        return [0, n]
    return np.linspace(0, n, per_thread * threads + 1).astype(np.int64).tolist()


@compiled
def rotate_range(P, R, t, out, a, b):  # pragma: no cover - compiled
    """out[a:b] = P[a:b] @ R.T + t, the sums in einsum's order (``_rotated``: the same numbers)."""
    for i in range(a, b):
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        for k in range(3):
            out[i, k] = ((x * R[k, 0] + z * R[k, 2]) + y * R[k, 1]) + t[k]


@compiled
def count_found(dist, a, b):  # pragma: no cover - compiled
    """How many of the queries a:b have a partner (a finite distance)."""
    n = 0
    for r in range(a, b):
        if np.isfinite(dist[r]):
            n += 1
    return n


@compiled
def found_range(dist, j, live, rep, slot, rule, tidx, code, found, pos, slots, rows, jf, a, b, n):  # pragma: no cover
    """The queries a:b (query order) with a partner, written from position ``n`` on: their positions
    ``found``, the leaf positions ``pos`` of their target points (``rep``: the tree's representative) and
    these points' places ``slots`` in the geometry cache (``slot``; -1: not cached yet), their rows ``rows``
    (``live[found]``) and target points ``jf`` (``j[found]``), and tidx at their rows; the others get the rule
    ``code`` (distance). Returns how many of their target points the geometry cache does not hold yet."""
    uncached = 0
    for r in range(a, b):
        i = live[r]
        if np.isfinite(dist[r]):
            p = rep[j[r]]
            s = slot[p]
            found[n], pos[n], slots[n], rows[n], jf[n] = r, p, s, i, j[r]
            tidx[i] = j[r]
            if s < 0:
                uncached += 1
            n += 1
        else:
            rule[i] = code
    return uncached


@compiled(inline="always")
def _gate(t0, t1, t2, x, y, z, R, target, source):  # pragma: no cover - compiled
    """The normal gates of one pair from scalars: (missing, cos). ``missing``: its target normal (t0, t1, t2; with
    ``target``) or its source normal (x, y, z; with ``source``) is NaN; ``cos`` = |R n_s . n_t| (with ``source``).
    ``R`` is a tuple of its rows: a helper inlined into a loop over pairs takes no arrays, since numba counted
    the references of every array argument at every pair (a pass over 248,000 pairs 12 -> 1.6 ms)."""
    missing = (target and np.isnan(t0)) or (source and np.isnan(x))
    a0 = (x * R[0][0] + z * R[0][2]) + y * R[0][1]
    a1 = (x * R[1][0] + z * R[1][2]) + y * R[1][1]
    a2 = (x * R[2][0] + z * R[2][2]) + y * R[2][1]
    return missing, abs((a0 * t0 + a2 * t2) + a1 * t1)


@compiled(inline="always")
def _rows_of(R):  # pragma: no cover - compiled
    """The rotation's rows as a tuple of tuples (for :func:`_gate`)."""
    return (R[0, 0], R[0, 1], R[0, 2]), (R[1, 0], R[1, 1], R[1, 2]), (R[2, 0], R[2, 1], R[2, 2])


@compiled
def gather_range(data, q, found, rows, pos, slots, slot, normals_buf, noise_buf, d, nt, noise, d2, rule, normals, R,
                 cosang, target, source, code, a, b):  # pragma: no cover - compiled
    """For the pairs a:b: d[i] = q_j - p_i, its square length d2 (the duplicate rule's distance, before a
    quadric's foot replaces d), nt[i] and noise[i] from the geometry cache (at ``slots``, or where ``slot``
    has placed a point cached since), at the rows i = ``rows``; with
    ``target`` / ``source`` also the gates of :func:`normal_gates_range` on them (``normals``: the source
    normals in query order, read at ``found``)."""
    rows_R = _rows_of(R)
    for n in range(a, b):
        i, r, p, s = rows[n], found[n], pos[n], slots[n]
        if s < 0:
            s = slot[p]
        x, y, z = data[p, 0] - q[r, 0], data[p, 1] - q[r, 1], data[p, 2] - q[r, 2]
        d[i, 0], d[i, 1], d[i, 2] = x, y, z
        d2[n] = (x * x + z * z) + y * y
        t0, t1, t2 = normals_buf[s, 0], normals_buf[s, 1], normals_buf[s, 2]
        nt[i, 0], nt[i, 1], nt[i, 2] = t0, t1, t2
        noise[i] = noise_buf[s]
        if target or source:
            sx, sy, sz = (normals[r, 0], normals[r, 1], normals[r, 2]) if source else (0.0, 0.0, 0.0)
            missing, c = _gate(t0, t1, t2, sx, sy, sz, rows_R, target, source)
            if missing and rule[i] == 0:
                rule[i] = code
            if source:
                cosang[n] = c


@compiled
def normal_gates_range(rows, found, nt, rule, normals, R, cosang, target, source, code, a, b):  # pragma: no cover
    """'degenerate' where the target normal (``target``) or the source normal (``source``; in query order, read
    at ``found``) of the pairs a:b is missing and no rule came first; with ``source`` also |R n_s . n_t| per
    pair (the same sums)."""
    rows_R = _rows_of(R)
    for n in range(a, b):
        i, r = rows[n], found[n]
        x, y, z = (normals[r, 0], normals[r, 1], normals[r, 2]) if source else (0.0, 0.0, 0.0)
        missing, c = _gate(nt[i, 0], nt[i, 1], nt[i, 2], x, y, z, rows_R, target, source)
        if missing and rule[i] == 0:
            rule[i] = code
        if source:
            cosang[n] = c


@compiled
def angles_range(rows, ang, has_angle, max_angle, gate, rule, angle, code, d2, a, b):  # pragma: no cover - compiled
    """angle[rows] = ang (NaN without source normals) and its gate (``code``) for the pairs a:b, the last gate
    before the duplicate rule: ``d2`` of the pairs it rejected or a gate before it set to -1 (the duplicate
    rule skips them without reading their rule)."""
    for n in range(a, b):
        i = rows[n]
        if has_angle:
            angle[i] = ang[n]
            if gate and rule[i] == 0 and ang[n] > max_angle:
                rule[i] = code
        else:
            angle[i] = np.nan
        if rule[i] != 0:
            d2[n] = -1.0


@compiled
def duplicates_range(rows, pos, d2, rule, best, best_d2, lo, hi, code):  # pragma: no cover - compiled
    """One source point per target point, for the target points at the leaf positions lo:hi: of the pairs
    not rejected yet (``d2`` not -1, :func:`angles_range`), the one with the smallest ``d2`` keeps it, equal
    distances the lower row; the others
    get the rule ``code`` (duplicate). Every pair is read, those of other target points skipped: each row
    has one target point, so a split by target points writes disjoint rows (the result does not depend on
    the order of the pairs). ``best`` / ``best_d2``: scratch of the tree's size, only lo:hi used."""
    for t in range(lo, hi):
        best[t] = -1
    for n in range(rows.shape[0]):
        t = pos[n]
        if t < lo or t >= hi or d2[n] < 0:
            continue
        i = rows[n]
        b = best[t]
        if b < 0:
            best[t], best_d2[t] = i, d2[n]
        elif d2[n] < best_d2[t] or (d2[n] == best_d2[t] and i < b):
            rule[b] = code
            best[t], best_d2[t] = i, d2[n]
        else:
            rule[i] = code


@compiled
def weights_planes_range(P, R, t, origin, rule, sigma_s, sigma_t, from_noise, min_var, tidx, nt, d, noise, angle,
                         weight, plane, xyz, a, b):  # pragma: no cover - compiled
    """Per row a:b: NaN in d, nt, noise and angle where it has no partner (``tidx`` -1), the weight
    1 / (sigma_s^2 + sigma_t^2) (0 where a rule rejected it; ``from_noise``: sigma_t = max(noise, MIN_SIGMA)
    from the noise given as ``sigma_t``), the plane distance nt . d and the moved source point in the
    caller's frame (R p + t + origin), as _numpy_call computes them."""
    for i in range(a, b):
        if tidx[i] < 0:
            for k in range(3):
                d[i, k] = np.nan
                nt[i, k] = np.nan
            noise[i] = np.nan
            angle[i] = np.nan
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        for k in range(3):
            xyz[i, k] = (((x * R[k, 0] + z * R[k, 2]) + y * R[k, 1]) + t[k]) + origin[k]
        plane[i] = (nt[i, 0] * d[i, 0] + nt[i, 2] * d[i, 2]) + nt[i, 1] * d[i, 1]
        if rule[i] != 0:
            weight[i] = 0.0
            continue
        st = sigma_t[i]
        if from_noise:
            v = st * st
            if v < min_var:
                v = min_var
            st = np.sqrt(v)
        ss = sigma_s[i]
        weight[i] = 1.0 / (ss * ss + st * st)
