"""Is a candidate sphere a sphere cap the scanner saw? The checks of ransac_sphere's Notes."""

from __future__ import annotations

import threading

import numpy as np

from ._ball import (
    ball_counts, ball_counts_t, ball_indices, ball_tally, best_plane, gather, near_shell, residuals, shell_points,
    shell_tally,
)
from .config import (
    BACKFACE_SHARE, BAND_K, COARSE_CLEAR, COARSE_POINTS, CONTRAST, INTERIOR_SHARE, MIN_LEVELS, MIN_SPREAD, PLANE_RATIO,
    SHADOW_SHARE, SHAPE_POINTS, TWO_PLANES_POINTS, TWO_PLANES_SHARE, VERIFY_MAX, S,
)
from .hypotheses import orthogonal_fit, squared_center_distances
from .refit import truncated_mad_scale


class Verifier:
    """Is a hypothesis a sphere cap seen by the scanner? Checks on the full cloud (reduced frame).

    ``accepts(x)`` is asked for every hypothesis that would become the best:
    it polishes x on its inliers (rounds of inliers -> orthogonal fit, on an
    even subsample of at most about ``SHAPE_POINTS`` points of the ball around
    it) and runs :meth:`reasons` (counts on every point of the full cloud near
    the shell, scale and shape statistics on that subsample). Rejected spheres are remembered,
    and hypotheses close to one of them are rejected without a new check.
    """

    def __init__(self, X, station, cfg, by_axis=None):
        self.X, self.station, self.cfg = np.ascontiguousarray(X, dtype=np.float64), station, cfg
        step = len(self.X) // COARSE_POINTS
        # the coarse test runs on an even subsample (or, for a small cloud, on every point), stored by axis (3, m);
        # ``by_axis``: X stored by axis already (X.T, C-contiguous)
        if step < 2 and by_axis is not None:
            self._sub = by_axis
        else:
            self._sub = np.ascontiguousarray(self.X[:: max(step, 1)].T)
        self._scale = len(self.X) / self._sub.shape[1] if step >= 2 else 1.0
        self._sub_all = step < 2
        self.n_rejected, self.n_checked = 0, 0
        self.best_rejection = ""
        self._best_rejected_score = -np.inf
        self._rejected = []  # polished spheres that failed
        self._R = None  # the same as an array (cached)
        self._ball = None  # (centre, radius, indices, points by axis) of the last ball read from the cloud
        self._sample = None  # (that ball, an even subsample of its points by axis) for the polishing

    def _by_axis(self, idx):
        """The points X[idx] stored by axis (3, k), for the compiled sums."""
        return gather(self.X, idx, by_axis=True)

    def ball(self, c, R):
        """Indices of the points within distance R of c (one pass over the cloud, no tree)."""
        return ball_indices(self.X, c, R)

    def start(self, cfg):
        self.cfg = cfg
        self.n_checked = 0  # the budget is per search (working set)

    @property
    def exhausted(self):
        return self.n_checked >= VERIFY_MAX

    def accepts(self, x, score=0.0):
        cfg = self.cfg
        if self.near_rejected(x[None, :])[0] or self.exhausted:
            return False
        self.n_checked += 1
        coarse = self._coarse_reason(x, cfg.threshold)
        if coarse:  # clearly not a sphere (counted in C, no polishing): most large spheres end here
            self._remember(coarse, x, score)
            return False
        x_pol = self._polish(x, cfg.threshold)
        reason = "its inliers do not determine a sphere" if x_pol is None else self.reasons(x_pol, cfg.threshold)
        if reason:
            self._remember(reason, x if x_pol is None else x_pol, score)
        return not reason

    def _remember(self, reason, x, score=0.0):
        if not self.best_rejection or score > self._best_rejected_score:
            self.best_rejection, self._best_rejected_score = reason, score
        self.n_rejected += 1
        self._rejected.append(np.asarray(x, dtype=np.float64))

    def _coarse_reason(self, x, t):
        """A quick interior test on the raw hypothesis: many points deep inside (beyond 5 t)."""
        c, r = x[:3], float(x[3])
        if r <= 5.0 * t:
            return ""
        radii = [r + t, r - t, r - 5.0 * t]
        about = ""
        if self._sub_all:  # a small cloud: every point counted at once
            outer, inner, deep = ball_counts_t(self._sub, c, radii)
        else:  # first on an even subsample: a clear verdict needs no pass over all points
            outer, inner, deep = ball_counts_t(self._sub, c, radii) * self._scale
            if deep >= COARSE_CLEAR * self._scale and deep > 2.0 * max(5.0 * INTERIOR_SHARE * (outer - inner), 20):
                about = "about "
            else:
                outer, inner, deep = ball_counts(self.X, c, radii)
        shell = int(outer - inner)
        if deep > max(5.0 * INTERIOR_SHARE * shell, 20):
            return (f"{about}{int(deep)} points lie deep inside it (for {about}{shell} on its shell): a solid sphere "
                    "hides its interior, so this is a cut through other surfaces or a volume of points, not a sphere")
        return ""

    def reject(self, *spheres):
        """Remember spheres that failed (e.g. in the final refit): hypotheses near them are not tried again."""
        self._rejected += [np.asarray(x, dtype=np.float64) for x in spheres if x is not None]
        self.n_rejected += 1

    def final_check(self, x, band):
        """Reasons to reject the final adjusted sphere (with the final band as shell half-width)."""
        return self.reasons(np.asarray(x, dtype=np.float64), max(band, self.cfg.threshold))

    def near_rejected(self, X):
        """For hypotheses X (B, 4): close to a sphere that already failed (centre and radius within
        max(t, 10 % of r))?"""
        if not self._rejected:
            return np.zeros(len(X), dtype=bool)
        if self._R is None or len(self._R) != len(self._rejected):
            self._R = np.array(self._rejected)
        R = self._R
        tol = np.maximum(self.cfg.threshold, 0.1 * R[:, 3])[None, :]
        dc2 = squared_center_distances(X[:, :3], np.einsum("ij,ij->i", X[:, :3], X[:, :3]), R[:, :3])
        return ((dc2 < tol * tol) & (np.abs(X[:, None, 3] - R[None, :, 3]) < tol)).any(axis=1)

    def _kept(self, c, r, reach):
        """The kept ball (centre, radius, indices, points by axis), read anew from the cloud unless it
        holds every point within r + reach of c.

        The polishing rounds and checks of one candidate ask for nearly the same ball
        again and again: the points of a somewhat larger ball are kept, and a ball inside
        it is answered from them (the same points in the same order).
        """
        if self._ball is not None:
            c0, R0 = self._ball[0], self._ball[1]
            if _norm(c - c0) + r + reach <= R0 * (1.0 - 1e-9):  # inside the kept ball
                return self._ball
        R0 = r + max(reach, 2.0 * BAND_K * self.cfg.threshold * 3.0) + max(2.0 * self.cfg.threshold, 0.05 * r)
        # (a small cloud is also stored by axis for the coarse test: contiguous columns read faster)
        idx0 = ball_indices(self._sub, c, R0, by_axis=True) if self._sub_all else ball_indices(self.X, c, R0)
        self._ball = (c.copy(), R0, idx0, self._by_axis(idx0))
        self._sample = None
        return self._ball

    def _local(self, x, reach):
        """Indices and residuals d (eq. 25) of the points within r + reach of the centre (from the kept ball)."""
        c, r = np.asarray(x[:3], dtype=np.float64), float(x[3])
        _, _, idx0, B0 = self._kept(c, r, reach)
        i, d = shell_points(B0, c, r, reach, by_axis=True)
        return np.take(idx0, i), d

    def _ball_sample(self, x, reach):
        """An even subsample of at most about ``SHAPE_POINTS`` points of the kept ball that holds every
        point within r + reach of the centre, by axis (3, k); every point of a small ball."""
        c, r = np.asarray(x[:3], dtype=np.float64), float(x[3])
        ball = self._kept(c, r, reach)
        if self._sample is None or self._sample[0] is not ball:
            B0 = ball[3]
            self._sample = (ball, np.ascontiguousarray(B0[:, :: -(-B0.shape[1] // SHAPE_POINTS)]))
        return self._sample[1]

    def near_shell(self, x, reach):
        """:func:`~labkit.ransac._ball.near_shell` of the cloud, from the kept ball when it holds the shell."""
        c, r = np.asarray(x[:3], dtype=np.float64), float(x[3])
        if self._ball is not None:
            c0, R0, idx0, B0 = self._ball
            if _norm(c - c0) + r + reach <= R0 * (1.0 - 1e-9):
                i, d, T = near_shell(B0, c, r, reach, by_axis=True)
                return np.take(idx0, i), d, T
        return near_shell(self.X, c, r, reach)

    def _polish(self, x, t):
        """Inliers -> orthogonal fit, three rounds; the band widens to k sigma_hat when t is below the noise.

        The polished sphere only decides the checks (the detection's sphere comes from the final
        refit), so fit and scale use an even subsample of at most about ``SHAPE_POINTS`` points of
        the kept ball around the candidate: every pass of a round runs over that many points only.
        """
        band = t
        T = self._ball_sample(x, 3.0 * t)  # holds every band of the rounds (band <= 3 t)
        ad = np.abs(residuals(T, x, by_axis=True))  # |d| (eq. 25)
        for round_ in range(3):
            inl = ad < band
            if np.count_nonzero(inl) <= S:
                return None
            x_new = orthogonal_fit(T, x, steps=2, mask=inl, by_axis=True)  # on the inliers, without gathering them
            if x_new is None:
                return None
            x = x_new
            if not 0.5 * self.cfg.r_min <= x[3] <= 2.0 * self.cfg.r_max:
                return x  # far outside the radius range: more rounds will not bring it back (reasons() rejects)
            if round_ == 2:
                break  # (the residuals and band below only serve a next round)
            T = self._ball_sample(x, 3.0 * t)  # (the same points unless the sphere left the kept ball)
            ad = np.abs(residuals(T, x, by_axis=True))
            ad_in = ad[ad < band]
            if len(ad_in) > S:
                band = max(t, min(BAND_K * truncated_mad_scale(ad_in, band), 3.0 * t))
        return x

    def reasons(self, x, t):
        """'' for a plausible sphere cap, else why not (checks of ransac_sphere's Notes)."""
        cfg = self.cfg
        c, r = x[:3], float(x[3])
        if not cfg.r_min <= r <= cfg.r_max:
            return f"the adjusted radius {r:.5g} m lies outside [{cfg.r_min:.5g}, {cfg.r_max:.5g}] m"
        # counts on the kept ball (every point within r + reach), shape statistics on its even subsample
        reach = 3.0 * max(t, 2.0 * BAND_K * t)
        c = np.asarray(c, dtype=np.float64)
        B = self._kept(c, r, reach)[3]
        T = self._ball_sample(x, reach)
        d = residuals(T, x, by_axis=True, simd=False)  # (a subset of the ball: never more points |d| < t)
        abs_d = np.abs(d)
        on = np.flatnonzero(abs_d < t)
        n_in = len(on)
        if T is not B and n_in < max(cfg.min_inliers, SHAPE_POINTS // 64):  # the subsample alone cannot tell
            n_in = ball_tally(B, c, r, reach, t)[0]
            T, d = B, residuals(B, x, by_axis=True, simd=False)
            abs_d = np.abs(d)
            on = np.flatnonzero(abs_d < t)
        if n_in < cfg.min_inliers:
            return f"only {n_in} points on its shell |d| < {t:.3g} m in the full cloud (< min_inliers = {cfg.min_inliers})"
        # robust, and consistent for the cut at t (a scale for the checks, from the subsample's shell)
        sigma_hat = truncated_mad_scale(abs_d[_even(on, SHAPE_POINTS)], t)
        margin = max(t, 3.5 * sigma_hat)
        # the shell: at least the noise band k sigma_hat (a t below the noise must not thin it out)
        t_cut, t = t, max(t, min(BAND_K * sigma_hat, 2.0 * t))
        n_in, inside, outside = ball_tally(B, c, r, reach, t, margin)  # on the shell, inside (d < -margin), just outside
        if inside > INTERIOR_SHARE * n_in:
            return (f"{inside} points lie inside it (for {n_in} on its shell): a solid sphere hides its interior, "
                    "so this is a cut through other surfaces or a volume of points, not a sphere")
        if n_in < CONTRAST * outside:
            return (f"too many points just outside the shell ({outside}, for {n_in} on it): no spherical surface "
                    "stands out, the points only pass through the shell (a cylinder, plane pieces, clutter)")
        # the shape statistics (shares, rms, spreads) on an even subsample of the shell (``on`` when t is unchanged)
        sel = _even(on if t == t_cut else np.flatnonzero(abs_d < t), SHAPE_POINTS)
        Pt = np.take(T, sel, axis=1)  # by axis (3, k), C-contiguous: each step below loops over one coordinate
        q = Pt - (Pt.sum(axis=1) / Pt.shape[1])[:, None]
        rms_plane = np.sqrt(max(np.linalg.eigvalsh(q @ q.T / Pt.shape[1])[0], 0.0))
        d_sel = d[sel]
        rms_sphere = np.sqrt(np.mean(np.multiply(d_sel, d_sel, out=d_sel)))
        if rms_plane < PLANE_RATIO * rms_sphere:
            return (f"the inliers are nearly flat (plane rms {rms_plane * 1e3:.3g} mm vs sphere rms "
                    f"{rms_sphere * 1e3:.3g} mm): a plane patch, not a sphere")
        P = Pt.T  # (k, 3)
        planes = _two_plane_share(P, t)
        if planes >= TWO_PLANES_SHARE:
            return (f"{planes:.0%} of its inliers lie on one or two planes: pieces of planes (a floor, a wall, "
                    "an edge) cut by the sphere, not a sphere")
        Nt = Pt - c[:, None]  # the normals from the model, not from neighbours
        length = Nt[0] * Nt[0]
        length += Nt[1] * Nt[1]
        length += Nt[2] * Nt[2]
        Nt /= np.sqrt(length, out=length)
        spread = _cap_spread(Nt, None if self.station is None else self.station - c)
        if spread < MIN_SPREAD:
            return (f"the inliers cover no cap (their normals spread over {np.degrees(np.sqrt(max(spread, 0))):.1f} deg "
                    "across): a ring or a strip, e.g. one scan line on a round object")
        if self.station is None:
            return ""
        return self._visibility(c, r, margin, Nt.T, P, n_in)

    def _visibility(self, c, r, margin, normals, P, n_in):
        s = self.station
        if np.linalg.norm(s - c) <= r:
            return "the station lies inside it: a scanner cannot see a solid sphere from inside"
        view = s - P
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        back = float(np.mean(np.einsum("ij,ij->i", normals, view) < -0.1))
        if back > BACKFACE_SHARE:
            return (f"{back:.0%} of its inliers lie on the side turned away from the station: "
                    "they cannot be a sphere the scanner saw")
        lines = _elevation_levels(P - s, 2.0 * np.arcsin(min(r / np.linalg.norm(s - c), 1.0)))
        if lines < MIN_LEVELS:
            return (f"its inliers lie on only {lines} scan line(s) (elevation levels seen from the station): "
                    "two rings on a round object such as a cylinder fit such a sphere as well")
        shadow = _points_behind(self.X, s, c, r - margin, margin)
        if shadow > SHADOW_SHARE * n_in:
            return (f"{shadow} points lie behind it seen from the station (for {n_in} on its shell): "
                    "the scanner looked through it, free space where a solid sphere would be")
        return ""


def _even(sel, m):
    """An even subsample of at most about m of the indices sel (all of them when there are fewer)."""
    return sel if len(sel) <= m else sel[:: -(-len(sel) // m)]


def _cap_spread(Nt, axis):
    """Smallest variance of the unit normals Nt (3, k), by axis, across the viewing axis (1/4 for a full
    hemisphere).

    The normals are projected onto the plane normal to ``axis`` (the direction
    to the station, or their mean direction when no station is known); a cap
    spreads in both directions, a ring or strip of one scan line in one only.
    """
    k = Nt.shape[1]
    if axis is None:
        axis = Nt.sum(axis=1) / k
        if _norm(axis) < 0.2:
            return 1.0  # normals all round the sphere (several stations): no single cap to check
    a = axis / _norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = _cross(a, helper)
    e1 /= _norm(e1)
    e2 = _cross(a, e1)
    if k <= 2:
        return 0.0
    uv = np.vstack([e1, e2]) @ Nt  # (2, k)
    uv -= (uv.sum(axis=1) / k)[:, None]
    return float(np.linalg.eigvalsh(uv @ uv.T / (k - 1))[0])  # (the sample covariance, as np.cov)


def _cross(a, b):
    """np.cross of two 3-vectors (the same products and differences, without its axis handling)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _norm(a):
    """np.linalg.norm of a 3-vector (the same sum of squares, as its dot product)."""
    return float(np.sqrt(a.dot(a)))


_PLANES = threading.local()  # per thread: a generator reset to the state of default_rng(0) for each share
_PLANE_SEED = np.random.default_rng(0).bit_generator.state


def _plane_generator():
    """This thread's generator, reset to the stream of default_rng(0) (cheaper than building one)."""
    gen = getattr(_PLANES, "gen", None)
    if gen is None:
        gen = _PLANES.gen = np.random.default_rng(0)
    gen.bit_generator.state = _PLANE_SEED
    return gen


def _two_plane_share(P, t, trials=256):
    """Largest share of the points P within t of one plane plus a second plane (greedy, sampled planes).

    A true cap puts at most one or two scan lines on any plane; a sphere
    through a floor and a wall (an edge) has nearly all its inliers on two.
    Planes through random point triples of a fixed-seed generator (deterministic).
    """
    if len(P) > TWO_PLANES_POINTS:  # a share: an even subsample of the cap estimates it to about 1 %
        P = P[:: -(-len(P) // TWO_PLANES_POINTS)]
    n = len(P)
    if n < 6:
        return 1.0
    P = np.ascontiguousarray(P)  # (the points of the first plane search, as P[all] would copy them)
    gen = _plane_generator()
    left = np.ones(n, dtype=bool)
    held = 0
    for round_ in range(2):
        Q = P if round_ == 0 else P[left]
        if len(Q) < 3:
            held += len(Q)
            break
        plane = best_plane(Q, gen.integers(0, len(Q), size=(trials, 3)), t)  # the most points within t
        if plane is None:
            break
        on = np.abs(Q @ plane[0] - plane[1]) < t
        held += int(np.count_nonzero(on))
        if round_ == 0:
            left[on] = False
    return held / n


def _elevation_levels(V, diameter):
    """Distinct elevation levels (z up) of the directions V from the station, in bins of 1/8 of the
    sphere's angular diameter: the scan lines of a multi-beam scanner, many for a TLS."""
    el = np.arcsin(np.clip(V[:, 2] / np.linalg.norm(V, axis=1), -1.0, 1.0))
    width = max(diameter / 8.0, 1e-9)
    return int(np.unique(np.floor(el / width)).size)


def _points_behind(X, s, c, r_inner, margin):
    """Points whose ray from the station s crosses the ball (c, r_inner) and ends beyond its entry."""
    if r_inner <= 0:
        return 0
    sc = c - s
    dist_c = np.linalg.norm(sc)
    # only rays within the cone that the ball subtends can cross it
    V = X - s
    rng_ = np.sqrt(np.einsum("ij,ij->i", V, V))
    cos_cone = np.sqrt(max(1.0 - (r_inner / dist_c) ** 2, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        tc = (V @ sc) / rng_  # distance along the ray to the foot of the centre
        in_cone = tc > cos_cone * dist_c  # cos(angle between ray and centre) > cos(half cone)
    tc, rng_ = tc[in_cone], rng_[in_cone]
    h2 = r_inner**2 - (dist_c**2 - tc**2)
    entry = tc - np.sqrt(np.maximum(h2, 0.0))
    return int(np.count_nonzero((h2 > 0) & (rng_ > entry + margin)))
