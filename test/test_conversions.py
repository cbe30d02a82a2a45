"""Property tests of bearing_loc_ros.ros_conversions (messages built in-process, no node).

Round trips go through real CDR serialisation (rclpy.serialization) so what is checked is what
a subscriber receives. Hypothesis runs derandomised (same examples every run) without an
example database, so the tests are reproducible and write nothing into the repository.

Tolerances: the quaternion (x, y, z, w) of a bearing is computed from sin/cos of θ/2 and ψ/2
and read back with atan2; each step is correct to a few ulp of 1, so angles come back within
4e-15 rad (about 9 ulp of π; the largest error seen over 2e4 random bearings was 6.7e-16) —
"exact up to float rounding". Positions, covariances, stamps
and frame ids are copied, so they must come back bit-identical.
"""

import math

from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from hypothesis import given, HealthCheck, settings, strategies as st
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import NavSatFix, NavSatStatus

from bearing_loc_ros import ros_conversions as rc
from bearing_loc_ros.core.bearings import Bearing
from bearing_loc_ros.core.conventions import (azel_from_quaternion, quaternion_from_azel,
                                              wrap_angle)
from bearing_loc_ros.core.geodesy import geodetic_to_enu

ANGLE_TOL = 4e-15
PROP = settings(max_examples=150, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
HALF_PI = math.pi / 2.0

azimuths = st.floats(-math.pi, math.pi, exclude_min=True)
elevations = st.floats(-HALF_PI, HALF_PI, exclude_min=True, exclude_max=True)
sigmas = st.floats(1e-6, 1.0)
coords = st.floats(-1e7, 1e7, allow_nan=False)
stamps = st.integers(0, rc.MAX_TIME_NS)
frames = st.text(alphabet='abcdefghijklmnopqrstuvwxyz_/0123456789', min_size=1, max_size=20)
finite9 = st.lists(st.floats(-100.0, 100.0), min_size=9, max_size=9)


def _psd(values):
    a = np.asarray(values, dtype=float).reshape(3, 3)
    return a @ a.T


@st.composite
def bearings(draw, two_d=None):
    """A valid core Bearing: 1D or 2D (random unless ``two_d`` is given)."""
    has_el = draw(st.booleans()) if two_d is None else two_d
    return Bearing(station='s1', stamp_ns=draw(stamps),
                   position=np.array([draw(coords), draw(coords), draw(coords)]),
                   azimuth=draw(azimuths),
                   elevation=draw(elevations) if has_el else float('nan'),
                   sigma_azimuth=draw(sigmas),
                   sigma_elevation=draw(sigmas) if has_el else float('nan'),
                   frame_id=draw(frames), position_covariance=_psd(draw(finite9)))


def _wire(msg):
    """What a subscriber receives: serialise to CDR and back."""
    return deserialize_message(serialize_message(msg), type(msg))


@PROP
@given(bearings())
def test_bearing_round_trip(b):
    msg = _wire(rc.bearing_to_msg(b))
    assert msg.header.frame_id == b.frame_id
    out = rc.bearing_from_msg(msg, 's1', expected_frame=b.frame_id)
    assert out.station == 's1' and out.frame_id == b.frame_id
    assert out.stamp_ns == b.stamp_ns
    assert np.array_equal(out.position, b.position)
    assert np.array_equal(out.position_covariance, b.position_covariance)
    assert -math.pi < out.azimuth <= math.pi
    assert abs(wrap_angle(out.azimuth - b.azimuth)) <= ANGLE_TOL
    assert out.sigma_azimuth == pytest.approx(b.sigma_azimuth, rel=1e-15)
    if b.has_elevation:
        assert out.has_elevation and abs(out.elevation) < HALF_PI
        assert abs(out.elevation - b.elevation) <= ANGLE_TOL
        assert out.sigma_elevation == pytest.approx(b.sigma_elevation, rel=1e-15)
    else:
        assert math.isnan(out.elevation) and math.isnan(out.sigma_elevation)
        assert msg.pose.covariance[rc.IDX_EL_VAR] == rc.NO_ELEVATION
    out.validate()


@pytest.mark.parametrize('az, el', [
    (math.pi, 0.0), (-math.pi + 1e-16, 0.3), (math.nextafter(-math.pi, 0.0), -0.2),
    (0.7, math.nextafter(HALF_PI, 0.0)), (-2.0, -math.nextafter(HALF_PI, 0.0)),
    (3.0, HALF_PI - 1e-9)])
def test_bearing_round_trip_edges(az, el):
    """The ±π wrap and lines of sight within rounding of the vertical still round-trip."""
    b = Bearing('s', 5, np.zeros(3), az, el, 0.01, 0.02)
    out = rc.bearing_from_msg(_wire(rc.bearing_to_msg(b)), 's')
    assert -math.pi < out.azimuth <= math.pi
    assert abs(wrap_angle(out.azimuth - az)) <= ANGLE_TOL
    assert abs(out.elevation - el) <= ANGLE_TOL and abs(out.elevation) < HALF_PI


def _vectorised_angles(msg):
    """Reference: the angles as the vectorised conventions functions compute them."""
    o = msg.pose.pose.orientation
    az, el, _ = azel_from_quaternion(np.array([o.x, o.y, o.z, o.w]))
    return wrap_angle(az), float(np.clip(el, -rc.MAX_ELEVATION, rc.MAX_ELEVATION))


def _ulps(a, b):
    return abs(a - b) / math.ulp(max(abs(a), abs(b)))


@PROP
@given(bearings(), st.floats(0.9995, 1.0005))
def test_bearing_from_msg_matches_vectorised_maths(b, scale):
    """The scalar per-message path gives the vectorised conventions' angles within 1 ulp
    (numpy's SIMD arctan2/arcsin round differently from libm on some inputs; both are within
    1 ulp of the true value), also for accepted non-unit quaternions (|q| within 1e-3 of 1),
    and plain Python floats / fresh float64 arrays that do not alias the message."""
    msg = rc.bearing_to_msg(b)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = o.x * scale, o.y * scale, o.z * scale, o.w * scale
    out = rc.bearing_from_msg(msg, 's1')
    az, el = _vectorised_angles(msg)
    assert type(out.azimuth) is float and _ulps(out.azimuth, az) <= 1.0
    if b.has_elevation:
        assert type(out.elevation) is float and _ulps(out.elevation, el) <= 1.0
        assert out.sigma_elevation == math.sqrt(msg.pose.covariance[rc.IDX_EL_VAR])
    assert out.sigma_azimuth == math.sqrt(msg.pose.covariance[rc.IDX_AZ_VAR])
    for arr, shape in ((out.position, (3,)), (out.position_covariance, (3, 3))):
        assert arr.dtype == np.float64 and arr.shape == shape and arr.flags.c_contiguous
    msg.pose.covariance[0] += 1.0
    msg.pose.pose.position.x += 1.0
    assert np.array_equal(out.position_covariance, b.position_covariance)
    assert np.array_equal(out.position, b.position)


@PROP
@given(bearings())
def test_bearing_to_msg_matches_vectorised_maths(b):
    """Orientation bit-identical to quaternion_from_azel; covariance laid out as before."""
    msg = rc.bearing_to_msg(b)
    o = msg.pose.pose.orientation
    q = quaternion_from_azel(b.azimuth, b.elevation if b.has_elevation else 0.0)
    assert np.array_equal([o.x, o.y, o.z, o.w], q)
    cov = np.zeros((6, 6))
    cov[:3, :3] = b.position_covariance
    cov[4, 4] = b.sigma_elevation ** 2 if b.has_elevation else rc.NO_ELEVATION
    cov[5, 5] = b.sigma_azimuth ** 2
    assert msg.pose.covariance.dtype == np.float64
    assert np.array_equal(msg.pose.covariance, cov.ravel())
    p = msg.pose.pose.position
    assert all(type(v) is float for v in (p.x, p.y, p.z, o.x, o.y, o.z, o.w))


def test_in_process_covariance_list_or_matrix():
    """A message built in-process may hold the covariance as a list or a (6, 6) array."""
    b = Bearing('s1', 7, np.array([1.0, 2.0, 3.0]), 0.4, 0.2, 0.01, 0.02,
                position_covariance=np.diag([1.0, 4.0, 9.0]))
    ref = rc.bearing_from_msg(rc.bearing_to_msg(b), 's1')
    for value in (rc.bearing_to_msg(b).pose.covariance.tolist(),
                  rc.bearing_to_msg(b).pose.covariance.reshape(6, 6)):
        msg = rc.bearing_to_msg(b)
        msg.pose.covariance = value
        out = rc.bearing_from_msg(msg, 's1')
        assert out.azimuth == ref.azimuth and out.elevation == ref.elevation
        assert np.array_equal(out.position_covariance, ref.position_covariance)


def test_rejection_order_and_messages():
    """The first broken rule is reported, in the documented order, with the same text."""
    b = Bearing('s1', 7, np.zeros(3), 0.4, 0.2, 0.01, 0.02)
    msg = rc.bearing_to_msg(b)
    cov = msg.pose.covariance.copy()
    cov[rc.IDX_AZ_VAR], cov[rc.IDX_EL_VAR], cov[0] = 0.0, -2.0, math.nan
    msg.pose.covariance = cov
    with pytest.raises(rc.ConversionError, match=r'^bad_azimuth_variance: azimuth variance '
                                                 r'0\.0$'):
        rc.bearing_from_msg(msg, 's1')
    cov[rc.IDX_AZ_VAR] = 1e-4
    msg.pose.covariance = cov
    with pytest.raises(rc.ConversionError, match=r'elevation variance -2\.0 \(use -1'):
        rc.bearing_from_msg(msg, 's1')
    cov[rc.IDX_EL_VAR] = rc.NO_ELEVATION
    msg.pose.covariance = cov
    assert _reason(msg) == 'bad_position_covariance'
    q = Rotation.from_euler('ZYX', [0.4, -0.2, 0.1]).as_quat()
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    with pytest.raises(rc.ConversionError, match=r'^nonzero_roll: roll about 0\.1 rad'):
        rc.bearing_from_msg(msg, 's1')
    o.w *= 2.0
    with pytest.raises(rc.ConversionError, match=r'^bad_quaternion: quaternion norm 1\.'):
        rc.bearing_from_msg(msg, 's1')
    msg.pose.pose.position.z = math.inf
    assert _reason(msg, expected_frame='map') == 'bad_position'
    assert _reason(msg, expected_frame='odom') == 'wrong_frame'


def test_bearing_to_msg_refuses_a_position_that_is_not_three_coordinates():
    b = Bearing('s1', 7, np.zeros((1, 3)), 0.4)
    with pytest.raises(ValueError, match='position'):
        rc.bearing_to_msg(b)


def _reason(msg, expected_frame=None):
    with pytest.raises(rc.ConversionError) as info:
        rc.bearing_from_msg(msg, 's1', expected_frame)
    return info.value.reason


@PROP
@given(bearings(), st.integers(0, 3), st.sampled_from([math.nan, math.inf, -math.inf]))
def test_rejects_non_finite_quaternion_or_position(b, i, bad):
    msg = rc.bearing_to_msg(b)
    o = msg.pose.pose.orientation
    setattr(o, 'xyzw'[i], bad)
    assert _reason(msg) == 'bad_quaternion'
    msg = rc.bearing_to_msg(b)
    setattr(msg.pose.pose.position, 'xyz'[i % 3], bad)
    assert _reason(msg) == 'bad_position'


@PROP
@given(bearings(), st.one_of(st.floats(0.0, 0.998), st.floats(1.002, 1e3)))
def test_rejects_non_unit_quaternion(b, scale):
    msg = rc.bearing_to_msg(b)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = o.x * scale, o.y * scale, o.z * scale, o.w * scale
    assert _reason(msg) == 'bad_quaternion'


def _reason_with_variance(b, index, var):
    """The rejection reason of b's message with covariance entry ``index`` set to ``var``."""
    msg = rc.bearing_to_msg(b)
    cov = list(msg.pose.covariance)
    cov[index] = var
    msg.pose.covariance = cov
    return _reason(msg)


@PROP
@given(bearings(), st.one_of(st.floats(max_value=0.0), st.just(math.nan)))
def test_rejects_bad_azimuth_variance(b, var):
    assert _reason_with_variance(b, rc.IDX_AZ_VAR, var) == 'bad_azimuth_variance'


@PROP
@given(bearings(), st.one_of(st.floats(max_value=0.0).filter(lambda v: v != -1.0),
                             st.just(math.nan), st.just(math.inf)))
def test_rejects_bad_elevation_variance(b, var):
    assert _reason_with_variance(b, rc.IDX_EL_VAR, var) == 'bad_elevation_variance'


@PROP
@given(azimuths, st.floats(-1.4, 1.4), st.floats(1e-3, math.pi), st.booleans())
def test_rejects_roll(az, el, roll, negative):
    """Any roll with |φ| ≥ 1e-3 (up to upside down, φ = ±π) is rejected.

    The check sees sin φ cos ψ and cos φ cos ψ against 1e-6; with |ψ| ≤ 1.4, cos ψ ≥ 0.17,
    so |φ| ≥ 1e-3 gives at least 1.7e-4, far above the tolerance.
    """
    phi = -roll if negative else roll
    b = Bearing('s1', 1, np.zeros(3), az, el, 0.01, 0.01)
    msg = rc.bearing_to_msg(b)
    q = Rotation.from_euler('ZYX', [az, -el, phi]).as_quat()
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    assert _reason(msg) == 'nonzero_roll'


def test_roll_of_pi_would_flip_the_azimuth():
    """Regression: φ = π used to pass (sin φ = 0) and report θ + π."""
    msg = rc.bearing_to_msg(Bearing('s1', 1, np.zeros(3), 0.5, 0.2, 0.01, 0.01))
    q = Rotation.from_euler('ZYX', [0.5, -0.2, math.pi]).as_quat()
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    assert _reason(msg) == 'nonzero_roll'


@PROP
@given(bearings(), frames)
def test_rejects_frames_and_position_covariance(b, other):
    msg = rc.bearing_to_msg(b)
    msg.header.frame_id = ''
    assert _reason(msg) == 'empty_frame_id'
    msg.header.frame_id = b.frame_id
    if other != b.frame_id:
        assert _reason(msg, expected_frame=other) == 'wrong_frame'
    cov = list(msg.pose.covariance)
    cov[7] = -1.0  # the y variance
    msg.pose.covariance = cov
    assert _reason(msg) == 'bad_position_covariance'
    cov[7], cov[1] = 1.0, math.nan
    msg.pose.covariance = cov
    assert _reason(msg) == 'bad_position_covariance'


@pytest.mark.parametrize('index, value', [(21, math.nan), (5, math.inf), (29, -math.inf)])
def test_a_non_finite_entry_anywhere_in_the_covariance_is_rejected(index, value):
    """Only the position block and the two angle variances are read; a NaN or inf elsewhere
    (roll variance, a cross term) was accepted without a word."""
    msg = rc.bearing_to_msg(Bearing('s1', 1, np.array([10.0, 20.0, 0.0]), 0.5, 0.2, 0.01,
                                    0.01))
    cov = list(msg.pose.covariance)
    cov[index] = value
    msg.pose.covariance = cov
    for read in (lambda: rc.bearing_from_msg(msg, 's1'),
                 lambda: rc.bearing_from_cdr(serialize_message(msg), 's1')):
        with pytest.raises(rc.ConversionError, match=rf'covariance\[{index}\]') as err:
            read()
        assert err.value.reason == 'bad_covariance'
    cov[index] = 0.0
    cov[21] = cov[22] = 1e308                           # huge but finite: not read, accepted
    msg.pose.covariance = cov
    assert rc.bearing_from_msg(msg, 's1').azimuth == pytest.approx(0.5)


def _with_position_covariance(P):
    msg = rc.bearing_to_msg(Bearing('s1', 1, np.array([10.0, 20.0, 0.0]), 0.5, 0.2, 0.01, 0.01))
    cov = list(msg.pose.covariance)
    for i in range(3):
        cov[6 * i:6 * i + 3] = [float(x) for x in P[i]]
    msg.pose.covariance = cov
    return msg


@pytest.mark.parametrize('P, problem', [
    # indefinite (eigenvalues -1e7, 0, 1e7): it made a lying station's gate distance negative
    ([[0.0, 1e7, 0.0], [1e7, 0.0, 0.0], [0.0, 0.0, 0.0]], 'not positive semi-definite'),
    ([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]], 'not positive semi-definite'),
    ([[4.0, 1.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 4.0]], 'not symmetric'),
    ([[4.0, 0.0, 0.0], [0.0, -1e-9, 0.0], [0.0, 0.0, 4.0]], 'negative variance'),
])
def test_position_covariance_must_be_a_covariance(P, problem):
    from bearing_loc_ros.core.fusion.stations import bearing_problem
    msg = _with_position_covariance(P)
    for read in (lambda: rc.bearing_from_msg(msg, 's1'),
                 lambda: rc.bearing_from_cdr(serialize_message(msg), 's1')):
        with pytest.raises(rc.ConversionError, match=problem) as err:
            read()
        assert err.value.reason == 'bad_position_covariance'
    b = Bearing('s1', 1, np.zeros(3), 0.5, 0.2, 0.01, 0.01,
                position_covariance=np.array(P, dtype=float))
    assert problem in bearing_problem(b)


def test_position_covariance_rounding_is_accepted():
    """A rotated covariance with rounding in its last bits, a singular (flat) one and a
    surveyed station's zeros are all covariances."""
    R = Rotation.from_euler('ZYX', [0.7, -0.3, 0.2]).as_matrix()
    for d in ([25.0, 4.0, 1.0], [25.0, 4.0, 0.0]):
        P = R @ np.diag(d) @ R.T
        P[0, 1] *= 1.0 + 1e-14                  # asymmetric in the last bits
        b = rc.bearing_from_msg(_with_position_covariance(P), 's1')
        np.testing.assert_array_equal(b.position_covariance, P)
    b = rc.bearing_from_msg(_with_position_covariance(np.zeros((3, 3))), 's1')
    assert not b.position_covariance.any()


def test_bearing_to_msg_refuses_invalid_bearings():
    ok = dict(station='s', stamp_ns=1, position=np.zeros(3), azimuth=0.1)
    with pytest.raises(ValueError, match='azimuth'):
        rc.bearing_to_msg(Bearing(**{**ok, 'azimuth': math.nan}))
    with pytest.raises(ValueError, match='sigma_azimuth'):
        rc.bearing_to_msg(Bearing(**ok, sigma_azimuth=0.0))
    with pytest.raises(ValueError, match='elevation'):
        rc.bearing_to_msg(Bearing(**ok, elevation=HALF_PI, sigma_elevation=0.1))
    with pytest.raises(ValueError, match='frame_id'):
        rc.bearing_to_msg(Bearing(**ok, frame_id=''))
    with pytest.raises(ValueError, match='position_covariance'):
        rc.bearing_to_msg(Bearing(**ok, position_covariance=np.eye(2)))
    with pytest.raises(ValueError, match='stamp'):
        rc.bearing_to_msg(Bearing(**{**ok, 'stamp_ns': -1}))


@PROP
@given(stamps)
def test_time_round_trip(ns):
    t = _wire(rc.ns_to_time(ns))
    assert 0 <= t.nanosec < rc.NS_PER_S
    assert rc.time_to_ns(t) == ns


def test_time_range():
    with pytest.raises(ValueError, match='negative'):
        rc.ns_to_time(-1)
    with pytest.raises(ValueError, match='int32'):
        rc.ns_to_time(rc.MAX_TIME_NS + 1)


@PROP
@given(st.lists(coords, min_size=3, max_size=3), finite9, stamps, frames)
def test_fix_round_trip(p, c, ns, frame):
    cov = _psd(c)
    msg = _wire(rc.fix_to_msg(p, cov, ns, frame))
    assert msg.header.frame_id == frame
    assert msg.pose.pose.orientation.w == 1.0
    assert msg.pose.covariance[35] == rc.UNKNOWN_ROTATION_VARIANCE
    stamp, pos, cov2 = rc.fix_from_msg(msg)
    assert stamp == ns and np.array_equal(pos, p) and np.array_equal(cov2, cov)


@PROP
@given(st.lists(coords, min_size=3, max_size=3), finite9, stamps,
       st.one_of(frames, st.text(max_size=12)))
def test_fix_to_cdr_is_the_serialized_fix_msg(p, c, ns, frame):
    """The node publishes fix_to_cdr's bytes: what rclpy serializes of fix_to_msg, byte for
    byte except the alignment padding after frame_id, which CDR leaves unspecified (rclpy's
    serializer leaves whatever its buffer held there; fix_to_cdr writes zeros)."""
    cov = np.asarray(c, dtype=float).reshape(3, 3)
    if '\x00' in frame:
        return          # rclpy truncates a string at NUL; a frame_id never holds one
    msg = rc.fix_to_msg(p, cov, ns, frame)
    got, want = rc.fix_to_cdr(p, cov, ns, frame), serialize_message(msg)
    end = 16 + len(frame.encode()) + 1          # header, stamp, length, frame_id and NUL
    pad = -(end - 4) % 8
    assert len(got) == len(want) and got[:end] == want[:end]
    assert got[end:end + pad] == bytes(pad) and got[end + pad:] == want[end + pad:]
    back = deserialize_message(got, PoseWithCovarianceStamped)
    assert back.header == msg.header and back.pose == msg.pose


def test_fix_to_cdr_packs_the_covariance_as_the_array_bytes():
    """The 3 × 3 covariance packed from floats gives the bytes of the 6 × 6 float64 array
    (also -0.0, NaN and inf); another shape that broadcasts takes the array path."""
    cov = np.array([[1.5, -0.0, np.nan], [np.inf, 2.0, -3e-300], [7.0, 8.0, -np.inf]])
    full = np.zeros((6, 6))
    full[:3, :3] = cov
    full[3, 3] = full[4, 4] = full[5, 5] = rc.UNKNOWN_ROTATION_VARIANCE
    assert rc.fix_to_cdr([1.0, 2.0, 3.0], cov, 5, 'map').endswith(full.tobytes())
    full[:3, :3] = [1.0, 2.0, 3.0]
    assert rc.fix_to_cdr([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], 5, 'map').endswith(
        full.tobytes())


def test_fix_to_cdr_refuses_what_fix_to_msg_refuses():
    for ns in (-1, rc.MAX_TIME_NS + 1):
        with pytest.raises(ValueError, match='stamp'):
            rc.fix_to_cdr([0.0, 0.0, 0.0], np.eye(3), ns, 'map')


origins = st.tuples(st.floats(-80.0, 80.0), st.floats(-180.0, 180.0), st.floats(-100.0, 3000.0))
enu_points = st.lists(st.floats(-50e3, 50e3), min_size=3, max_size=3)


@PROP
@given(enu_points, finite9, stamps, origins)
def test_navsat_round_trip(p, c, ns, origin):
    cov = _psd(c)
    msg = _wire(rc.fix_to_navsat(p, cov, ns, origin, 'gps'))
    assert msg.status.status == NavSatStatus.STATUS_FIX
    assert msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_KNOWN
    assert rc.time_to_ns(msg.header.stamp) == ns and msg.header.frame_id == 'gps'
    assert -90.0 <= msg.latitude <= 90.0 and -180.0 <= msg.longitude <= 180.0
    stamp, pos, cov2 = rc.navsat_to_fix(msg, origin)
    assert stamp == ns
    # pymap3d's geodetic inversions are accurate to well below a micrometre at these ranges.
    np.testing.assert_allclose(pos, p, rtol=0, atol=1e-6)
    # Rotations are orthonormal to rounding: relative error ~ 1e-15 of the largest entry.
    np.testing.assert_allclose(cov2, cov, rtol=0, atol=1e-12 * max(1.0, np.abs(cov).max()))
    # The covariance is a similarity transform: same eigenvalues (PSD, same trace).
    reported = np.asarray(msg.position_covariance).reshape(3, 3)
    assert np.trace(reported) == pytest.approx(np.trace(cov), rel=1e-12, abs=1e-12)


def test_navsat_at_origin_and_known_point():
    origin = (46.017, 7.750, 1673.0)  # Zermatt (MATLAB geodetic2enu example, test_geodesy)
    cov = np.diag([4.0, 9.0, 16.0])
    at_origin = rc.fix_to_navsat([0.0, 0.0, 0.0], cov, 10, origin, 'map')
    assert (at_origin.latitude, at_origin.longitude, at_origin.altitude) == \
        pytest.approx(origin, abs=1e-9)
    np.testing.assert_allclose(np.reshape(at_origin.position_covariance, (3, 3)), cov,
                               atol=1e-12)
    matterhorn = rc.fix_to_navsat([-7134.8, -4556.3, 2852.4], cov, 10, origin, 'map')
    assert (matterhorn.latitude, matterhorn.longitude) == pytest.approx((45.976, 7.658),
                                                                        abs=1e-6)
    assert matterhorn.altitude == pytest.approx(4531.0, abs=0.1)
    # 8.5 km away the ENU axes have turned by ~1.7 mrad: the variances move a little.
    reported = np.reshape(matterhorn.position_covariance, (3, 3))
    assert not np.allclose(reported, cov, atol=1e-6)
    np.testing.assert_allclose(np.diag(reported), np.diag(cov), atol=0.05)


def test_navsat_rejections():
    origin = (10.0, 20.0, 0.0)
    with pytest.raises(ValueError, match='position'):
        rc.fix_to_navsat([0.0, math.nan, 0.0], np.eye(3), 0, origin, 'map')
    with pytest.raises(ValueError, match='covariance'):
        rc.fix_to_navsat([0.0, 0.0, 0.0], np.eye(2), 0, origin, 'map')
    with pytest.raises(ValueError, match='geodetic_origin|origin'):
        rc.fix_to_navsat([0.0, 0.0, 0.0], np.eye(3), 0, (95.0, 0.0, 0.0), 'map')
    msg = rc.fix_to_navsat([1.0, 2.0, 3.0], np.eye(3), 0, origin, 'map')
    msg.status.status = NavSatStatus.STATUS_NO_FIX
    with pytest.raises(rc.ConversionError) as info:
        rc.navsat_to_fix(msg, origin)
    assert info.value.reason == 'no_fix'
    msg.status.status = NavSatStatus.STATUS_FIX
    msg.latitude = math.nan
    with pytest.raises(rc.ConversionError) as info:
        rc.navsat_to_fix(msg, origin)
    assert info.value.reason == 'bad_position'


def test_navsat_matches_geodesy():
    origin = (42.0, -82.0, 200.0)
    msg = rc.fix_to_navsat([186.27752081659352, 286.842227851714, 939.6926207859083],
                           np.eye(3), 0, origin, 'map')
    # pymap3d test suite: aer (33°, 70°, 1000 m) from (42, -82, 200) is lla1 below.
    assert (msg.latitude, msg.longitude, msg.altitude) == pytest.approx(
        (42.002582, -81.997752, 1.1397018e3), abs=1e-6)
    back = geodetic_to_enu(msg.latitude, msg.longitude, msg.altitude, origin)
    np.testing.assert_allclose(back, [186.27752081659352, 286.842227851714,
                                      939.6926207859083], atol=1e-6)


def test_raw_reading_from_vector3_stamped():
    msg = Vector3Stamped()
    msg.header.stamp = rc.ns_to_time(1_700_000_000_500_000_000)
    msg.vector.x, msg.vector.y = 90.0, math.nan
    r = rc.raw_reading_from_msg(msg, 'deg')
    assert r.stamp_ns == 1_700_000_000_500_000_000
    assert r.azimuth == pytest.approx(HALF_PI) and math.isnan(r.elevation)
    msg.vector.y = 0.1
    assert rc.raw_reading_from_msg(msg, 'rad').elevation == 0.1
    for field, value, reason in (('x', math.nan, 'bad_azimuth'),
                                 ('y', math.inf, 'bad_elevation')):
        bad = _wire(msg)
        setattr(bad.vector, field, value)
        with pytest.raises(rc.ConversionError) as info:
            rc.raw_reading_from_msg(bad, 'rad')
        assert info.value.reason == reason
    msg.header.stamp = rc.ns_to_time(0)
    with pytest.raises(rc.ConversionError) as info:
        rc.raw_reading_from_msg(msg, 'rad')
    assert info.value.reason == 'bad_stamp'


def test_pose_from_odometry():
    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = 'map', 'base_link'
    msg.header.stamp = rc.ns_to_time(123)
    msg.pose.pose.position.x = 5.0
    q = Rotation.from_euler('z', 0.3).as_quat()
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    cov = np.zeros(36)
    cov[0] = cov[7] = cov[14] = 0.25
    msg.pose.covariance = cov.tolist()
    pose = rc.pose_from_odometry(_wire(msg), 'map')
    assert pose.stamp_ns == 123 and pose.position[0] == 5.0
    np.testing.assert_allclose(pose.quaternion, q, atol=1e-15)
    np.testing.assert_allclose(pose.position_covariance, 0.25 * np.eye(3))
    cases = [('frame', 'odom', 'odometry_wrong_frame'),
             ('w', math.nan, 'odometry_bad_quaternion'),
             ('w', 3.0, 'odometry_bad_quaternion'),
             ('x', math.inf, 'odometry_bad_position')]
    for what, value, reason in cases:
        bad = _wire(msg)
        if what == 'frame':
            bad.header.frame_id = value
        elif what in 'xyz' and reason.endswith('position'):
            setattr(bad.pose.pose.position, what, value)
        else:
            setattr(bad.pose.pose.orientation, what, value)
        with pytest.raises(rc.ConversionError) as info:
            rc.pose_from_odometry(bad, 'map')
        assert info.value.reason == reason


def test_unset_default_message_is_rejected():
    """A default-constructed message (all zeros) breaks the contract on several fields."""
    assert _reason(PoseWithCovarianceStamped()) == 'empty_frame_id'
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = 'map'
    # ROS defaults the orientation to identity (w = 1), so the first broken field is the
    # zero azimuth variance.
    assert _reason(msg) == 'bad_azimuth_variance'


def test_position_covariance_computed_in_single_precision_is_accepted():
    # Rank-2 covariances (a GNSS fix without height information) built in float32: their
    # smallest eigenvalue is rounding, down to a few 1e-7 of the largest.
    rng = np.random.default_rng(4)
    for _ in range(200):
        A = rng.normal(size=(3, 2)).astype(np.float32) * np.float32(5.0)
        P = (A @ A.T).astype(np.float32).astype(float)
        b = rc.bearing_from_msg(_with_position_covariance(P), 's1')
        np.testing.assert_array_equal(b.position_covariance, P)
