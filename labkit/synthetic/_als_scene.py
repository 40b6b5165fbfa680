"""Geometry and sensor models behind :mod:`labkit.synthetic.als`.

A scene lives in a local frame: x, y in [0, Lx] x [0, Ly] (metres), z about 0.
It is a 2.5D first-surface model (terrain, water, roads, fields, buildings)
plus tree crowns (ellipsoids) and building walls. Two sensors sample it:

- ALS: pulses at random xy; a pulse hitting a crown gives a first return in the
  crown, maybe a second inside it and maybe a last return on the hard surface
  below; walls receive a few extra points (slightly off-nadir beams).
- DIM: dense image matching; one point per sample on the *visible* surface
  (crown tops, no ground below trees), building edges rounded by a smoothing
  kernel, large noise on textureless materials.

Everything is vectorized over points; loops run over the buildings, each on the points of the grid
cells under its footprint (cost linear in the area).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

# --------------------------------------------------------------------------- materials
# code: (name, ASPRS class, ALS sigma [m], DIM sigma [m], intensity mean, intensity sd)
MATERIALS = {
    0: ("ground", 2, 0.025, 0.04, 25000, 4000),
    1: ("road", 11, 0.015, 0.05, 11000, 1500),
    2: ("field", 2, 0.05, 0.09, 30000, 5000),
    3: ("water", 9, 0.07, 0.30, 2500, 1200),
    4: ("pitched roof", 6, 0.02, 0.035, 18000, 3000),
    5: ("flat roof", 6, 0.02, 0.10, 14000, 2000),
    6: ("wall", 6, 0.03, 0.06, 15000, 3000),
    7: ("vegetation", 5, 0.05, 0.20, 20000, 6000),
    8: ("low vegetation", 3, 0.08, 0.15, 22000, 5000),
}
GROUND, ROAD, FIELD, WATER, ROOF, FLAT_ROOF, WALL, VEG, LOW_VEG = range(9)
GRID_CELL = 10.0  # side (m) of the cells that sort the points for the per-building evaluation


def _table(col: int) -> np.ndarray:
    return np.array([MATERIALS[k][col] for k in sorted(MATERIALS)], dtype=np.float64)


# --------------------------------------------------------------------------- scene parts
@dataclass(frozen=True)
class Terrain:
    """z = sx (x - xc) + sy (y - yc) + sum A sin(kx x + ky y + phase)."""

    centre: tuple = (30.0, 30.0)
    slope: tuple = (0.0, 0.0)
    waves: tuple = ()  # (A, kx, ky, phase) each

    def z(self, x, y):
        z = self.slope[0] * (x - self.centre[0]) + self.slope[1] * (y - self.centre[1])
        for A, kx, ky, ph in self.waves:
            z = z + A * np.sin(kx * x + ky * y + ph)
        return z


@dataclass(frozen=True)
class Building:
    """A rectangular building; ``kind`` in gable_x (ridge along x), gable_y, hip, flat."""

    kind: str
    cx: float
    cy: float
    hx: float  # half extents (m)
    hy: float
    base: float  # floor level (m, local)
    eave: float  # eave height above base (m)
    slope: float  # tan(roof pitch)
    epochs: tuple = (True, True)  # present in (target, source)

    def roof(self, x, y):
        """Roof height at x, y; -inf outside the footprint."""
        dx, dy = np.abs(x - self.cx), np.abs(y - self.cy)
        inside = (dx <= self.hx) & (dy <= self.hy)
        if self.kind == "gable_x":
            rise = self.hy - dy
        elif self.kind == "gable_y":
            rise = self.hx - dx
        elif self.kind == "hip":
            rise = np.minimum(self.hx - dx, self.hy - dy)
        else:
            rise = np.zeros_like(dx)
        return np.where(inside, self.base + self.eave + self.slope * rise, -np.inf)

    def near_edge(self, x, y, r: float):
        """True within ``r`` of an eave, gable or ridge/hip line (where a smoothing kernel acts)."""
        dx, dy = np.abs(x - self.cx), np.abs(y - self.cy)
        box = (dx <= self.hx + r) & (dy <= self.hy + r)
        rim = (dx >= self.hx - r) | (dy >= self.hy - r)
        if self.kind == "gable_x":
            crease = dy <= r
        elif self.kind == "gable_y":
            crease = dx <= r
        elif self.kind == "hip":
            crease = np.abs((self.hx - dx) - (self.hy - dy)) <= 1.5 * r
            crease |= (dx <= r) if self.hx <= self.hy else (dy <= r)
        else:
            crease = np.zeros_like(box)
        return box & (rim | crease)

    @property
    def material(self) -> int:
        return FLAT_ROOF if self.kind == "flat" else ROOF

    @property
    def ridge_height(self) -> float:
        rise = {"gable_x": self.hy, "gable_y": self.hx, "hip": min(self.hx, self.hy)}.get(self.kind, 0.0)
        return self.eave + self.slope * rise


@dataclass(frozen=True)
class Trees:
    """Tree crowns as ellipsoids: centre (cx, cy, zc), horizontal radius r, vertical semi-axis a."""

    cx: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    zc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    r: np.ndarray = field(default_factory=lambda: np.zeros(0))
    a: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self):
        return len(self.cx)

    def subset(self, mask) -> "Trees":
        return Trees(self.cx[mask], self.cy[mask], self.zc[mask], self.r[mask], self.a[mask])

    def crown(self, x, y):
        """Top and bottom of the highest crown above each (x, y); NaN where no crown."""
        top = np.full(x.shape, np.nan)
        bot = np.full(x.shape, np.nan)
        if len(self) == 0:
            return top, bot
        tree = cKDTree(np.column_stack([self.cx, self.cy]))
        xy = np.column_stack([x, y])
        rmax = float(self.r.max())
        near = np.nonzero(tree.query(xy, k=1, distance_upper_bound=rmax, workers=-1)[0] < rmax)[0]
        k = min(4, len(self))  # crowns overlap at most a few deep
        dist, idx = tree.query(xy[near], k=k, distance_upper_bound=rmax, workers=-1)
        dist, idx = dist.reshape(len(near), k), idx.reshape(len(near), k)
        ok = idx < len(self)
        j = np.where(ok, idx, 0)
        q = np.where(ok, 1.0 - (dist / self.r[j]) ** 2, -1.0)
        h = np.sqrt(np.clip(q, 0.0, None)) * self.a[j]
        t = np.where(q > 0, self.zc[j] + h, -np.inf)
        best = np.argmax(t, axis=1)
        rows = np.arange(len(near))
        hit = np.isfinite(t[rows, best])
        sel = near[hit]
        top[sel] = t[rows, best][hit]
        bot[sel] = (self.zc[j] - h)[rows, best][hit]
        return top, bot


@dataclass(frozen=True)
class Scene:
    """Everything one region contains, in the local frame of the target epoch."""

    size: tuple
    terrain: Terrain
    buildings: tuple = ()
    trees: tuple = (Trees(), Trees())  # crowns in (target, source)
    water: tuple | None = None  # (cx, cy, ax, ay, depth, bank_slope, level_target, level_source)
    roads: tuple = ()  # (axis 'x'|'y', centre, half_width)
    fields: tuple = ()  # (x0, x1, y0, y1)
    low_veg: tuple | None = None  # ground cover height in (target, source) or None
    patches: tuple = ()  # (x0, x1, y0, y1, height_target, height_source): shrubs/slash on open ground


# --------------------------------------------------------------------------- surfaces
def ground_z(scene: Scene, x, y):
    """Bare-earth height including the lake bed."""
    z = scene.terrain.z(x, y)
    if scene.water is not None:
        cx, cy, ax, ay, depth, bank, *_ = scene.water
        rho = np.hypot((x - cx) / ax, (y - cy) / ay)
        inside = np.clip((1.0 - rho) * min(ax, ay), 0.0, None)  # distance inside the shore (approx.)
        z = z - np.minimum(depth, bank * inside)
    return z


class _Grid:
    """Points sorted once into square cells, so a building touches only the points near its footprint.

    Evaluating every roof on every point costs (number of buildings) x (number of points), which grows
    with the square of the area; through the grid each building costs only the points of the cells its
    footprint covers, and the whole surface stays linear in the area. The values are the same as the
    full evaluation: a roof is -inf (no effect) outside its footprint.
    """

    def __init__(self, x, y, cell: float = GRID_CELL):
        self.cell = float(cell)
        self.x0, self.y0 = (float(x.min()), float(y.min())) if x.size else (0.0, 0.0)
        ix = ((x - self.x0) // self.cell).astype(np.int64) if x.size else np.zeros(0, np.int64)
        iy = ((y - self.y0) // self.cell).astype(np.int64) if y.size else np.zeros(0, np.int64)
        self.nx = int(ix.max()) + 1 if x.size else 1
        self.ny = int(iy.max()) + 1 if y.size else 1
        key = iy * self.nx + ix
        self.order = np.argsort(key, kind="stable")
        self.start = np.searchsorted(key[self.order], np.arange(self.nx * self.ny + 1))

    def points_in(self, x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
        """Indices of all points in the cells that meet the box [x0, x1] x [y0, y1] (a superset of the box)."""
        i0 = max(int((x0 - self.x0) // self.cell), 0)
        i1 = min(int((x1 - self.x0) // self.cell), self.nx - 1)
        j0 = max(int((y0 - self.y0) // self.cell), 0)
        j1 = min(int((y1 - self.y0) // self.cell), self.ny - 1)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, dtype=np.int64)
        rows = [self.order[self.start[j * self.nx + i0]:self.start[j * self.nx + i1 + 1]]
                for j in range(j0, j1 + 1)]
        return np.concatenate(rows)


def _footprint(b: "Building", pad: float = 0.0):
    return b.cx - b.hx - pad, b.cx + b.hx + pad, b.cy - b.hy - pad, b.cy + b.hy + pad


def hard_surface(scene: Scene, x, y, epoch: int, grid: _Grid | None = None):
    """First hard surface (no vegetation crowns) at x, y: height and material code.

    Each building's roof is evaluated only on the points of the grid cells under its footprint
    (``grid``, built here when not given), so the cost is linear in the number of points.
    """
    z = ground_z(scene, x, y)
    mat = np.full(x.shape, GROUND, dtype=np.int8)
    for x0, x1, y0, y1 in scene.fields:
        mat[(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)] = FIELD
    for axis, centre, half in scene.roads:
        mat[np.abs((x if axis == "y" else y) - centre) <= half] = ROAD
    if scene.low_veg is not None:
        cover = (mat == GROUND)
        z = z + np.where(cover, scene.low_veg[epoch], 0.0)
        mat[cover] = LOW_VEG
    for x0, x1, y0, y1, *height in scene.patches:
        if height[epoch] > 0:
            cover = (mat == GROUND) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            z = z + np.where(cover, height[epoch], 0.0)
            mat[cover] = LOW_VEG
    if scene.water is not None:
        level = scene.water[6 + epoch]
        wet = z < level
        z = np.where(wet, level, z)
        mat[wet] = WATER
    present = [b for b in scene.buildings if b.epochs[epoch]]
    if present:
        z = np.array(z, dtype=np.float64, copy=True)
        grid = _Grid(x, y) if grid is None else grid
    for b in present:
        idx = grid.points_in(*_footprint(b))
        if idx.size == 0:
            continue
        zr = b.roof(x[idx], y[idx])
        up = zr > z[idx]
        z[idx] = np.where(up, zr, z[idx])
        mat[idx[up]] = b.material
    return z, mat


def _kernel(radius: float):
    """Offsets and weights of a small Gaussian-like smoothing kernel (DIM edge rounding)."""
    ang = np.linspace(0, 2 * np.pi, 7)[:-1]
    rings = [(0.0, 1, 1.0), (0.45 * radius, 6, 0.6), (radius, 6, 0.25)]
    off, w = [], []
    for r, n, wt in rings:
        a = ang[:n] + (0.5 if r > 0.5 * radius else 0.0)
        off.append(np.column_stack([r * np.cos(a), r * np.sin(a)]))
        w += [wt] * n
    w = np.array(w)
    return np.vstack(off), w / w.sum()


def rounded_surface(scene: Scene, x, y, epoch: int, radius: float = 0.35):
    """Hard surface smoothed near buildings, as dense image matching renders edges."""
    grid = _Grid(x, y)
    z, mat = hard_surface(scene, x, y, epoch, grid)
    near = np.zeros(x.shape, dtype=bool)
    for b in scene.buildings:
        if b.epochs[epoch]:
            idx = grid.points_in(*_footprint(b, radius))
            near[idx] |= b.near_edge(x[idx], y[idx], radius)
    if near.any():
        off, w = _kernel(radius)
        xs, ys = x[near], y[near]
        zs = np.zeros(xs.shape)
        for (dx, dy), wk in zip(off, w):
            zs += wk * hard_surface(scene, xs + dx, ys + dy, epoch)[0]
        z = z.copy()
        z[near] = zs
    return z, mat


# --------------------------------------------------------------------------- sensors
@dataclass
class Samples:
    """Raw samples of one epoch in the local frame (before cropping and transformation)."""

    xyz: np.ndarray
    mat: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    pulse_xy: np.ndarray  # xy of the emitting pulse (for GPS time)
    height: np.ndarray  # height above bare earth (for vegetation classes)


def _uniform_xy(box, density, rng):
    (x0, x1), (y0, y1) = box
    n = rng.poisson(density * (x1 - x0) * (y1 - y0))
    return rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)


def _noise(xyz, mat, col, rng):
    sigma = _table(col)[mat]
    return xyz + rng.normal(size=xyz.shape) * sigma[:, None]


def sample_als(scene: Scene, box, density: float, epoch: int, rng) -> Samples:
    """ALS pulses with multiple returns in vegetation, sparse water returns and a few wall points."""
    x, y = _uniform_xy(box, density, rng)
    zh, mat = hard_surface(scene, x, y, epoch)
    # water absorbs most pulses: only about a quarter return
    keep = (mat != WATER) | (rng.random(len(x)) < 0.25)
    x, y, zh, mat = x[keep], y[keep], zh[keep], mat[keep]
    top, bot = scene.trees[epoch].crown(x, y)
    veg = np.isfinite(top) & (top > zh)
    # first return: penetrates a little into the crown
    depth = np.minimum(rng.exponential(0.4, len(x)), np.where(veg, top - bot, 0.0))
    z1 = np.where(veg, top - depth, zh)
    mat1 = np.where(veg, VEG, mat).astype(np.int8)
    has_mid = veg & (rng.random(len(x)) < 0.45)
    has_last = veg & (rng.random(len(x)) < 0.55)
    nret = (1 + has_mid + has_last).astype(np.uint8)
    low = np.where(veg, np.maximum(bot, zh), z1)
    zmid = low + rng.random(len(x)) * np.clip(z1 - low, 0.0, None)
    under = rng.random(len(x)) < 0.3  # some intermediate returns come from shrubs below the crown
    zmid = np.where(under, np.minimum(zh + rng.uniform(0.1, 1.8, len(x)), z1), zmid)
    parts = [
        (x, y, z1, mat1, np.ones(len(x), np.uint8), nret),
        (x[has_mid], y[has_mid], zmid[has_mid], np.full(has_mid.sum(), VEG, np.int8),
         np.full(has_mid.sum(), 2, np.uint8), nret[has_mid]),
        (x[has_last], y[has_last], zh[has_last], mat[has_last], nret[has_last], nret[has_last]),
    ]
    xs, ys, zs, ms, rn, nr = (np.concatenate(c) for c in zip(*parts))
    xyz = np.column_stack([xs, ys, zs])
    walls = sample_walls(scene, box, 0.12 * density, epoch, rng)
    xyz = np.vstack([xyz, walls])
    ms = np.concatenate([ms, np.full(len(walls), WALL, np.int8)])
    ones = np.ones(len(walls), np.uint8)
    rn, nr = np.concatenate([rn, ones]), np.concatenate([nr, ones])
    pulse = xyz[:, :2].copy()
    height = xyz[:, 2] - ground_z(scene, xyz[:, 0], xyz[:, 1])
    xyz = _noise(xyz, ms, 2, rng)
    return Samples(xyz, ms, rn, nr, pulse, height)


def sample_dim(scene: Scene, box, density: float, epoch: int, rng) -> Samples:
    """Dense image matching: visible surface only, rounded edges, texture-dependent noise."""
    x, y = _uniform_xy(box, density, rng)
    zh, mat = rounded_surface(scene, x, y, epoch)
    keep = (mat != WATER) | (rng.random(len(x)) < 0.5)  # matching fails on much of the water
    x, y, zh, mat = x[keep], y[keep], zh[keep], mat[keep]
    top, _ = scene.trees[epoch].crown(x, y)
    veg = np.isfinite(top) & (top > zh)
    z = np.where(veg, top, zh)
    mat = np.where(veg, VEG, mat).astype(np.int8)
    xyz = np.column_stack([x, y, z])
    height = z - ground_z(scene, x, y)
    ones = np.ones(len(x), np.uint8)
    return Samples(_noise(xyz, mat, 3, rng), mat, ones, ones.copy(), xyz[:, :2].copy(), height)


def sample_walls(scene: Scene, box, density: float, epoch: int, rng) -> np.ndarray:
    """Points on the vertical faces of every building present (uniform, up to the roof edge)."""
    out = [np.zeros((0, 3))]
    (bx0, bx1), (by0, by1) = box
    for b in scene.buildings:
        if not b.epochs[epoch]:
            continue
        top = b.base + b.ridge_height
        for axis, sign in (("x", -1), ("x", 1), ("y", -1), ("y", 1)):
            if axis == "x":  # face at x = cx +- hx, running along y
                lo, hi = max(b.cy - b.hy, by0), min(b.cy + b.hy, by1)
            else:
                lo, hi = max(b.cx - b.hx, bx0), min(b.cx + b.hx, bx1)
            if hi <= lo:
                continue
            n = rng.poisson(density * (hi - lo) * (top - b.base))
            u = rng.uniform(lo, hi, n)
            z = rng.uniform(b.base, top, n)
            if axis == "x":
                px, py = np.full(n, b.cx + sign * (b.hx - 1e-6)), u
            else:
                px, py = u, np.full(n, b.cy + sign * (b.hy - 1e-6))
            ok = (z < b.roof(px, py)) & (z > ground_z(scene, px, py))
            out.append(np.column_stack([px, py, z])[ok])
    pts = np.vstack(out)
    inbox = (pts[:, 0] >= bx0) & (pts[:, 0] <= bx1) & (pts[:, 1] >= by0) & (pts[:, 1] <= by1)
    return pts[inbox]


# --------------------------------------------------------------------------- attributes
def classify(mat, height) -> np.ndarray:
    """ASPRS classes; vegetation split by height above ground (3 < 0.5 m <= 4 < 2 m <= 5)."""
    cls = _table(1)[mat].astype(np.uint8)
    veg = (mat == VEG) | (mat == LOW_VEG)
    cls[veg] = np.where(height[veg] < 0.5, 3, np.where(height[veg] < 2.0, 4, 5))
    return cls


def intensity(mat, return_number, rng) -> np.ndarray:
    """Plausible 16-bit intensities per material; later returns carry less energy."""
    mean, sd = _table(4)[mat], _table(5)[mat]
    val = (mean + sd * rng.normal(size=len(mat))) / return_number
    return np.clip(val, 0, 65535).astype(np.uint16)


def gps_time(pulse_xy_world, t0: float, strip_width: float = 40.0, speed: float = 60.0):
    """GPS time along east-west flight strips (alternating direction) and the strip id."""
    strip = np.floor(pulse_xy_world[:, 1] / strip_width).astype(np.int64)
    x = pulse_xy_world[:, 0] - np.floor(pulse_xy_world[:, 0].min() / 1000.0) * 1000.0
    along = np.where(strip % 2 == 0, x, 2000.0 - x) / speed
    t = t0 + (strip - strip.min()) * 90.0 + along
    return t, (strip - strip.min() + 1).astype(np.uint16)
