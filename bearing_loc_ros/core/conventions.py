"""Angle and frame conventions of bearing_loc_ros (DESIGN.md, REP-103).

World frame: local ENU Cartesian (x East, y North, z Up), metres.

* Azimuth θ: ENU yaw, counter-clockwise from +x (East),
  θ = atan2(y_t − y_s, x_t − x_s)  (Wang, Zhang & Wu (2006) eq. (1), first line).
* Elevation ψ: angle above the local horizontal plane,
  ψ = atan2(z_t − z_s, sqrt((x_t − x_s)² + (y_t − y_s)²))  (same eq. (1), second line).
* Line-of-sight unit vector u = (cos ψ cos θ, cos ψ sin θ, sin ψ).
* Compass bearing β (clockwise from North, as in Lin et al. and most DF receivers): θ = π/2 − β.
* A bearing as an orientation: the rotation taking +x onto u, i.e. yaw = θ, pitch = −ψ,
  roll = 0 (REP-103 yaw-pitch-roll, Z-Y'-X''), quaternion order (x, y, z, w).

All functions are vectorised: they accept scalars or arrays of any (broadcastable) shape.
Angles are radians everywhere; nothing here handles degrees.

Per-message paths (one bearing per ROS message) use the ``*_scalar`` twins: the same formulas
on Python floats with the ``math`` module, about 50 times faster than numpy on 1-element
arrays. They agree with the vectorised functions to float rounding (the tests check it); they
are not always bit-identical because numpy may evaluate arctan2/arcsin/hypot with its own SIMD
routines (1 ulp apart from the C library's on about 8 % of inputs).
"""

import math
import sys

import numpy as np

TWO_PI = 2.0 * np.pi

#: Layout of the bearing message's row-major 6x6 pose covariance (DESIGN.md "The bearing
#: message"): index of σ_ψ² (pitch = −ψ) and of σ_θ² (yaw = θ).
IDX_EL_VAR = 4 * 6 + 4
IDX_AZ_VAR = 5 * 6 + 5
#: σ_ψ² value marking an azimuth-only (1D) bearing.
NO_ELEVATION_VARIANCE = -1.0


def wrap_angle(angle):
    """Wrap angles to the half-open interval (−π, π].

    Maths: a ↦ a − 2π·ceil((a − π) / 2π). Units: radians. NaN stays NaN.
    Used for azimuth differences (residuals, interpolation) across the ±π wrap.
    """
    a = np.asarray(angle, dtype=float)
    wrapped = a - TWO_PI * np.ceil((a - np.pi) / TWO_PI)
    # Rounding can leave the result one ulp outside (−π, π] (for example a just above −π
    # gives 3.1415926535897936); fold those values back in.
    wrapped = np.where(wrapped > np.pi, wrapped - TWO_PI, wrapped)
    wrapped = np.where(wrapped <= -np.pi, wrapped + TWO_PI, wrapped)
    return wrapped if wrapped.ndim else float(wrapped)


def wrap_angle_scalar(angle):
    """Scalar twin of :func:`wrap_angle`: one angle (rad) -> float in (−π, π].

    Same maths, a ↦ a − 2π·ceil((a − π) / 2π) and the same one-ulp folds, so the result is
    bit-identical to ``wrap_angle`` (including ``wrap_angle(−0.0) = +0.0``). NaN and ±inf give
    NaN, as ``wrap_angle`` does.
    """
    a = float(angle)
    if not math.isfinite(a):
        return math.nan
    t = (a - math.pi) / TWO_PI
    # np.ceil keeps the sign of a zero result (ceil(−0.5) = −0.0) and a − 2π·(−0.0) turns
    # a = −0.0 into +0.0; math.ceil returns an int, so put the sign back.
    wrapped = a - TWO_PI * math.copysign(math.ceil(t), t)
    if wrapped > math.pi:
        wrapped -= TWO_PI
    if wrapped <= -math.pi:
        wrapped += TWO_PI
    return wrapped


def compass_to_enu(compass):
    """Convert a compass bearing β (clockwise from North, rad) to ENU azimuth θ = π/2 − β.

    The result is wrapped to (−π, π]. DESIGN.md "Frames, units, angles".
    """
    return wrap_angle(np.pi / 2.0 - np.asarray(compass, dtype=float))


def enu_to_compass(azimuth):
    """Convert ENU azimuth θ (CCW from East, rad) to a compass bearing β = π/2 − θ in [0, 2π)."""
    return np.mod(np.pi / 2.0 - np.asarray(azimuth, dtype=float), TWO_PI)


def los_vector(azimuth, elevation=0.0):
    """Line-of-sight unit vector u = (cos ψ cos θ, cos ψ sin θ, sin ψ), shape (..., 3).

    ``elevation`` NaN (azimuth-only bearing) is treated as 0 (the horizontal direction).
    """
    az = np.asarray(azimuth, dtype=float)
    el = np.nan_to_num(np.asarray(elevation, dtype=float), nan=0.0)
    az, el = np.broadcast_arrays(az, el)
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)


def azimuth_elevation(delta):
    """Azimuth θ and elevation ψ (rad) of the vector(s) ``delta`` (..., 3) = target − station.

    θ = atan2(Δy, Δx), ψ = atan2(Δz, hypot(Δx, Δy)) (Wang, Zhang & Wu (2006) eq. (1)).
    Returns (θ, ψ).
    """
    d = np.asarray(delta, dtype=float)
    az = np.arctan2(d[..., 1], d[..., 0])
    el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    return az, el


def quaternion_from_azel(azimuth, elevation=0.0):
    """Quaternion (x, y, z, w) of the rotation yaw = θ, pitch = −ψ, roll = 0.

    This rotation maps +x onto the line of sight u (DESIGN.md bearing message).
    q = q_z(θ) ⊗ q_y(−ψ) = (sin(ψ/2) sin(θ/2), −sin(ψ/2) cos(θ/2),
    cos(ψ/2) sin(θ/2), cos(ψ/2) cos(θ/2)). NaN elevation is treated as 0. Shape (..., 4).
    """
    az = np.asarray(azimuth, dtype=float)
    el = np.nan_to_num(np.asarray(elevation, dtype=float), nan=0.0)
    az, el = np.broadcast_arrays(az, el)
    cy, sy = np.cos(az / 2.0), np.sin(az / 2.0)
    cp, sp = np.cos(-el / 2.0), np.sin(-el / 2.0)
    return np.stack([-sp * sy, sp * cy, cp * sy, cp * cy], axis=-1)


def quaternion_from_azel_scalar(azimuth, elevation=0.0):
    """Scalar twin of :func:`quaternion_from_azel`: (θ, ψ) rad -> tuple (x, y, z, w).

    Same maths, q = q_z(θ) ⊗ q_y(−ψ) = (sin(ψ/2) sin(θ/2), −sin(ψ/2) cos(θ/2),
    cos(ψ/2) sin(θ/2), cos(ψ/2) cos(θ/2)), evaluated in the same order, so the result is
    bit-identical (math.sin/cos and numpy's agree). As in the vectorised version
    (``np.nan_to_num``), a NaN elevation counts as 0 and ±inf as ±the largest float; a
    non-finite azimuth gives NaN components.
    """
    az = float(azimuth)
    el = float(elevation)
    if math.isnan(el):
        el = 0.0
    elif math.isinf(el):
        el = math.copysign(sys.float_info.max, el)
    if math.isinf(az):
        az = math.nan  # math.sin(inf) raises; np.sin(inf) is NaN
    cy, sy = math.cos(az / 2.0), math.sin(az / 2.0)
    cp, sp = math.cos(-el / 2.0), math.sin(-el / 2.0)
    return (-sp * sy, sp * cy, cp * sy, cp * cy)


def azel_from_quaternion(q):
    """Azimuth θ, elevation ψ and roll (rad) of quaternion(s) q = (x, y, z, w), shape (..., 4).

    Inverse of :func:`quaternion_from_azel`. With R the rotation matrix of q, the line of
    sight is u = R e_x, so ψ = atan2(u_z, hypot(u_x, u_y)). The azimuth is read from the image
    of the y axis, R e_y = (−sin θ, cos θ, 0) when roll = 0, which stays well conditioned even
    for a nearly vertical line of sight: θ = atan2(−(R e_y)_x, (R e_y)_y). The returned roll is
    asin((R e_y)_z): zero exactly when the bearing has no roll (the DESIGN.md contract); callers
    reject |roll| above their tolerance. q need not be normalised (it is normalised here;
    callers that must reject non-unit quaternions check the norm themselves).
    """
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    ux = 1.0 - 2.0 * (y * y + z * z)
    uy = 2.0 * (x * y + w * z)
    uz = 2.0 * (x * z - w * y)
    yx = 2.0 * (x * y - w * z)
    yy = 1.0 - 2.0 * (x * x + z * z)
    yz = 2.0 * (y * z + w * x)
    az = np.arctan2(-yx, yy)
    el = np.arctan2(uz, np.hypot(ux, uy))
    roll = np.arcsin(np.clip(yz, -1.0, 1.0))
    return az, el, roll


# Scalar twin kept on purpose: the per-message conversions run on Python floats, which cut
# bearing_from_msg from 41-68 µs to about 7 µs (bench/bench_conversions.py, docs/benchmarks.md
# "Message conversions"); a test holds both versions within 1 ulp of each other.
def azel_from_quaternion_scalar(x, y, z, w):
    """Scalar twin of :func:`azel_from_quaternion`: quaternion components -> (θ, ψ, roll), rad.

    Same maths: q is normalised (|q|² summed in numpy's order, so the normalised components
    are bit-identical), u = R e_x gives ψ = atan2(u_z, hypot(u_x, u_y)), the image of the y
    axis gives θ = atan2(−(R e_y)_x, (R e_y)_y) (well conditioned for a nearly vertical line
    of sight) and roll = asin((R e_y)_z), clipped to [−1, 1]. Results agree with the
    vectorised function to float rounding (math.atan2/asin/hypot against numpy's SIMD
    versions: at most a few ulp). A zero quaternion gives NaN, as in the vectorised version.
    """
    norm = math.sqrt(((x * x + y * y) + z * z) + w * w)
    if norm == 0.0:
        return math.nan, math.nan, math.nan
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    ux = 1.0 - 2.0 * (y * y + z * z)
    uy = 2.0 * (x * y + w * z)
    uz = 2.0 * (x * z - w * y)
    yx = 2.0 * (x * y - w * z)
    yy = 1.0 - 2.0 * (x * x + z * z)
    yz = 2.0 * (y * z + w * x)
    az = math.atan2(-yx, yy)
    el = math.atan2(uz, math.hypot(ux, uy))
    roll = math.asin(min(max(yz, -1.0), 1.0))
    return az, el, roll


def bearing_covariance6(position_covariance, sigma_az, sigma_el=None):
    """Row-major 6x6 pose covariance (36,) of a bearing message (DESIGN.md bearing message).

    Layout: rows/columns (x, y, z, roll, pitch, yaw). [0..2, 0..2] = the station position
    covariance (m², ENU); [4, 4] (``IDX_EL_VAR``) = σ_ψ² (rad², elevation above horizontal,
    carried by pitch = −ψ), or ``NO_ELEVATION_VARIANCE`` (−1) when ``sigma_el`` is None (an
    azimuth-only bearing); [5, 5] (``IDX_AZ_VAR``) = σ_θ² (rad², ENU azimuth, carried by yaw).
    Every other entry is 0. Returns a float64 numpy array of 36 values.
    """
    cov = np.zeros(36)
    pcov = np.asarray(position_covariance, dtype=float)
    cov[0:3], cov[6:9], cov[12:15] = pcov
    cov[IDX_EL_VAR] = NO_ELEVATION_VARIANCE if sigma_el is None else sigma_el ** 2
    cov[IDX_AZ_VAR] = sigma_az ** 2
    return cov


def stamp_text(stamp_ns):
    """Integer ns since the epoch as exact decimal seconds (``1796534163.604000000``); a
    float of the seconds would print ``1796534163.604000092``."""
    stamp_ns = int(stamp_ns)
    sign, stamp_ns = ('-', -stamp_ns) if stamp_ns < 0 else ('', stamp_ns)
    return f'{sign}{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d}'


def check_frame_id(frame_id, field='frame_id'):
    """Return ``frame_id`` when it is a usable world frame name: a non-empty string without
    whitespace (ROS frame names hold none); else ValueError ``<field>: ...``."""
    if not isinstance(frame_id, str) or not frame_id or any(c.isspace() for c in frame_id):
        raise ValueError(f'{field}: must be a non-empty name without spaces, got {frame_id!r}')
    return frame_id
