"""Fuzzing the message conversions the nodes run on every received message.

bearing_from_msg (bag process), bearing_from_cdr (fusion node), raw_reading_from_msg and
pose_from_odometry (station node) get messages with arbitrary field values: NaN, ±inf,
±1e308, subnormals, negative variances, non-normalised stamps (nanosec ≥ 1e9), empty or
foreign frames. Property: each call returns a core object that passes the core's own
validation, or raises ConversionError with a documented reason; nothing else escapes, and an
accepted message's stamp is the one it carries (sec · 1e9 + nanosec, normalised).
bearing_from_cdr gives exactly what rclpy's deserialiser and bearing_from_msg give, on
serialised fuzzed messages and on malformed bytes.

Hypothesis runs derandomised with no example database and a fixed budget (a few seconds).
"""

import math
import struct

from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from hypothesis import example, given, HealthCheck, settings, strategies as st
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from bearing_loc_ros import ros_conversions as rc
from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.core.station import MAX_ABS_ANGLE

FUZZ = settings(max_examples=500, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck))
BEARING_REASONS = ('empty_frame_id', 'wrong_frame', 'bad_position', 'bad_quaternion',
                   'nonzero_roll', 'bad_azimuth_variance', 'bad_elevation_variance',
                   'bad_position_covariance', 'bad_covariance', 'bad_stamp')
RAW_REASONS = ('bad_stamp', 'bad_azimuth', 'bad_elevation')
ODOMETRY_REASONS = ('odometry_wrong_frame', 'odometry_bad_stamp', 'odometry_bad_position',
                    'odometry_bad_quaternion', 'odometry_bad_covariance')

INT32 = (-2 ** 31, 2 ** 31 - 1)
UINT32_MAX = 2 ** 32 - 1
nasty = st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -5e-324,
                         0.0, -0.0, 1e30, -1e30, 1e-30, -1.0, 1.0, 4e9])
floats = st.one_of(nasty, st.floats(), st.floats(-10.0, 10.0))
secs = st.one_of(st.integers(*INT32), st.sampled_from([0, 1, -1, INT32[1], INT32[0]]))
nanosecs = st.one_of(st.integers(0, UINT32_MAX),
                     st.sampled_from([0, 999_999_999, 1_000_000_000, 4_000_000_000,
                                      UINT32_MAX]))
frames = st.sampled_from(['map', '', 'odom', 'map ', 'MAP', 'μ'])


def _stamp(msg, sec, nanosec):
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec


def _accepted_stamp(sec, nanosec, got_ns):
    assert sec >= 0 and 0 <= nanosec < rc.NS_PER_S
    assert got_ns == sec * rc.NS_PER_S + nanosec


def _valid_bearing_msg():
    b = Bearing(station='s', stamp_ns=1_700_000_000_123_456_789, position=np.array([1., 2., 3.]),
                azimuth=0.5, elevation=0.2, sigma_azimuth=0.01, sigma_elevation=0.02,
                frame_id='map', position_covariance=np.eye(3))
    return rc.bearing_to_msg(b)


@st.composite
def bearing_msgs(draw):
    """A valid bearing message with some fields replaced by arbitrary values."""
    msg = _valid_bearing_msg()
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    cov = list(msg.pose.covariance)
    for obj, name in draw(st.lists(st.sampled_from(
            [(p, 'x'), (p, 'y'), (p, 'z'), (o, 'x'), (o, 'y'), (o, 'z'), (o, 'w')]),
            max_size=3)):
        setattr(obj, name, draw(floats))
    for i in draw(st.lists(st.sampled_from([0, 1, 7, 14, 12, rc.IDX_EL_VAR, rc.IDX_AZ_VAR,
                                            rc.IDX_AZ_VAR, rc.IDX_EL_VAR]), max_size=4)):
        cov[i] = draw(floats)
    msg.pose.covariance = cov
    if draw(st.booleans()):
        _stamp(msg, draw(secs), draw(nanosecs))
    if draw(st.booleans()):
        msg.header.frame_id = draw(frames)
    return msg


# ------------------------------------------------------------------ bearing_from_msg

@FUZZ
@given(bearing_msgs(), st.sampled_from([None, 'map']))
def test_bearing_from_msg(msg, expected_frame):
    try:
        b = rc.bearing_from_msg(msg, 'station_1', expected_frame=expected_frame)
    except rc.ConversionError as exc:
        assert exc.reason in BEARING_REASONS, exc
        return
    b.validate()  # what the core accepts, never an invalid or silently changed bearing
    assert -math.pi < b.azimuth <= math.pi
    assert b.frame_id == msg.header.frame_id != ''
    _accepted_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec, b.stamp_ns)


@pytest.mark.parametrize('sec, nanosec', [(1_700_000_000, 1_000_000_000),
                                          (1_700_000_000, 4_000_000_000),
                                          (5, UINT32_MAX), (-1, 0), (-2 ** 31, 5)])
def test_non_normalised_stamps_are_rejected(sec, nanosec):
    """nanosec ≥ 1e9 was taken as is (4e9 shifted the stamp by +4 s)."""
    msg = _valid_bearing_msg()
    _stamp(msg, sec, nanosec)
    with pytest.raises(rc.ConversionError) as info:
        rc.bearing_from_msg(msg, 'station_1')
    assert info.value.reason == 'bad_stamp'
    raw = Vector3Stamped()
    _stamp(raw, sec, nanosec)
    raw.vector.x = 1.0
    with pytest.raises(rc.ConversionError) as info:
        rc.raw_reading_from_msg(raw, 'rad')
    assert info.value.reason == 'bad_stamp'
    odom = Odometry()
    odom.header.frame_id = 'map'
    odom.pose.pose.orientation.w = 1.0
    _stamp(odom, sec, nanosec)
    with pytest.raises(rc.ConversionError) as info:
        rc.pose_from_odometry(odom, 'map')
    assert info.value.reason == 'odometry_bad_stamp'


def test_normalised_stamp_limits_are_accepted():
    msg = _valid_bearing_msg()
    _stamp(msg, 1_700_000_000, 999_999_999)
    assert rc.bearing_from_msg(msg, 's').stamp_ns == 1_700_000_000_999_999_999
    _stamp(msg, 0, 0)
    assert rc.bearing_from_msg(msg, 's').stamp_ns == 0


@pytest.mark.parametrize('index, value, reason', [
    (rc.IDX_AZ_VAR, 1e30, 'bad_azimuth_variance'),
    (rc.IDX_AZ_VAR, 1e-30, 'bad_azimuth_variance'),
    (rc.IDX_AZ_VAR, 5e-324, 'bad_azimuth_variance'),
    (rc.IDX_EL_VAR, 1e30, 'bad_elevation_variance'),
    (rc.IDX_EL_VAR, 1e-300, 'bad_elevation_variance'),
])
def test_variances_the_core_would_refuse_are_conversion_rejections(index, value, reason):
    """A σ outside the core's [1e-12, 1e3] rad is a counted conversion rejection, not an
    invalid bearing handed to the core (which logged one warning per message)."""
    msg = _valid_bearing_msg()
    cov = list(msg.pose.covariance)
    cov[index] = value
    msg.pose.covariance = cov
    with pytest.raises(rc.ConversionError) as info:
        rc.bearing_from_msg(msg, 's')
    assert info.value.reason == reason


# ------------------------------------------------------------------ bearing_from_cdr

def _outcome(convert):
    """('bearing', the Bearing's fields as reprs) or ('rejected', reason, text)."""
    try:
        b = convert()
    except rc.ConversionError as exc:
        return ('rejected', exc.reason, str(exc))
    return ('bearing', {k: repr(getattr(b, k)) for k in b.__dataclass_fields__})


def _plain(raw, expected_frame):
    """The plain path: rclpy deserialises, bearing_from_msg converts; bytes rclpy cannot
    deserialise are the reason malformed_cdr."""
    try:
        msg = deserialize_message(raw, PoseWithCovarianceStamped)
    except RuntimeError:
        return ('rejected', 'malformed_cdr')
    return _outcome(lambda: rc.bearing_from_msg(msg, 'station_1', expected_frame))


def _assert_same(raw, expected_frame):
    fast = _outcome(lambda: rc.bearing_from_cdr(raw, 'station_1', expected_frame))
    plain = _plain(raw, expected_frame)
    assert fast[:len(plain)] == plain, (raw, fast, plain)
    return fast


@FUZZ
@given(bearing_msgs(), st.sampled_from([None, 'map']), st.sampled_from(['', 'map', 'μ', 'a' * 9]))
def test_bearing_from_cdr_equals_the_plain_path(msg, expected_frame, frame):
    """The raw subscription's decoder gives exactly what rclpy's message plus
    bearing_from_msg give: the same Bearing bit for bit, or the same rejection."""
    if frame != 'map':
        msg.header.frame_id = frame      # frame lengths change the 8-byte padding
    _assert_same(serialize_message(msg), expected_frame)


@FUZZ
@given(st.data())
def test_bearing_from_cdr_on_malformed_bytes(data):
    """Truncated, extended, overwritten or random CDR: the same outcome as rclpy's
    deserialiser followed by bearing_from_msg (malformed_cdr where rclpy fails)."""
    raw = bytearray(serialize_message(_valid_bearing_msg()))
    for _ in range(data.draw(st.integers(1, 3))):
        kind = data.draw(st.sampled_from(['truncate', 'append', 'byte', 'length', 'random']))
        if kind == 'truncate':
            del raw[data.draw(st.integers(0, len(raw))):]
        elif kind == 'append':
            raw += data.draw(st.binary(max_size=16))
        elif kind == 'byte' and raw:
            raw[data.draw(st.integers(0, min(len(raw), 24) - 1))] = data.draw(
                st.integers(0, 255))
        elif kind == 'length' and len(raw) >= 16:
            raw[12:16] = data.draw(st.sampled_from([0, 1, 3, 4, 5, 8, 9, 400, 2 ** 31,
                                                    UINT32_MAX])).to_bytes(4, 'little')
        elif kind == 'random':
            raw = bytearray(data.draw(st.binary(max_size=400)))
    _assert_same(bytes(raw), data.draw(st.sampled_from([None, 'map'])))


def test_bearing_from_cdr_edge_layouts():
    """The forms the struct reader leaves to rclpy: big-endian CDR, a frame_id without
    its NUL, with an inner NUL, not UTF-8, empty; and bytes rclpy refuses."""
    raw = serialize_message(_valid_bearing_msg())
    assert raw[:2] == b'\x00\x01' and raw[12:20] == b'\x04\x00\x00\x00map\x00'
    sec, nanosec = struct.unpack_from('<iI', raw, 4)
    values = struct.unpack_from('<43d', raw, 20)
    big = b'\x00\x00\x00\x00' + struct.pack('>iII', sec, nanosec, 4) + b'map\x00' \
        + struct.pack('>43d', *values)
    assert _assert_same(big, 'map') == _outcome(
        lambda: rc.bearing_from_cdr(raw, 'station_1', 'map'))
    assert _assert_same(big, 'map')[0] == 'bearing'
    for frame_bytes, reason in ((b'mapx', 'wrong_frame'), (b'm\x00p\x00', 'wrong_frame'),
                                (b'\xffap\x00', 'wrong_frame'), (b'\x00\x00\x00\x00', None)):
        edited = raw[:16] + frame_bytes + raw[20:]
        out = _assert_same(edited, 'map')
        assert out[1] == (reason or 'empty_frame_id'), out
    empty = raw[:12] + (0).to_bytes(4, 'little') + raw[16:]
    assert _assert_same(empty, None)[:2] == ('rejected', 'empty_frame_id')
    for bad in (b'', raw[:3], raw[:-1], raw[:12] + b'\xff' * 4 + raw[16:],
                b'\x01' + raw[1:]):
        assert _assert_same(bad, 'map')[:2] == ('rejected', 'malformed_cdr'), bad


# ------------------------------------------------------------------ station inputs

@FUZZ
@given(floats, floats, secs, nanosecs, st.sampled_from(['rad', 'deg']))
@example(1e300, math.nan, 1, 0, 'deg')
def test_raw_reading_from_msg(x, y, sec, nanosec, units):
    msg = Vector3Stamped()
    msg.vector.x, msg.vector.y = x, y
    _stamp(msg, sec, nanosec)
    try:
        r = rc.raw_reading_from_msg(msg, units)
    except rc.ConversionError as exc:
        assert exc.reason in RAW_REASONS, exc
        return
    assert math.isfinite(r.azimuth) and abs(r.azimuth) <= MAX_ABS_ANGLE
    assert math.isnan(r.elevation) or abs(r.elevation) <= MAX_ABS_ANGLE
    _accepted_stamp(sec, nanosec, r.stamp_ns)


@FUZZ
@given(st.lists(floats, min_size=7, max_size=7), st.lists(floats, min_size=3, max_size=3),
       secs, nanosecs, frames)
def test_pose_from_odometry(pose, variances, sec, nanosec, frame):
    msg = Odometry()
    msg.header.frame_id = frame
    _stamp(msg, sec, nanosec)
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z, o.x, o.y, o.z, o.w = pose
    cov = [0.0] * 36
    cov[0], cov[7], cov[14] = variances
    msg.pose.covariance = cov
    try:
        s = rc.pose_from_odometry(msg, 'map')
    except rc.ConversionError as exc:
        assert exc.reason in ODOMETRY_REASONS, exc
        return
    assert np.all(np.isfinite(s.position)) and np.all(np.isfinite(s.position_covariance))
    assert abs(np.linalg.norm(s.quaternion) - 1.0) < 1e-12
    assert np.all(np.diag(s.position_covariance) >= 0.0)
    _accepted_stamp(sec, nanosec, s.stamp_ns)
