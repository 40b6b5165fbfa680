"""One weighted least-squares step of ICP on the current correspondences (eqs. 5.7-5.12).

The design rows of the point-to-plane (eq. 5.2, 5.4) and point-to-point (eq. 5.1, 5.5) metric, the
robust weights (:mod:`.weights`), the degeneracy report on the information that survives
re-matching (:mod:`.information`) and the solution with held parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ...core.errors import EmptyRegionError, LabkitError
from ...transforms import skew
from .covariance import block_covariance, held_rotation_covariance
from .information import normal_information, sandwich_precision, tilt_information
from .weights import robust_weights
from ..consistency import normal_equations
from ..degeneracy import degeneracy_report
from ..matching.match import Correspondences

NAMES = {"translation": ("tx", "ty", "tz"), "rigid": ("rx", "ry", "rz", "tx", "ty", "tz")}
#: A parameter with this squared share in the undetermined eigen-directions is held fixed (and reported).
HELD_SHARE = 0.05


@dataclass(frozen=True, eq=False)
class IcpSettings:
    """The checked options of one ICP run that its steps read (private; built once by :func:`icp`).

    The names are those of the keywords of :func:`labkit.registration.icp`; besides them the shared local
    ``origin``, the source radius ``L`` that scales rotations to metres, the prior std of a held rotation
    (radians) and of a held shift (m), the tilt covariance of the target normals (``tilt``, eq. 5.12b), and
    ``cascade``: whether parameters left imprecise by held shifts are held too (the robust stage only).
    """

    origin: np.ndarray
    dof: str
    metric: str
    robust: str | None
    reject_sigma: float | None
    L: float
    rel_threshold: float
    min_correspondences: int
    covariance: str
    block_size: float
    held_rotation_std: float
    consistency_alpha: float | None
    max_std: float
    held_shift_std: float
    tilt: object
    sample: object
    cascade: bool = True


@dataclass(frozen=True, eq=False)
class Adjustment:
    """One weighted least-squares step (private)."""

    dx: np.ndarray  # update of the parameters (unscaled)
    N: np.ndarray  # normal matrix in scaled parameters
    Qxx: np.ndarray  # cofactor matrix of the unscaled parameters (inf where undetermined)
    block_cov: object  # () -> cluster-robust covariance (unscaled), covariance="block"; only the last one is used
    held_cov: np.ndarray  # effect of the held rotations' prior on the other parameters (unscaled)
    sigma0: float
    rms: float
    redundancy: int
    degeneracy: object
    corr: Correspondences
    scale: float
    n_deleted: int


def adjust(corr, R, t, opts):
    """One weighted LS step on the current correspondences (eqs. 5.7-5.12)."""
    ok_rows = np.flatnonzero(corr.rule == 0)  # the accepted rows, found once
    check_count(corr, opts, len(ok_rows))
    A, l, w = design(corr, R, t, opts, rows=ok_rows)
    keep, factor, scale, u, centred = robust_weights(l, w, opts.reject_sigma, opts.robust)
    all_kept = bool(keep.all())
    pw = w * factor  # 0 where deleted (factor is)
    corr = corr.with_robust_weights(ok_rows, pw, None if all_kept else ok_rows[~keep])
    check_count(corr, opts, len(ok_rows) if all_kept else int(np.count_nonzero(keep)))
    A_all, l_all = A, l
    if all_kept:  # nothing deleted: the rows as they are (no copies)
        P, kept_rows = pw, ok_rows
    else:
        at = np.flatnonzero(keep)  # the kept rows gathered by index (several times faster than by the mask)
        P, A, l, kept_rows = np.take(pw, at), np.take(A, at, axis=0), np.take(l, at, axis=0), np.take(ok_rows, at)
    N, nvec = normal_equations(A, P, l)  # N = A^T P A, n = A^T P l  (eq. 5.7)
    names = NAMES[opts.dof]
    N_eps = tilt_information(corr, kept_rows, P, opts, R)
    normals = lambda: corr.target_normal[kept_rows]  # noqa: E731 - read only by point-to-point
    N_sig = normal_information(A, P, normals, N, opts) - N_eps  # (eq. 5.12b)
    deg = degeneracy_report(
        sandwich_precision(N, N_sig), names, opts.rel_threshold, slice(len(names) - 3, None), share_threshold=HELD_SHARE,
        hold_first=names[:-3], sigma0=scale, max_std=opts.max_std,
    )  # rotations are given up before translations; precision limit (eq. 5.12a)  # fmt: skip
    dx_s, Q_s, step_s = solve(N, nvec, deg, N_sig)
    shift_prior_only = replace(opts, held_rotation_std=0.0)
    for _ in range(len(names) if opts.cascade else 0):  # once settled: a parameter left imprecise by
        # held shifts (prior: max_distance) is held too
        if deg.parameter_determined[-3:].all():  # no shift held: nothing spreads its prior
            break
        held_s = held_rotation_covariance(N_sig, deg, shift_prior_only)
        with np.errstate(invalid="ignore"):
            std_s = np.sqrt(np.clip(scale**2 * np.diag(Q_s) + np.diag(held_s), 0, None))
        worse = deg.parameter_determined & (std_s > opts.max_std)
        if not worse.any():
            break
        keep_det = deg.parameter_determined & ~worse
        deg = replace(deg, parameter_determined=keep_det, axis_determined=keep_det[-3:].copy())
        dx_s, Q_s, step_s = solve(N, nvec, deg, N_sig)
    v = np.einsum("mru,u->mr", A, dx_s) - l  # residuals after the step
    vPv = float(np.einsum("mr,m,mr->", v, P, v))
    r = len(P) * A.shape[1] - int(deg.constrained.sum())  # redundancy
    sigma0 = np.sqrt(vPv / r) if r > 0 else np.nan  # (eq. 5.10)
    rms = float(np.sqrt(np.einsum("mr,m,mr->", l, P, l) / max(P.sum(), 1e-300)))
    S = np.ones(len(names))
    S[: len(names) - 3] = opts.L  # rotation columns were divided by L
    dx = step_s / S  # the update: Newton on the fixed point, whose slope is N_sig (eq. 5.12b)
    Qxx = Q_s / np.outer(S, S)
    held_cov = held_rotation_covariance(N_sig, deg, opts) / np.outer(S, S)
    block = None
    if opts.covariance == "block":
        free = np.isinf(np.diag(Q_s))
        args = (A_all, l_all, w, u, centred, keep, factor, dx_s, free)

        def block(cell=None):  # evaluated for the last step only; ``cell``: the block cells of its kept rows
            xy = corr.source_xyz[ok_rows, :2] - opts.origin[:2] if cell is None else None
            return block_covariance(*args, xy, N - N_sig, opts, cell=cell) / np.outer(S, S)
    return Adjustment(
        dx=dx, N=N, Qxx=Qxx, block_cov=block, held_cov=held_cov, sigma0=float(sigma0), rms=rms, redundancy=r,
        degeneracy=deg, corr=corr, scale=float(scale), n_deleted=int((~keep).sum()),
    )


def design(corr, R, t, opts, rows=None):
    """Design rows A (m, r, u), observations l (m, r) and weights of the accepted rows (``rows``: their
    indices, when the caller has them)."""
    rows = np.flatnonzero(corr.rule == 0) if rows is None else rows
    rigid = opts.dof == "rigid"
    p = np.take(corr.source_xyz, rows, axis=0) - opts.origin if rigid else None  # current source points, local frame
    n = np.take(corr.target_normal, rows, axis=0)
    if opts.metric == "point_to_plane":
        # l_i = n . (q - p)  (eq. 5.2): the matcher's plane distance, the same numbers
        l = np.take(corr.plane_distance, rows)[:, None]
        A = n[:, None, :]
        if rigid:  # n . (omega x p) = omega . (p x n)  (eq. 5.4)
            A = np.concatenate([np.cross(p, n)[:, None, :] / opts.L, A], axis=2)
    else:
        l = np.take(corr.d, rows, axis=0)  # three components per correspondence (eq. 5.1)
        A = np.broadcast_to(np.eye(3), (len(l), 3, 3))
        if rigid:  # omega x p = -[p]x omega  (eq. 5.5)
            A = np.concatenate([-skew(p) / opts.L, A], axis=2)
    return A, l, np.take(corr.weight, rows)


def solve(N, nvec, deg, N_sig=None):
    """Least-squares step, cofactor matrix and update; the datum is fixed when N is degenerate (eq. 5.12).

    The step solves N (the linearization for the current correspondences); the cofactor
    matrix is the sandwich N_sig^-1 N N_sig^-1 with the information that survives re-matching
    (eq. 5.12b) as bread: the fixed point of the iteration moves with N_sig, not with N. The
    update N_sig^-1 A^T P l is Newton's step on that fixed point: a step with N would move a weak
    direction only by N_sig / N of the way in each iteration (slow on gently sloped terrain).

    Parameters with a real share in an undetermined eigen-direction are held at
    their current value (their column is removed), the others are solved from the
    reduced normal equations. A minimum-norm step along the constrained
    eigen-directions alone would let the undetermined parameters drift: those
    eigenvectors carry small components of every parameter (noise in the normals).
    """
    N_sig = N if N_sig is None else N_sig
    if deg.well_posed and deg.parameter_determined.all():
        try:
            c = cho_factor(N)
        except np.linalg.LinAlgError:
            raise LabkitError(
                "the normal equations of ICP are singular although every direction looked determined; "
                "check the clouds for degenerate (identical or collinear) neighbourhoods"
            ) from None
        Si = np.linalg.inv(0.5 * (N_sig + N_sig.T))
        return cho_solve(c, nvec), Si @ N @ Si, Si @ nvec
    free = ~deg.parameter_determined  # a real share in an undetermined direction: held (the report names them)
    fixed = ~free
    dx = np.zeros(len(N))
    step = np.zeros(len(N))
    Q = np.full((len(N), len(N)), np.nan)
    if fixed.any():
        Nr = N[np.ix_(fixed, fixed)]
        lam, V = np.linalg.eigh(0.5 * (Nr + Nr.T))
        ok = lam >= 1e-12 * max(lam[-1], 1e-300)  # numerical guard
        V, lam = V[:, ok], lam[ok]
        dx[fixed] = V @ ((V.T @ nvec[fixed]) / lam)
        Sr = N_sig[np.ix_(fixed, fixed)]
        lam_s, V_s = np.linalg.eigh(0.5 * (Sr + Sr.T))
        ok = lam_s > 1e-12 * max(lam_s[-1], 1e-300)
        Si = (V_s[:, ok] / lam_s[ok]) @ V_s[:, ok].T
        Q[np.ix_(fixed, fixed)] = Si @ Nr @ Si
        step[fixed] = Si @ nvec[fixed]
    Q[free, free] = np.inf
    return dx, Q, step


def check_count(corr, opts, n=None):
    """Raise when fewer than ``min_correspondences`` (at least 6) rows are accepted (``n``: their number,
    when known)."""
    n = corr.n_accepted if n is None else n
    if n < max(opts.min_correspondences, 6):
        counts = ", ".join(f"{name}: {c}" for name, c in corr.rejected if c)
        raise EmptyRegionError(
            f"only {n} correspondences left after rejection (needed: {max(opts.min_correspondences, 6)}; "
            f"rejected - {counts or 'none'}); do the clouds overlap? Check the frames, give an "
            "initial transformation or relax max_distance / max_angle_deg"
        )


def default_max_std(max_std, max_distance):
    """The precision limit of determinability: given, or a tenth of the matching distance."""
    if max_std is not None:
        return float(max_std)
    return 0.1 * max_distance if np.isfinite(max_distance) else 0.1


def held_shift_std(max_distance):
    """Prior std of a held translation: its true value can lie anywhere within the matching distance."""
    return float(max_distance) if np.isfinite(max_distance) else 1.0
