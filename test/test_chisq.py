"""core.chisq gives scipy.stats.chi2's quantiles without importing scipy."""
import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.stats import chi2

from bearing_loc_ros.core import chisq

PROBABILITIES = [1e-12, 1e-6, 5e-4, 0.0005000000000000004, 0.05, 0.5, 0.9, 0.99, 0.999,
                 0.9995, 0.9999, 0.999999, 1 - 1e-12]


@pytest.mark.parametrize('p', PROBABILITIES)
def test_quantiles_match_scipy_stats(p):
    # Both are floating-point evaluations of the same quantile: they agree to ~1e-14
    # relative (scipy's own distance from the exact value is of the same order, see below).
    dof = np.concatenate([np.arange(1, 401), [0.5, 1.5, 2.5, 7.5]])
    np.testing.assert_allclose(chisq.ppf(p, dof), chi2.ppf(p, dof), rtol=5e-14, atol=0)
    np.testing.assert_allclose(chisq.isf(p, dof), chi2.isf(p, dof), rtol=5e-14, atol=0)
    small = dof[:10]        # the thresholds of a few bearings: a few units in the last place
    np.testing.assert_allclose(chisq.ppf(p, small), chi2.ppf(p, small), rtol=5e-15, atol=0)
    np.testing.assert_allclose(chisq.isf(p, small), chi2.isf(p, small), rtol=5e-15, atol=0)


@pytest.mark.parametrize('p', [1e-6, 1e-3, 0.3, 0.5, 0.9, 0.99, 0.999, 0.9995, 0.9999])
def test_closed_forms(p):
    # χ²_2: ppf(p) = −2 ln(1 − p), isf(q) = −2 ln q; χ²_1: Q(x) = erfc(√(x/2)).
    exact = -2.0 * math.log1p(-p)
    assert abs(chisq.ppf(p, 2) - exact) <= 4 * np.spacing(exact)
    exact = -2.0 * math.log(p)
    assert abs(chisq.isf(p, 2) - exact) <= 4 * np.spacing(exact)
    x1 = chisq.ppf(p, 1)
    assert math.erfc(math.sqrt(x1 / 2.0)) == pytest.approx(1.0 - p, rel=1e-14, abs=0)


def test_known_values():
    assert chisq.ppf(0.999, 2) == pytest.approx(-2.0 * np.log(1e-3), rel=1e-13)
    assert chisq.ppf(0.95, 1) == pytest.approx(3.841458820694124, rel=1e-12)
    # lower tail of χ²_1: P(x) = erf(√(x/2)) ≈ √(2x/π), so ppf(p) = π p² / 2 for tiny p
    assert chisq.ppf(1e-12, 1) == pytest.approx(math.pi / 2 * 1e-24, rel=4e-16)


def test_shapes_and_types():
    assert isinstance(chisq.ppf(0.9, 3), np.floating)
    assert chisq.ppf([0.9], 3).shape == (1,)
    out = chisq.ppf(0.9, np.array([[1, 2], [3, 2]]))
    assert out.shape == (2, 2) and out[0, 1] == out[1, 1] == chisq.ppf(0.9, 2)
    both = chisq.isf(np.array([0.1, 0.01]), np.array([[3], [4]]))
    assert both.shape == (2, 2)
    np.testing.assert_allclose(both, chi2.isf([0.1, 0.01], [[3], [4]]), rtol=1e-14)


def test_domain_edges_are_scipy_special():
    # Outside (0, 1) x (0, MAX_DOF]: exactly what scipy.special gives (0, inf, NaN).
    p = np.array([0.0, 1.0, np.nan, 0.5])
    np.testing.assert_array_equal(chisq.ppf(p, 3), chi2.ppf(p, 3))
    np.testing.assert_array_equal(chisq.isf(p, 3), chi2.isf(p, 3))
    assert np.isnan(chisq.ppf(0.5, 0))
    big = np.array([401, 1000, 5000])
    np.testing.assert_array_equal(chisq.ppf(0.999, big), chi2.ppf(0.999, big))


def test_no_scipy_import():
    code = ('import sys; from bearing_loc_ros.core import chisq; '
            'chisq.ppf(0.9999, 1); chisq.ppf([0.0005, 0.9995], [2, 3]); chisq.isf(0.01, 40); '
            'print(sorted(m for m in sys.modules if m.split(".")[0] == "scipy"))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == '[]'
