"""Registration uncertainty for :func:`labkit.m3c2` (module ``labkit.change``, eq. 5-6 of notebook 10).

The registration term of the level of detection, n^T Sigma_t n, from a 3x3 shift
covariance or from a registration's parameter covariance (angles and shift), and a
small JSON form of a registration so that ``labkit change --registration`` can read it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import LabkitError
from ..registration.file import check_covariance, load_registration as _load_file, save_registration as _save_file
from ..transforms import apply_transform


def registration_variance(registration, points, normals, held_std=None) -> np.ndarray:
    """The registration term n^T Sigma_t n of eq. 5 at each point (eq. 6 for a rigid registration).

    Parameters
    ----------
    registration : None, (3, 3) array_like or RegistrationResult
        Covariance of the shift (m^2), or a registration whose ``covariance`` refers to
        ``parameter_names`` ('tx', 'ty', 'tz' and optionally 'rx', 'ry', 'rz' in radians
        about ``origin``).
    points : ndarray (m, 3)
        Where the displacement is propagated (the core points, caller's frame).
    normals : ndarray (m, 3)
        Unit normals.
    held_std : dict of str -> float, optional
        A prior standard deviation for parameters the registration did not determine (infinite
        variance), e.g. ``{"rz": np.radians(0.02)}`` for a rotation ICP held at its initial
        value. Without it such a parameter makes the term infinite wherever it moves the
        point along the normal. Its covariance with the other parameters is taken as zero
        (ICP already adds the prior's effect on them to their covariance).

    Returns
    -------
    ndarray (m,)
        Variance of the registration displacement along the normal; inf where an
        undetermined parameter (infinite variance) has a non-zero weight; NaN for NaN normals.

    References
    ----------
    .. [1] Notebook 10, eq. 5 and section 4 (the registration term); eq. 6 of the
       :mod:`labkit.change` module notes (a rigid registration).
    .. [2] D. Lague, N. Brodu, J. Leroux (2013): Accurate 3D comparison of complex topography with
       terrestrial laser scanner: application to the Rangitikei canyon (N-Z). ISPRS Journal of
       Photogrammetry and Remote Sensing 82, 10-26, doi:10.1016/j.isprsjprs.2013.04.009.

    Examples
    --------
    A 1 cm isotropic shift uncertainty seen along a vertical normal:

    >>> import numpy as np
    >>> from labkit.change.m3c2 import registration_variance
    >>> var = registration_variance(np.eye(3) * 0.01**2, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    >>> np.sqrt(var).round(4).tolist()
    [0.01]
    """
    m = len(normals)
    if registration is None:
        return np.zeros(m)
    if hasattr(registration, "covariance") and hasattr(registration, "parameter_names"):
        names = tuple(registration.parameter_names)
        Sigma = _with_priors(_check_covariance(registration.covariance, len(names), allow_inf=True), names,
                             held_std)
        G = np.zeros((m, len(names)))
        for axis, name in enumerate(("tx", "ty", "tz")):
            G[:, names.index(name)] = normals[:, axis]  # d(n . dp) / dt = n
        if "rx" in names:
            lever = np.cross(np.asarray(points) - np.asarray(registration.origin), normals)  # (eq. 6)
            for axis, name in enumerate(("rx", "ry", "rz")):
                G[:, names.index(name)] = lever[:, axis]  # n . (dw x a) = dw . (a x n)
        if "scale" in names:  # p' = (1 + ds) R (p - o) + ...: d(n . dp) / ds = n . (p - o)
            G[:, names.index("scale")] = np.einsum("ij,ij->i", np.asarray(points) - np.asarray(registration.origin),
                                                   normals)
    else:
        Sigma = _check_covariance(registration, 3, allow_inf=False)
        G = np.asarray(normals, dtype=np.float64)
    return _quadratic_form(G, Sigma)


@dataclass(frozen=True, eq=False)
class RegistrationCovariance:
    """A registration as read from JSON: the 4x4 matrix (compared -> reference) and its covariance.

    It has the fields :func:`registration_variance` reads from a ``RegistrationResult``
    (``covariance``, ``parameter_names``, ``origin``) and ``apply``, so either can be passed on.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.change.m3c2 import RegistrationCovariance
    >>> from labkit.transforms import make_transform
    >>> reg = RegistrationCovariance(make_transform(np.eye(3), [0.0, 0.0, 0.1]), np.eye(3) * 1e-4)
    >>> reg.apply(np.zeros((1, 3))).tolist(), reg.parameter_names
    ([[0.0, 0.0, 0.1]], ('tx', 'ty', 'tz'))
    """

    matrix: np.ndarray
    covariance: np.ndarray
    parameter_names: tuple = ("tx", "ty", "tz")
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, points) -> np.ndarray:
        """Map compared points into the reference frame."""
        return apply_transform(self.matrix, points)


def save_registration(result, path) -> Path:
    """Write a registration (``RegistrationResult`` or :class:`RegistrationCovariance`) as JSON, atomically.

    The registration file of :func:`labkit.save_registration` (matrix compared -> reference,
    covariance with parameter names, ``null`` for an undetermined entry, origin, CRS, inputs,
    version); :func:`load_registration` reads it back.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> from labkit.change.m3c2 import RegistrationCovariance, load_registration, save_registration
    >>> from labkit.transforms import make_transform
    >>> reg = RegistrationCovariance(make_transform(np.eye(3), [0.0, 0.0, 0.1]), np.diag([1e-4, 1e-4, np.inf]))
    >>> path = save_registration(reg, Path(tempfile.mkdtemp()) / "registration.json")
    >>> load_registration(path).covariance.diagonal().tolist()  # inf is written as null and read back
    [0.0001, 0.0001, inf]
    """
    return _save_file(path, result)


def load_registration(path) -> RegistrationCovariance:
    """Read a registration JSON: the file :func:`save_registration` writes, or a bare 3x3 shift covariance.

    The registration file (with ``format``) is read by :func:`labkit.load_registration`
    (unknown keys refused) and comes back as a :class:`labkit.RegistrationFile`.

    Accepted: ``{"matrix": 4x4 (optional, default identity), "covariance": 3x3}`` (a shift
    covariance in m^2), the same with ``parameter_names`` and ``origin`` for a rigid
    registration, or a plain JSON 3x3 list. ``null`` in the covariance means undetermined (inf).

    Examples
    --------
    A bare 3x3 shift covariance is a registration too (identity matrix):

    >>> import json, tempfile
    >>> from pathlib import Path
    >>> from labkit.change.m3c2 import load_registration
    >>> path = Path(tempfile.mkdtemp()) / "cov.json"
    >>> _ = path.write_text(json.dumps([[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 4e-4]]))
    >>> reg = load_registration(path)
    >>> reg.matrix[:3, 3].tolist(), reg.covariance.diagonal().tolist()
    ([0.0, 0.0, 0.0], [0.0001, 0.0001, 0.0004])
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LabkitError(f"cannot read the registration file {path}: {exc}") from None
    if isinstance(doc, dict) and "format" in doc:  # the registration file of labkit.save_registration
        return _load_file(path)
    if isinstance(doc, list):
        doc = {"covariance": doc}
    if not isinstance(doc, dict) or "covariance" not in doc:
        raise LabkitError(f"{path}: expected a JSON object with 'covariance' (and optionally 'matrix', "
                          "'parameter_names', 'origin') or a 3x3 list")
    try:
        cov = np.array([[np.inf if v is None else v for v in row] for row in doc["covariance"]], dtype=np.float64)
        matrix = np.array(doc.get("matrix", np.eye(4)), dtype=np.float64)
        names = tuple(doc.get("parameter_names", ("tx", "ty", "tz")))
        origin = np.array(doc.get("origin", np.zeros(3)), dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LabkitError(f"{path}: malformed registration: {exc}") from None
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all() or origin.shape != (3,):
        raise LabkitError(f"{path}: 'matrix' must be a finite 4x4 list and 'origin' 3 numbers")
    if not {"tx", "ty", "tz"} <= set(names) or not set(names) <= {"rx", "ry", "rz", "tx", "ty", "tz"}:
        raise LabkitError(f"{path}: parameter_names must hold tx, ty, tz (and optionally rx, ry, rz), got {names}")
    _check_covariance(cov, len(names), allow_inf=True)
    return RegistrationCovariance(matrix, cov, names, origin)


# --------------------------------------------------------------------------- private steps
def _with_priors(Sigma, names, held_std):
    """Sigma with an undetermined parameter's row and column replaced by its prior variance only."""
    if not held_std:
        return Sigma
    S = Sigma.copy()
    for name, std in dict(held_std).items():
        if name not in names:
            raise LabkitError(f"held_std names {name!r}, which is not one of the parameters {names}")
        if not (np.isfinite(std) and std >= 0):
            raise LabkitError(f"held_std[{name!r}] must be a finite number >= 0, got {std!r}")
        i = names.index(name)
        if np.isinf(S[i, i]):
            S[i, :] = S[:, i] = 0.0
            S[i, i] = float(std) ** 2
    return S


def _quadratic_form(G, Sigma):
    """g^T Sigma g per row of G; parameters with infinite variance make it inf where their weight is not 0."""
    loose = ~np.isfinite(np.diag(Sigma))
    S = np.where(loose[:, None] | loose[None, :], 0.0, Sigma)
    with np.errstate(invalid="ignore"):
        q = np.einsum("mi,ij,mj->m", G, S, G)
        touched = (np.abs(G[:, loose]) > 0).any(axis=1) if loose.any() else np.zeros(len(G), dtype=bool)
    return np.where(touched, np.inf, np.clip(q, 0.0, None))


def _check_covariance(cov, p, allow_inf):
    return check_covariance(cov, p, "registration_covariance", allow_inf)
