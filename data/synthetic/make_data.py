"""Generate the small synthetic data files of this folder (fixed seeds, atomic writes).

Run from anywhere:

    python data/synthetic/make_data.py [--out FOLDER]

Files (see README.md): a TLS scan of a sphere target on a tripod (ASCII and LAZ)
with its truth, and one ALS epoch pair per comparison case (ALS-ALS, ALS-ALS
with a change, ALS-DIM) with ``pairs.json`` and ``references.json`` for
``labkit compare``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from labkit.core.atomic import atomic_write_text
from labkit.cloud import PointCloud
from labkit.io import write_cloud
from labkit import save_references, truth_reference
from labkit.synthetic import als_epochs, sphere_on_tripod
from labkit.synthetic.tripod import UTM_OFFSET

HERE = Path(__file__).resolve().parent

TRIPOD_SEED = 2026
# (region, case, dim, seed): one pair per case of seed 003
ALS_PAIRS = (
    ("xyz", "als-als", False, 14),
    ("demolished", "changes", False, 15),
    ("xyz", "als-dim", True, 16),
)
ALS_SIZE = (60.0, 60.0)  # m; smaller regions leave rotation and shift poorly separated for rigid ICP
ALS_DENSITY = 5.0  # pts/m^2 (ALS)
DIM_DENSITY = 10.0  # pts/m^2 of the dense-image-matching source
SHIFT = (0.23, -0.17, 0.11)  # m, the true shift 2016 -> 2014


def make_tripod(out: Path) -> list[Path]:
    """The tripod scene: local ASCII xyz, UTM-sized LAZ with labels, and the true sphere."""
    scene = sphere_on_tripod(n_sphere=2000, noise=0.001, rng=TRIPOD_SEED)
    labels = scene.labels.astype(np.uint8)
    local = PointCloud(scene.points, name="tripod_scene")
    utm = PointCloud(scene.points + UTM_OFFSET, {"classification": labels}, name="tripod_scene")
    truth = {
        "sphere_local": scene.sphere.tolist(),
        "sphere_utm": (scene.sphere + np.r_[UTM_OFFSET, 0.0]).tolist(),
        "utm_offset": UTM_OFFSET.tolist(),
        "noise_m": scene.noise,
        "points": int(scene.n),
        "sphere_points": int(scene.is_sphere.sum()),
        "labels": dict(enumerate(scene.label_names)),
        "seed": TRIPOD_SEED,
        "generator": "labkit.synthetic.sphere_on_tripod(n_sphere=2000, noise=0.001)",
    }
    return [
        write_cloud(local, out / "tripod_scene.xyz", scale=0.0001),
        write_cloud(utm, out / "tripod_scene.laz", scale=0.0001),
        atomic_write_text(out / "tripod_truth.json", json.dumps(truth, indent=2) + "\n"),
    ]


def make_als(out: Path) -> list[Path]:
    """One epoch pair per case, the pair list and the reference (truth) file."""
    written, entries, references = [], [], []
    for region, case, dim, seed in ALS_PAIRS:
        pair = als_epochs(region, shift=SHIFT, size=ALS_SIZE, density=ALS_DENSITY,
                          source_density=DIM_DENSITY if dim else None, dim=dim, rng=seed)
        src_name, tgt_name = f"{case}_{region}_2016{'_dim' if dim else ''}.laz", f"{case}_{region}_2014.laz"
        written += [write_cloud(pair.source, out / src_name), write_cloud(pair.target, out / tgt_name)]
        entries.append({"region": region, "case": case, "source": src_name, "target": tgt_name,
                        "constrained": list(pair.constrained)})
        references.append(truth_reference(pair.truth, region=region, case=case,
                                          note=f"synthetic truth, als_epochs(rng={seed})"))
    written.append(atomic_write_text(out / "pairs.json", json.dumps({"pairs": entries}, indent=2) + "\n"))
    written.append(save_references(references, out / "references.json"))
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE, help="target folder (default: this script's folder)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    written = make_tripod(args.out) + make_als(args.out)
    total = sum(p.stat().st_size for p in written)
    for p in written:
        print(f"{p.stat().st_size / 1024:8.1f} KiB  {p.name}")
    print(f"{total / 1024**2:8.2f} MiB  total")


if __name__ == "__main__":
    main()
