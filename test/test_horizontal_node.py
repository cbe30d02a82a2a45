"""The fusion node with azimuth-only stations: horizontal fixes over DDS, consistent with
their published covariance; the solve reported in /diagnostics; the window mode."""

import numpy as np
import pytest
from scipy.stats import chi2

from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.ros_conversions import bearing_to_msg, fix_from_msg

pytestmark = pytest.mark.ros

S = 1_000_000_000
# Wang, Zhang & Wu section 4 layout scaled to 5 km, azimuth only; target altitude known.
STATIONS = {'s1': [0.0, 0.0, 0.0], 's2': [5000.0, 0.0, 20.0], 's3': [0.0, 6000.0, 40.0]}
TARGET = np.array([2500.0, 3000.0, 300.0])
SIGMA = 0.005


def az_bearing(station, t_ns, rng, target=TARGET):
    p = np.array(STATIONS[station])
    az = np.arctan2(target[1] - p[1], target[0] - p[0]) + SIGMA * rng.standard_normal()
    return Bearing(station=station, stamp_ns=int(t_ns), position=p, azimuth=float(az),
                   sigma_azimuth=SIGMA)


def values(status):
    return {kv.key: kv.value for kv in status.values}


def test_three_azimuth_only_stations_give_consistent_horizontal_fixes(harness):
    """40 epochs of noisy azimuths: every fix has z = the stated altitude, z variance = σ_z²,
    and the mean NEES (2 dof) of the horizontal error is inside the χ² 99 % band."""
    h = harness(target_altitude=[300.0], target_altitude_sigma=10.0)
    rng = np.random.default_rng(2024)
    nees = []
    for k in range(40):
        t = (100 + k) * S
        h.set_clock(t)
        n = len(h.fixes)
        for s in STATIONS:
            h.send(bearing_to_msg(az_bearing(s, t, rng)), s)
        assert h.spin(lambda: len(h.fixes) > n), f'no fix at epoch {k}'
        stamp, pos, cov = fix_from_msg(h.fixes[-1])
        assert stamp == t
        assert pos[2] == pytest.approx(300.0)
        assert cov[2, 2] == pytest.approx(100.0) and np.all(cov[:2, 2] == 0.0)
        e = pos[:2] - TARGET[:2]
        nees.append(e @ np.linalg.solve(cov[:2, :2], e))
    n = len(nees)
    lo, hi = chi2.ppf([0.005, 0.995], 2 * n) / n
    assert lo < np.mean(nees) < hi, np.mean(nees)
    d = h.diag(lambda d: values(d['fusion']).get('fixes') == str(n))
    v = values(d['fusion'])
    assert v['solve'] == 'horizontal' and v['no_fix.no_elevation'] == '0'


def test_azimuth_only_without_altitude_is_a_counted_no_fix(harness):
    h = harness()
    rng = np.random.default_rng(1)
    h.set_clock(100 * S)
    for s in STATIONS:
        h.send(bearing_to_msg(az_bearing(s, 100 * S, rng)), s)
    d = h.diag(lambda d: values(d['fusion']).get('no_fix.no_elevation') == '1')
    assert values(d['fusion'])['fixes'] == '0'
    assert not h.fixes


def test_window_mode_with_one_moving_station(harness):
    """One car, azimuths every 0.5 s, window mode: fixes once the range is resolved, the last
    one within its covariance (χ²₂ 99.9 %)."""
    h = harness(stations=['car'], mode='window', target_altitude=[0.0], trigger='timer',
                rate=1.0, window=600.0, buffer_age=30.0)
    rng = np.random.default_rng(8)
    target = np.array([1500.0, 3000.0, 0.0])
    sigma = np.radians(4.0)
    stats = h.fusion.core.station_stats
    for k in range(120):
        t = 100 * S + k * S // 2
        pos = np.array([10.0 * k, 200.0 * np.sin(k / 60.0), 0.0])
        az = np.arctan2(target[1] - pos[1], target[0] - pos[0])
        az += sigma * rng.standard_normal()
        h.set_clock(t)
        h.send(bearing_to_msg(Bearing('car', t, pos, float(az), sigma_azimuth=sigma)), 'car')
        assert h.spin(lambda: stats('car').received == k + 1)
    h.set_clock(161 * S)
    assert h.spin(lambda: h.fixes and fix_from_msg(h.fixes[-1])[0] == 100 * S + 119 * S // 2)
    _, pos, cov = fix_from_msg(h.fixes[-1])
    e = pos[:2] - target[:2]
    assert e @ np.linalg.solve(cov[:2, :2], e) < 13.8
    d = h.diag(lambda d: values(d['fusion']).get('window_bearings') == '120')
    assert values(d['fusion'])['solve'] == 'horizontal'
