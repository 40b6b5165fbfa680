"""Epoch pairs to compare registrations on: the study's synthetic cases, or pairs listed in a file.

Every pair has ``source``, ``target``, ``region``, ``case``, and optionally ``truth`` (4x4) and
``constrained`` (the axes the data determine); :func:`labkit.registration.compare.compare_methods`
takes them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.checks import as_rng, choice
from ..core.errors import LabkitError
from ..io import read_cloud
from ..synthetic import REGIONS, als_epochs
from ..transforms import check_transform
from .references import _json_entries

__all__ = ["CASES", "CHANGE_REGIONS", "FilePair", "load_pairs", "synthetic_cases"]


CASES = ("als-als", "changes", "als-dim")
CHANGE_REGIONS = ("demolished", "new_building", "trees_felled", "trees_planted")


def synthetic_cases(regions=None, cases=CASES, *, size=(60.0, 60.0), density=10.0, dim_density=None,
                    shift=(0.23, -0.17, 0.11), rotation_deg=None, rng=None) -> dict:
    """The registration study's three cases on synthetic regions: ``{(region, case): EpochPair}``.

    ``"als-als"``: two ALS epochs of the stable regions; ``"changes"``: two ALS
    epochs of the regions with changes (demolished, new building, trees felled
    or planted); ``"als-dim"``: ALS against dense image matching on the stable
    regions. ``regions`` restricts the regions (default: all of
    :data:`labkit.synthetic.REGIONS`).

    References
    ----------
    .. [1] Seed 003, step 5 (ALS/ALS, ALS/ALS with change, ALS/DIM); notebook 07, section 1.

    Examples
    --------
    >>> from labkit.registration.compare import synthetic_cases
    >>> pairs = synthetic_cases(regions=["xyz"], cases=("als-als",), size=(20.0, 20.0), density=2.0, rng=0)
    >>> list(pairs)
    [('xyz', 'als-als')]
    """
    regions = REGIONS if regions is None else tuple(choice(r, REGIONS, "region") for r in regions)
    gen = as_rng(rng)
    out = {}
    for case in cases:
        choice(case, CASES, "case")
        for region in regions:
            if (region in CHANGE_REGIONS) != (case == "changes"):
                continue
            dim = case == "als-dim"
            out[(region, case)] = als_epochs(region, shift=shift, rotation_deg=rotation_deg, size=size,
                                             density=density, source_density=dim_density if dim else None,
                                             dim=dim, rng=gen.spawn(1)[0])
    if not out:
        raise LabkitError(f"no region among {regions} belongs to the cases {cases}")
    return out


@dataclass(frozen=True, eq=False)
class FilePair:
    """Two epochs of one region read from files (see :func:`load_pairs`).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.pairs import FilePair
    >>> pair = FilePair(np.zeros((4, 3)), np.ones((4, 3)), "tile", "epochs", constrained=(True, True, False))
    >>> pair.region, pair.constrained, pair.truth is None
    ('tile', (True, True, False), True)
    """

    source: object
    target: object
    region: str
    case: str = ""
    constrained: tuple | None = None
    truth: np.ndarray | None = None


def load_pairs(path) -> dict:
    """Read a JSON list of epoch pairs ``{(region, case): FilePair}``.

    Each entry: ``{"region": ..., "case": ..., "source": file, "target": file}``
    with optional ``"constrained": [true, false, true]``, ``"bbox": [xmin,
    ymin, xmax, ymax]`` (crop while reading) and ``"truth"``, a 4x4 matrix
    source -> target (a known transformation, e.g. of synthetic data; used as the
    reference when no other is given). Relative file names are taken relative to
    the JSON file.

    Examples
    --------
    >>> import json, tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.registration.compare import load_pairs
    >>> from labkit.io import write_cloud
    >>> folder = Path(tempfile.mkdtemp())
    >>> for name in ("e1.laz", "e2.laz"):
    ...     _ = write_cloud(PointCloud(np.random.default_rng(0).uniform(0, 10, (50, 3))), folder / name)
    >>> _ = (folder / "pairs.json").write_text(json.dumps(
    ...     [{"region": "tile", "case": "epochs", "source": "e2.laz", "target": "e1.laz"}]))
    >>> pairs = load_pairs(folder / "pairs.json")
    >>> pair = pairs[("tile", "epochs")]
    >>> list(pairs), len(pair.source), len(pair.target)
    ([('tile', 'epochs')], 50, 50)
    """
    path = Path(path)
    entries = _json_entries(path, "pairs", "pair file", "a list of epoch pairs")
    if not isinstance(entries, list):
        raise LabkitError(f"{path} is not a list of epoch pairs (got {type(entries).__name__})")
    out = {}
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not {"region", "source", "target"} <= set(e):
            raise LabkitError(f"{path}: pair {i} needs 'region', 'source' and 'target'")
        if not all(isinstance(e[k], str) for k in ("source", "target")) or not (
                e.get("constrained") is None or isinstance(e["constrained"], list)):
            raise LabkitError(f"{path}: pair {i}: 'source' and 'target' must be file names, 'constrained' a list")
        files = [(path.parent / e[k]) for k in ("source", "target")]
        src, tgt = (read_cloud(f, bbox=e.get("bbox")) for f in files)
        c = e.get("constrained")
        truth = None
        if e.get("truth") is not None:
            try:
                truth = check_transform(np.asarray(e["truth"], dtype=np.float64))
            except (LabkitError, ValueError, TypeError) as exc:
                raise LabkitError(f"{path}: pair {i}: 'truth' must be a 4x4 transformation matrix ({exc})") from None
        out[(str(e["region"]), str(e.get("case", "")))] = FilePair(
            src, tgt, str(e["region"]), str(e.get("case", "")), None if c is None else tuple(map(bool, c)), truth)
    return out
