"""The RANSAC threshold from the data: the noise estimate against known noise, and the default on real scans."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from labkit.ransac.threshold import estimate_threshold

SPHERES = Path(__file__).resolve().parents[2] / "data" / "real" / "spheres"


@pytest.mark.parametrize("sigma", [0.001, 0.003, 0.005])  # below the point spacing (14 mm)
def test_noise_of_a_surface_is_recovered(sigma):
    """A gently curved surface, densely sampled, with normal noise sigma along z."""
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 2, (20000, 2))
    z = 0.05 * np.sin(xy[:, 0]) + rng.normal(0, sigma, len(xy))
    est = estimate_threshold(np.c_[xy, z], rng=0)
    assert 0.8 * sigma < est.noise < 1.15 * sigma, est  # low as sigma nears the spacing
    assert est.threshold == pytest.approx(max(3 * est.noise, 0.001))


def test_noise_along_scan_lines_is_recovered():
    """Rings of a multi-beam scanner: 8 neighbours on one line; the noise (in the ring plane) from lambda_2."""
    rng = np.random.default_rng(2)
    sigma = 0.007
    rings = []
    for elev in np.radians(np.arange(-15, 16, 2.0)):
        az = np.arange(0, 2 * np.pi, np.radians(0.4))
        r = 3.0 + rng.normal(0, sigma, len(az))  # range noise
        rings.append(np.c_[r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az), r * np.sin(elev)])
    est = estimate_threshold(np.vstack(rings), rng=0)
    assert est.share_lines > 0.9 and 0.8 * sigma < est.noise < 1.2 * sigma, est


def test_quantised_duplicates_keep_a_floor():
    xyz = np.repeat(np.c_[np.arange(0, 1, 0.01)[:, None].repeat(2, 1), np.zeros(100)], 5, axis=0)
    assert estimate_threshold(xyz).threshold == 0.001


@pytest.mark.skipif(not SPHERES.exists(), reason="data/real/spheres not shipped")
def test_default_threshold_finds_the_sphere_in_a_real_multibeam_scan(capsys):
    from labkit.cli.main import main

    name = "spherecalib_ex3_L1_S1.xyz"
    ref = json.loads((SPHERES / "reference.json").read_text())[name]
    assert main(["sphere", str(SPHERES / name), "--radius-range", "0.25", "0.35"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"inlier threshold \d+ mm = 3 x noise \d+\.\d mm", out)
    centre = np.array([float(v) for v in re.search(r"^centre\s+\[([^\]]+)\]", out, re.M).group(1).split(",")])
    assert np.linalg.norm(centre - ref["center"]) < 0.005  # the independent reference fit, within 5 mm


def test_a_failed_search_names_the_threshold_and_a_value_to_try(tmp_path, capsys):
    from labkit.cli.main import main
    from labkit.cloud import PointCloud
    from labkit.io import write_cloud

    pts = np.random.default_rng(0).uniform(0, 1, (2000, 3))  # a box of noise: no sphere
    write_cloud(PointCloud(pts), tmp_path / "noise.xyz")
    assert main(["sphere", str(tmp_path / "noise.xyz"), "--radius-range", "0.05", "0.1", "--threshold", "0.003"]) == 1
    err = capsys.readouterr().err
    assert re.search(r"tried with --threshold 0.003 m: try --threshold [0-9.]+", err)
