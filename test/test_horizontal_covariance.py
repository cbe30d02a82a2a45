"""Covariance of the horizontal solve with an uncertain stated altitude, and its input bounds.

Scenario: five stations, target (1500, 2500, 600) m, σ = 0.6 mrad (σ r ≈ 2-3 m), the true
altitude drawn from the stated prior N(z₀, σ_z²). The error of a fix is (x, y, z) − truth with
z = z₀ reported, so the NEES of the 3 × 3 covariance is χ²₃ when the covariance is honest:
mean 3, variance 6, and the mean of K values lies in 3 ± 2.576 sqrt(6/K) with probability
0.99 (K = 2000: ± 0.141). σ_z = 0: 2 × 2, mean 2, band 2 ± 2.576 sqrt(4/K).
The estimators are called directly (core.horizontal.ESTIMATORS, no robust screen or
consistency check), so every fix is the estimator's own.
"""
import numpy as np
import pytest

from bearing_loc_ros.core import chisq
from bearing_loc_ros.core.bearings import MAX_ABS_POSITION
from bearing_loc_ros.core.horizontal import ESTIMATORS, locate_horizontal, simulate_bearings
from bearing_loc_ros.core.horizontal_crlb import horizontal_crlb
from bearing_loc_ros.core.horizontal_estimators import (
    altitude_covariance, fix_result, linear_altitude_covariance, linear_covariance,
    MAX_ALTITUDE_SIGMA, prepare, solve_ls)

STATIONS = np.array([[0.0, 0.0, 0.0], [4000.0, 500.0, 20.0], [-2000.0, 3000.0, 5.0],
                     [1000.0, -2500.0, 0.0], [3000.0, 4000.0, 10.0]])
TARGET = np.array([1500.0, 2500.0, 600.0])
K = 2000


def _trials(elevation_stations, sigma_z, seed=1):
    rng = np.random.default_rng(seed)
    truth = np.tile(TARGET, (K, 1))
    truth[:, 2] += sigma_z * rng.standard_normal(K)
    has_el = [i in elevation_stations for i in range(len(STATIONS))]
    bs = simulate_bearings(truth, STATIONS, 0.6e-3, 0.6e-3, has_elevation=has_el, rng=rng)
    return truth, prepare(bs, TARGET[2], sigma_z)


def _nees(method, truth, p):
    r = ESTIMATORS[method](p)
    assert np.all(r.status == 'ok'), method
    assert np.all(np.isfinite(r.covariance)), method
    np.testing.assert_array_equal(r.covariance, np.swapaxes(r.covariance, 1, 2))
    d = 3 if p.sz[0] > 0 else 2
    e = (r.position - truth)[:, :d]
    return np.einsum('mi,mij,mj->m', e, np.linalg.inv(r.covariance[:, :d, :d]), e)


@pytest.mark.parametrize('elevation_stations, sigma_z', [
    ((1,), 300.0),        # one elevation station: before the fix tls 281, ctls 332, ctls_am 3.4
    ((1, 4), 100.0),      # two: before tls 16.8, ctls 81, ctls_am 4.0
])
@pytest.mark.parametrize('method', ['tls', 'ctls', 'ctls_am'])
def test_altitude_sigma_is_carried_through_the_fit(method, elevation_stations, sigma_z):
    # These fits hold z = z0 and are not linear in z0 once an elevation is used; σ_z is
    # carried through the fit itself (refits at the Gauss-Hermite nodes), so the mean NEES
    # is χ²₃'s 3. (The first-order ls gain gave the means in the comments above.)
    truth, p = _trials(elevation_stations, sigma_z)
    nees = _nees(method, truth, p)
    assert abs(np.mean(nees) - 3.0) < 2.576 * np.sqrt(6.0 / K)


@pytest.mark.parametrize('elevation_stations, sigma_z', [
    ((), 0.0), ((), 300.0), ((1,), 0.0), ((1,), 10.0)])
@pytest.mark.parametrize('method', ['ls', 'tls', 'ctls', 'ctls_am', 'mle'])
def test_linear_regime_mean_and_tail(method, elevation_stations, sigma_z):
    # Azimuth only (the fit does not depend on z0), σ_z = 0, or σ_z small against the range
    # error an elevation carries: the error is Gaussian to first order, so the mean is in the
    # χ² band and the tail beyond the χ²_d 0.9999 quantile has rate 1e-4, i.e. 0.2 of 2000
    # fixes expected; more than 4 has Poisson probability 2e-6.
    truth, p = _trials(elevation_stations, sigma_z)
    nees = _nees(method, truth, p)
    d = 3 if sigma_z > 0 else 2
    assert abs(np.mean(nees) - d) < 2.576 * np.sqrt(2.0 * d / K)
    assert np.count_nonzero(nees > chisq.isf(1e-4, d)) <= 4


def test_refit_rule_reproduces_the_exact_term_of_a_linear_fit():
    # ls is linear in z0, so the Gauss-Hermite refits (exact for polynomials of degree ≤ 9)
    # must give its closed-form σ_z term, x-y/z correlation included.
    truth, p = _trials((0, 1, 4), 50.0)
    p = p.take(slice(0, 20))
    xy, ok, H, w, Ainv = solve_ls(p)
    P0, k = linear_covariance(p, xy, ok, H, w, Ainv)
    exact = linear_altitude_covariance(p, P0, k)
    refits = altitude_covariance(p, xy, P0, k, lambda q, idx: solve_ls(q)[0])
    np.testing.assert_allclose(refits, exact, rtol=1e-9, atol=1e-9 * np.max(np.abs(exact)))
    assert np.all(np.abs(exact[:, 0, 2]) > 1.0)        # the elevations correlate x with z


def _one_set():
    return simulate_bearings(TARGET, STATIONS[:3], 1e-3, 1e-3,
                             has_elevation=[True, False, False], rng=np.random.default_rng(3))


def _two_sets():
    return simulate_bearings(np.tile(TARGET, (2, 1)), STATIONS[:3], 1e-3, 1e-3,
                             has_elevation=[True, False, False], rng=np.random.default_rng(3))


@pytest.mark.parametrize('bearings', [_one_set, _two_sets])
@pytest.mark.parametrize('z0, sz, field', [
    (1e300, 0.0, 'target_altitude'), (-2e12, 0.0, 'target_altitude'),
    (600.0, 1e155, 'target_altitude_sigma'), (600.0, 1e100, 'target_altitude_sigma'),
    (600.0, 1.000001e6, 'target_altitude_sigma'), (600.0, -1.0, 'target_altitude_sigma')])
@pytest.mark.parametrize('method', ['ls', 'tls', 'ctls', 'ctls_am', 'mle', 'wmle'])
def test_altitude_and_sigma_are_bounded(method, z0, sz, field, bearings):
    # Before: σ_z = 1e155 gave ok fixes with covariance diagonal [nan, nan, inf] (ls, tls,
    # ctls), σ_z = 1e100 an ok mle fix with a NaN σ_z², z0 = 1e300 ok fixes with NaN.
    with pytest.raises(ValueError, match=f'^{field}: '):
        locate_horizontal(method, bearings(), z0, sz)


@pytest.mark.parametrize('z0', [600.0, 1e7, MAX_ABS_POSITION, -MAX_ABS_POSITION])
@pytest.mark.parametrize('method', ['ls', 'tls', 'ctls', 'ctls_am', 'mle', 'wmle'])
def test_no_ok_fix_with_a_non_finite_covariance_at_the_bounds(method, z0):
    for has_el in ([True, False, False], [False] * 3):
        bs = simulate_bearings(TARGET, STATIONS[:3], 1e-3, 1e-3, has_elevation=has_el,
                               rng=np.random.default_rng(3))
        for sz in (0.0, MAX_ALTITUDE_SIGMA):
            r = locate_horizontal(method, bs, z0, sz)
            if r.status[0] == 'ok':
                assert np.all(np.isfinite(r.covariance)), (method, z0, sz, has_el)
                assert np.all(np.isfinite(r.position)), (method, z0, sz, has_el)


def test_fix_result_never_marks_a_non_finite_covariance_ok():
    bs = _one_set()
    p = prepare(bs, TARGET[2], 10.0)
    cov = np.full((1, 3, 3), np.nan)
    r = fix_result(p, np.array([[1500.0, 2500.0]]), cov, np.zeros(1, dtype=int),
                   np.array([True]), np.array(['ok']), 'ls')
    assert r.status[0] == 'degenerate_geometry'
    assert np.all(np.isnan(r.position)) and np.all(np.isinf(r.covariance))


def test_prior_covariance_stays_finite_for_a_huge_sigma():
    # Azimuth-only: P_zz = σ_z². Before, (qᵀP_h q)/s² was 0/0 once s² underflowed.
    P = horizontal_crlb(TARGET, STATIONS[:3], 1e-3, sigma_z=1e100)[0]
    assert P[2, 2] == pytest.approx(1e200)
    assert np.all(np.isfinite(P))
