"""The one module that converts core objects to and from ROS messages (DESIGN.md).

Bearing message (station -> fusion): ``geometry_msgs/PoseWithCovarianceStamped``

| field | meaning |
|---|---|
| header.stamp | observation time (integer ns on the node clock) |
| header.frame_id | world frame of the ray (must equal the fusion node's frame) |
| pose.pose.position | station phase-centre position, m |
| pose.pose.orientation | rotation taking +x onto the line of sight: yaw = θ, pitch = −ψ, roll = 0 |
| pose.covariance[0..2, 0..2] | station position covariance, m² |
| pose.covariance[4*6+4] | σ_ψ², rad²; −1 means "elevation not measured" (1D station) |
| pose.covariance[5*6+5] | σ_θ², rad² |

Fix message (fusion -> users): position = estimate, position covariance = estimator
covariance, orientation identity with rotational variance :data:`UNKNOWN_ROTATION_VARIANCE`.
"""

import math

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np

from .core.bearings import Bearing, HALF_PI
from .core.conventions import azel_from_quaternion, quaternion_from_azel

#: Index of σ_ψ² (pitch) and σ_θ² (yaw) in the row-major 6x6 pose covariance.
IDX_EL_VAR = 4 * 6 + 4
IDX_AZ_VAR = 5 * 6 + 5
#: σ_ψ² value marking an azimuth-only (1D) bearing.
NO_ELEVATION = -1.0
#: Rotational variance (rad²) published on fixes, whose orientation is unknown.
UNKNOWN_ROTATION_VARIANCE = 1.0e6
#: Tolerances of the contract checks.
QUATERNION_NORM_TOL = 1.0e-3
ROLL_TOL = 1.0e-6

NS_PER_S = 1_000_000_000


class ConversionError(ValueError):
    """A message breaks the contract; ``reason`` is a short machine-friendly tag."""

    def __init__(self, reason, detail=''):
        super().__init__(f'{reason}: {detail}' if detail else reason)
        self.reason = reason


def ns_to_time(ns):
    """Integer nanoseconds -> builtin_interfaces/Time (sec, nanosec); ns must be >= 0."""
    ns = int(ns)
    if ns < 0:
        raise ValueError(f'stamp: negative time {ns} ns')
    return Time(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def time_to_ns(t):
    """builtin_interfaces/Time -> integer nanoseconds (exact)."""
    return int(t.sec) * NS_PER_S + int(t.nanosec)


def bearing_to_msg(bearing):
    """Core :class:`Bearing` -> PoseWithCovarianceStamped following the contract above."""
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = ns_to_time(bearing.stamp_ns)
    msg.header.frame_id = bearing.frame_id
    p = np.asarray(bearing.position, dtype=float)
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = map(float, p)
    el = bearing.elevation if bearing.has_elevation else 0.0
    q = quaternion_from_azel(bearing.azimuth, el)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.asarray(bearing.position_covariance, dtype=float)
    cov.flat[IDX_EL_VAR] = (bearing.sigma_elevation ** 2 if bearing.has_elevation
                            else NO_ELEVATION)
    cov.flat[IDX_AZ_VAR] = bearing.sigma_azimuth ** 2
    msg.pose.covariance = cov.ravel().tolist()
    return msg


def bearing_from_msg(msg, station, expected_frame=None):
    """PoseWithCovarianceStamped -> core :class:`Bearing`, or raise :class:`ConversionError`.

    Rejected (reason tag in parentheses): empty frame_id (``empty_frame_id``), frame_id not
    equal to ``expected_frame`` when given (``wrong_frame``), non-finite position
    (``bad_position``), NaN or non-unit quaternion (``bad_quaternion``), roll ≠ 0
    (``nonzero_roll``), azimuth variance NaN or <= 0 (``bad_azimuth_variance``), elevation
    variance neither −1 nor finite > 0 (``bad_elevation_variance``), |elevation| >= π/2
    (``bad_elevation``), non-finite or negative-diagonal position covariance
    (``bad_position_covariance``).
    """
    frame = msg.header.frame_id
    if not frame:
        raise ConversionError('empty_frame_id', 'header.frame_id is empty')
    if expected_frame is not None and frame != expected_frame:
        raise ConversionError('wrong_frame', f'frame_id {frame!r} != {expected_frame!r}')
    p = msg.pose.pose.position
    pos = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(pos)):
        raise ConversionError('bad_position', 'non-finite station position')
    o = msg.pose.pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise ConversionError('bad_quaternion', f'quaternion norm {norm:.6g} is not 1')
    az, el, roll = azel_from_quaternion(q)
    if abs(float(roll)) > ROLL_TOL:
        raise ConversionError('nonzero_roll', f'roll {float(roll):.3g} rad; a bearing has none')
    cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
    var_az = cov.flat[IDX_AZ_VAR]
    if not math.isfinite(var_az) or var_az <= 0.0:
        raise ConversionError('bad_azimuth_variance', f'azimuth variance {var_az}')
    var_el = cov.flat[IDX_EL_VAR]
    if var_el == NO_ELEVATION:
        elevation, sigma_el = float('nan'), float('nan')
    elif math.isfinite(var_el) and var_el > 0.0:
        elevation, sigma_el = float(el), math.sqrt(var_el)
        if abs(elevation) >= HALF_PI:
            raise ConversionError('bad_elevation', f'elevation {elevation} rad')
    else:
        raise ConversionError('bad_elevation_variance',
                              f'elevation variance {var_el} (use -1 for azimuth-only)')
    pcov = cov[:3, :3]
    if not np.all(np.isfinite(pcov)) or np.any(np.diag(pcov) < 0.0):
        raise ConversionError('bad_position_covariance', 'non-finite or negative variance')
    return Bearing(station=station, stamp_ns=time_to_ns(msg.header.stamp), position=pos,
                   azimuth=float(az), elevation=elevation, sigma_azimuth=math.sqrt(var_az),
                   sigma_elevation=sigma_el, frame_id=frame, position_covariance=pcov.copy())


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


def fix_from_msg(msg):
    """PoseWithCovarianceStamped fix -> (stamp_ns, position (3,), covariance (3, 3))."""
    p = msg.pose.pose.position
    cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3].copy()
    return time_to_ns(msg.header.stamp), np.array([p.x, p.y, p.z]), cov
