"""Register terrestrial scans with sphere targets: detection, correspondences, one network adjustment (notebook 11).

Steps of :func:`register_scans`: find the spheres of the given size in every scan; match them between scans by
the distances between targets (no IDs); register the scans one after another for initial values; adjust all
poses and all target positions in one Gauss-Helmert model with the centres' covariances; test every observed
centre and leave out, one at a time, those that do not fit (moved or mismatched targets).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from . import pose as _pose
from .. import ransac
from ..core.checks import count, non_negative, probability
from ..core.frame import local_origin
from ..core.report import ReportMixin, fmt
from ..core.stats import GlobalTest, global_test, w_critical
from .matching import match_targets
from .network import adjust, caller_pose
from ..core.errors import LabkitError

__all__ = ["register_targets", "register_scans", "TargetNetwork", "TargetTable"]

_COLLINEAR = 1e-3  # second/first singular value of a scan's shared targets below this: on a line


def register_targets(centers, covariances, *, reference: int = 0, scale: bool = False, alpha: float = 0.05,
                     alpha_w: float = 0.001, match_tolerance: float = 0.05) -> TargetNetwork:
    """Register scans by their target centres in one Gauss-Helmert adjustment of all poses and targets.

    Parameters
    ----------
    centers : sequence of array_like (m_i, 3)
        Target (sphere) centres found in each scan, in that scan's frame (m), in any order.
    covariances : sequence of array_like (m_i, 3, 3)
        Their covariance matrices (m^2), e.g. the sphere adjustment's Sigma_xx blocks.
    reference : int
        The scan whose frame is the common frame.
    scale : bool
        Estimate a scale factor per scan as well.
    alpha : float
        Significance level of the global test.
    alpha_w : float
        Level of the test of each observed centre (critical normal value 3.29 for 0.001).
    match_tolerance : float
        Floor of the tolerance with which distances between targets must agree to match (m); the centres'
        covariances add 5 standard deviations. It lets targets moved by less than this through the matching,
        so that the test finds and names them.

    Returns
    -------
    TargetNetwork
        ``matrices[i]`` (scan i -> reference), ``covariances[i]`` of [rx, ry, rz, tx, ty, tz, (scale)],
        ``undetermined[i]``, the target table and ``excluded``.

    Raises
    ------
    LabkitError
        Bad shapes, a reference index out of range, fewer than three targets in the reference scan.

    Notes
    -----
    A scan that shares fewer than three targets with the scans registered before it gets no initial pose:
    two shared targets fix neither the rotation about their line nor which target is which. It is refused
    (matrix NaN, the reason in ``undetermined[i]``). Targets seen in one scan only carry no information and
    are listed with the status ``seen once``. Standard deviations use the a priori sigma0 = 1 (the centres'
    covariances are taken as known); the global test checks that assumption. A target seen in two scans only
    cannot show which of its two centres is wrong (their tests are equal): one is left out, and with it the target.

    References
    ----------
    .. [1] Notebook 11, sections 7-10: matching by distances (section 7), the network's conditions and
       blocks (eqs. 13-14), the tests and the exclusion of moved targets (sections 9-10).
    .. [2] Seed 000, section 1 (the Gauss-Helmert model), here with one 3x3 block per observed centre.
    .. [3] W. Baarda (1968): A testing procedure for use in geodetic networks. Netherlands Geodetic
       Commission, Publications on Geodesy 2(5).
    .. [4] K. R. Koch (1999): Parameter Estimation and Hypothesis Testing in Linear Models. 2nd edition,
       Springer, Berlin (singular normal equations, estimable functions).

    Examples
    --------
    >>> import numpy as np
    >>> import labkit
    >>> from labkit.transforms import make_transform, rotation_from_angles, apply_transform, invert
    >>> rng = np.random.default_rng(0)
    >>> world = rng.uniform(-10, 10, (5, 3))
    >>> poses = [np.eye(4), make_transform(rotation_from_angles(0, 0, 1.0), [2.0, 1.0, 0.0])]
    >>> centres = [apply_transform(invert(T), world) + rng.normal(0, 5e-4, (5, 3)) for T in poses]
    >>> covs = [np.tile(np.eye(3) * 2.5e-7, (5, 1, 1))] * 2
    >>> net = labkit.register_targets(centres, covs)
    >>> bool(np.allclose(net.matrices[1], poses[1], atol=2e-3)), net.global_test.passed, net.excluded
    (True, True, ())
    """
    C, S = _check(centers, covariances)
    k = len(C)
    reference = count(reference, "reference", minimum=0, maximum=k - 1)
    alpha, alpha_w = probability(alpha, "alpha"), probability(alpha_w, "alpha_w")
    floor = non_negative(match_tolerance, "match_tolerance")
    if len(C[reference]) < 3:
        raise LabkitError(f"the reference scan {reference} has {len(C[reference])} targets; it needs at least 3")

    # Reduce each scan to a local origin; initial poses scan by scan (matching by distances)
    origins = np.array([local_origin(c) if len(c) else np.zeros(3) for c in C])
    red = [c - o for c, o in zip(C, origins)]
    poses0, assign, X0, refused = _initial(red, S, reference, floor)

    # Observations of targets seen in at least two registered scans; adjust, test, leave out, repeat
    obs = np.array([(s, i, g) for s in range(k) for i, g in enumerate(assign[s]) if g >= 0], int).reshape(-1, 3)
    status = np.array(["unmatched" if s in refused else "used" for s in range(k) for _ in C[s]], dtype=object)
    row = {(s, i): r for r, (s, i) in enumerate((s, i) for s in range(k) for i in range(len(C[s])))}
    crit = w_critical(alpha_w)
    excluded, left_out = [], {}
    while True:
        use = np.array([status[row[s, i]] == "used" for s, i, _ in obs], bool)
        seen = np.bincount(obs[use, 2], minlength=len(X0))
        once = use & (seen[obs[:, 2]] < 2)
        for s, i, _ in obs[once]:
            status[row[s, i]] = "seen once"
        use &= ~once
        o = obs[use]
        if len(o) == 0:
            why = "; ".join(f"scan {s} {r}" for s, r in sorted(refused.items()))
            raise LabkitError("no target is seen in two registered scans: nothing connects the scans"
                              + (f" ({why})" if why else ""))
        cen = np.array([red[s][i] for s, i, _ in o])
        cov = np.array([S[s][i] for s, i, _ in o])
        net = adjust(o[:, 0], o[:, 2], cen, cov, origins, poses0, X0, reference, scale)
        T, r, p, z = _pose.point_tests(net.e, net.Qee, 1.0, True, net.dof, net.omega)
        if not np.isfinite(z).any() or np.nanmax(z) <= crit:
            break
        j = int(np.nanargmax(z))
        status[row[o[j, 0], o[j, 1]]] = "excluded"
        left_out[row[o[j, 0], o[j, 1]]] = (z[j], p[j])  # its test when it was left out
        excluded.append((int(o[j, 0]), int(o[j, 2])))
        poses0, X0 = _poses_of(net, poses0), net.X

    return _result(C, red, o, net, z, p, status, row, origins, reference, scale, refused, excluded, assign,
                   alpha, alpha_w, crit, left_out)


def register_scans(scans, radius_range, *, reference: int = 0, scale: bool = False, alpha: float = 0.05,
                   alpha_w: float = 0.001, match_tolerance: float = 0.05, station_at_origin: bool = True,
                   rng=None) -> TargetNetwork:
    """Find the sphere targets in every scan and register all scans into the reference scan's frame.

    Parameters
    ----------
    scans : sequence of array_like (n_i, 3) or PointCloud
        The scans, each in its own frame (m).
    radius_range : (float, float)
        Smallest and largest radius of the targets (m); spheres of other sizes are ignored.
    reference, scale, alpha, alpha_w, match_tolerance
        As in :func:`register_targets`.
    station_at_origin : bool
        Each scan is in its scanner's own frame (the station at the origin), as a TLS delivers it: the
        detection uses the station for its visibility checks. False when the scans were moved before.
    rng : int or numpy.random.Generator, optional
        Seed of the sphere detection (RANSAC).

    Returns
    -------
    TargetNetwork
        With ``spheres[i]``, the spheres found in scan i.

    References
    ----------
    .. [1] Notebook 11, sections 7-10 (the network) and notebook 02 (finding spheres with RANSAC).
    .. [2] Seed 000, sections 1-2 (the sphere in the Gauss-Helmert model, RANSAC).

    Examples
    --------
    >>> import numpy as np
    >>> import labkit
    >>> from labkit.synthetic import target_stations
    >>> hall = target_stations(n_stations=2, n_points=300_000, rng=1)
    >>> net = labkit.register_scans(hall.scans, (0.09, 0.11), rng=0)
    >>> len(net.matrices), net.undetermined[1]
    (2, ())
    >>> bool(np.abs(net.matrices[1] - np.linalg.inv(hall.poses[0]) @ hall.poses[1]).max() < 0.003)
    True
    """
    scans = list(scans)
    if len(scans) < 2:
        raise LabkitError(f"register_scans needs at least two scans, got {len(scans)}")
    gen = np.random.default_rng(rng)
    station = np.zeros(3) if station_at_origin else None
    spheres = [tuple(ransac.find_spheres(s, radius_range, station=station, rng=gen)) for s in scans]
    centers = [np.array([sp.center for sp in found]).reshape(-1, 3) for found in spheres]
    covs = [np.array([_centre_cov(sp) for sp in found]).reshape(-1, 3, 3) for found in spheres]
    net = register_targets(centers, covs, reference=reference, scale=scale, alpha=alpha, alpha_w=alpha_w,
                           match_tolerance=match_tolerance)
    return _with_spheres(net, tuple(spheres))


def _centre_cov(sphere):
    """The centre's 3x3 covariance of a sphere result (``covariance`` or ``Sigma_xx``)."""
    c = getattr(sphere, "covariance", None)
    if c is None:
        c = sphere.Sigma_xx
    return np.asarray(c, dtype=np.float64)[:3, :3]


def _with_spheres(net, spheres):
    """The network with the spheres found in each scan."""
    return replace(net, spheres=spheres)


def _check(centers, covariances):
    try:
        C = [np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in centers]
        S = [np.asarray(c, dtype=np.float64).reshape(-1, 3, 3) for c in covariances]
    except (TypeError, ValueError):
        raise LabkitError("centers must be a sequence of (m, 3) arrays and covariances of (m, 3, 3) arrays") from None
    if len(C) < 2 or len(C) != len(S) or any(len(c) != len(s) for c, s in zip(C, S)):
        raise LabkitError("give at least two scans, and one (3, 3) covariance per centre of every scan")
    if not all(np.isfinite(c).all() for c in C + S):
        raise LabkitError("centers or covariances contain NaN or infinite values")
    for s in S:
        if len(s) and (np.linalg.eigvalsh(0.5 * (s + s.transpose(0, 2, 1)))[:, 0] <= 0).any():
            raise LabkitError("every centre covariance must be positive definite")
    return C, S


def _initial(red, S, reference, floor):
    """Initial poses by matching each scan to the targets registered so far (the best-connected scan first)."""
    k = len(red)
    poses0 = np.full((k, 4, 4), np.nan)
    poses0[reference] = np.eye(4)
    assign = [np.full(len(c), -1) for c in red]
    assign[reference] = np.arange(len(red[reference]))
    X, XC = list(red[reference]), list(S[reference])
    pending, refused = set(range(k)) - {reference}, {}
    while pending:
        best = None
        for s in sorted(pending):
            pairs, line = _verified(np.array(X), np.array(XC), red[s], S[s], floor)
            if not line and (best is None or len(pairs) > len(best[1])):
                best = (s, pairs)
        if best is None or len(best[1]) < 3:
            break
        s, pairs = best
        R, t, _ = _pose.closed_form(red[s][pairs[:, 1]], np.array(X)[pairs[:, 0]])
        poses0[s, :3, :3], poses0[s, :3, 3], poses0[s, 3] = R, t, [0, 0, 0, 1]
        assign[s][pairs[:, 1]] = pairs[:, 0]
        for i in np.flatnonzero(assign[s] < 0):  # new targets
            assign[s][i] = len(X)
            X.append(R @ red[s][i] + t)
            XC.append(R @ S[s][i] @ R.T)
        pending.discard(s)
    for s in pending:
        pairs, line = _verified(np.array(X), np.array(XC), red[s], S[s], floor)
        n = len(pairs)
        refused[s] = ((f"refused: its {n} shared targets lie on a line, the rotation about it is not determined"
                       if line else f"refused: shares only {n} target(s) with the other scans")
                      + "; at least 3 not on a line are needed"
                      + (" (two fix neither the rotation about their line nor which is which)" if n == 2 else ""))
    return poses0, assign, np.array(X), refused


def _verified(X, XC, B, CB, floor):
    """Matched pairs (world, scan) that also fit a rigid transformation, and whether they lie on a line."""
    pairs = match_targets(X, XC, B, CB, floor)
    if len(pairs) < 3:
        return pairs, False
    R, t, _ = _pose.closed_form(B[pairs[:, 1]], X[pairs[:, 0]])
    res = np.linalg.norm(B[pairs[:, 1]] @ R.T + t - X[pairs[:, 0]], axis=1)
    pairs = pairs[res <= 2 * floor + 1e-9]
    if len(pairs) >= 3:
        sv = np.linalg.svd(B[pairs[:, 1]] - B[pairs[:, 1]].mean(axis=0), compute_uv=False)
        return pairs, bool(sv[1] < _COLLINEAR * sv[0])
    return pairs, False


def _poses_of(net, poses0):
    """Current poses (reduced frames) of an adjusted network, as initial values of the next run."""
    out = poses0.copy()
    for s in net.pose_index:
        out[s, :3, :3] = net.s[s] * _pose.rotation_from_angles(*net.angles[s])
        out[s, :3, 3] = net.t[s]
    return out


def _result(C, red, o, net, z, p, status, row, origins, reference, scale, refused, excluded, assign,
            alpha, alpha_w, crit, left_out):
    """Poses and covariances in the caller's frames, the named undetermined directions and the target table."""
    k, u = len(C), (7 if scale else 6)
    mats, pars, covs, undet = np.full((k, 4, 4), np.nan), np.full((k, u), np.nan), [], []
    for s in range(k):
        if s == reference:
            mats[s], pars[s] = np.eye(4), np.r_[np.zeros(6), [1.0] * scale]
            covs.append(np.zeros((u, u)))
            undet.append(())
        elif s in refused or s not in net.pose_index:
            covs.append(np.full((u, u), np.nan))
            undet.append((refused.get(s, "refused: none of its targets is seen in another scan"),))
        else:
            mats[s], pars[s], cov, bad = caller_pose(net, s, origins, reference, scale)
            covs.append(cov)
            undet.append(_name(red[s][o[o[:, 0] == s, 1]], o[o[:, 0] == s, 2], bad, scale) if bad.any() else ())
    n = len(status)
    table = TargetTable(
        scan=np.array([s for s in range(k) for _ in C[s]], int), index=np.array([i for s in range(k) for i in
                                                                              range(len(C[s]))], int),
        target=np.concatenate([assign[s] for s in range(k)]).astype(int) if n else np.zeros(0, int),
        center=np.concatenate(C) if n else np.zeros((0, 3)), residual=np.full((n, 3), np.nan),
        test=np.full(n, np.nan), p=np.full(n, np.nan), status=status.astype(str))
    rows = [row[s, i] for s, i, _ in o]
    table.residual[rows], table.test[rows], table.p[rows] = net.v, z, p
    for r, (zr, pr) in left_out.items():
        table.test[r], table.p[r] = zr, pr
    sigma0 = float(np.sqrt(net.omega / net.dof)) if net.dof > 0 else np.nan
    g = global_test(net.omega, net.dof, 1.0, alpha)
    world = net.X + origins[reference]
    return TargetNetwork(matrices=mats, parameters=pars, covariances=tuple(covs), undetermined=tuple(undet),
                         table=table, excluded=tuple(excluded), targets=world, global_test=g, sigma0=sigma0,
                         redundancy=net.dof, iterations=net.iterations, converged=net.converged, scaled=scale,
                         reference=reference, w_critical=crit, alpha_w=alpha_w)


def _name(points, targets, bad, scale):
    names = ", ".join(np.array(("rx", "ry", "rz", "tx", "ty", "tz", "scale"))[np.flatnonzero(bad)])
    ids = ", ".join(str(int(g)) for g in targets)
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) if len(points) > 1 else np.zeros(3)
    if len(points) <= 2 or sv[1] < _COLLINEAR * sv[0]:
        return (f"rotation about the line through targets {ids} (affects {names})",)
    return (f"the targets {ids} do not fix {names}",)


@dataclass(frozen=True, eq=False, repr=False)
class TargetTable(ReportMixin):
    """Every sphere centre found in every scan, with its target, residual and test.

    Attributes
    ----------
    scan, index : ndarray of int (n,)
        Scan and position of the centre in that scan's list.
    target : ndarray of int (n,)
        Target number in the network (-1: unmatched).
    center : ndarray (n, 3)
        Centre in its scan's frame (m).
    residual : ndarray (n, 3)
        Residual v of the centre (m), NaN where not used.
    test : ndarray (n,)
        Test of the centre as a standard normal value (compare with 3.29 at alpha_w = 0.001); for an excluded
        centre its value when it was left out; NaN where not tested.
    p : ndarray (n,)
        Its p-value.
    status : ndarray of str (n,)
        ``used``, ``excluded`` (left out by the test), ``seen once`` or ``unmatched`` (scan refused).

    Examples
    --------
    >>> import numpy as np
    >>> t = TargetTable(np.zeros(1, int), np.zeros(1, int), np.zeros(1, int), np.zeros((1, 3)),
    ...                 np.zeros((1, 3)), np.zeros(1), np.ones(1), np.array(["used"]))
    >>> len(t)
    1
    """

    scan: np.ndarray
    index: np.ndarray
    target: np.ndarray
    center: np.ndarray
    residual: np.ndarray
    test: np.ndarray
    p: np.ndarray
    status: np.ndarray

    def __len__(self) -> int:
        return len(self.scan)

    def _report(self):
        rows = []
        for r in range(len(self)):
            v = self.residual[r] * 1e3
            res = "-" if np.isnan(v).all() else (f"[{v[0]:+6.2f} {v[1]:+6.2f} {v[2]:+6.2f}] mm  "
                                                 f"|v| {np.linalg.norm(v):5.2f}")
            test = "" if np.isnan(self.test[r]) else f"  test {self.test[r]:5.2f}"
            rows.append((f"scan {self.scan[r]} sphere {self.index[r]} -> target {self.target[r]}",
                         f"{res}{test}  {self.status[r]}"))
        return "Targets: residuals and tests", [("", rows)]


@dataclass(frozen=True, eq=False, repr=False)
class TargetNetwork(ReportMixin):
    """Scans registered by sphere targets in one Gauss-Helmert adjustment (see :func:`register_targets`).

    Attributes
    ----------
    matrices : ndarray (k, 4, 4)
        Scan i -> reference frame (NaN for a refused scan).
    parameters : ndarray (k, 6) or (k, 7)
        [rx, ry, rz (rad), tx, ty, tz (m), (scale)] of each scan, R = Rz Ry Rx.
    covariances : tuple of ndarray (6, 6) or (7, 7)
        Their covariances (a priori sigma0 = 1); undetermined parameters: variance inf, row/column NaN.
    undetermined : tuple of tuple of str
        Per scan, what its targets do not determine (empty when all is determined).
    table : TargetTable
    excluded : tuple of (scan, target)
        Observations left out by the test, in the order they were found.
    targets : ndarray (G, 3)
        Adjusted target positions in the reference frame (those seen once: from the initial registration).
    global_test : GlobalTest
    sigma0 : float
    redundancy, iterations : int
    converged, scaled : bool
    reference : int
    w_critical, alpha_w : float
    spheres : tuple
        Per scan, the spheres found (``register_scans`` only).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.targets.register import register_targets
    >>> world = np.array([[0.0, 0, 0], [8, 0, 1], [0, 6, 2], [5, 5, 0.5]])
    >>> covs = [np.tile(np.eye(3) * 1e-6, (4, 1, 1))] * 2
    >>> net = register_targets([world, world + [1.0, 0, 0]], covs)
    >>> (net.matrices[1][:3, 3].round(6) + 0.0).tolist()
    [-1.0, 0.0, 0.0]
    """

    matrices: np.ndarray
    parameters: np.ndarray
    covariances: tuple
    undetermined: tuple
    table: TargetTable
    excluded: tuple
    targets: np.ndarray
    global_test: GlobalTest
    sigma0: float
    redundancy: int
    iterations: int
    converged: bool
    scaled: bool
    reference: int
    w_critical: float
    alpha_w: float
    spheres: tuple = ()

    @property
    def std(self) -> np.ndarray:
        """Standard deviations (k, u) of ``parameters``: rad, m (inf where undetermined, NaN if refused)."""
        return np.sqrt(np.array([np.diag(c) for c in self.covariances]))

    @property
    def names(self) -> tuple:
        return ("rx", "ry", "rz", "tx", "ty", "tz", "scale")[: self.parameters.shape[1]]

    def registration_covariance(self, scan: int):
        """(names, covariance) of scan ``scan`` in the registration file's terms (``labkit.save_registration``).

        The file describes a small change of the pose as p' -> p' + dt + dw x p' (+ ds p'), with a shift, a
        rotation vector dw about the axes of the reference frame at its origin and a relative scale. With
        R = Rz Ry Rx the rotation vector is dw = Rz Ry e_x drx + Rz e_y dry + e_z drz; the shift absorbs
        dw x t, so dt_file = dt + t x dw - t ds / s. NaN for a refused scan.
        """
        x, C = self.parameters[scan], self.covariances[scan]
        names = ("tx", "ty", "tz", "rx", "ry", "rz") + (("scale",) if self.scaled else ())
        u = len(names)
        if not np.isfinite(x).all():
            return names, np.full((u, u), np.nan)
        Rx, Ry, Rz = (_pose.rotation_from_angles(*a) for a in np.diag(x[:3]))
        Jw = np.column_stack([Rz @ Ry[:, 0], Rz[:, 1], [0.0, 0.0, 1.0]])
        t, s = x[3:6], (x[6] if self.scaled else 1.0)
        G = np.zeros((u, u))
        G[:3, :3], G[:3, 3:6], G[3:6, :3] = _pose.skew(t) @ Jw, np.eye(3), Jw
        if self.scaled:
            G[:3, 6], G[6, 6] = -t / s, 1.0 / s
        with np.errstate(invalid="ignore"):
            return names, G @ C @ G.T

    def _report(self):
        sections = []
        for s in range(len(self.matrices)):
            if s == self.reference:
                sections.append((f"Scan {s} (reference)", [("", "identity")]))
                continue
            rows = [("", u) for u in self.undetermined[s]]
            if np.isfinite(self.parameters[s]).all():
                x, sd = self.parameters[s], self.std[s]
                rows += [(n, f"{np.degrees(x[i]):+11.6f} deg  +- {np.degrees(sd[i]) * 3600:7.2f} arcsec")
                         for i, n in enumerate(self.names[:3])]
                rows += [(n, f"{x[i]:+11.4f} m    +- {sd[i] * 1e3:7.2f} mm") for i, n in enumerate(self.names[3:6], 3)]
                if self.scaled:
                    rows.append(("scale", f"{x[6]:.8f}  +- {sd[6] * 1e6:.2f} ppm"))
            sections.append((f"Scan {s} -> scan {self.reference}", rows))
        g = self.global_test
        used = int((self.table.status == "used").sum())
        sections.append(("Adjustment", [
            ("observed centres", f"{used} used, {len(self.excluded)} excluded"),
            ("redundancy", f"{self.redundancy}"), ("sigma0", fmt(self.sigma0, 3)),
            ("global test", f"T = {g.statistic:.2f}, accepted [{g.lower:.2f}, {g.upper:.2f}]: "
             + {True: "passed", False: "REJECTED", None: "not testable"}[g.passed]),
            ("excluded", ", ".join(f"scan {s} target {t}" for s, t in self.excluded) or "none"),
        ]))
        return "Scans registered by sphere targets (Gauss-Helmert network)", sections
