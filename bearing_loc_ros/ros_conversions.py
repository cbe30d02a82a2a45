"""The one module that converts core objects to and from ROS messages (DESIGN.md).

Bearing message (station -> fusion): ``geometry_msgs/PoseWithCovarianceStamped``

| field | meaning |
|---|---|
| header.stamp | observation time (integer ns on the node clock) |
| header.frame_id | world frame of the ray (must equal the fusion node's frame) |
| pose.pose.position | station phase-centre position, m |
| pose.pose.orientation | rotation taking +x onto the line of sight: yaw θ, pitch −ψ, roll 0 |
| pose.covariance[0..2, 0..2] | station position covariance, m² |
| pose.covariance[4*6+4] | σ_ψ², rad²; −1 means "elevation not measured" (1D station) |
| pose.covariance[5*6+5] | σ_θ², rad² |

Fix message (fusion -> users): position = estimate, position covariance = estimator
covariance, orientation identity with rotational variance :data:`UNKNOWN_ROTATION_VARIANCE`.
With a geodetic origin the fix is also a ``sensor_msgs/NavSatFix`` (:func:`fix_to_navsat`).

TMA track (``nav_msgs/Odometry``, :func:`track_to_msg`), simulator truth
(``geometry_msgs/PoseStamped``, :func:`truth_to_msg`), RViz markers of a fix
(``visualization_msgs/MarkerArray``, :func:`fix_markers_msg`) and the expected-accuracy map
(``nav_msgs/OccupancyGrid``, :func:`occupancy_grid_msg`) are built here too; their geometry
comes from :mod:`bearing_loc_ros.core.display`.

Station inputs: ``geometry_msgs/Vector3Stamped`` raw readings (:func:`raw_reading_from_msg`)
and ``nav_msgs/Odometry`` platform poses (:func:`pose_from_odometry`).

Every ``*_from_msg`` function either returns a valid core object or raises
:class:`ConversionError` (a ``ValueError``) whose ``reason`` tag is counted by the nodes;
a message that breaks the contract is never converted. :func:`bearing_from_cdr` is
:func:`bearing_from_msg` on the serialized bytes of a raw subscription (the fusion node's
per-message path), with the same results and rejections.
"""

import math
import struct

from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
import numpy as np
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import NavSatFix, NavSatStatus
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from .core import geodesy
from .core.display import fix_markers
from .core.bearings import Bearing, HALF_PI, MAX_ABS_POSITION, SIGMA_MAX, SIGMA_MIN
from .core.conventions import (azel_from_quaternion_scalar, bearing_covariance6,
                               IDX_AZ_VAR, IDX_EL_VAR, NO_ELEVATION_VARIANCE,
                               quaternion_from_azel_scalar, wrap_angle_scalar)
from .core.fusion.stations import covariance3_problem
from .core.station import pose_sample, raw_reading, ReadingError

#: σ_ψ² value marking an azimuth-only (1D) bearing (IDX_EL_VAR / IDX_AZ_VAR: the indices of
#: σ_ψ² and σ_θ² in the 6x6 covariance, from core.conventions).
NO_ELEVATION = NO_ELEVATION_VARIANCE
#: Rotational variance (rad²) published on fixes, whose orientation is unknown.
UNKNOWN_ROTATION_VARIANCE = 1.0e6
#: Tolerances of the contract checks.
QUATERNION_NORM_TOL = 1.0e-3
ROLL_TOL = 1.0e-6
#: Largest float below π/2: a received line of sight within rounding of the vertical is
#: reported at this elevation (the azimuth stays defined by the yaw, see bearing_from_msg).
MAX_ELEVATION = float(np.nextafter(HALF_PI, 0.0))

NS_PER_S = 1_000_000_000
#: builtin_interfaces/Time.sec is an int32.
MAX_TIME_NS = (2 ** 31 - 1) * NS_PER_S + NS_PER_S - 1


class ConversionError(ValueError):
    """A message breaks the contract; ``reason`` is a short machine-friendly tag."""

    def __init__(self, reason, detail=''):
        super().__init__(f'{reason}: {detail}' if detail else reason)
        self.reason = reason


def ns_to_time(ns):
    """Integer nanoseconds -> builtin_interfaces/Time (sec, nanosec), exact.

    ns must be in [0, (2³¹ − 1) s + 999999999 ns] (Time.sec is an int32); else ValueError.
    """
    sec, nanosec = _split_ns(ns)
    return Time(sec=sec, nanosec=nanosec)


def _split_ns(ns):
    ns = int(ns)
    if ns < 0:
        raise ValueError(f'stamp: negative time {ns} ns')
    if ns > MAX_TIME_NS:
        raise ValueError(f'stamp: {ns} ns does not fit builtin_interfaces/Time (int32 sec)')
    return ns // NS_PER_S, ns % NS_PER_S


def time_to_ns(t, reason='bad_stamp'):
    """builtin_interfaces/Time -> integer nanoseconds (exact): sec · 10⁹ + nanosec.

    A stamp that is not normalised (nanosec ≥ 10⁹, which would shift the time by whole
    seconds) or before 1970 (sec < 0) raises :class:`ConversionError` ``reason``.
    """
    sec, nanosec = int(t.sec), int(t.nanosec)
    if sec < 0 or not 0 <= nanosec < NS_PER_S:
        raise ConversionError(reason, f'stamp sec={sec} nanosec={nanosec} is not normalised '
                                      '(need sec >= 0 and 0 <= nanosec < 1e9)')
    return sec * NS_PER_S + nanosec


def bearing_to_msg(bearing):
    """Core :class:`Bearing` -> PoseWithCovarianceStamped following the contract above.

    The bearing is validated first (``Bearing.validate``: ValueError naming the field), and
    an empty frame_id, a position that is not 3 coordinates or a position covariance that is
    not a finite (3, 3) array is a ValueError too, so a message that breaks the contract is
    never produced. Per-message path: scalar maths
    (:func:`~bearing_loc_ros.core.conventions.quaternion_from_azel_scalar`, bit-identical to
    the vectorised function) and the covariance assigned as one float64 array.
    """
    bearing.validate()
    if not bearing.frame_id:
        raise ValueError('frame_id: must not be empty')
    pcov = np.asarray(bearing.position_covariance, dtype=float)
    if pcov.shape != (3, 3) or not all(map(math.isfinite, pcov.ravel().tolist())):
        raise ValueError('position_covariance: expected a finite (3, 3) array, m²')
    pos = np.asarray(bearing.position, dtype=float)
    if pos.shape != (3,):
        raise ValueError(f'position: expected 3 coordinates, got shape {pos.shape}')
    has_el = bearing.has_elevation
    msg = PoseWithCovarianceStamped()
    header = msg.header
    header.stamp = ns_to_time(bearing.stamp_ns)
    header.frame_id = bearing.frame_id
    pose = msg.pose
    p = pose.pose.position
    p.x, p.y, p.z = pos.tolist()
    o = pose.pose.orientation
    o.x, o.y, o.z, o.w = quaternion_from_azel_scalar(bearing.azimuth,
                                                     bearing.elevation if has_el else 0.0)
    pose.covariance = bearing_covariance6(pcov, bearing.sigma_azimuth,
                                          bearing.sigma_elevation if has_el else None)
    return msg


def bearing_from_msg(msg, station, expected_frame=None):
    """PoseWithCovarianceStamped -> core :class:`Bearing`, or raise :class:`ConversionError`.

    Rejected (reason tag in parentheses): empty frame_id (``empty_frame_id``), frame_id not
    equal to ``expected_frame`` when given (``wrong_frame``), non-finite position or a
    coordinate beyond ±1e12 m (``bad_position``), NaN or non-unit quaternion
    (``bad_quaternion``), roll ≠ 0 (``nonzero_roll``: |sin φ cos ψ| or −cos φ cos ψ above
    1e-6, so any roll of 1e-6/cos ψ or more, including an upside-down φ = π), azimuth
    variance whose σ is not in the core's
    [SIGMA_MIN, SIGMA_MAX] = [1e-12, 1e3] rad, NaN and <= 0 included
    (``bad_azimuth_variance``), elevation variance neither −1 nor such a σ²
    (``bad_elevation_variance``), a position covariance that is not finite, symmetric and
    positive semi-definite (``bad_position_covariance``,
    :func:`~bearing_loc_ros.core.fusion.stations.covariance3_problem`), a NaN or infinite
    entry anywhere else in the covariance (``bad_covariance``: the other entries are not
    read, but a non-finite one shows a broken sender), header.stamp not
    normalised (``bad_stamp``: nanosec ≥ 10⁹ or sec < 0, :func:`time_to_ns`); the first rule
    that applies, in this order.

    The azimuth is returned wrapped to (−π, π]. Round trips through :func:`bearing_to_msg`
    are exact up to float rounding (~1e-15 rad) for any θ and any |ψ| < π/2. A quaternion
    can only say that a line of sight is within ~1e-16 rad of the vertical; such an
    elevation is reported as :data:`MAX_ELEVATION` (the largest float below π/2), so a valid
    message is never rejected because of rounding (the azimuth is read from the yaw, which
    stays defined there).

    Cost: ~7 µs per message (was ~44 µs with numpy on 1-element arrays), measured by
    ``bench/bench_conversions.py``; the angles come from the scalar twins
    :func:`~bearing_loc_ros.core.conventions.azel_from_quaternion_scalar` and
    :func:`~bearing_loc_ros.core.conventions.wrap_angle_scalar` (within 1 ulp of the
    vectorised functions).
    """
    # Per-message path (the fusion node calls this for every bearing): Python floats and the
    # math module throughout; the angle maths are the scalar twins in core.conventions.
    header = msg.header
    frame = header.frame_id
    _check_frame(frame, expected_frame)
    p = msg.pose.pose.position
    o = msg.pose.pose.orientation
    stamp = header.stamp
    return _bearing_from_fields(station, frame, stamp.sec, stamp.nanosec,
                                float(p.x), float(p.y), float(p.z),
                                float(o.x), float(o.y), float(o.z), float(o.w),
                                msg.pose.covariance)


def _check_frame(frame, expected_frame):
    if not frame:
        raise ConversionError('empty_frame_id', 'header.frame_id is empty')
    if expected_frame is not None and frame != expected_frame:
        raise ConversionError('wrong_frame', f'frame_id {frame!r} != {expected_frame!r}')


def _bearing_from_fields(station, frame, sec, nanosec, px, py, pz, qx, qy, qz, qw, cov):
    """The contract checks and maths of :func:`bearing_from_msg` after the frame check, on
    the message's fields (Python floats; ``cov``: the 36 covariance values, row-major)."""
    if not (abs(px) <= MAX_ABS_POSITION and abs(py) <= MAX_ABS_POSITION
            and abs(pz) <= MAX_ABS_POSITION):
        raise ConversionError('bad_position', 'non-finite station position or |coordinate| '
                              f'above {MAX_ABS_POSITION:g} m')
    norm = math.sqrt(((qx * qx + qy * qy) + qz * qz) + qw * qw)
    if not math.isfinite(norm) or abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise ConversionError('bad_quaternion', f'quaternion norm {norm:.6g} is not 1')
    az, el, roll = azel_from_quaternion_scalar(qx, qy, qz, qw)
    az = wrap_angle_scalar(az)
    el = min(max(el, -MAX_ELEVATION), MAX_ELEVATION)
    # Roll φ: (R e_y)_z = sin φ cos ψ (checked by azel_from_quaternion's roll) and
    # (R e_z)_z = 1 − 2(x² + y²) = cos φ cos ψ, which is negative for |φ| > π/2: a roll of π
    # leaves (R e_y)_z = 0 but flips R e_y, so without this second test the azimuth would be
    # read off by π.
    x, y = qx / norm, qy / norm
    zz = 1.0 - 2.0 * (x * x + y * y)
    if abs(roll) > ROLL_TOL or zz < -ROLL_TOL:
        phi = math.atan2(math.sin(roll), zz)
        raise ConversionError('nonzero_roll', f'roll about {phi:.3g} rad; a bearing has none')
    if type(cov) is list:
        c = cov
    else:
        if type(cov) is not np.ndarray or cov.shape != (36,):
            # An in-process message may hold a list or a (6, 6) array (rclpy checks no shape).
            cov = np.asarray(cov, dtype=float).reshape(36)
        c = cov.tolist()
    var_az = c[IDX_AZ_VAR]
    if not (var_az > 0.0 and SIGMA_MIN <= math.sqrt(var_az) <= SIGMA_MAX):
        raise ConversionError('bad_azimuth_variance', f'azimuth variance {var_az}')
    var_el = c[IDX_EL_VAR]
    if var_el == NO_ELEVATION:
        elevation, sigma_el = math.nan, math.nan
    elif var_el > 0.0 and SIGMA_MIN <= math.sqrt(var_el) <= SIGMA_MAX:
        elevation, sigma_el = el, math.sqrt(var_el)
    else:
        raise ConversionError('bad_elevation_variance',
                              f'elevation variance {var_el} (use -1 for azimuth-only)')
    rows = (c[0:3], c[6:9], c[12:15])
    problem = covariance3_problem(rows[0] + rows[1] + rows[2])
    if problem is not None:
        raise ConversionError('bad_position_covariance', problem)
    if not math.isfinite(sum(c)):       # finite entries can overflow the sum: look closer
        bad = next((k for k, v in enumerate(c) if not math.isfinite(v)), None)
        if bad is not None:
            raise ConversionError('bad_covariance', f'covariance[{bad}] = {c[bad]} (row '
                                  f'{bad // 6}, column {bad % 6}) is not finite')
    sec, nanosec = int(sec), int(nanosec)
    if sec < 0 or not 0 <= nanosec < NS_PER_S:
        raise ConversionError('bad_stamp', f'stamp sec={sec} nanosec={nanosec} is not '
                              'normalised (need sec >= 0 and 0 <= nanosec < 1e9)')
    return Bearing(station=station, stamp_ns=sec * NS_PER_S + nanosec,
                   position=np.array((px, py, pz)), azimuth=az, elevation=elevation,
                   sigma_azimuth=math.sqrt(var_az), sigma_elevation=sigma_el, frame_id=frame,
                   position_covariance=np.array(rows))


#: CDR of PoseWithCovarianceStamped after the 4-byte encapsulation header: stamp sec
#: (int32), nanosec (uint32), the frame_id length (uint32, with its NUL), the frame_id
#: bytes; then, 8-aligned, position (3 float64), orientation (4) and covariance (36).
_CDR_HEAD = {1: struct.Struct('<iII'), 0: struct.Struct('>iII')}
_CDR_POSE = {1: struct.Struct('<43d'), 0: struct.Struct('>43d')}
_FIX_POSE = struct.Struct('<7d')
_FIX_COVARIANCE = struct.Struct('<36d')


def bearing_from_cdr(raw, station, expected_frame=None):
    """Serialized PoseWithCovarianceStamped (CDR bytes, as a ``raw=True`` subscription or a
    bag delivers them) -> core :class:`Bearing`, or raise :class:`ConversionError`.

    The same result as ``bearing_from_msg(deserialize_message(raw), ...)``, the same
    rejections in the same order, without building the rclpy message (~25 µs of Python
    per bearing saved). The fields are read with ``struct`` from the plain XCDR1 layout
    (encapsulation CDR_LE or CDR_BE, a NUL-terminated UTF-8 frame_id); any other form
    (another encapsulation, a frame_id without its NUL or with an inner NUL, invalid UTF-8,
    a short buffer) is handed to rclpy's deserializer, so its reading of such bytes is kept
    exactly. Bytes that rclpy cannot deserialize raise ``malformed_cdr``.
    """
    fields = _cdr_fields(raw)
    if fields is None:
        try:
            msg = deserialize_message(raw, PoseWithCovarianceStamped)
        except (RuntimeError, TypeError, ValueError) as exc:
            raise ConversionError('malformed_cdr', f'{len(raw)} bytes: {exc}'[:200]) from None
        return bearing_from_msg(msg, station, expected_frame)
    frame, sec, nanosec, v = fields
    _check_frame(frame, expected_frame)
    return _bearing_from_fields(station, frame, sec, nanosec, *v[:7], list(v[7:]))


def _cdr_fields(raw):
    """(frame_id, sec, nanosec, 43 floats) of the plain CDR layout, or None for any other."""
    if len(raw) < 16 or raw[0] != 0 or raw[1] > 1:
        return None
    little = raw[1]
    sec, nanosec, n = _CDR_HEAD[little].unpack_from(raw, 4)
    end = 16 + n                  # one past the NUL of the frame_id
    start = 4 + ((12 + n + 7) & ~7)
    if n == 0 or start + 344 > len(raw) or raw.find(0, 16, end) != end - 1:
        return None
    try:
        frame = raw[16:end - 1].decode()
    except UnicodeDecodeError:
        return None
    return frame, sec, nanosec, _CDR_POSE[little].unpack_from(raw, start)


def fix_to_msg(position, covariance, stamp_ns, frame_id):
    """Estimate -> PoseWithCovarianceStamped (``fix`` topic, DESIGN.md).

    Position (3,) m and covariance (3, 3) m² go into pose.position and covariance[0..2,0..2];
    orientation is identity with variance :data:`UNKNOWN_ROTATION_VARIANCE` on the three
    rotational axes (the emitter's orientation is not estimated).
    """
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = frame_id
    x, y, z = (float(v) for v in position)
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = x, y, z
    msg.pose.pose.orientation.w = 1.0
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.asarray(covariance, dtype=float)
    cov[3, 3] = cov[4, 4] = cov[5, 5] = UNKNOWN_ROTATION_VARIANCE
    msg.pose.covariance = cov.ravel().tolist()
    return msg


def fix_to_cdr(position, covariance, stamp_ns, frame_id):
    """:func:`fix_to_msg`'s message as CDR bytes (``Publisher.publish`` takes them as they
    are): ``serialize_message(fix_to_msg(...))`` byte for byte but for the alignment padding
    after frame_id, which CDR leaves unspecified (zeros here), without building the rclpy
    message (~5 µs instead of ~45 µs with the serialization, once per fix on the node's
    latency path). Same arguments, units and ValueError for a stamp out of range.
    """
    sec, nanosec = _split_ns(stamp_ns)
    frame = frame_id.encode() + b'\0'
    c = np.asarray(covariance, dtype=float)
    if c.shape == (3, 3):
        # The 6 × 6 row-major block packed from floats: the same bytes as the array's.
        (a, b, d), (e, f, g), (h, i, j) = c.tolist()
        u = UNKNOWN_ROTATION_VARIANCE
        cov = _FIX_COVARIANCE.pack(a, b, d, 0.0, 0.0, 0.0, e, f, g, 0.0, 0.0, 0.0,
                                   h, i, j, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, u, 0.0, 0.0,
                                   0.0, 0.0, 0.0, 0.0, u, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, u)
    else:
        full = np.zeros((6, 6))
        full[:3, :3] = c
        full[3, 3] = full[4, 4] = full[5, 5] = UNKNOWN_ROTATION_VARIANCE
        cov = full.astype('<f8').tobytes()
    x, y, z = (float(v) for v in position)
    return b''.join((b'\x00\x01\x00\x00', _CDR_HEAD[1].pack(sec, nanosec, len(frame)), frame,
                     bytes(-(12 + len(frame)) % 8), _FIX_POSE.pack(x, y, z, 0.0, 0.0, 0.0, 1.0),
                     cov))


def fix_from_msg(msg):
    """PoseWithCovarianceStamped fix -> (stamp_ns, position (3,), covariance (3, 3))."""
    p = msg.pose.pose.position
    cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3].copy()
    return time_to_ns(msg.header.stamp), np.array([p.x, p.y, p.z]), cov


def fix_to_navsat(position_enu, covariance_enu, stamp_ns, origin, frame_id):
    """Estimate in the local ENU frame -> ``sensor_msgs/NavSatFix`` (``fix/navsat`` topic).

    ``position_enu`` (3,) m and ``covariance_enu`` (3, 3) m² are in the ENU frame of the
    geodetic ``origin`` (lat0_deg, lon0_deg, h0_m; WGS84). latitude/longitude (degrees) and
    altitude (m above the WGS84 ellipsoid, as NavSatFix specifies) come from
    :func:`bearing_loc_ros.core.geodesy.enu_to_geodetic` (pymap3d). NavSatFix's
    position_covariance is ENU too, but in the tangent plane through the reported position,
    so the covariance is rotated C' = R C Rᵀ with R from
    :func:`~bearing_loc_ros.core.geodesy.enu_axes_rotation` (identity at the origin, a
    1.6 mrad tilt 10 km away). status = STATUS_FIX, service = 0 (no GNSS involved),
    position_covariance_type = COVARIANCE_TYPE_KNOWN. ValueError for non-finite input, a
    bad origin or an empty frame_id.
    """
    p = np.asarray(position_enu, dtype=float)
    c = np.asarray(covariance_enu, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError('position: expected 3 finite ENU coordinates, m')
    if c.shape != (3, 3) or not np.all(np.isfinite(c)):
        raise ValueError('covariance: expected a finite (3, 3) array, m²')
    if not frame_id:
        raise ValueError('frame_id: must not be empty')
    lat, lon, alt = (float(v) for v in geodesy.enu_to_geodetic(p, origin))
    R = geodesy.enu_axes_rotation(origin, lat, lon)
    msg = NavSatFix()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = frame_id
    msg.status.status = NavSatStatus.STATUS_FIX
    msg.status.service = 0
    msg.latitude, msg.longitude, msg.altitude = lat, lon, alt
    msg.position_covariance = (R @ c @ R.T).ravel().tolist()
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_KNOWN
    return msg


def navsat_to_fix(msg, origin):
    """``sensor_msgs/NavSatFix`` -> (stamp_ns, position_enu (3,), covariance_enu (3, 3)).

    Inverse of :func:`fix_to_navsat`: the position is converted to the ENU frame of
    ``origin`` and the covariance rotated back, C = Rᵀ C' R (an unknown covariance type
    gives NaN covariance). Rejected: status NO_FIX (``no_fix``), non-finite or out of range
    latitude/longitude/altitude (``bad_position``).
    """
    if msg.status.status == NavSatStatus.STATUS_NO_FIX:
        raise ConversionError('no_fix', 'status is STATUS_NO_FIX')
    try:
        pos = geodesy.geodetic_to_enu(msg.latitude, msg.longitude, msg.altitude, origin,
                                      field='navsat')
    except ValueError as exc:
        raise ConversionError('bad_position', str(exc)) from None
    if msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_UNKNOWN:
        cov = np.full((3, 3), np.nan)
    else:
        R = geodesy.enu_axes_rotation(origin, msg.latitude, msg.longitude)
        cov = R.T @ np.asarray(msg.position_covariance, dtype=float).reshape(3, 3) @ R
    return time_to_ns(msg.header.stamp), pos, cov


def _reading_error(exc):
    return ConversionError(exc.reason, str(exc).partition(': ')[2])


def raw_reading_from_msg(msg, input_units):
    """``geometry_msgs/Vector3Stamped`` raw DF reading -> core ``RawReading``.

    x = azimuth, y = elevation (NaN = not measured), in the sensor's own reference and in
    ``input_units`` ('deg' or 'rad'); z is ignored; header.stamp is the observation time.
    Rejected (``ConversionError`` reasons of :func:`bearing_loc_ros.core.station.raw_reading`):
    ``bad_stamp`` (zero, i.e. not set), ``bad_azimuth`` (non-finite), ``bad_elevation``
    (infinite).
    """
    try:
        return raw_reading(time_to_ns(msg.header.stamp), msg.vector.x, msg.vector.y,
                           input_units)
    except ReadingError as exc:
        raise _reading_error(exc) from None


def pose_from_odometry(msg, expected_frame):
    """``nav_msgs/Odometry`` -> core ``PoseSample`` (body pose in the world frame).

    header.frame_id must equal ``expected_frame`` (the station's world frame), else
    ``odometry_wrong_frame``; the pose's position, orientation (body -> world, REP-103 body
    axes x forward, y left, z up) and position covariance block are validated by
    :func:`bearing_loc_ros.core.station.pose_sample` (reasons ``odometry_bad_stamp``,
    ``odometry_bad_position``, ``odometry_bad_quaternion``, ``odometry_bad_covariance``).
    Twist is not used.
    """
    if msg.header.frame_id != expected_frame:
        raise ConversionError('odometry_wrong_frame',
                              f'frame_id {msg.header.frame_id!r} != {expected_frame!r}')
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3]
    try:
        return pose_sample(time_to_ns(msg.header.stamp, 'odometry_bad_stamp'), [p.x, p.y, p.z],
                           [o.x, o.y, o.z, o.w], cov)
    except ReadingError as exc:
        raise _reading_error(exc) from None


def track_to_msg(position, velocity, state_covariance, stamp_ns, frame_id):
    """TMA target state -> nav_msgs/Odometry (the ``track`` topic).

    header.frame_id = child_frame_id = ``frame_id`` (the world frame): the velocity is
    expressed in the world frame, and nav_msgs/Odometry defines the twist in
    child_frame_id, so both name the world frame. pose.pose.position = position (3,) m,
    orientation identity; pose.covariance[0..2, 0..2] = state_covariance[:3, :3] (m²);
    twist.twist.linear = velocity (3,) m/s, twist.covariance[0..2, 0..2] =
    state_covariance[3:, 3:] (m²/s²); the rotational blocks (orientation, angular velocity:
    not estimated) get variance :data:`UNKNOWN_ROTATION_VARIANCE`. The position-velocity
    cross-covariance (state_covariance[:3, 3:], m²/s) has no field in Odometry and is
    dropped.
    """
    C = np.asarray(state_covariance, dtype=float)
    msg = Odometry()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = frame_id
    p, v = msg.pose.pose.position, msg.twist.twist.linear
    p.x, p.y, p.z = (float(x) for x in position)
    v.x, v.y, v.z = (float(x) for x in velocity)
    msg.pose.pose.orientation.w = 1.0
    for block, target in ((C[:3, :3], msg.pose), (C[3:, 3:], msg.twist)):
        cov = np.zeros((6, 6))
        cov[:3, :3] = block
        cov[3, 3] = cov[4, 4] = cov[5, 5] = UNKNOWN_ROTATION_VARIANCE
        target.covariance = cov.ravel().tolist()
    return msg


def truth_to_msg(position, stamp_ns, frame_id):
    """Ground truth -> geometry_msgs/PoseStamped (position (3,) m, identity orientation)."""
    msg = PoseStamped()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = frame_id
    p = msg.pose.position
    p.x, p.y, p.z = (float(v) for v in position)
    msg.pose.orientation.w = 1.0
    return msg


#: Marker colours: bearings in the fix, bearings the gate rejected, fix, error ellipsoid.
USED_COLOR = ColorRGBA(r=0.1, g=0.8, b=0.2, a=0.9)
REJECTED_COLOR = ColorRGBA(r=0.9, g=0.1, b=0.1, a=0.9)
FIX_COLOR = ColorRGBA(r=0.1, g=0.3, b=1.0, a=1.0)
ELLIPSOID_COLOR = ColorRGBA(r=0.2, g=0.5, b=1.0, a=0.3)


def fix_markers_msg(epoch, frame_id, ray_length=0.0, n_sigma=3.0, lifetime_ns=0):
    """Fix Epoch -> visualization_msgs/MarkerArray (the ``markers`` topic).

    Markers (namespace, id): ``bearings`` 0, a LINE_LIST of the rays of the bearings in the
    fix (green) and of those the outlier gate rejected (red); ``fix`` 1, a SPHERE at the
    fix; ``ellipsoid`` 2, a SPHERE scaled and rotated to the ``n_sigma`` error ellipsoid.
    Geometry (m, world frame ``frame_id``): :func:`bearing_loc_ros.core.display.fix_markers`.
    Every marker lives ``lifetime_ns`` (0 = forever) and is stamped with the epoch time.
    """
    g = fix_markers(epoch, ray_length, n_sigma)
    stamp = ns_to_time(epoch.stamp_ns)
    life = Duration(sec=int(lifetime_ns) // NS_PER_S, nanosec=int(lifetime_ns) % NS_PER_S)
    out = MarkerArray()
    rays = Marker(type=Marker.LINE_LIST, action=Marker.ADD, ns='bearings', id=0,
                  lifetime=life)
    rays.header.stamp, rays.header.frame_id = stamp, frame_id
    rays.pose.orientation.w = 1.0
    rays.scale.x = g.ray_width
    for seg, color in ((g.used_rays, USED_COLOR), (g.rejected_rays, REJECTED_COLOR)):
        for a, b in seg.tolist():
            rays.points += [Point(x=a[0], y=a[1], z=a[2]), Point(x=b[0], y=b[1], z=b[2])]
            rays.colors += [color, color]
    out.markers.append(rays)
    x, y, z = (float(v) for v in epoch.position)
    size = g.fix_size
    for mid, ns, scale, quat, color in (
            (1, 'fix', (size, size, size), (0.0, 0.0, 0.0, 1.0), FIX_COLOR),
            (2, 'ellipsoid', g.ellipsoid_diameters, g.ellipsoid_quaternion, ELLIPSOID_COLOR)):
        m = Marker(type=Marker.SPHERE, action=Marker.ADD, ns=ns, id=mid, lifetime=life,
                   color=color)
        m.header.stamp, m.header.frame_id = stamp, frame_id
        m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, z
        o = m.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quat)
        m.scale.x, m.scale.y, m.scale.z = (max(float(v), 1e-6) for v in scale)
        out.markers.append(m)
    return out


def occupancy_grid_msg(grid, data, stamp_ns, frame_id):
    """Expected-accuracy map -> nav_msgs/OccupancyGrid (the ``accuracy_map`` topic).

    ``grid`` is a core.planning.GridSpec (origin_x, origin_y, resolution m, width, height
    cells, altitude m), ``data`` the row-major int8 cell values (0-100, −1 unknown).
    info.origin = (origin_x, origin_y, altitude) with identity orientation; map_load_time =
    header.stamp = ``stamp_ns``.
    """
    msg = OccupancyGrid()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = frame_id
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(grid.resolution)
    msg.info.width, msg.info.height = grid.width, grid.height
    o = msg.info.origin
    o.position.x, o.position.y, o.position.z = grid.origin_x, grid.origin_y, grid.altitude
    o.orientation.w = 1.0
    msg.data = np.asarray(data).tolist()
    return msg


#: core diagnostic levels -> diagnostic_msgs/DiagnosticStatus levels.
DIAGNOSTIC_LEVELS = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN,
                     'error': DiagnosticStatus.ERROR}


def diagnostic_array(entries, prefix, stamp_ns):
    """Core DiagnosticEntry list -> diagnostic_msgs/DiagnosticArray (``/diagnostics``).

    Each entry becomes a DiagnosticStatus named ``<prefix>: <entry name>`` with its level
    (:data:`DIAGNOSTIC_LEVELS`), message, hardware_id and values as string KeyValues.
    """
    arr = DiagnosticArray()
    arr.header.stamp = ns_to_time(stamp_ns)
    arr.status = [DiagnosticStatus(
        level=DIAGNOSTIC_LEVELS[d.level], name=f'{prefix}: {d.name}', message=d.message,
        hardware_id=d.hardware_id,
        values=[KeyValue(key=str(k), value=str(v)) for k, v in d.values.items()])
        for d in entries]
    return arr
