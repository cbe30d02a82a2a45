"""core.chisq gives exactly scipy.stats.chi2's quantiles (without importing scipy.stats)."""
import numpy as np
import pytest
from scipy.stats import chi2

from bearing_loc_ros.core import chisq


@pytest.mark.parametrize('p', [1e-6, 5e-4, 0.05, 0.5, 0.9, 0.99, 0.999, 0.9995, 0.9999])
def test_quantiles_equal_scipy_stats(p):
    dof = np.arange(1, 400)
    assert np.array_equal(chisq.ppf(p, dof), chi2.ppf(p, dof))
    assert np.array_equal(chisq.isf(p, dof), chi2.isf(p, dof))


def test_known_values():
    # χ²_2 quantile has the closed form −2 ln(1 − p); χ²_1 at 0.95 is 1.959964² = 3.841459.
    assert chisq.ppf(0.999, 2) == pytest.approx(-2.0 * np.log(1e-3), rel=1e-13)
    assert chisq.ppf(0.95, 1) == pytest.approx(3.841458820694124, rel=1e-12)
