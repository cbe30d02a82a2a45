"""Fuzzing the message conversions the nodes run on every received message.

bearing_from_msg (fusion node, bag process), raw_reading_from_msg and pose_from_odometry
(station node) get messages with arbitrary field values: NaN, ±inf, ±1e308, subnormals,
negative variances, non-normalised stamps (nanosec ≥ 1e9), empty or foreign frames.
Property: each call returns a core object that passes the core's own validation, or raises
ConversionError with a documented reason; nothing else escapes, and an accepted message's
stamp is the one it carries (sec · 1e9 + nanosec, normalised).

Hypothesis runs derandomised with no example database and a fixed budget (a few seconds).
"""

import math

from geometry_msgs.msg import Vector3Stamped
from hypothesis import example, given, HealthCheck, settings, strategies as st
from nav_msgs.msg import Odometry
import numpy as np
import pytest

from bearing_loc_ros import ros_conversions as rc
from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.core.station import MAX_ABS_ANGLE

FUZZ = settings(max_examples=500, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck))
BEARING_REASONS = ('empty_frame_id', 'wrong_frame', 'bad_position', 'bad_quaternion',
                   'nonzero_roll', 'bad_azimuth_variance', 'bad_elevation_variance',
                   'bad_position_covariance', 'bad_stamp')
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
