"""Monte Carlo acceptance of the horizontal solve (fixed seeds, statistically derived bounds).

Wang, Zhang & Wu's three stations (config/scenarios/seed000.yaml), all azimuth only, target
at its known altitude. For K independent trials the relative standard error of an RMSE
estimate is at most 1/sqrt(2K) (one error component; smaller when the error spreads over two).
The mean of K NEES values of 2 degrees of freedom (χ²₂: mean 2, variance 4) has standard
deviation 2/sqrt(K); its two-sided 99 % band is 2 ± 2.576 · 2/sqrt(K).
"""
import os

import numpy as np
import pytest

from bearing_loc_ros.core.horizontal import locate_horizontal, simulate_bearings
from bearing_loc_ros.core.horizontal_crlb import horizontal_crlb_for, horizontal_gdop
from bearing_loc_ros.core.simulation import load_scenario, station_position, target_position

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENARIO = load_scenario(os.path.join(REPO, 'config', 'scenarios', 'seed000.yaml'))
STATIONS = np.array([station_position(s, 0.0) for s in SCENARIO.stations])
TARGET = np.asarray(target_position(SCENARIO.targets[0], 0.0), dtype=float)


@pytest.mark.parametrize('sigma', [1.5e-3, 4.5e-3])
def test_mle_attains_the_2d_crlb_with_an_honest_covariance(sigma):
    # K = 20000: RMSE standard error ≤ 1/sqrt(40000) = 0.5 %, so the 3 % requirement is
    # 4 standard errors plus 1 % for the MLE's second-order bias (σ r ≲ 0.4 km at 30-90 km).
    # NEES band: 2 ± 2.576 · 2/sqrt(20000) = 2 ± 0.036.
    K = 20000
    bs = simulate_bearings(np.tile(TARGET, (K, 1)), STATIONS, sigma,
                           rng=np.random.default_rng(11))
    # The paper's estimator (Zong & Cui 2015), not the robust screen on top of it.
    r = locate_horizontal('mle', bs, TARGET[2], robust=False)
    assert np.all(r.converged)
    assert np.all(r.position[:, 2] == TARGET[2])
    bound = horizontal_gdop(horizontal_crlb_for(TARGET[None], bs.problem(0))[0])
    e = r.position[:, :2] - TARGET[:2]
    rmse = np.sqrt(np.mean(np.sum(e * e, axis=1)))
    assert abs(rmse / bound - 1.0) < 0.03
    nees = np.einsum('mi,mij,mj->m', e, np.linalg.inv(r.covariance[:, :2, :2]), e)
    assert abs(np.mean(nees) - 2.0) < 2.576 * 2.0 / np.sqrt(K)


def test_posterior_with_elevations_and_an_uncertain_altitude_is_honest():
    # Mixed 1D/2D stations, short range; the true altitude is drawn from the stated prior
    # N(z0, σ_z²), so the 3 × 3 posterior covariance (with its real x-y/z correlation) must
    # give NEES ~ χ²₃: mean 3, sd sqrt(6/K); 99 % band 3 ± 2.576 sqrt(6/K).
    K = 4000
    rng = np.random.default_rng(12)
    st = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0],
                   [1000.0, -2500.0, 0.0]])
    z0, sz = 600.0, 40.0
    truth = np.tile([1500.0, 2500.0, z0], (K, 1))
    truth[:, 2] += sz * rng.standard_normal(K)
    bs = simulate_bearings(truth, st, 2e-3, 3e-3, has_elevation=[True, False, True, False],
                           rng=rng)
    band = 2.576 * np.sqrt(6.0 / K)
    for method in ('mle', 'ctls', 'ctls_am', 'ls', 'tls'):
        # every fix, as the estimators compute it (no robust or consistency status)
        r = locate_horizontal(method, bs, z0, sz,
                              **({'robust': False} if method == 'mle' else
                                 {'consistency': False}))
        assert np.all(r.converged), method
        e = r.position - truth
        P = r.covariance
        nees = np.einsum('mi,mij,mj->m', e, np.linalg.inv(P), e)
        if method == 'mle':
            assert abs(np.mean(nees) - 3.0) < band
            assert P[0, 2, 2] < 0.1 * sz ** 2          # the elevations measure the height
            continue
        # The pseudo-linear fits keep z = z0 and carry σ_z to (x, y) through the elevation
        # rows (first order: 0.1 allowed beyond the band). The x/z error correlation they
        # predict is real: it matches the sample correlation within 4 standard errors
        # ((1 − ρ²)/sqrt(K)) and is far from zero.
        assert np.all(r.position[:, 2] == z0)
        assert abs(np.mean(nees) - 3.0) < band + 0.1, method
        rho = P[0, 0, 2] / np.sqrt(P[0, 0, 0] * P[0, 2, 2])
        se = (1.0 - rho ** 2) / np.sqrt(K)
        assert abs(rho) > 8 * se, method
        assert abs(np.corrcoef(e[:, 0], e[:, 2])[0, 1] - rho) < 4 * se, method
