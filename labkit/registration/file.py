"""The registration file: what ``labkit register`` (or a target-based registration) hands to ``labkit change``.

One JSON object with exactly these keys (anything else is refused, so a typo never
passes silently):

- ``format``            ``"labkit-registration"`` and ``format_version`` 2
- ``matrix``            4x4, maps the moved epoch (source, compared) into the reference (target)
                        frame: p' = M p, in the coordinates labkit read (``units``)
- ``parameter_names``   names of the estimated parameters: ``tx ty tz`` (m), optionally
                        ``rx ry rz`` (rad, small rotations about ``origin``) and ``scale``
                        (unitless, about ``origin``)
- ``covariance``        p x p covariance of those parameters (m^2, rad^2); ``null`` marks a
                        parameter the data did not determine (infinite variance)
- ``origin``            the frame origin the rotations refer to (notebook 10, eq. 6), in the
                        input frame: p' = R (p - origin) + origin + t
- ``units``             unit of ``matrix``'s translation, ``origin`` and the covariance (``"m"``)
- ``crs``               the inputs' CRS as the file states it (WKT or ``EPSG:n``), or ``null``
- ``inputs``            ``{"source": path, "target": path}`` as given on the command line
- ``method``            how it was estimated (``"icp"``, ``"targets"``, ...)
- ``labkit_version``    the version that wrote it

A covariance whose parameters are not determined by the data is written, not hidden:
its ``null`` entries come back as ``inf`` and the level of detection of
:func:`labkit.m3c2` turns infinite where such a parameter moves the surface along the
normal (or takes the prior ``held_std``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from .. import __version__
from ..core.atomic import as_path, atomic_write_text
from ..core.crs import crs_summary
from ..core.errors import LabkitError
from ..core.lengths import length_text
from ..core.report import ReportMixin
from ..transforms import apply_transform

__all__ = ["RegistrationFile", "load_registration", "save_registration"]

FORMAT = "labkit-registration"
FORMAT_VERSION = 2
KEYS = ("format", "format_version", "matrix", "parameter_names", "covariance", "origin", "units", "crs", "inputs",
        "method", "labkit_version")
NAMES = ("tx", "ty", "tz", "rx", "ry", "rz", "scale")


@dataclass(frozen=True, eq=False)
class RegistrationFile(ReportMixin):
    """A registration as read from its JSON file (see :func:`load_registration`).

    It has the fields :func:`labkit.change.m3c2.registration_variance` reads from a
    ``RegistrationResult`` (``matrix``, ``covariance``, ``parameter_names``, ``origin``)
    and ``apply``, so it can be passed to :func:`labkit.m3c2` as ``registration_covariance``.

    Parameters
    ----------
    matrix : ndarray (4, 4)
        Moved epoch -> reference frame, in the coordinates labkit read (metres).
    covariance : ndarray (p, p)
        Covariance of ``parameter_names``; ``inf`` on the diagonal: not determined.
    parameter_names : tuple of str
    origin : ndarray (3,)
        The point the rotations (and scale) refer to.
    units : str
        Unit of the translation, origin and covariance (``"m"``).
    crs : str or None
        CRS of the inputs as their files state it; None when they state none (the summary says the
        coordinates are in an unknown frame).
    inputs : tuple of (str, str)
        ``(("source", path), ("target", path))``: what was registered onto what.
    method : str
    labkit_version : str
        The version that wrote the file.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit import RegistrationFile
    >>> reg = RegistrationFile(np.eye(4), np.eye(3) * 1e-6, ("tx", "ty", "tz"), np.zeros(3))
    >>> reg.std.tolist(), reg.apply([[1.0, 2.0, 3.0]]).tolist()
    ([0.001, 0.001, 0.001], [[1.0, 2.0, 3.0]])
    """

    matrix: np.ndarray
    covariance: np.ndarray
    parameter_names: tuple
    origin: np.ndarray
    units: str = "m"
    crs: str | None = None
    inputs: tuple = ()
    method: str = ""
    labkit_version: str = __version__

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the parameters (inf: not determined)."""
        return np.sqrt(np.diag(self.covariance))

    def apply(self, points) -> np.ndarray:
        """Map points of the moved epoch into the reference frame."""
        return apply_transform(self.matrix, points)

    def _report(self):
        def std_text(name, s):
            if not np.isfinite(s):
                return f"{name} not determined"
            if name == "scale":
                return f"scale {s * 1e6:.3g} ppm"
            return f"{name} {length_text(s)}" if name[0] == "t" else f"{name} {np.degrees(s) * 3600:.3g} arcsec"

        params = ", ".join(std_text(n, s) for n, s in zip(self.parameter_names, self.std))
        rows = [("translation", ", ".join(length_text(v, sign=True) for v in self.matrix[:3, 3])),
                ("standard deviations", params),
                ("origin", ", ".join(f"{v:.3f}" for v in self.origin) + f" {self.units}"),
                ("CRS", crs_summary(self.crs))]
        rows += [(role, path) for role, path in self.inputs]
        rows.append(("written by", f"labkit {self.labkit_version}"))
        return f"Registration ({self.method or 'method not stated'})", [("", rows)]

    def inverse(self) -> "RegistrationFile":
        """The registration the other way round (reference -> moved epoch), to first order in the covariance.

        With p' = s R (p - o) + o + t, the inverse is p = R^T (p' - o') / s + o' - t about
        o' = o + t: its parameters are (-w, -t, -ds) to first order, so the covariance and
        names stay and the origin moves to o'. The inputs swap their roles.
        """
        M = self.matrix
        o2 = M[:3, 3] + M[:3, :3] @ self.origin  # = o + t
        roles = {"source": "target", "target": "source"}
        return RegistrationFile(np.linalg.inv(M), self.covariance, self.parameter_names, o2, self.units, self.crs,
                                tuple((roles.get(k, k), v) for k, v in self.inputs), self.method,
                                self.labkit_version)


def save_registration(path, registration=None, *, matrix=None, covariance=None, parameter_names=None, origin=None,
                      crs=None, inputs=None, method=None):
    """Write a registration file (JSON, atomically): matrix, covariance with names, origin, CRS, inputs, version.

    Parameters
    ----------
    path : str or Path
        The JSON file to write (``labkit register --out R`` writes ``R/registration.json``).
    registration : RegistrationResult or RegistrationFile, optional
        The result of :func:`labkit.icp` or :func:`labkit.max_consensus` (or a file read
        back). Without it, give ``matrix``, ``covariance`` and ``parameter_names``
        (e.g. from a target-based registration).
    matrix : array_like (4, 4), optional
        Moved epoch -> reference; overrides the registration's.
    covariance : array_like (p, p), optional
        Parameter covariance (m^2, rad^2); ``inf`` on the diagonal marks an undetermined parameter.
    parameter_names : sequence of str, optional
        Among ``tx ty tz rx ry rz scale``; ``tx ty tz`` are required.
    origin : array_like (3,), optional
        Point the rotations refer to (default: the registration's, else 0).
    crs : str, optional
        The inputs' CRS (``PointCloud.crs``).
    inputs : dict or sequence of (str, str), optional
        ``{"source": ..., "target": ...}``.
    method : str, optional
        Default: the registration's ``method``.

    Returns
    -------
    Path

    Raises
    ------
    LabkitError
        A matrix that is not a finite 4x4 rigid/similarity transformation, a covariance of the
        wrong shape, not symmetric or not positive semi-definite, unknown parameter names.

    References
    ----------
    .. [1] Notebook 10, section 4 and eq. 6 (the registration term of the level of detection).
    .. [2] L. Winiwarter, K. Anders, B. Hoefle (2021): M3C2-EP: Pushing the limits of 3D topographic
       point cloud change detection by error propagation. ISPRS Journal of Photogrammetry and Remote
       Sensing 178, 240-258.

    Examples
    --------
    A target-based registration (a shift with 2 mm / 2 mm / 5 mm standard deviations):

    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> from labkit import load_registration, save_registration
    >>> from labkit.transforms import make_transform
    >>> path = Path(tempfile.mkdtemp()) / "registration.json"
    >>> _ = save_registration(path, matrix=make_transform(np.eye(3), [0.1, 0.0, 0.0]),
    ...                       covariance=np.diag([2e-3, 2e-3, 5e-3]) ** 2, parameter_names=("tx", "ty", "tz"),
    ...                       crs="EPSG:25832", inputs={"source": "2016.laz", "target": "2014.laz"}, method="targets")
    >>> reg = load_registration(path)
    >>> reg.std.round(4).tolist(), reg.crs, dict(reg.inputs)["source"]
    ([0.002, 0.002, 0.005], 'EPSG:25832', '2016.laz')
    """
    path = as_path(path, "registration file")
    if registration is not None:
        matrix = registration.matrix if matrix is None else matrix
        covariance = registration.covariance if covariance is None else covariance
        parameter_names = registration.parameter_names if parameter_names is None else parameter_names
        origin = getattr(registration, "origin", None) if origin is None else origin
        method = getattr(registration, "method", "") if method is None else method
        crs = getattr(registration, "crs", None) if crs is None else crs
        inputs = getattr(registration, "inputs", None) if inputs is None else inputs
    if matrix is None or covariance is None or parameter_names is None:
        raise LabkitError("save_registration needs a registration result, or matrix, covariance and parameter_names")
    names = _check_names(parameter_names, path)
    M = _check_matrix(matrix, path)
    cov = check_covariance(covariance, len(names), f"{path}: covariance")
    o = _check_origin(np.zeros(3) if origin is None else origin, path)
    doc = {"format": FORMAT, "format_version": FORMAT_VERSION, "matrix": M.tolist(), "parameter_names": list(names),
           "covariance": [[v if np.isfinite(v) else None for v in row] for row in cov.tolist()],
           "origin": o.tolist(), "units": "m", "crs": None if crs is None else str(crs),
           "inputs": {str(k): str(v) for k, v in _pairs(inputs, path)}, "method": str(method or ""),
           "labkit_version": __version__}
    return atomic_write_text(path, _dumps(doc))


def load_registration(path) -> RegistrationFile:
    """Read a registration file written by :func:`save_registration` (or ``labkit register --out``).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    RegistrationFile
        Frozen; ``covariance`` has ``inf`` where the file says ``null`` (not determined).

    Raises
    ------
    LabkitError
        Unreadable or not JSON, another format or version, a missing or an unknown key,
        a malformed matrix, covariance, origin or parameter name.

    References
    ----------
    .. [1] Notebook 10, section 4 and eq. 6 (the registration term of the level of detection).
    .. [2] T. Bray (ed.) (2017): The JavaScript Object Notation (JSON) Data Interchange Format. RFC 8259.

    Examples
    --------
    >>> import json, tempfile
    >>> from pathlib import Path
    >>> from labkit import load_registration
    >>> path = Path(tempfile.mkdtemp()) / "registration.json"
    >>> _ = path.write_text(json.dumps({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    ...                                 "covariance": [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-4]], "sigma": 1}))
    >>> try:
    ...     load_registration(path)
    ... except Exception as exc:
    ...     print(str(exc).split(": ", 1)[1])
    not a labkit registration file (format 'labkit-registration', version 2); unknown keys: sigma
    """
    path = as_path(path, "registration file")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LabkitError(f"cannot read the registration file {path}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("format_version") != FORMAT_VERSION:
        extra = sorted(set(doc) - set(KEYS)) if isinstance(doc, dict) else []
        raise LabkitError(f"{path}: not a labkit registration file (format {FORMAT!r}, version {FORMAT_VERSION})"
                          + (f"; unknown keys: {', '.join(extra)}" if extra else ""))
    unknown, missing = sorted(set(doc) - set(KEYS)), [k for k in KEYS if k not in doc]
    if unknown or missing:
        raise LabkitError(f"{path}: " + "; ".join(
            ([f"unknown keys: {', '.join(unknown)}"] if unknown else [])
            + ([f"missing keys: {', '.join(missing)}"] if missing else [])))
    if doc["units"] != "m":
        raise LabkitError(f"{path}: units must be 'm', got {doc['units']!r}")
    names = _check_names(doc["parameter_names"], path)
    try:
        cov = np.array([[np.inf if v is None else v for v in row] for row in doc["covariance"]], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LabkitError(f"{path}: malformed covariance: {exc}") from None
    crs = doc["crs"]
    if crs is not None and not isinstance(crs, str):
        raise LabkitError(f"{path}: crs must be a string or null")
    if not isinstance(doc["inputs"], dict):
        raise LabkitError(f"{path}: inputs must be an object such as {{'source': ..., 'target': ...}}")
    cov = check_covariance(cov, len(names), f"{path}: covariance")
    return RegistrationFile(_check_matrix(doc["matrix"], path), cov, names, _check_origin(doc["origin"], path), "m",
                            crs, _pairs(doc["inputs"], path), str(doc["method"]), str(doc["labkit_version"]))


# --------------------------------------------------------------------------- checks
def _dumps(doc) -> str:
    """JSON with one key per line and a matrix row per line (readable and diff-friendly)."""
    def value(v):
        if isinstance(v, list) and v and all(isinstance(r, list) for r in v):
            return "[\n" + ",\n".join("  " + json.dumps(r) for r in v) + "\n ]"
        return json.dumps(v)

    return "{\n" + ",\n".join(f" {json.dumps(k)}: {value(v)}" for k, v in doc.items()) + "\n}\n"


def _check_names(names, where):
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise LabkitError(f"{where}: parameter_names must be a list of strings, got {names!r}")
    names = tuple(names)
    if (not {"tx", "ty", "tz"} <= set(names) or not set(names) <= set(NAMES)
            or len(set(names)) != len(names)):
        raise LabkitError(f"{where}: parameter_names must hold tx, ty, tz once each and optionally rx, ry, rz, "
                          f"scale; got {names}")
    return names


def _check_matrix(matrix, where):
    try:
        M = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"{where}: matrix must be a 4x4 list of numbers") from None
    if M.shape != (4, 4) or not np.isfinite(M).all() or not np.allclose(M[3], [0, 0, 0, 1]):
        raise LabkitError(f"{where}: matrix must be a finite 4x4 transformation with last row 0 0 0 1")
    R = M[:3, :3]
    s = np.cbrt(np.linalg.det(R))
    if not (s > 0 and np.allclose(R @ R.T, s**2 * np.eye(3), atol=1e-6 * s**2)):
        raise LabkitError(f"{where}: matrix must be a rotation (times a scale) and a shift, not a general 4x4")
    return M


def check_covariance(cov, p, what="covariance", allow_inf=True):
    """A p x p covariance as float array: symmetric, positive semi-definite; ``inf`` on the diagonal
    (a parameter not determined, if ``allow_inf``) with its row and column set to 0 off the diagonal.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.file import check_covariance
    >>> check_covariance(np.diag([1e-4, np.inf]), 2).tolist()
    [[0.0001, 0.0], [0.0, inf]]
    """
    try:
        S = np.array(cov, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"{what} must be a {p} x {p} matrix of numbers") from None
    if S.shape != (p, p):
        raise LabkitError(f"{what} must be {p} x {p} (one row per parameter), got shape {S.shape}")
    loose = np.isinf(np.diag(S)) & (np.diag(S) > 0) & bool(allow_inf)
    core = S[np.ix_(~loose, ~loose)]
    if not np.isfinite(core).all() or np.isnan(S).any():
        raise LabkitError(f"{what} contains NaN or infinite entries (inf is allowed only on the diagonal, for a "
                          "parameter not determined)" if allow_inf else f"{what} contains NaN or infinite entries")
    if not np.allclose(core, core.T, rtol=1e-8, atol=1e-12 * max(1.0, np.abs(core).max(initial=0))):
        raise LabkitError(f"{what} must be symmetric")
    if core.size:
        lam = np.linalg.eigvalsh(0.5 * (core + core.T))
        if lam[0] < -1e-9 * max(lam[-1], 1e-300):
            raise LabkitError(f"{what} must be positive semi-definite; smallest eigenvalue {lam[0]:.3g}")
    S[loose, :] = S[:, loose] = 0.0
    S[loose, loose] = np.inf
    return S


def _check_origin(origin, where):
    try:
        o = np.array(origin, dtype=np.float64)
    except (TypeError, ValueError):
        o = np.full(1, np.nan)
    if o.shape != (3,) or not np.isfinite(o).all():
        raise LabkitError(f"{where}: origin must be 3 finite numbers")
    return o


def _pairs(inputs, where):
    if inputs is None:
        return ()
    items = inputs.items() if isinstance(inputs, dict) else inputs
    try:
        pairs = tuple((str(k), str(v)) for k, v in items)
    except (TypeError, ValueError):
        raise LabkitError(f"{where}: inputs must map a role (source, target) to a file name") from None
    return pairs
