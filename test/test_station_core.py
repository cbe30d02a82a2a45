"""bearing_loc_ros.core.station without ROS: datagrams, configuration, raw -> world bearings,
platform pose interpolation.

Expected bearings are computed from the geometry (target − station, Wang, Zhang & Wu (2006)
eq. (1)) and the reading is built the way each kind of sensor would report it, so the
conversions are checked against the definition, not against themselves.
"""

import math
import socket

import numpy as np
import pymap3d
import pytest
from scipy.spatial.transform import Rotation

from bearing_loc_ros.core import geodesy, udp
from bearing_loc_ros.core.conventions import azimuth_elevation, wrap_angle
from bearing_loc_ros.core.station import (ConfigError, parse_datagram, pose_sample, PoseBuffer,
                                          raw_reading, ReadingError, station_config,
                                          to_world_bearing)
from bearing_loc_ros.core.station import (MAX_ABS_ANGLE, MAX_DATAGRAM_BYTES,
                                          MAX_NUMBER_CHARS)

TOL = 1e-12  # radians: a few float operations on angles of order 1


# ---------------------------------------------------------------- datagrams

def test_datagram_full_and_exact_time():
    r = parse_datagram(b'{"t": 1700000000.123456789, "azimuth_deg": 90, "elevation_deg": -45.0,'
                       b' "sigma_deg": 2, "sigma_elevation_deg": 4.0, "extra": "ignored"}')
    assert r.stamp_ns == 1_700_000_000_123_456_789  # exact, not float-rounded
    assert r.azimuth == pytest.approx(math.pi / 2, abs=TOL)
    assert r.elevation == pytest.approx(-math.pi / 4, abs=TOL)
    assert r.sigma_azimuth == pytest.approx(math.radians(2.0))
    assert r.sigma_elevation == pytest.approx(math.radians(4.0))


def test_datagram_minimal_and_null_elevation():
    for data in (b'{"t": 12, "azimuth_deg": -10.5}',
                 '{"t": 12, "azimuth_deg": -10.5, "elevation_deg": null}'.encode()):
        r = parse_datagram(data)
        assert r.stamp_ns == 12 * 10 ** 9
        assert r.azimuth == pytest.approx(math.radians(-10.5))
        assert math.isnan(r.elevation) and math.isnan(r.sigma_azimuth)


@pytest.mark.parametrize('data, reason', [
    (b'', 'bad_json'),
    (b'not json', 'bad_json'),
    (b'\xff\xfe\x00', 'bad_json'),
    (b'{"t": 1, "azimuth_deg": NaN}', 'bad_json'),
    (b'{"t": 1, "azimuth_deg": Infinity}', 'bad_json'),
    (b'[1, 2]', 'not_object'),
    (b'"text"', 'not_object'),
    (b'{"azimuth_deg": 1}', 'missing_t'),
    (b'{"t": "now", "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": true, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": -5, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 0, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 1e12, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 1e999999999, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 1}', 'missing_azimuth'),
    (b'{"t": 1, "azimuth_deg": null}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": "10"}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": 1e400}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": 1, "elevation_deg": "up"}', 'bad_elevation'),
    (b'{"t": 1, "azimuth_deg": 1, "elevation_deg": 1e400}', 'bad_elevation'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_deg": 0}', 'bad_sigma'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_deg": -1}', 'bad_sigma'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_elevation_deg": [1]}', 'bad_sigma'),
    (b'[' * 100000, 'too_large'),
    (b'[' * 8000, 'bad_json'),
    (b' ' * (MAX_DATAGRAM_BYTES + 1), 'too_large'),
    # Integer literals past float range (once OverflowError, killing the node).
    (b'{"t": 1, "azimuth_deg": 1' + b'0' * 400 + b'}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": 1, "elevation_deg": -1' + b'0' * 400 + b'}', 'bad_elevation'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_deg": 1' + b'0' * 400 + b'}', 'bad_sigma'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_elevation_deg": ' + b'9' * 400 + b'}',
     'bad_sigma'),
    (b'{"t": 1' + b'0' * 400 + b', "azimuth_deg": 1}', 'bad_t'),
    # Huge exponents (once built into a 10^200000 integer: a stall of seconds).
    (b'{"t": 1e200000, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 1e999990, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 1e-999990, "azimuth_deg": 1}', 'bad_t'),
    (b'{"t": 1, "azimuth_deg": 1e-999990}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": 0.' + b'0' * 60 + b'1}', 'bad_azimuth'),
    # Angles whose wrap would be meaningless (1e300 was published as azimuth 0.0).
    (b'{"t": 1, "azimuth_deg": 1e300}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": -573000}', 'bad_azimuth'),
    (b'{"t": 1, "azimuth_deg": 1, "elevation_deg": 1e300}', 'bad_elevation'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_deg": 1e300}', 'bad_sigma'),
    (b'{"t": 1, "azimuth_deg": 1, "sigma_deg": 1e-300}', 'bad_sigma'),
])
def test_datagram_rejections(data, reason):
    with pytest.raises(ReadingError) as info:
        parse_datagram(data)
    assert info.value.reason == reason


def test_datagram_number_rejections_say_why():
    with pytest.raises(ReadingError, match=r'azimuth_deg: number literal of 401 characters'):
        parse_datagram(b'{"t": 1, "azimuth_deg": 1' + b'0' * 400 + b'}')
    with pytest.raises(ReadingError, match=r'exponent beyond'):
        parse_datagram(b'{"t": 1e200000, "azimuth_deg": 1}')


def test_datagram_limits_are_inclusive_and_ignored_keys_harmless():
    # The largest accepted angle is MAX_ABS_ANGLE rad; a sane sensor never comes near it.
    limit_deg = math.degrees(MAX_ABS_ANGLE)
    r = parse_datagram(f'{{"t": 1, "azimuth_deg": {limit_deg * (1 - 1e-12)!r}}}'.encode())
    assert r.azimuth == pytest.approx(MAX_ABS_ANGLE)
    # A 40-character literal is still converted exactly; an absurd literal in a key the
    # format ignores does not reject the reading.
    t = '1700000000.' + '1' * 29
    assert len(t) == MAX_NUMBER_CHARS
    r = parse_datagram(f'{{"t": {t}, "azimuth_deg": 1, "x": 1{"0" * 999}}}'.encode())
    assert r.stamp_ns == 1_700_000_000_111_111_111
    assert r.azimuth == pytest.approx(math.radians(1.0))


@pytest.mark.parametrize('literal', [b'1e1000000000000000000', b'-1E+1000000000000000000',
                                     b'1e-1000000000000000000', b'1e' + b'9' * 38])
def test_datagram_exponent_beyond_decimal_range_is_refused_never_raised(literal):
    """Exponents beyond what decimal can even hold (Decimal('1e1000000000000000000') raises
    InvalidOperation, which once escaped the parser and stopped the node): refused from the
    text, as a field's rejection; harmless in an ignored key; a zero is a zero."""
    with pytest.raises(ReadingError) as info:
        parse_datagram(b'{"t": 1700000000, "azimuth_deg": ' + literal + b'}')
    assert info.value.reason == 'bad_azimuth' and 'exponent beyond' in str(info.value)
    with pytest.raises(ReadingError) as info:
        parse_datagram(b'{"t": ' + literal + b', "azimuth_deg": 1}')
    assert info.value.reason == 'bad_t'
    r = parse_datagram(b'{"t": 1700000000, "azimuth_deg": 2, "x": ' + literal + b'}')
    assert r.stamp_ns == 1_700_000_000 * 10 ** 9
    assert r.azimuth == pytest.approx(math.radians(2.0))
    zero = b'0' + literal[literal.lower().index(b'e'):]
    r = parse_datagram(b'{"t": 1700000000, "azimuth_deg": ' + zero + b'}')
    assert r.azimuth == 0.0


def test_literal_exponent_is_the_decimal_exponent_without_converting():
    import decimal
    import random
    from bearing_loc_ros.core.datagram import json_decimal, literal_exponent
    rng = random.Random(5)
    for _ in range(3000):
        whole = rng.choice(['0', str(rng.randrange(1, 10 ** rng.randrange(1, 12)))])
        frac = ''.join(rng.choice('0123456789') for _ in range(rng.randrange(0, 12)))
        text = rng.choice(['', '-']) + whole + ('.' + frac if frac else '')
        if rng.random() < 0.7:
            text += rng.choice('eE') + rng.choice(['', '+', '-']) + str(rng.randrange(0, 500))
        d = decimal.Decimal(text)
        assert literal_exponent(text) == (d.adjusted() if d else None), text
        got = json_decimal(text)
        if d and abs(d.adjusted()) > 400:
            assert 'exponent beyond' in got.problem, text
        else:
            assert got == d, text


def test_datagram_without_t_when_restamping():
    assert parse_datagram(b'{"azimuth_deg": 3}', require_t=False).azimuth == \
        pytest.approx(math.radians(3))
    # re-stamped on receipt, t is not read: a bad one no longer rejects the datagram
    for t in (b'"soon"', b'0', b'null', b'-5'):
        assert parse_datagram(b'{"t": %s, "azimuth_deg": 3}' % t, require_t=False).stamp_ns == 1
        with pytest.raises(ReadingError) as e:
            parse_datagram(b'{"t": %s, "azimuth_deg": 3}' % t)
        assert e.value.reason == 'bad_t'


def test_an_azimuth_only_station_does_not_read_elevation_fields():
    data = b'{"t": 1700000000, "azimuth_deg": 3, "elevation_deg": "n/a", ' \
           b'"sigma_elevation_deg": -1}'
    r = parse_datagram(data, elevation=False)
    assert math.isnan(r.elevation) and math.isnan(r.sigma_elevation)
    with pytest.raises(ReadingError) as e:
        parse_datagram(data)
    assert e.value.reason == 'bad_elevation'


def test_a_key_given_twice_rejects_the_datagram():
    """json keeps the last value silently: the first azimuth was lost without a count."""
    with pytest.raises(ReadingError, match="duplicate key 'azimuth_deg'") as e:
        parse_datagram(b'{"t": 1700000000, "azimuth_deg": 10, "azimuth_deg": 200}')
    assert e.value.reason == 'bad_json'


def test_raw_reading_units_and_rejections():
    r = raw_reading(5, 180.0, 30.0, 'deg')
    assert (r.azimuth, r.elevation) == pytest.approx((math.pi, math.pi / 6))
    assert raw_reading(5, 1.0, units='rad').azimuth == 1.0
    for kwargs, reason in (({'stamp_ns': 0}, 'bad_stamp'),
                           ({'azimuth': math.inf}, 'bad_azimuth'),
                           ({'elevation': -math.inf}, 'bad_elevation'),
                           ({'sigma_azimuth': 0.0}, 'bad_sigma'),
                           ({'stamp_ns': 'now'}, 'bad_stamp'),
                           ({'azimuth': 10 ** 400}, 'bad_azimuth'),
                           ({'azimuth': 1e300}, 'bad_azimuth'),
                           ({'azimuth': 'north'}, 'bad_azimuth'),
                           ({'azimuth': True}, 'bad_azimuth'),
                           ({'elevation': 1e300}, 'bad_elevation'),
                           ({'sigma_elevation': 1e300}, 'bad_sigma'),
                           ({'sigma_azimuth': 1e-300}, 'bad_sigma')):
        args = {'stamp_ns': 5, 'azimuth': 1.0, **kwargs}
        with pytest.raises(ReadingError) as info:
            raw_reading(**args)
        assert info.value.reason == reason
    with pytest.raises(ValueError, match='units'):
        raw_reading(5, 1.0, units='grad')


# ---------------------------------------------------------------- configuration

def test_config_enu_and_geodetic_positions():
    c = station_config('s1', position=[1.0, 2.0, 3.0], position_covariance=[1.0, 4.0, 9.0],
                       sigma_azimuth_deg=1.5, azimuth_offset_deg=-2.0)
    np.testing.assert_array_equal(c.position, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(c.position_covariance, np.diag([1.0, 4.0, 9.0]))
    assert c.sigma_azimuth == pytest.approx(math.radians(1.5))
    assert c.azimuth_offset == pytest.approx(math.radians(-2.0))
    origin = [46.017, 7.750, 1673.0]
    g = station_config('s1', geodetic_position=[45.976, 7.658, 4531.0], geodetic_origin=origin)
    np.testing.assert_allclose(g.position, geodesy.geodetic_to_enu(45.976, 7.658, 4531.0,
                                                                   origin))
    m = station_config('s1', moving=True, geodetic_origin=origin)
    assert m.position is None and m.moving


@pytest.mark.parametrize('kwargs, field', [
    ({}, 'position'),
    ({'position': [1.0, 2.0]}, 'position'),
    ({'position': [1.0, math.nan, 2.0]}, 'position'),
    ({'position': [0.0, 0.0, 0.0], 'geodetic_position': [1.0, 2.0, 3.0]}, 'geodetic_position'),
    ({'geodetic_position': [1.0, 2.0, 3.0]}, 'geodetic_origin'),
    ({'geodetic_position': [1.0, 2.0, 3.0], 'geodetic_origin': [91.0, 0.0, 0.0]},
     'geodetic_origin'),
    ({'geodetic_position': [1.0, 200.0, 3.0], 'geodetic_origin': [1.0, 2.0, 0.0]},
     'geodetic_position'),
    ({'moving': True, 'position': [0.0, 0.0, 0.0]}, 'position'),
    ({'moving': True, 'geodetic_origin': [0.0, 0.0]}, 'geodetic_origin'),
    ({'position_covariance': [1.0, 2.0]}, 'position_covariance'),
    ({'position_covariance': [1.0, -2.0, 3.0]}, 'position_covariance'),
    ({'position_covariance': [1, 2, 0, 0, 1, 0, 0, 0, 1]}, 'position_covariance'),
    ({'position_covariance': [1, 0, 0, 0, 1, 0, 0, 0, math.inf]}, 'position_covariance'),
    ({'sigma_azimuth_deg': 0.0}, 'sigma_azimuth_deg'),
    ({'sigma_elevation_deg': 200.0}, 'sigma_elevation_deg'),
    ({'azimuth_reference': 'north'}, 'azimuth_reference'),
    ({'azimuth_offset_deg': 400.0}, 'azimuth_offset_deg'),
    ({'frame_id': ''}, 'frame_id'),
    ({'frame_id': 'a b'}, 'frame_id'),           # the fusion node refuses it
])
def test_config_errors_name_the_parameter(kwargs, field):
    if 'position' not in kwargs and 'geodetic_position' not in kwargs and field != 'position' \
            and not kwargs.get('moving'):
        kwargs = {'position': [0.0, 0.0, 0.0], **kwargs}
    with pytest.raises(ConfigError) as info:
        station_config('s1', **kwargs)
    assert info.value.field == field
    assert str(info.value).startswith(field + ': ')


def test_config_needs_a_station_id():
    with pytest.raises(ConfigError) as info:
        station_config('', position=[0.0, 0.0, 0.0])
    assert info.value.field == 'station_id'


# ---------------------------------------------------------------- raw -> world

STATION = np.array([100.0, -50.0, 10.0])
TARGETS = np.array([[900.0, 400.0, 300.0], [-700.0, -20.0, 5.0], [90.0, -800.0, -200.0],
                    [-300.0, 600.0, 900.0], [99.0, -50.0 - 1e-3, 10.0]])


@pytest.mark.parametrize('reference', ['enu', 'compass'])
@pytest.mark.parametrize('offset_deg', [0.0, 7.5, -123.0])
@pytest.mark.parametrize('two_d', [True, False])
def test_fixed_station_matches_geometry(reference, offset_deg, two_d):
    c = station_config('s1', position=STATION, azimuth_reference=reference,
                       azimuth_offset_deg=offset_deg, measures_elevation=two_d,
                       sigma_azimuth_deg=1.0, sigma_elevation_deg=3.0)
    delta = math.radians(offset_deg)
    for target in TARGETS:
        theta, psi = (float(v) for v in azimuth_elevation(target - STATION))
        # What the sensor reports: its own reference, minus its mounting offset.
        raw = (theta if reference == 'enu' else math.pi / 2 - theta) - delta
        b = to_world_bearing(raw_reading(77, raw, psi), c)
        assert abs(wrap_angle(b.azimuth - theta)) < TOL and -math.pi < b.azimuth <= math.pi
        assert b.stamp_ns == 77 and b.station == 's1' and b.frame_id == 'map'
        np.testing.assert_array_equal(b.position, STATION)
        assert b.sigma_azimuth == pytest.approx(math.radians(1.0))
        if two_d:
            assert b.elevation == pytest.approx(psi, abs=TOL)
            assert b.sigma_elevation == pytest.approx(math.radians(3.0))
        else:
            assert not b.has_elevation and math.isnan(b.sigma_elevation)
        b.validate()


@pytest.mark.parametrize('geodetic', [True, False])
def test_geodetic_station_uses_its_own_north_and_horizontal(geodetic):
    """A compass/elevation reading taken at a station 30 km from the origin is relative to the
    station's true North and horizon. The reading is what pymap3d.geodetic2aer gives at the
    station (azimuth clockwise from North, elevation above the local horizon); the bearing
    must point from the station to the target in the origin's ENU frame."""
    origin = (46.0, 7.0, 500.0)
    station_lla = (46.2, 7.3, 1200.0)
    target_lla = (46.25, 7.1, 3000.0)
    st_enu = geodesy.geodetic_to_enu(*station_lla, origin)
    kw = dict(geodetic_position=station_lla) if geodetic else dict(position=st_enu)
    c = station_config('far', geodetic_origin=origin, azimuth_reference='compass',
                       measures_elevation=True, **kw)
    az_deg, el_deg, _ = pymap3d.geodetic2aer(*target_lla, *station_lla)
    b = to_world_bearing(raw_reading(1, float(az_deg), float(el_deg), 'deg'), c)
    theta, psi = azimuth_elevation(geodesy.geodetic_to_enu(*target_lla, origin) - st_enu)
    assert abs(wrap_angle(b.azimuth - theta)) < 1e-9
    assert b.elevation == pytest.approx(psi, abs=1e-9)
    np.testing.assert_allclose(b.position, st_enu, atol=1e-9)
    # Without the correction the azimuth would be 3.3 mrad off here (meridian convergence
    # 3.8 mrad, partly offset by the tilt of the horizon; elevation 2.2 mrad off).
    naive = math.pi / 2 - math.radians(float(az_deg))
    assert abs(wrap_angle(naive - theta)) > 3e-3


def test_compass_examples_and_offset_sign():
    c = station_config('s1', position=[0.0, 0.0, 0.0], azimuth_reference='compass',
                       azimuth_offset_deg=10.0)
    # Compass 80° + offset 10° = 90° = due East -> ENU azimuth 0.
    assert to_world_bearing(raw_reading(1, 80.0, units='deg'), c).azimuth == \
        pytest.approx(0.0, abs=TOL)
    c = station_config('s1', position=[0.0, 0.0, 0.0], azimuth_offset_deg=10.0)
    # ENU 80° + 10° = 90° = due North.
    assert to_world_bearing(raw_reading(1, 80.0, units='deg'), c).azimuth == \
        pytest.approx(math.pi / 2)


def test_reading_sigma_overrides_and_bad_elevation():
    c = station_config('s1', position=[0.0, 0.0, 0.0], measures_elevation=True)
    b = to_world_bearing(raw_reading(1, 0.1, 0.2, sigma_azimuth=0.05, sigma_elevation=0.07), c)
    assert (b.sigma_azimuth, b.sigma_elevation) == (0.05, 0.07)
    with pytest.raises(ReadingError) as info:
        to_world_bearing(raw_reading(1, 0.1, math.pi / 2), c)
    assert info.value.reason == 'bad_elevation'
    # A 2D station whose reading lacks an elevation publishes an azimuth-only bearing.
    assert not to_world_bearing(raw_reading(1, 0.1), c).has_elevation


def _body_reading(target, pose, reference, delta):
    """What a body-mounted sensor reports for ``target`` (REP-103 body axes)."""
    u_b = Rotation.from_quat(pose.quaternion).inv().apply(target - pose.position)
    theta_b, psi_b = (float(v) for v in azimuth_elevation(u_b))
    raw = (theta_b if reference == 'enu' else -theta_b) - delta
    return raw, psi_b


@pytest.mark.parametrize('reference', ['enu', 'compass'])
def test_moving_platform_matches_geometry(reference):
    c = station_config('boat', moving=True, measures_elevation=True, azimuth_reference=reference,
                       azimuth_offset_deg=15.0, position_covariance=[1.0, 1.0, 1.0])
    rng = np.random.default_rng(3)
    for k in range(20):
        q = Rotation.from_euler('ZYX', [rng.uniform(-np.pi, np.pi), rng.uniform(-0.4, 0.4),
                                        rng.uniform(-0.4, 0.4)]).as_quat()
        pose = pose_sample(5, rng.uniform(-100, 100, 3), q, 0.5 * np.eye(3))
        target = rng.uniform(-2000, 2000, 3)
        raw, psi_b = _body_reading(target, pose, reference, math.radians(15.0))
        b = to_world_bearing(raw_reading(5, raw, psi_b), c, pose)
        theta, psi = (float(v) for v in azimuth_elevation(target - pose.position))
        assert abs(wrap_angle(b.azimuth - theta)) < 1e-9
        assert b.elevation == pytest.approx(psi, abs=1e-9)
        np.testing.assert_array_equal(b.position, pose.position)
        np.testing.assert_allclose(b.position_covariance, 1.5 * np.eye(3))


def test_moving_platform_level_1d_and_relative_bearing():
    """Heading 30° (ENU yaw); a contact 90° to starboard (compass relative 90°) is at
    yaw 30° − 90° = −60°."""
    c = station_config('boat', moving=True, azimuth_reference='compass')
    pose = pose_sample(1, [1.0, 2.0, 0.0], Rotation.from_euler('z', 30, degrees=True).as_quat())
    b = to_world_bearing(raw_reading(1, 90.0, units='deg'), c, pose)
    assert b.azimuth == pytest.approx(math.radians(-60.0)) and not b.has_elevation
    with pytest.raises(ValueError, match='pose'):
        to_world_bearing(raw_reading(1, 90.0, units='deg'), c)


# ---------------------------------------------------------------- pose buffer

def _pose(t_ns, x, yaw_deg):
    return pose_sample(t_ns, [x, 2.0 * x, 0.0],
                       Rotation.from_euler('z', yaw_deg, degrees=True).as_quat(),
                       np.eye(3) * (1.0 + x))


def test_pose_buffer_interpolation():
    buf = PoseBuffer(maxlen=10, tolerance_ns=50)
    with pytest.raises(ReadingError) as info:
        buf.interpolate(0)
    assert info.value.reason == 'no_odometry'
    assert buf.add(_pose(1000, 0.0, 0.0)) == 'ok'
    assert buf.add(_pose(2000, 10.0, 90.0)) == 'ok'
    p = buf.interpolate(1250)
    np.testing.assert_allclose(p.position, [2.5, 5.0, 0.0])
    np.testing.assert_allclose(p.position_covariance, np.eye(3) * 3.5)
    yaw = Rotation.from_quat(p.quaternion).as_euler('ZYX', degrees=True)
    np.testing.assert_allclose(yaw, [22.5, 0.0, 0.0], atol=1e-9)  # slerp: uniform rate
    # Within the tolerance outside the interval: the nearest pose, held.
    np.testing.assert_allclose(buf.interpolate(2040).position, [10.0, 20.0, 0.0])
    np.testing.assert_allclose(buf.interpolate(960).position, [0.0, 0.0, 0.0])
    for t, reason in ((2051, 'after_odometry'), (949, 'before_odometry')):
        with pytest.raises(ReadingError) as info:
            buf.interpolate(t)
        assert info.value.reason == reason


def test_pose_buffer_slerp_takes_the_short_way():
    buf = PoseBuffer()
    buf.add(_pose(0 + 1, 0.0, 170.0))
    buf.add(_pose(100 + 1, 0.0, -170.0))
    yaw = Rotation.from_quat(buf.interpolate(51).quaternion).as_euler('ZYX', degrees=True)[0]
    assert abs(wrap_angle(math.radians(yaw) - math.pi)) < 1e-9


def test_pose_buffer_bounded_ordered_and_reset():
    buf = PoseBuffer(maxlen=3, tolerance_ns=0, jump_ns=100)
    for k in range(1, 6):
        buf.add(_pose(k * 100, float(k), 0.0))
    assert len(buf) == 3 and buf.interval == (300, 500)
    assert buf.add(_pose(500, 9.0, 0.0)) == 'duplicate'
    assert buf.add(_pose(400, 9.0, 0.0)) == 'late'   # back by exactly jump_ns: reordered
    assert buf.interval == (300, 500)
    assert buf.add(_pose(399, 0.0, 0.0)) == 'reset'  # further: time jumped (bag restarted)
    assert len(buf) == 1 and buf.interval == (399, 399)
    for bad in (dict(maxlen=1), dict(max_gap_ns=0), dict(jump_ns=-1)):
        with pytest.raises(ValueError):
            PoseBuffer(**bad)


S_NS = 1_000_000_000


def test_pose_buffer_does_not_interpolate_across_an_odometry_outage():
    # Heading east at 1 s, west at 61 s (the car turned during a 60 s outage): the pose at
    # 31 s is unknown, not the midpoint heading north.
    buf = PoseBuffer()
    assert buf.max_gap_ns == 2 * S_NS
    buf.add(_pose(1 * S_NS, 0.0, 0.0))
    buf.add(_pose(61 * S_NS, 0.0, 180.0))
    with pytest.raises(ReadingError) as info:
        buf.interpolate(31 * S_NS)
    assert info.value.reason == 'odometry_gap' and '60.000 s' in str(info.value)
    # The poses themselves (within the hold tolerance) still serve, also inside the buffer:
    # a pose with another after the gap, at its own stamp and 50 ms off (tolerance 100 ms).
    np.testing.assert_allclose(buf.interpolate(61 * S_NS).position, [0.0, 0.0, 0.0])
    buf.add(_pose(62 * S_NS, 0.0, 180.0))
    for t in (S_NS, S_NS + 50_000_000, 61 * S_NS - 50_000_000):
        assert buf.interpolate(t).stamp_ns == t
    # A gap of exactly the limit is interpolated, one nanosecond more is not.
    buf = PoseBuffer(max_gap_ns=2 * S_NS)
    buf.add(_pose(S_NS, 0.0, 0.0))
    buf.add(_pose(3 * S_NS, 10.0, 0.0))
    np.testing.assert_allclose(buf.interpolate(2 * S_NS).position, [5.0, 10.0, 0.0])
    buf.add(_pose(5 * S_NS + 1, 20.0, 0.0))
    with pytest.raises(ReadingError) as info:
        buf.interpolate(4 * S_NS)
    assert info.value.reason == 'odometry_gap'


def test_one_late_odometry_message_does_not_wipe_the_buffer():
    buf = PoseBuffer()
    for k in range(1, 101):                      # 0.1 ... 10 s at 10 Hz
        assert buf.add(_pose(k * S_NS // 10, float(k), 0.0)) == 'ok'
    assert buf.add(_pose(95 * S_NS // 10 - 1, 9.5, 0.0)) == 'late'
    assert len(buf) == 100 and buf.interval == (S_NS // 10, 10 * S_NS)
    # An earlier bearing still finds its pose.
    np.testing.assert_allclose(buf.interpolate(5 * S_NS).position, [50.0, 100.0, 0.0])
    # A jump back by more than jump_ns (1 s) is a new clock: the buffer restarts.
    assert buf.add(_pose(8 * S_NS, 0.0, 0.0)) == 'reset' and len(buf) == 1


def test_pose_sample_rejections():
    q = [0.0, 0.0, 0.0, 1.0]
    for args, reason in ((dict(stamp_ns=0), 'odometry_bad_stamp'),
                         (dict(position=[0, math.nan, 0]), 'odometry_bad_position'),
                         (dict(quaternion=[0, 0, 0, 2.0]), 'odometry_bad_quaternion'),
                         (dict(quaternion=[math.nan, 0, 0, 1]), 'odometry_bad_quaternion'),
                         (dict(position_covariance=-np.eye(3)), 'odometry_bad_covariance')):
        kw = {'stamp_ns': 1, 'position': [0, 0, 0], 'quaternion': q, **args}
        with pytest.raises(ReadingError) as info:
            pose_sample(**kw)
        assert info.value.reason == reason


# ---------------------------------------------------------------- kernel UDP drops

@pytest.mark.parametrize('family, address', [(socket.AF_INET, '127.0.0.1'),
                                             (socket.AF_INET6, '::1')])
def test_udp_drops_counts_what_the_kernel_discarded(family, address):
    """Overflow a small receive buffer on loopback: received + dropped = sent, exactly."""
    try:
        rx = socket.socket(family, socket.SOCK_DGRAM)
        rx.bind((address, 0))
    except OSError:
        pytest.skip(f'no {address} loopback')
    tx = socket.socket(family, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        rx.setblocking(False)
        assert udp.udp_drops(rx) == 0
        sent = 300
        for _ in range(sent):
            tx.sendto(b'{"t": 1, "azimuth_deg": 1}'.ljust(200), rx.getsockname()[:2])
        received = 0
        while True:
            try:
                rx.recv(65535)
            except BlockingIOError:
                break
            received += 1
        drops = udp.udp_drops(rx)
        assert 0 < received < sent and drops == sent - received
        # Both sources read the same kernel counter.
        assert udp._drops_proc(rx) == drops
        assert udp._drops_meminfo(rx) in (drops, None)
    finally:
        tx.close()
        rx.close()
    assert udp.udp_drops(rx) is None  # closed: unknown, not an exception


def test_udp_drops_unsupported_sources_give_none(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        assert udp._drops_proc(s, tables=(str(tmp_path / 'missing'),)) is None
        other = tmp_path / 'udp'
        other.write_text('  sl  local_address rem_address ...\n'
                         '   0: 0100007F:0001 00000000:0000 07 0:0 00:0 0 0 0 1 2 0 5\n')
        assert udp._drops_proc(s, tables=(str(other),)) is None  # another socket's line
