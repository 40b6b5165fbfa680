"""labkit.core.distributions gives scipy.stats' numbers bit for bit, and the command line starts without scipy.stats."""

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from labkit.core import distributions as d

RNG = np.random.default_rng(7)
P = np.r_[0.0, 1e-300, 1e-12, RNG.uniform(0, 1, 500), 0.5, 1 - 1e-12, 1.0, -0.1, 1.1, np.nan]
X = np.r_[-3.0, 0.0, 1e-9, RNG.exponential(5, 500), 50.0, 1e3, np.inf, -np.inf, np.nan]
DOFS = [1, 2, 3, 4, 7, 10, 57, 1000, 2.5]


@pytest.mark.parametrize("dof", DOFS)
def test_same_numbers_as_scipy_stats(dof):
    pairs = {
        "chi2.sf": (d.chi2_sf(X, dof), stats.chi2.sf(X, dof)),
        "chi2.isf": (d.chi2_isf(P, dof), stats.chi2.isf(P, dof)),
        "chi2.ppf": (d.chi2_ppf(P, dof), stats.chi2.ppf(P, dof)),
        "t.ppf": (d.t_ppf(P, dof), stats.t.ppf(P, dof)),
        "f.ppf": (d.f_ppf(P, 3, dof), stats.f.ppf(P, 3, dof)),
        "beta.sf": (d.beta_sf(X / 40, dof / 2, 1.5), stats.beta.sf(X / 40, dof / 2, 1.5)),
    }
    for name, (ours, theirs) in pairs.items():
        np.testing.assert_array_equal(ours, theirs, err_msg=name)


def test_normal_same_numbers_as_scipy_stats():
    np.testing.assert_array_equal(d.norm_ppf(P), stats.norm.ppf(P))
    np.testing.assert_array_equal(d.norm_isf(P), stats.norm.isf(P))
    np.testing.assert_array_equal(d.norm_cdf(X), stats.norm.cdf(X))
    np.testing.assert_array_equal(d.norm_sf(X), stats.norm.sf(X))
    np.testing.assert_array_equal(d.norm_cdf(-X), stats.norm.cdf(-X))
    assert d.norm_sf(3.0) == stats.norm.sf(3.0) and d.norm_cdf(3.0) == stats.norm.cdf(3.0)  # scalars
    grid = np.linspace(-5, 5, 101)
    np.testing.assert_array_equal(d.norm_pdf(grid, 0.7), stats.norm.pdf(grid, 0, 0.7))


def test_dof_broadcast_like_scipy_stats():
    dof = np.array([1, 2, 3, 3, 2])
    T = np.array([0.5, 3.0, 7.8, np.nan, 0.0])
    np.testing.assert_array_equal(d.chi2_sf(T, dof), stats.chi2.sf(T, dof))
    np.testing.assert_array_equal(d.chi2_isf(0.01, [1, 2, 3]), stats.chi2.isf(0.01, [1, 2, 3]))


@pytest.mark.parametrize("module", ["labkit.cli", "labkit.cli.main", "labkit.registration"])
def test_command_line_starts_without_scipy_stats(module):
    """`labkit ...` imports labkit.cli.main (the console script); scipy.stats alone costs about a second."""
    code = f"import sys, {module}; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_icp_with_its_covariance_and_robust_weights_runs_without_scipy_stats():
    """A registration (block covariance, deletion limits, Tukey weights, the class check) never needs it."""
    code = """
import sys, numpy as np
from labkit import PointCloud
from labkit.registration import icp
from labkit.synthetic import wavy_surface
rng = np.random.default_rng(1)
t, s = wavy_surface(3000, rng), wavy_surface(1000, rng) - [0.05, 0.02, 0.03]
icp(s, t); icp(s, t, robust="tukey"); icp(s, t, reject_sigma=3)
cls = lambda n: np.where(np.arange(n) % 4 == 0, 5, 2)
icp(PointCloud(s, {"classification": cls(len(s))}), PointCloud(t, {"classification": cls(len(t))}))
print('scipy.stats' in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"
