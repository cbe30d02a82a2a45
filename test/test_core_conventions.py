"""Conventions of DESIGN.md: wrapping, compass, line of sight, quaternions, validation."""
import numpy as np
import pytest

from bearing_loc_ros.core.bearings import Bearing, BearingSet, simulate_bearings
from bearing_loc_ros.core.conventions import (azel_from_quaternion, azimuth_elevation,
                                              compass_to_enu, enu_to_compass, los_vector,
                                              quaternion_from_azel, wrap_angle)
from bearing_loc_ros.core.crlb import crlb, fisher_information, gdop


def test_wrap_angle_half_open_interval():
    a = np.array([np.pi, -np.pi, 3 * np.pi, 0.5, -0.5 - 4 * np.pi, 7.0])
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert w[0] == pytest.approx(np.pi) and w[1] == pytest.approx(np.pi)
    assert np.allclose(np.exp(1j * w), np.exp(1j * a))


def test_compass_round_trip_and_cardinal_points():
    # North (compass 0) is ENU +y (pi/2); East (compass pi/2) is ENU 0.
    assert compass_to_enu(0.0) == pytest.approx(np.pi / 2)
    assert compass_to_enu(np.pi / 2) == pytest.approx(0.0)
    assert compass_to_enu(np.pi) == pytest.approx(-np.pi / 2)
    c = np.linspace(0, 2 * np.pi, 37, endpoint=False)
    assert np.allclose(enu_to_compass(compass_to_enu(c)), c)


def test_los_vector_matches_azimuth_elevation():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(100, 3))
    az, el = azimuth_elevation(d)
    assert np.allclose(los_vector(az, el), d / np.linalg.norm(d, axis=1, keepdims=True))


def test_quaternion_round_trip_and_rotates_x_onto_los():
    rng = np.random.default_rng(2)
    az = rng.uniform(-np.pi, np.pi, 200)
    el = rng.uniform(-1.5, 1.5, 200)
    q = quaternion_from_azel(az, el)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
    az2, el2, roll = azel_from_quaternion(q)
    assert np.allclose(wrap_angle(az2 - az), 0, atol=1e-12)
    assert np.allclose(el2, el, atol=1e-12)
    assert np.allclose(roll, 0, atol=1e-12)


def test_bearing_set_validation_names_the_field():
    pos = np.array([[0, 0, 0], [1000, 0, 0], [0, 1000, 0.0]])
    good = dict(positions=pos, azimuth=[0.1, 0.2, 0.3], elevation=[0.1, np.nan, 0.2],
                sigma_az=0.01, sigma_el=0.01)
    BearingSet.from_arrays(**good)
    for field_, value, word in [('azimuth', [np.nan, 0.2, 0.3], 'azimuth'),
                                ('elevation', [2.0, np.nan, 0.2], 'elevation'),
                                ('sigma_az', -0.01, 'sigma_azimuth'),
                                ('sigma_el', 0.0, 'sigma_elevation'),
                                ('elevation', None, 'elevation')]:
        bad = dict(good, **{field_: value})
        with pytest.raises(ValueError, match=word):
            BearingSet.from_arrays(**bad)
    with pytest.raises(ValueError, match='two'):
        BearingSet.from_arrays(pos[:1], [0.1], [0.1], 0.01, 0.01)
    with pytest.raises(ValueError, match='position'):
        Bearing('s', 0, np.array([np.nan, 0, 0]), 0.1).validate()


def test_crlb_equals_inverse_fisher_and_matches_monte_carlo_linearisation():
    pos = np.array([[30e3, -10e3, 100], [30e3, 20e3, 200], [-30e3, 5e3, 150.0]])
    tgt = np.array([[10e3, 40e3, 5e3]])
    J = fisher_information(tgt, pos, 1.5e-3)
    C = crlb(tgt, pos, 1.5e-3)
    assert np.allclose(C[0] @ J[0], np.eye(3), atol=1e-9)
    # Numerical Jacobian of the angles confirms the analytic gradients inside J.
    eps = 1e-3
    rows = []
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = eps
        a1, e1 = azimuth_elevation(tgt[0] + dp - pos)
        a0, e0 = azimuth_elevation(tgt[0] - dp - pos)
        rows.append(np.concatenate([a1 - a0, e1 - e0]) / (2 * eps))
    G = np.array(rows).T / 1.5e-3
    assert np.allclose(G.T @ G, J[0], rtol=1e-6)
    assert gdop(C)[0] > 0


def test_simulate_bearings_noise_free_is_exact():
    pos = np.array([[0, 0, 0], [1000, 0, 0.0]])
    bs = simulate_bearings([500, 500, 100], pos, 0.01, has_elevation=[True, False])
    assert bs.azimuth[0, 0] == pytest.approx(np.pi / 4)
    assert np.isnan(bs.elevation[0, 1]) and np.isnan(bs.sigma_el[0, 1])
