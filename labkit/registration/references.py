"""Reference transformations per test region (the registration study, step 1.5; notebook 07).

A reference is what a registration is checked against: the synthetic truth,
a manual reference typed in by a user (e.g. read off CloudCompare) with its
uncertainty, repeated manual references averaged with their spread (the registration study
repeats them "for certainty"), or a reference from control points: sphere-target
centres found in both epochs, or picked point pairs, by weighted least squares.
References are kept in a small JSON file keyed by region and case.

Equation numbers refer to ``notebooks/07-comparing-transformations.ipynb``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_write_text
from ..core.checks import as_points
from ..core.report import ReportMixin, fmt
from ..core.errors import LabkitError
from ..transforms import check_transform, make_transform

AXES = ("X", "Y", "Z")
REFERENCE_FORMAT = "labkit-references"


@dataclass(frozen=True, eq=False, repr=False)
class Reference(ReportMixin):
    """A reference transformation source -> target for one region and case.

    Attributes
    ----------
    translation : ndarray (3,)
        Translation t of ``p' = R p + t`` in the caller's frame (m).
    covariance : ndarray (3, 3)
        Covariance of the shift (m^2); zeros for a synthetic truth.
    rotation : ndarray (3, 3)
        Rotation R (identity for a pure shift).
    region, case : str
        Labels, e.g. ``"gable_y"`` and ``"als-als"``.
    kind : str
        ``"truth"``, ``"manual"``, ``"mean of manual"``, ``"targets"`` or ``"pairs"``.
    n : int
        Number of repeats or control points behind the reference.
    spread : ndarray (3,)
        Sample standard deviation of the repeats (NaN for a single value).
    sigma0 : float
        A posteriori standard deviation of unit weight of the control-point
        or averaging adjustment (NaN when there is no redundancy).
    residuals : ndarray (n, 3)
        Residuals v of the control points or repeats (empty when not applicable).
    note : str
        Free text (who measured it, with which tool).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.references import Reference
    >>> ref = Reference(np.array([0.10, -0.05, 0.02]), np.diag([1e-4, 1e-4, 4e-4]), region="roof", case="als-als")
    >>> ref.key, ref.std.tolist(), ref.matrix[:3, 3].tolist()
    (('roof', 'als-als'), [0.01, 0.01, 0.02], [0.1, -0.05, 0.02])
    """

    translation: np.ndarray
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    region: str = ""
    case: str = ""
    kind: str = "manual"
    n: int = 1
    spread: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    sigma0: float = float("nan")
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    note: str = ""

    def __post_init__(self):
        T = check_transform(make_transform(self.rotation, self.translation))
        C = _as_covariance(self.covariance, "reference covariance")
        for name, value in (("translation", T[:3, 3]), ("rotation", T[:3, :3]), ("covariance", C)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "spread", np.asarray(self.spread, dtype=float).reshape(3))
        object.__setattr__(self, "residuals", np.asarray(self.residuals, dtype=float).reshape(-1, 3))

    def __repr__(self) -> str:
        return self.summary()

    @property
    def key(self) -> tuple:
        """(region, case), the key in a reference file."""
        return (self.region, self.case)

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 matrix source -> target."""
        return make_transform(self.rotation, self.translation)

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the shift components (m)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    def to_dict(self) -> dict:
        """A JSON-ready dictionary (lists of floats)."""
        out = {"region": self.region, "case": self.case, "kind": self.kind,
               "translation": self.translation.tolist(), "covariance": self.covariance.tolist(), "n": self.n}
        if not np.allclose(self.rotation, np.eye(3)):
            out["rotation"] = self.rotation.tolist()
        if np.isfinite(self.spread).any():
            out["spread"] = self.spread.tolist()
        if np.isfinite(self.sigma0):
            out["sigma0"] = self.sigma0
        if len(self.residuals):
            out["residuals"] = self.residuals.tolist()
        if self.note:
            out["note"] = self.note
        return out

    def _report(self):
        rows = [(f"d{a}", f"{t:+.4f} m  +- {s:.4f} m") for a, t, s in zip(AXES, self.translation, self.std)]
        if not np.allclose(self.rotation, np.eye(3)):
            rows.append(("rotation", "yes (see .rotation)"))
        rows.append(("kind", f"{self.kind} (n = {self.n})"))
        if np.isfinite(self.spread).any():
            rows.append(("spread of repeats", fmt(self.spread, 4, "m")))
        if np.isfinite(self.sigma0):
            rows.append(("sigma0", fmt(self.sigma0, 3)))
        if self.note:
            rows.append(("note", self.note))
        label = " / ".join(s for s in (self.region, self.case) if s)
        return f"Reference transformation {label}".strip(), [("", rows)]


def truth_reference(T, *, region: str = "", case: str = "", note: str = "synthetic truth") -> Reference:
    """A reference from a known 4x4 transformation (zero covariance).

    References
    ----------
    .. [1] Notebook 07, section 2 (the known shift of the synthetic cases).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.references import truth_reference
    >>> from labkit.transforms import make_transform
    >>> ref = truth_reference(make_transform(np.eye(3), [0.2, 0.0, -0.1]), region="xyz")
    >>> ref.kind, ref.translation.tolist(), ref.std.tolist()
    ('truth', [0.2, 0.0, -0.1], [0.0, 0.0, 0.0])
    """
    T = check_transform(T)
    return Reference(T[:3, 3], np.zeros((3, 3)), T[:3, :3], region, case, "truth", 1, note=note)


def manual_reference(translation, std=None, *, covariance=None, rotation=None, region: str = "",
                     case: str = "", note: str = "") -> Reference:
    """A reference entered by hand, with its uncertainty as ``std`` (scalar or (3,)) or ``covariance``.

    References
    ----------
    .. [1] Seed 003, step 1.5 (a manual reference transformation per test region); notebook 07,
       section 2.

    Examples
    --------
    >>> from labkit.registration.references import manual_reference
    >>> ref = manual_reference([0.12, 0.0, 0.03], std=[0.01, 0.01, 0.02], region="roof")
    >>> ref.kind, ref.std.tolist()
    ('manual', [0.01, 0.01, 0.02])
    """
    if std is not None and covariance is not None:
        raise LabkitError("give the uncertainty either as std or as covariance, not both")
    if covariance is None:
        s = np.broadcast_to(np.asarray(0.0 if std is None else std, dtype=float), (3,))
        if (s < 0).any() or not np.isfinite(s).all():
            raise LabkitError(f"std must be finite and >= 0, got {std!r}")
        covariance = np.diag(s**2)
    rot = np.eye(3) if rotation is None else rotation
    return Reference(np.asarray(translation, dtype=float), covariance, rot, region, case, "manual", 1, note=note)


def average_references(references, *, note: str = "") -> Reference:
    """Combine repeated manual references of one region into one, with their spread.

    With stated covariances C_i the mean is the weighted mean (eq. 1); its
    internal covariance (sum C_i^-1)^-1 is scaled by the variance factor
    s0^2 = sum v_i^T C_i^-1 v_i / (3 (n - 1)) when the repeats scatter more
    than stated (eq. 2: the larger of internal and external accuracy). Without
    stated uncertainties the mean is plain and its covariance is the sample
    covariance over n. Rotations must agree (pure shifts are the usual case).

    References
    ----------
    .. [1] Notebook 07, section 2, eqs. 1-3; the registration study, step 1.5 (manual references made several
       times).
    .. [2] W. Niemeier (2008): Ausgleichungsrechnung. 2nd edition, de Gruyter, Berlin.

    Examples
    --------
    Three repeated picks of the same shift, each +- 1 cm:

    >>> from labkit.registration.references import average_references, manual_reference
    >>> picks = [manual_reference([t, 0.0, 0.0], std=0.01) for t in (0.10, 0.12, 0.11)]
    >>> mean = average_references(picks)
    >>> mean.kind, mean.n, mean.translation.round(3).tolist(), mean.spread.round(3).tolist()
    ('mean of manual', 3, [0.11, 0.0, 0.0], [0.01, 0.0, 0.0])
    >>> float(mean.std[0].round(4))  # stated 1 cm / sqrt(3); the repeats scatter no more than stated
    0.0058
    """
    refs = list(references)
    if not refs:
        raise LabkitError("average_references needs at least one reference")
    if any(not np.allclose(r.rotation, refs[0].rotation, atol=1e-9) for r in refs):
        raise LabkitError("repeated references with different rotations cannot be averaged component-wise")
    t = np.array([r.translation for r in refs])  # (n, 3)
    C = np.array([r.covariance for r in refs])  # (n, 3, 3)
    n = len(refs)
    spread = t.std(axis=0, ddof=1) if n > 1 else np.full(3, np.nan)
    stated = all(np.linalg.eigvalsh(c)[0] > 0 for c in C)
    if stated:
        mean, cov, v, s0 = _weighted_mean(t, C)  # (eq. 1, 2)
        cov = cov * max(1.0, s0**2) if np.isfinite(s0) else cov
    else:
        mean = t.mean(axis=0)
        v = t - mean
        cov = np.cov(t.T, ddof=1) / n if n > 1 else np.zeros((3, 3))
        s0 = float("nan")
    first = refs[0]
    return Reference(mean, cov, first.rotation, first.region, first.case, "mean of manual", n, spread, s0, v,
                     note or first.note)


def reference_from_targets(centres_source, cov_source, centres_target, cov_target, *, region: str = "",
                           case: str = "", kind: str = "targets", note: str = "") -> Reference:
    """Translation from m control points (e.g. sphere centres) measured in both epochs.

    Each target gives an observed shift d_i = c_target,i - c_source,i with
    covariance C_i = Sigma_source,i + Sigma_target,i; the translation is their
    weighted least-squares mean t = (sum C_i^-1)^-1 sum C_i^-1 d_i (eq. 1) with
    covariance (sum C_i^-1)^-1 (eq. 2); with m >= 2 the variance factor
    s0^2 = sum v_i^T C_i^-1 v_i / (3 (m - 1)) is reported (eq. 3) and scales the
    covariance when it exceeds 1.

    Parameters
    ----------
    centres_source, centres_target : array_like (m, 3)
        The same targets in the source and the target epoch, in the same order.
    cov_source, cov_target : array_like (m, 3, 3) or (3, 3)
        Their covariances, e.g. ``ransac_sphere(...).fit.Sigma_xx[:3, :3]``.

    References
    ----------
    .. [1] Notebook 07, section 2, eqs. 1-3.
    .. [2] W. Niemeier (2008): Ausgleichungsrechnung. 2nd edition, de Gruyter, Berlin.
    .. [3] E. M. Mikhail, F. Ackermann (1976): Observations and Least Squares. IEP-Dun-Donnelley,
       New York.

    Examples
    --------
    Two sphere centres (1 mm each) measured in both epochs, the second epoch shifted by 5 cm in Z:

    >>> import numpy as np
    >>> from labkit.registration.references import reference_from_targets
    >>> source = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 1.0]])
    >>> ref = reference_from_targets(source, np.eye(3) * 1e-6, source + [0, 0, 0.05], np.eye(3) * 1e-6)
    >>> ref.translation.round(3).tolist(), ref.n, ref.std.round(4).tolist()
    ([0.0, 0.0, 0.05], 2, [0.001, 0.001, 0.001])
    """
    cs = as_points(centres_source, name="centres_source")
    ct = as_points(centres_target, name="centres_target")
    if cs.shape != ct.shape:
        raise LabkitError(f"centres_source {cs.shape} and centres_target {ct.shape} must list the same targets")
    Cs = _stack_cov(cov_source, len(cs), "cov_source")
    Ct = _stack_cov(cov_target, len(cs), "cov_target")
    d = ct - cs  # observed shifts
    mean, cov, v, s0 = _weighted_mean(d, Cs + Ct)
    if np.isfinite(s0):
        cov = cov * max(1.0, s0**2)
    return Reference(mean, cov, np.eye(3), region, case, kind, len(cs), sigma0=s0, residuals=v, note=note)


def reference_from_pairs(source_points, target_points, std=0.01, *, region: str = "", case: str = "",
                         note: str = "picked point pairs") -> Reference:
    """Translation from picked point pairs; ``std`` is the picking precision per coordinate (m).

    ``std`` is a scalar, one value per pair, or (m, 3); both picks get it.

    References
    ----------
    .. [1] Notebook 07, section 2, eqs. 1-3 (picked pairs as control points).
    .. [2] W. Niemeier (2008): Ausgleichungsrechnung. 2nd edition, de Gruyter, Berlin.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.references import reference_from_pairs
    >>> picked = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 1.0], [5.0, 5.0, 1.0]])
    >>> ref = reference_from_pairs(picked, picked + [0.1, 0.0, 0.0], std=0.02)
    >>> ref.kind, ref.translation.round(3).tolist(), ref.std.round(3).tolist()
    ('pairs', [0.1, 0.0, 0.0], [0.014, 0.014, 0.014])
    """
    ps = as_points(source_points, name="source_points")
    s = np.broadcast_to(np.asarray(std, dtype=float).reshape(-1, 1) if np.ndim(std) == 1
                        else np.asarray(std, dtype=float), ps.shape)
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise LabkitError("std of the picked points must be finite and > 0")
    C = np.einsum("ni,ij->nij", s**2, np.eye(3))
    return reference_from_targets(ps, C, target_points, C, region=region, case=case, kind="pairs", note=note)


def save_references(references, path) -> Path:
    """Write references (an iterable or a mapping of them) to a JSON file, atomically.

    References
    ----------
    .. [1] Seed 003, step 1.5; notebook 07, section 2 (the reference file).

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from labkit.registration.references import load_references, manual_reference, save_references
    >>> path = save_references([manual_reference([0.1, 0, 0], std=0.01, region="roof", case="als-als")],
    ...                        Path(tempfile.mkdtemp()) / "references.json")
    >>> back = load_references(path)
    >>> list(back), back[("roof", "als-als")].translation.tolist()
    ([('roof', 'als-als')], [0.1, 0.0, 0.0])
    """
    try:
        refs = list(references.values()) if isinstance(references, Mapping) else list(references)
    except TypeError:
        raise LabkitError(f"save_references needs Reference objects (a list or a mapping), "
                          f"got {type(references).__name__}") from None
    bad = [type(r).__name__ for r in refs if not isinstance(r, Reference)]
    if bad:
        raise LabkitError(f"save_references needs Reference objects (see manual_reference), got {bad[0]}")
    if not isinstance(path, (str, os.PathLike)) or not str(path).strip():
        raise LabkitError(f"save_references needs a file path, got {path!r}")
    if Path(path).is_dir():
        raise LabkitError(f"cannot write references to {path}: it is a folder")
    entries = ",\n".join("    " + json.dumps(r.to_dict()) for r in refs)  # one line per reference
    head = json.dumps({"format": REFERENCE_FORMAT, "version": 1})[:-1]
    return atomic_write_text(path, f'{head}, "references": [\n{entries}\n]}}\n')


def _json_entries(path: Path, key: str, label: str, what: str) -> list:
    """The entries of a JSON file: the document itself, or its ``key`` when it is an object.

    ``label`` names the file in the not-found error (``"reference file"``), ``what`` says what it should
    be in the parse error (``"a labkit reference file"``).
    """
    if not path.is_file():
        raise LabkitError(f"{label} not found: {path}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        return doc[key] if isinstance(doc, dict) else doc
    except (json.JSONDecodeError, KeyError, UnicodeDecodeError, TypeError) as exc:
        raise LabkitError(f"{path} is not {what}: {exc}") from None
    except OSError as exc:
        raise LabkitError(f"cannot read {path}: {exc}") from None


def load_references(path) -> dict:
    """Read a reference file; returns ``{(region, case): Reference}``.

    An entry holds either ``translation`` (with ``covariance`` or ``std``,
    optional ``rotation``), or ``matrix`` (4x4), or ``repeats`` (a list of
    translations, optional per-component ``std``), which are averaged with
    :func:`average_references`. Several entries with the same region and case
    are averaged too.

    References
    ----------
    .. [1] Seed 003, step 1.5; notebook 07, section 2 (the reference file).

    Examples
    --------
    Entries with the same region and case (here repeats) are averaged:

    >>> import json, tempfile
    >>> from pathlib import Path
    >>> from labkit.registration.references import load_references
    >>> path = Path(tempfile.mkdtemp()) / "references.json"
    >>> _ = path.write_text(json.dumps({"references": [
    ...     {"region": "roof", "case": "als-als", "repeats": [[0.10, 0, 0], [0.12, 0, 0]],
    ...      "std": [0.01, 0.01, 0.01]}]}))
    >>> ref = load_references(path)[("roof", "als-als")]
    >>> ref.kind, ref.n, ref.translation.round(3).tolist()
    ('mean of manual', 2, [0.11, 0.0, 0.0])
    """
    if not isinstance(path, (str, os.PathLike)):
        raise LabkitError(f"load_references needs a file path, got {type(path).__name__}")
    path = Path(path)
    entries = _json_entries(path, "references", "reference file", "a labkit reference file")
    if not isinstance(entries, list):
        raise LabkitError(f"{path} is not a labkit reference file: expected a list of entries, "
                          f"got {type(entries).__name__}")
    grouped: dict = {}
    for i, entry in enumerate(entries):
        try:
            if not isinstance(entry, dict):
                raise LabkitError(f"expected an object with region, case and translation, got {type(entry).__name__}")
            for ref in _entry_references(entry):
                grouped.setdefault(ref.key, []).append(ref)
        except (LabkitError, KeyError, TypeError, ValueError, AttributeError) as exc:
            raise LabkitError(f"{path}: reference entry {i} is invalid: {exc}") from None
    return {k: (v[0] if len(v) == 1 else average_references(v)) for k, v in grouped.items()}


def _entry_references(entry: dict) -> list:
    labels = {"region": str(entry.get("region", "")), "case": str(entry.get("case", "")),
              "note": str(entry.get("note", ""))}
    if "repeats" in entry:
        refs = [manual_reference(t, entry.get("std"), **labels) for t in entry["repeats"]]
        return [average_references(refs)] if len(refs) > 1 else refs
    if "matrix" in entry:
        ref = truth_reference(np.asarray(entry["matrix"], dtype=float), **labels)
        if entry.get("kind", "truth") == "truth":
            return [ref]
        return [manual_reference(ref.translation, entry.get("std"), rotation=ref.rotation, **labels)]
    rot = entry.get("rotation")
    if "covariance" in entry:
        ref = manual_reference(entry["translation"], covariance=entry["covariance"], rotation=rot, **labels)
    else:
        ref = manual_reference(entry["translation"], entry.get("std"), rotation=rot, **labels)
    kind = entry.get("kind", "manual")
    extra = {k: entry[k] for k in ("n", "spread", "sigma0", "residuals") if k in entry}
    return [Reference(ref.translation, ref.covariance, ref.rotation, ref.region, ref.case, kind,
                      **{**{"n": 1}, **extra}, note=ref.note)]


def _weighted_mean(d: np.ndarray, C: np.ndarray):
    """Weighted mean of vectors d_i (n, 3) with covariances C_i (n, 3, 3); returns mean, cov, v, s0."""
    try:
        W = np.linalg.solve(C, np.broadcast_to(np.eye(3), C.shape))  # weights P_i = C_i^-1, batched
    except np.linalg.LinAlgError:
        raise LabkitError("a covariance matrix of the control points is singular") from None
    N = W.sum(axis=0)  # sum C_i^-1
    n_vec = np.einsum("nij,nj->i", W, d)
    if np.linalg.cond(N) > 1e12:
        raise LabkitError("the combined weight matrix of the control points is ill-conditioned")
    mean = np.linalg.solve(N, n_vec)  # (eq. 1)
    cov = np.linalg.solve(N, np.eye(3))  # (eq. 2)
    v = mean - d
    r = 3 * (len(d) - 1)
    s0 = float(np.sqrt(np.einsum("ni,nij,nj->", v, W, v) / r)) if r > 0 else float("nan")  # (eq. 3)
    return mean, 0.5 * (cov + cov.T), v, s0


def _stack_cov(cov, m: int, name: str) -> np.ndarray:
    C = np.asarray(cov, dtype=float)
    if C.shape == (3, 3):
        C = np.broadcast_to(C, (m, 3, 3))
    if C.shape != (m, 3, 3):
        raise LabkitError(f"{name} must have shape ({m}, 3, 3) or (3, 3), got {C.shape}")
    return np.array([_as_covariance(c, name) for c in C])


def _as_covariance(C, name: str) -> np.ndarray:
    C = np.asarray(C, dtype=float)
    if C.shape != (3, 3):
        raise LabkitError(f"{name} must have shape (3, 3), got {C.shape}")
    if not np.isfinite(C).all() or not np.allclose(C, C.T, atol=1e-12 + 1e-9 * np.abs(C).max()):
        raise LabkitError(f"{name} must be a finite symmetric 3x3 matrix")
    if np.linalg.eigvalsh(0.5 * (C + C.T))[0] < -1e-12 * max(1.0, np.abs(C).max()):
        raise LabkitError(f"{name} must be positive semi-definite")
    return 0.5 * (C + C.T)
