"""Receiver geometry (core.receiver): DOA sense, heading sources, position, σ mapping."""

import cmath
import math

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

from bearing_loc_ros.core import geodesy
from bearing_loc_ros.core.kraken import KrakenError, KrakenRecord
from bearing_loc_ros.core.receiver import (compass_bearing_deg, receiver_config,
                                           ReceiverGeometry, SigmaModel)
from bearing_loc_ros.core.station import ConfigError, PoseSample

ORIGIN = (48.85, 2.35, 35.0)
T0 = 1_700_000_000_000_000_000


def rec(doa, heading=math.nan, lat=math.nan, lon=math.nan, speed=math.nan, conf=1.0,
        stamp_ns=T0, snr=math.nan):
    return KrakenRecord(stamp_ns=stamp_ns, station_id='rx', frequency_hz=433.92e6,
                        doa_deg=doa, reported_deg=doa, confidence=conf, snr_db=snr,
                        latitude_deg=lat, longitude_deg=lon, heading_deg=heading, speed=speed)


def independent_compass(doa, heading, sense):
    """β from unit phasors: compass angles as exp(iβ) (clockwise positive); a DOA counter-
    clockwise from the array front is the clockwise angle −D; flipping multiplies by −1."""
    z = cmath.exp(1j * math.radians(heading))
    d = cmath.exp(1j * math.radians(doa))
    z *= {'inverted': d.conjugate(), 'flipped': -d, 'plain': d}[sense]
    return math.degrees(cmath.phase(z)) % 360.0


def ang_diff_deg(a, b):
    return abs((a - b + 180.0) % 360.0 - 180.0)


@settings(max_examples=300, deadline=None)
@given(doa=st.floats(0.0, 360.0), heading=st.floats(-360.0, 360.0),
       sense=st.sampled_from(['inverted', 'flipped', 'plain']))
def test_sense_against_independent_formula(doa, heading, sense):
    beta = compass_bearing_deg(doa, heading, sense)
    assert 0.0 <= beta < 360.0
    assert ang_diff_deg(beta, independent_compass(doa, heading, sense)) < 1e-9
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0], sense=sense,
                          array_heading_deg=heading)
    b = ReceiverGeometry(cfg).to_bearing(rec(doa))
    theta = math.pi / 2.0 - math.radians(independent_compass(doa, heading, sense))
    assert abs(cmath.phase(cmath.exp(1j * (b.azimuth - theta)))) < 1e-9


def test_sense_vectorised_and_unknown():
    d = np.array([0.0, 90.0, 270.0])
    np.testing.assert_allclose(compass_bearing_deg(d, 10.0), [10.0, 280.0, 100.0])
    np.testing.assert_allclose(compass_bearing_deg(d, 10.0, 'flipped'), [190.0, 280.0, 100.0])
    np.testing.assert_allclose(compass_bearing_deg(d, 10.0, 'plain'), [10.0, 100.0, 280.0])
    with pytest.raises(ValueError):
        compass_bearing_deg(1.0, 2.0, 'mirror')


def doa_for(station_xy, target_xy, heading_deg):
    """The DOA a KrakenSDR (counter-clockwise from the array front) reports."""
    dx, dy = target_xy[0] - station_xy[0], target_xy[1] - station_xy[1]
    beta = math.degrees(math.atan2(dx, dy)) % 360.0
    return (heading_deg - beta) % 360.0


def test_fixed_station_points_at_target_with_declination_and_offset():
    target = (400.0, -300.0)
    # array front at magnetic 100°, declination +2° East -> true 102°
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0], array_heading_deg=100.0,
                          heading_reference='magnetic', declination_deg=2.0)
    b = ReceiverGeometry(cfg).to_bearing(rec(doa_for((0, 0), target, 102.0)))
    assert b.azimuth == pytest.approx(math.atan2(-300.0, 400.0), abs=1e-12)
    # a receiver that reads 5° too far clockwise is corrected by heading_offset_deg = -5
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0], array_heading_deg=0.0,
                          heading_offset_deg=-5.0)
    b = ReceiverGeometry(cfg).to_bearing(rec((doa_for((0, 0), target, 0.0) - 5.0) % 360.0))
    assert b.azimuth == pytest.approx(math.atan2(-300.0, 400.0), abs=1e-12)


def test_gps_position_through_origin():
    enu_station = np.array([3000.0, -2000.0, 0.0])
    lat, lon, _ = geodesy.enu_to_geodetic(enu_station, ORIGIN)
    target = np.array([8000.0, 5000.0, 0.0])
    lat_t, lon_t, _ = geodesy.enu_to_geodetic(target, ORIGIN)
    # true bearing at the station: true North of the station itself
    here = (float(lat), float(lon), ORIGIN[2])
    d_local = geodesy.geodetic_to_enu(lat_t, lon_t, ORIGIN[2], here)
    beta = math.degrees(math.atan2(d_local[0], d_local[1])) % 360.0
    cfg = receiver_config('rx', geodetic_origin=list(ORIGIN), position_source='gps',
                          heading_source='fixed', array_heading_deg=40.0)
    geo = ReceiverGeometry(cfg)
    b = geo.to_bearing(rec((40.0 - beta) % 360.0, lat=float(lat), lon=float(lon)))
    np.testing.assert_allclose(b.position[:2], enu_station[:2], atol=1e-3)
    want = math.atan2(target[1] - b.position[1], target[0] - b.position[0])
    assert b.azimuth == pytest.approx(want, abs=2e-4)   # 10 km: curvature only
    assert b.position_covariance[0, 0] == pytest.approx(25.0)
    for lat_, lon_, reason in ((0.0, 0.0, 'zero_gps'), (math.nan, 1.0, 'no_gps')):
        with pytest.raises(KrakenError) as e:
            geo.to_bearing(rec(10.0, lat=lat_, lon=lon_))
        assert e.value.reason == reason


def circle_records(radius=200.0, speed=10.0, n=60, target=(1500.0, 700.0), with_speed=True):
    """A vehicle driving counter-clockwise on a circle about the origin (array front = bow)."""
    out = []
    omega = speed / radius
    for k in range(n):
        t = k * 1.0
        phi = omega * t
        p = (radius * math.cos(phi), radius * math.sin(phi))
        course = (math.degrees(math.atan2(-math.sin(phi), math.cos(phi)))) % 360.0
        lat, lon, _ = geodesy.enu_to_geodetic([p[0], p[1], 0.0], ORIGIN)
        doa = doa_for(p, target, course)
        out.append((p, course, rec(doa, heading=course, lat=float(lat), lon=float(lon),
                                   speed=speed if with_speed else math.nan,
                                   stamp_ns=T0 + int(t * 1e9))))
    return out


@pytest.mark.parametrize('with_speed', [True, False])
def test_vehicle_circle_gps_heading(with_speed):
    target = (1500.0, 700.0)
    cfg = receiver_config('van', geodetic_origin=list(ORIGIN), position_source='gps',
                          heading_source='gps', min_speed=2.0)
    geo = ReceiverGeometry(cfg)
    drive = circle_records(target=target, with_speed=with_speed)
    for k, (p, _, r) in enumerate(drive):
        if not with_speed and k == 0:     # no speed yet: derived from the next fix on
            with pytest.raises(KrakenError) as e:
                geo.to_bearing(r)
            assert e.value.reason == 'no_heading'
            continue
        b = geo.to_bearing(r)
        want = math.atan2(target[1] - b.position[1], target[0] - b.position[0])
        assert abs(cmath.phase(cmath.exp(1j * (b.azimuth - want)))) < 3e-4
    moving = geo.counts['heading_gps']
    assert moving == len(drive) - (0 if with_speed else 1)
    # stopped at the last point: the GPS course is noise, the held heading is right
    p, course, last = drive[-1]
    rng = np.random.default_rng(5)
    for k in range(10):
        junk = float(rng.uniform(0.0, 360.0))
        r = rec(doa_for(p, target, course), heading=junk, lat=last.latitude_deg,
                lon=last.longitude_deg, speed=0.3 if with_speed else math.nan,
                stamp_ns=last.stamp_ns + (k + 1) * 1_000_000_000)
        b = geo.to_bearing(r)
        want = math.atan2(target[1] - p[1], target[0] - p[0])
        assert abs(cmath.phase(cmath.exp(1j * (b.azimuth - want)))) < 3e-4
    assert geo.counts['heading_held'] == 10
    assert geo.counts['heading_gps'] == moving


def test_held_heading_timeout_and_odometry_fallback():
    cfg = receiver_config('van', position=[0.0, 0.0, 0.0], heading_source='gps',
                          min_speed=1.0, heading_hold_timeout_s=5.0)
    geo = ReceiverGeometry(cfg)
    geo.to_bearing(rec(0.0, heading=90.0, speed=5.0))
    geo.to_bearing(rec(0.0, heading=0.0, speed=0.0, stamp_ns=T0 + 4_000_000_000))
    with pytest.raises(KrakenError) as e:
        geo.to_bearing(rec(0.0, heading=0.0, speed=0.0, stamp_ns=T0 + 6_000_000_000))
    assert e.value.reason == 'no_heading'
    cfg = receiver_config('van', position=[0.0, 0.0, 0.0], heading_source='gps',
                          low_speed='odometry')
    assert cfg.needs_odometry
    geo = ReceiverGeometry(cfg)
    yaw = math.radians(30.0)      # ENU yaw 30° = compass 60°
    pose = PoseSample(T0, np.zeros(3), np.array([0.0, 0.0, math.sin(yaw / 2),
                                                 math.cos(yaw / 2)]))
    b = geo.to_bearing(rec(0.0, heading=200.0, speed=0.1), pose)
    assert b.azimuth == pytest.approx(yaw, abs=1e-12)
    with pytest.raises(KrakenError) as e:
        geo.to_bearing(rec(0.0, heading=200.0, speed=0.1), None)
    assert e.value.reason == 'no_odometry'


def test_low_confidence_rejected():
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0], min_confidence=0.3)
    with pytest.raises(KrakenError) as e:
        ReceiverGeometry(cfg).to_bearing(rec(10.0, conf=0.2))
    assert e.value.reason == 'low_confidence'


def test_sigma_model():
    m = SigmaModel()
    assert m.sigma(1.0) == pytest.approx(math.radians(3.0))
    assert m.sigma(5.0) == pytest.approx(math.radians(3.0))         # clipped to c = 1
    assert m.sigma(0.0) == pytest.approx(math.radians(12.0))
    assert m.sigma(0.5) == pytest.approx(math.radians(6.0))         # geometric midpoint
    assert m.sigma(math.nan) == pytest.approx(math.radians(12.0))
    crlb = SigmaModel(snr_slope=1.0, snr_ref_db=10.0, sigma_min_deg=0.01)
    # 20 dB above the reference: sigma / 10 (sigma ∝ SNR^-1/2)
    assert crlb.sigma(1.0, 30.0) == pytest.approx(math.radians(0.3))
    assert crlb.sigma(1.0, math.nan) == pytest.approx(math.radians(3.0))
    np.testing.assert_allclose(m.sigma(np.array([1.0, 0.0])), np.radians([3.0, 12.0]))
    assert SigmaModel(sigma_max_deg=5.0).sigma(0.0) == pytest.approx(math.radians(5.0))
    for bad in (dict(sigma_conf1_deg=0.0), dict(sigma_min_deg=50.0),
                dict(snr_slope=-1.0), dict(sigma_conf0_deg=math.nan)):
        with pytest.raises(ValueError):
            SigmaModel(**bad).validate()


@pytest.mark.parametrize('kw, field', [
    (dict(sense='mirror'), 'kraken.sense'),
    (dict(heading_source='compass'), 'kraken.heading_source'),
    (dict(declination_deg=200.0), 'kraken.declination_deg'),
    (dict(min_speed=-1.0), 'kraken.min_speed'),
    (dict(position_source='gps'), 'geodetic_origin'),
    (dict(position_source='satellite'), 'kraken.position_source'),
    (dict(sigma=SigmaModel(sigma_conf1_deg=-1.0)), 'kraken.sigma_conf1_deg'),
])
def test_config_errors_name_the_parameter(kw, field):
    args = dict(position=[0.0, 0.0, 0.0])
    if kw.get('position_source') in ('gps', 'satellite'):
        args = {}
    args.update(kw)
    with pytest.raises(ConfigError) as e:
        receiver_config('rx', **args)
    assert e.value.field == field


@pytest.mark.parametrize('kw, field, says', [
    (dict(position=[1.0, 2.0, 3.0], position_source='gps', geodetic_origin=[48.0, 11.0, 0.0]),
     'position', 'kraken.position_source: gps'),
    (dict(geodetic_position=[48.0, 11.0, 0.0], geodetic_origin=[48.0, 11.0, 0.0],
          position_source='odometry'), 'geodetic_position', 'kraken.position_source: odometry'),
    (dict(position_source='parameters'), 'position', 'kraken.position_source: gps or '
                                                     'odometry'),
])
def test_position_conflicts_name_the_receiver_parameter(kw, field, says):
    """A position given with kraken.position_source gps once said "must not be set with
    platform_odometry", a parameter the user never set."""
    with pytest.raises(ConfigError) as e:
        receiver_config('rx', **kw)
    assert e.value.field == field
    assert says in e.value.problem and 'platform_odometry' not in e.value.problem


def test_max_age_with_receive_stamps_is_a_start_up_error():
    """kraken.max_age was silently ignored with kraken.stamp: receive."""
    from bearing_loc_ros.core.receiver_params import receiver_from_params
    p = {'position': [0.0, 0.0, 0.0], 'kraken.stamp': 'receive', 'kraken.max_age': 5.0}
    with pytest.raises(ConfigError) as e:
        receiver_from_params('rx', p)
    assert e.value.field == 'kraken.max_age' and 'kraken.stamp: receive' in e.value.problem
    receiver_from_params('rx', dict(p, **{'kraken.max_age': 0.0}))
    receiver_from_params('rx', dict(p, **{'kraken.stamp': 'receiver'}))
