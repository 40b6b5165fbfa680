"""Synthetic airborne laser scanning (ALS) test regions with two epochs and known truth.

The regions follow the list of test areas in the registration study (step 1): well
constrained in XYZ, only in XZ (ridges along y), only in YZ (ridges along x),
XY with a weak Z, forest, field, water, road, a building demolished or newly
built, trees felled or planted. Each region is built as a surface model in the
target (2014) frame; the two epochs sample it independently and the source
(2016) epoch is moved by the inverse of a known transformation, so that

    target surface = truth(source).

``dim=True`` replaces the 2016 ALS epoch by a dense-image-matching cloud:
about 100 pts/m^2, crown surface only (no ground under trees), large noise on
textureless materials and rounded building edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.checks import as_rng, choice, positive
from ..core.report import ReportMixin, fmt
from ..cloud import PointCloud
from ..core.errors import LabkitError
from ..transforms import angles_from_rotation, apply_transform, invert, make_transform, rotation_from_angles
from . import _als_scene as S

REGIONS: tuple[str, ...] = (
    "xyz", "xz", "yz", "xy", "forest", "field", "water", "road",
    "demolished", "new_building", "trees_felled", "trees_planted",
)
#: Regions meant for large areas at low density (not in :data:`REGIONS`, whose scenes fit 30-60 m).
SPARSE_REGIONS: tuple[str, ...] = ("hills",)

CELL = 20.0  # layout cell (m): one building or tree group per cell
T2014, T2016 = 8.27e7, 1.458e8  # adjusted standard GPS time (s) of the two campaigns

_INFO = {
    "xyz": ((True, True, True),
            "Village on sloped, undulating terrain: gable roofs with ridges along x and along y, hip and "
            "pyramid roofs, a flat roof, a tree group. Every direction is constrained. Change: tree crowns "
            "grow and sway."),
    "xz": ((True, False, True),
           "Rows of long halls with gable roofs, ridges along y, running through the whole region on flat "
           "terrain, a road along y between two rows. No surface has a y component in its normal: X and Z are "
           "constrained, Y is not (any shift along y fits equally well)."),
    "yz": ((False, True, True),
           "Rows of long halls with gable roofs, ridges along x, running through the whole region on flat "
           "terrain, a road along x. No surface has an x component in its normal: Y and Z are constrained, "
           "X is not."),
    "xy": ((True, True, True),
           "Old town with steep roofs (55-62 deg) with ridges along x and y and steep pyramid roofs, tree groups; "
           "the open ground is covered by low vegetation that grew 0.2 m between the epochs. X and Y are strongly "
           "constrained by the steep roof planes; Z rests mainly on those planes (|n_z| about 0.5) and the few "
           "walls carry none, so Z is the weakest direction (still determined) and biased if the grown "
           "vegetation is used."),
    "forest": ((False, False, True),
               "Closed forest on gently undulating terrain (amplitude 0.3 m): crowns with first, intermediate and "
               "last returns, ground from last returns only. Only the crowns vary in x and y, and they grow and "
               "sway between the epochs; the terrain constrains Z (XY at most very weakly)."),
    "field": ((False, False, True),
              "Flat, rough arable field (surface roughness about 5 cm, independent per epoch). Only Z is "
              "constrained; X and Y are undetermined."),
    "water": ((True, True, True),
              "Pond with steep banks (1:2, 1.8 m high) in a flat meadow, a few trees on the shore. Water gives "
              "few and noisy returns (class 9) and its level rose 7 cm between the epochs. Z is constrained by "
              "the meadow, X and Y only weakly by the bank ring."),
    "road": ((False, False, True),
             "Straight, very flat road along x (class 11) between grass verges and a field, flat terrain. Only Z "
             "is constrained; X and Y are undetermined."),
    "demolished": ((True, True, True),
                   "Village as in 'xyz' (flat terrain) in which a large hip-roofed building present in 2014 was "
                   "demolished by 2016 (bare ground). The remaining buildings (ridges along x and y) fix the shift; "
                   "the missing building pulls a plain ICP."),
    "new_building": ((True, True, True),
                     "Village as in 'xyz' (flat terrain) in which a large hip-roofed building was built between "
                     "2014 and 2016 on former open ground. Stable buildings with ridges along x and y fix the "
                     "shift; the new building pulls a plain ICP."),
    "trees_felled": ((True, True, True),
                     "Village as in 'xyz' (flat terrain) with a group of large trees present in 2014 and felled by "
                     "2016; the clearing is covered by slash and regrowth about 0.8 m high (classes 3/4). Stable "
                     "buildings fix the shift; the lost crowns and the regrowth pull a plain ICP."),
    "trees_planted": ((True, True, True),
                      "Village as in 'xyz' (flat terrain) with a group of young trees (4-7 m) planted between 2014 "
                      "and 2016 on open ground. Stable buildings fix the shift; the new crowns pull a plain ICP."),
    "hills": ((True, True, True),
              "Bare hilly terrain for sparse ALS (use e.g. size=(200, 200), density=0.5-1): 30-40 m of relief "
              "from three long waves (wavelengths 120-250 m) on a regional slope, no buildings or trees. "
              "Every direction is constrained by the slopes, X and Y much more weakly than Z; at 1 pt/m^2 "
              "the neighbourhoods of the normals span several metres of curved ground."),
}


@dataclass(frozen=True, eq=False, repr=False)
class EpochPair(ReportMixin):
    """Two epochs of a synthetic ALS region with the transformation between them.

    Attributes
    ----------
    source : PointCloud
        Epoch 2 ("ALS 2016"), or the dense-image-matching cloud ("DIM 2016") with ``dim=True``.
    target : PointCloud
        Epoch 1 ("ALS 2014"), the ALS base.
    truth : ndarray (4, 4)
        Maps source coordinates onto the target surface in the caller's (UTM) frame:
        ``target ~ R @ source + t``; equals ``RegistrationResult.matrix`` of a perfect registration.
    region : str
        One of :data:`REGIONS`.
    constrained : tuple of bool
        Whether the region's stable geometry constrains X, Y, Z.
    description : str
        What the region contains and what changed between the epochs.
    origin : ndarray (3,)
        The scene's local origin (south-west corner of the area, terrain level).
    centre : ndarray (3,)
        The rotation centre (origin + centre of the area); ``translation`` and
        ``rotation`` refer to it: ``p' = R (p - centre) + centre + translation``.

    Examples
    --------
    >>> from labkit.synthetic import als_epochs
    >>> pair = als_epochs("xyz", size=(20.0, 20.0), density=2.0, rng=0)
    >>> type(pair).__name__, pair.region, pair.truth.shape, len(pair.source) > 0
    ('EpochPair', 'xyz', (4, 4), True)
    """

    source: PointCloud
    target: PointCloud
    truth: np.ndarray
    region: str
    constrained: tuple
    description: str
    origin: np.ndarray
    centre: np.ndarray | None = None

    @property
    def rotation(self) -> np.ndarray:
        """The 3x3 rotation of ``truth``."""
        return self.truth[:3, :3].copy()

    @property
    def translation(self) -> np.ndarray:
        """The true shift (dX, dY, dZ) about ``centre`` (the ``shift`` argument)."""
        c = self.origin if self.centre is None else self.centre
        return self.truth[:3, 3] + self.truth[:3, :3] @ c - c

    def _report(self):
        ang = np.degrees(angles_from_rotation(self.rotation)) * 3600
        area = np.prod(np.ptp(self.target.xyz[:, :2], axis=0))
        rows = [
            ("region", self.region),
            ("target", f"{self.target.name}: {len(self.target)} points, {len(self.target) / area:.1f} pts/m^2"),
            ("source", f"{self.source.name}: {len(self.source)} points, {len(self.source) / area:.1f} pts/m^2"),
            ("true shift dX, dY, dZ", fmt(self.translation, 4, "m")),
            ("true rotation rx, ry, rz", fmt(ang, 2, "arcsec")),
            ("constrained X, Y, Z", ", ".join("yes" if c else "NO" for c in self.constrained)),
            ("origin", fmt(self.origin, 3, "m")),
        ]
        return f"Synthetic ALS epochs: {self.region}", [("", rows), ("Description", [("", self.description)])]


# --------------------------------------------------------------------------- public API
def als_scene(region: str = "xyz", *, size=(60.0, 60.0), density=20.0, rng=None,
              origin=(600000.0, 5400000.0, 300.0)) -> PointCloud:
    """One ALS epoch ("ALS 2014") of a named test region.

    Parameters
    ----------
    region : str
        One of :data:`REGIONS`.
    size : (float, float)
        Extent in x and y (m); the layout is built from 20 m cells.
    density : float
        Pulse density (first returns per m^2) on land; vegetation adds later returns.
    rng : int or numpy.random.Generator, optional
    origin : (3,) float
        South-west corner of the area; coordinates are ``origin + local``.

    Examples
    --------
    >>> from labkit.synthetic import als_scene
    >>> cloud = als_scene("xyz", size=(20.0, 20.0), density=2.0, rng=0)
    >>> len(cloud) > 500, sorted(cloud.attributes)[:3]
    (True, ['classification', 'gps_time', 'intensity'])
    """
    return als_epochs(region, size=size, density=density, rng=rng, origin=origin).target


def als_epochs(region: str = "xyz", *, shift=(0.23, -0.17, 0.11), rotation_deg=None,
               size=(60.0, 60.0), density=20.0, source_density=None, dim=False,
               rng=None, origin=(600000.0, 5400000.0, 300.0), layout_rng=None) -> EpochPair:
    """Two epochs of a named test region with a known transformation (the registration study, steps 1 and 1.5).

    Parameters
    ----------
    region : str
        One of :data:`REGIONS` or :data:`SPARSE_REGIONS` ('hills': sparse hilly terrain, meant for
        e.g. ``size=(200, 200), density=0.8``).
    shift : (3,) float
        True translation (m) that maps the source onto the target (about the area centre).
    rotation_deg : (3,) float, optional
        True rotation angles (rx, ry, rz) in degrees, ``R = Rz Ry Rx``, about the area centre
        (each at most 10 degrees).
    size : (float, float)
        Extent in x and y (m).
    density : float
        ALS pulse density (pts/m^2) of the target and, without ``dim``, of the source.
    source_density : float, optional
        Density of the source; default ``density`` (ALS) or 100 pts/m^2 (DIM).
    dim : bool
        Make the source a dense-image-matching cloud instead of a second ALS epoch.
    rng : int or numpy.random.Generator, optional
    origin : (3,) float
        South-west corner of the area (UTM-sized by default).
    layout_rng : int or numpy.random.Generator, optional
        Seed of the surface model alone (buildings, trees, terrain); ``rng`` then draws only the
        sampling and noise of the two epochs. Monte Carlo runs over one fixed scene use it.

    Returns
    -------
    EpochPair
        ``truth`` maps ``source`` onto ``target``: ``apply_transform(pair.truth, pair.source.xyz)``
        lies on the target surface.

    Examples
    --------
    >>> from labkit.synthetic import als_epochs
    >>> pair = als_epochs("xyz", size=(20.0, 20.0), density=2.0, rng=0)
    >>> pair.translation.round(2).tolist(), pair.truth.shape
    ([0.23, -0.17, 0.11], (4, 4))
    """
    region = choice(region, REGIONS + SPARSE_REGIONS, "region")
    size, density, origin, shift, angles = _check_args(size, density, origin, shift, rotation_deg)
    src_density = density if source_density is None and not dim else (
        100.0 if source_density is None else positive(source_density, "source_density"))
    seeds = as_rng(rng).integers(0, 2**63 - 1, size=3)
    layout_rng_, target_rng, source_rng = (np.random.default_rng(s) for s in seeds)
    layout_rng = layout_rng_ if layout_rng is None else as_rng(layout_rng)
    # Build the surface model in the target frame
    scene = _LAYOUTS[region](size, layout_rng)
    # Sample the target on the area, the source over a margin so that it still fills the area when moved
    margin = 1.0 + float(np.linalg.norm(shift)) + np.sin(np.abs(angles).max()) * float(np.hypot(*size))
    box = ((-margin, size[0] + margin), (-margin, size[1] + margin))
    tgt = S.sample_als(scene, ((0.0, size[0]), (0.0, size[1])), density, 0, target_rng)
    src = (S.sample_dim if dim else S.sample_als)(scene, box, src_density, 1, source_rng)
    # The truth, as a motion about the area centre
    centre_local = np.array([size[0] / 2, size[1] / 2, 0.0])
    T_local = make_transform(rotation_from_angles(*angles), shift)
    src.xyz = apply_transform(invert(T_local), src.xyz, origin=centre_local)
    centre = origin + centre_local
    R = T_local[:3, :3]
    truth = make_transform(R, shift + centre - R @ centre)
    constrained, description = _INFO[region]
    return EpochPair(
        source=_to_cloud(src, size, origin, T2016, "DIM 2016" if dim else "ALS 2016", source_rng),
        target=_to_cloud(tgt, size, origin, T2014, "ALS 2014", target_rng),
        truth=truth, region=region, constrained=constrained, description=description,
        origin=origin.copy(), centre=centre,
    )


# --------------------------------------------------------------------------- checks, output
def _check_args(size, density, origin, shift, rotation_deg):
    try:
        size = tuple(float(s) for s in size)
    except (TypeError, ValueError):
        raise LabkitError(f"size must be two numbers (x, y extent in m), got {size!r}") from None
    if len(size) != 2 or not all(np.isfinite(s) and s >= 5.0 for s in size):
        raise LabkitError(f"size must be two finite extents of at least 5 m, got {size!r}")
    density = positive(density, "density")
    vecs = []
    for name, val in (("origin", origin), ("shift", shift), ("rotation_deg", rotation_deg or (0, 0, 0))):
        arr = np.asarray(val, dtype=np.float64)
        if arr.shape != (3,) or not np.isfinite(arr).all():
            raise LabkitError(f"{name} must be three finite numbers, got {val!r}")
        vecs.append(arr)
    if np.abs(vecs[2]).max() > 10.0:
        raise LabkitError(f"rotation_deg must be small (each angle within +-10 degrees), got {rotation_deg!r}")
    return size, density, vecs[0], vecs[1], np.radians(vecs[2])


def _to_cloud(samples, size, origin, t0, name, rng) -> PointCloud:
    """Crop the samples to the area (in their own frame), move to the origin and add attributes."""
    xyz = samples.xyz
    inside = (xyz[:, 0] >= 0) & (xyz[:, 0] <= size[0]) & (xyz[:, 1] >= 0) & (xyz[:, 1] <= size[1])
    mat, rn = samples.mat[inside], samples.return_number[inside]
    pulse = samples.pulse_xy[inside] + origin[:2]
    t, strip = S.gps_time(pulse, t0)
    attrs = {
        "classification": S.classify(mat, samples.height[inside]),
        "intensity": S.intensity(mat, rn, rng),
        "return_number": rn,
        "number_of_returns": samples.number_of_returns[inside],
        "gps_time": t,
        "point_source_id": strip,
    }
    return PointCloud(xyz[inside] + origin, attrs, name=name)


# --------------------------------------------------------------------------- layouts
def _cells(size):
    nx, ny = max(1, round(size[0] / CELL)), max(1, round(size[1] / CELL))
    wx, wy = size[0] / nx, size[1] / ny
    centres = [((i + 0.5) * wx, (j + 0.5) * wy) for j in range(ny) for i in range(nx)]
    return centres, (wx, wy)


def _building(kind, centre, cell, terrain, rng, *, steep=False, epochs=(True, True)):
    """One building filling part of a layout cell."""
    wx, wy = cell
    long_, short = rng.uniform(0.6, 0.8), rng.uniform(0.4, 0.55)
    fx, fy = {"gable_x": (long_, short), "gable_y": (short, long_), "pyramid": (0.6, 0.6)}.get(
        kind, (rng.uniform(0.45, 0.75), rng.uniform(0.45, 0.75)))
    if steep:
        fx, fy = fx + 0.12, fy + 0.12
    hx, hy = min(fx * wx / 2, wx / 2 - 1.5), min(fy * wy / 2, wy / 2 - 1.5)
    cx = centre[0] + rng.uniform(-1, 1) * max(wx / 2 - hx - 1.5, 0.0)
    cy = centre[1] + rng.uniform(-1, 1) * max(wy / 2 - hy - 1.5, 0.0)
    low, high = (55, 62) if steep else ((25, 35) if kind in ("hip", "pyramid") else (28, 45))
    pitch = rng.uniform(low, high)
    if kind == "flat":
        eave, slope = rng.uniform(6, 11), 0.0
    else:
        eave, slope = rng.uniform(3, 6.5), np.tan(np.radians(pitch))
    base = float(terrain.z(np.array(cx), np.array(cy)))
    kind = "hip" if kind == "pyramid" else kind
    return S.Building(kind, cx, cy, hx, hy, base, eave, slope, epochs)


def _tree_group(centre, cell, n, terrain, rng, *, height=(10, 20), radius=(2.5, 4.0)):
    """n trees scattered in a cell (arrays for :class:`Trees`)."""
    wx, wy = cell
    cx = centre[0] + rng.uniform(-0.3, 0.3, n) * wx
    cy = centre[1] + rng.uniform(-0.3, 0.3, n) * wy
    return _trees(cx, cy, terrain, rng, height, radius)


def _trees(cx, cy, terrain, rng, height, radius):
    H = rng.uniform(*height, len(cx))
    a = rng.uniform(0.3, 0.42, len(cx)) * H
    zc = terrain.z(cx, cy) + H - a
    return S.Trees(cx, cy, zc, rng.uniform(*radius, len(cx)), a)


def _join(*groups) -> S.Trees:
    groups = [g for g in groups if len(g)]
    if not groups:
        return S.Trees()
    return S.Trees(*(np.concatenate([getattr(g, k) for g in groups]) for k in ("cx", "cy", "zc", "r", "a")))


def _grow(trees: S.Trees, rng) -> S.Trees:
    """The same crowns two years later: grown a little and swayed by wind."""
    n = len(trees)
    da = rng.uniform(0.05, 0.2, n)
    return S.Trees(trees.cx + rng.normal(0, 0.1, n), trees.cy + rng.normal(0, 0.1, n),
                   trees.zc + rng.uniform(0.05, 0.25, n), trees.r + rng.uniform(0.0, 0.25, n), trees.a + da)


def _hilly(size, rng, amplitude=0.6, slope=(0.04, -0.03)):
    waves = tuple((amplitude * rng.uniform(0.5, 1.0), 2 * np.pi / rng.uniform(40, 80) * np.cos(th),
                   2 * np.pi / rng.uniform(40, 80) * np.sin(th), rng.uniform(0, 2 * np.pi))
                  for th in rng.uniform(0, np.pi, 2))
    return S.Terrain((size[0] / 2, size[1] / 2), slope, waves)


def _hills(size, rng, relief=(30.0, 40.0), wavelength=(120.0, 250.0)):
    """Long waves on a regional slope, scaled to a relief (max - min over the area) drawn from ``relief``."""
    th = rng.uniform(0, np.pi, 3)
    lam = rng.uniform(*wavelength, 3)
    waves = [(1.0, 2 * np.pi / w * np.cos(a), 2 * np.pi / w * np.sin(a), rng.uniform(0, 2 * np.pi))
             for w, a in zip(lam, th)]
    slope = tuple(rng.uniform(-0.05, 0.05, 2))
    probe = S.Terrain((size[0] / 2, size[1] / 2), slope, tuple(waves))
    gx, gy = np.meshgrid(np.linspace(0, size[0], 41), np.linspace(0, size[1], 41))
    f = rng.uniform(*relief) / np.ptp(probe.z(gx, gy))  # scale the whole surface to the drawn relief
    waves = tuple((f * A, kx, ky, ph) for A, kx, ky, ph in waves)
    return S.Terrain((size[0] / 2, size[1] / 2), (f * slope[0], f * slope[1]), waves)


def _layout_hills(size, rng):
    return S.Scene(size, _hills(size, rng))


def _flat(size):
    return S.Terrain((size[0] / 2, size[1] / 2))


_TOWN_KINDS = ("gable_x", "gable_y", "hip", "trees", "flat", "gable_y", "gable_x", "pyramid", "open")
_OLD_TOWN_KINDS = ("gable_x", "gable_y", "pyramid", "trees", "hip", "gable_y", "gable_x", "trees", "pyramid")


def _town(size, rng, terrain, *, reserved=0, steep=False):
    """Buildings and tree groups on the layout cells; the first ``reserved`` cells stay empty."""
    centres, cell = _cells(size)
    free = centres[reserved:]
    order = rng.permutation(len(free))
    buildings, groups = [], []
    kinds = _OLD_TOWN_KINDS if steep else _TOWN_KINDS
    for k, i in enumerate(order):
        kind = kinds[k % len(kinds)]
        if kind == "trees":
            groups.append(_tree_group(free[i], cell, int(rng.integers(2, 5)), terrain, rng))
        elif kind != "open":
            buildings.append(_building(kind, free[i], cell, terrain, rng, steep=steep))
    return buildings, _join(*groups), centres[:reserved], cell


def _layout_town(size, rng):
    terrain = _hilly(size, rng)
    buildings, trees, _, _ = _town(size, rng, terrain)
    return S.Scene(size, terrain, tuple(buildings), (trees, _grow(trees, rng)))


def _layout_steep(size, rng):
    terrain = _hilly(size, rng, amplitude=0.3, slope=(0.02, 0.01))
    buildings, trees, _, _ = _town(size, rng, terrain, steep=True)
    return S.Scene(size, terrain, tuple(buildings), (trees, _grow(trees, rng)), low_veg=(0.25, 0.45))


def _layout_rows(axis):
    """Long gable-roofed halls running through the region along ``axis`` (x or y) on flat ground."""
    def layout(size, rng):
        terrain = _flat(size)
        across, along = (1, 0) if axis == "x" else (0, 1)
        n = max(1, round(size[across] / CELL))
        w = size[across] / n
        buildings = []
        for i in range(n):
            c = (i + 0.5) * w + rng.uniform(-0.5, 0.5)
            half = rng.uniform(0.55, 0.75) * w / 2
            through = size[along]  # extends half a region beyond both ends: no gable walls inside
            cx, cy, hx, hy = (size[0] / 2, c, through, half) if axis == "x" else (c, size[1] / 2, half, through)
            kind = "gable_x" if axis == "x" else "gable_y"
            slope = np.tan(np.radians(rng.uniform(28, 45)))
            buildings.append(S.Building(kind, cx, cy, hx, hy, 0.0, rng.uniform(3, 6.5), slope))
        roads = ((axis, w, 1.5),) if n >= 2 else ()  # a road along the rows, between the first two
        return S.Scene(size, terrain, tuple(buildings), roads=roads)
    return layout


def _layout_forest(size, rng):
    terrain = _hilly(size, rng, amplitude=0.3, slope=(0.0, 0.0))
    step = 6.5
    gx, gy = np.meshgrid(np.arange(-4, size[0] + 5, step), np.arange(-4, size[1] + 5, step))
    cx, cy = gx.ravel() + rng.uniform(-1.5, 1.5, gx.size), gy.ravel() + rng.uniform(-1.5, 1.5, gx.size)
    keep = rng.random(cx.size) > 0.12  # a few gaps
    trees = _trees(cx[keep], cy[keep], terrain, rng, (14, 24), (2.8, 4.2))
    return S.Scene(size, terrain, (), (trees, _grow(trees, rng)))


def _layout_field(size, rng):
    return S.Scene(size, _flat(size), fields=((-1e4, 1e4, -1e4, 1e4),))


def _layout_water(size, rng):
    terrain = _flat(size)
    ax, ay = 0.32 * size[0], 0.26 * size[1]
    cx, cy = 0.5 * size[0] + rng.uniform(-2, 2), 0.45 * size[1] + rng.uniform(-2, 2)
    water = (cx, cy, ax, ay, 3.0, 0.5, -1.8, -1.73)
    ang = rng.uniform(0.6, 1.4, 4) * np.pi / 2 + np.pi / 4
    rr = 1.0 + 7.0 / min(ax, ay)
    trees = _trees(cx + rr * ax * np.cos(ang), cy + rr * ay * np.sin(ang), terrain, rng, (8, 15), (2.0, 3.5))
    return S.Scene(size, terrain, (), (trees, _grow(trees, rng)), water=water)


def _layout_road(size, rng):
    mid = size[1] / 2
    return S.Scene(size, _flat(size), roads=(("x", mid, 3.5),), fields=((-1e4, 1e4, mid + 8.0, 1e4),))


def _layout_change(change):
    """A village on flat ground whose first layout cell(s) hold the changing object."""
    def layout(size, rng):
        terrain = _flat(size)
        centres, (wx, wy) = _cells(size)
        nx = max(1, round(size[0] / CELL))
        reserved = 2 if nx >= 2 else 1
        buildings, trees, spots, cell = _town(size, rng, terrain, reserved=reserved)
        cx = np.mean([c[0] for c in spots])
        cy = spots[0][1]
        hx, hy = reserved * wx / 2 - 2.0, wy / 2 - 3.0
        trees_t, trees_s, patches = trees, _grow(trees, rng), ()
        if change in ("demolished", "new_building"):
            present = (True, False) if change == "demolished" else (False, True)
            buildings.append(S.Building("hip", cx, cy, hx, hy, 0.0, 8.0, np.tan(np.radians(30)), present))
        else:
            big = change == "trees_felled"
            n = 4 * reserved if big else 5 * reserved
            gx = cx + rng.uniform(-hx, hx, n)
            gy = cy + rng.uniform(-hy, hy, n)
            group = _trees(gx, gy, terrain, rng, (14, 22) if big else (4, 7), (3.0, 4.5) if big else (1.2, 2.2))
            if big:  # the clearing is covered by slash and regrowth (about 0.8 m) in 2016
                trees_t = _join(trees, group)
                patches = ((cx - hx - 2, cx + hx + 2, cy - hy - 2, cy + hy + 2, 0.0, 0.8),)
            else:
                trees_s = _join(trees_s, group)
        return S.Scene(size, terrain, tuple(buildings), (trees_t, trees_s), patches=patches)
    return layout


_LAYOUTS = {
    "xyz": _layout_town,
    "xz": _layout_rows("y"),
    "yz": _layout_rows("x"),
    "xy": _layout_steep,
    "forest": _layout_forest,
    "field": _layout_field,
    "water": _layout_water,
    "road": _layout_road,
    "demolished": _layout_change("demolished"),
    "new_building": _layout_change("new_building"),
    "trees_felled": _layout_change("trees_felled"),
    "trees_planted": _layout_change("trees_planted"),
    "hills": _layout_hills,
}
