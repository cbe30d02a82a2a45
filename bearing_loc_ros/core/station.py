"""The pure part of a DF station: raw readings -> world-frame bearings (no ROS).

A station (``station_node``) receives raw direction-finding readings, in the sensor's own
angular reference and units, from a ROS topic or from UDP JSON datagrams, and publishes
world-frame bearings (DESIGN.md "The bearing message"). Everything here is numpy/scipy and is
tested without ROS:

* :class:`RawReading` and :func:`raw_reading`: one reading (azimuth, optional elevation,
  optional σ) converted to radians, still in the sensor's reference.
* :func:`parse_datagram`: the UDP JSON format
  ``{"t": unix_seconds, "azimuth_deg": a, "elevation_deg": e | null, "sigma_deg": s}``,
  parsed in time linear in the datagram's size (at most :data:`MAX_DATAGRAM_BYTES`): no
  number literal is ever converted to a big integer or decimal.
* :func:`station_config`: station parameters (the ROS parameter names, degrees in ``_deg``
  names) -> validated :class:`StationConfig` in SI units, or :class:`ConfigError` naming the
  parameter.
* :func:`to_world_bearing`: reading + configuration (+ platform pose) -> core
  :class:`~bearing_loc_ros.core.bearings.Bearing`.
* :class:`PoseBuffer`: bounded buffer of platform poses (nav_msgs/Odometry) interpolated to
  a bearing's stamp (linear position, slerp orientation).

Angle conventions (DESIGN.md, REP-103), with a = raw azimuth and δ = ``azimuth_offset``:

* The offset is added in the sensor's own reference and sense, before any conversion:
  a_c = a + δ. So δ > 0 turns the reading counter-clockwise (seen from above) for an
  ``enu`` sensor and clockwise for a ``compass`` sensor. Use it for the array's mounting
  angle or a calibration: if a sensor reads a − δ for a true direction a, set δ.
* Fixed station: ``enu`` gives θ = a_c (ENU yaw, CCW from East); ``compass`` gives
  θ = π/2 − a_c (compass bearings are clockwise from North; DESIGN.md). With a geodetic
  origin, North and the horizontal are the station's own (true North, local vertical), and
  the line of sight is rotated into the origin's ENU axes (``StationConfig.local_to_world``).
* Moving platform: the reading is in the body frame (REP-103: x forward, y left, z up).
  ``enu`` gives the body yaw θ_b = a_c (CCW from the bow); ``compass`` is a relative bearing
  clockwise from the bow, θ_b = −a_c. The body line of sight u_b = (cos ψ_b cos θ_b,
  cos ψ_b sin θ_b, sin ψ_b) is rotated into the world, u = R(q) u_b, and θ, ψ are recomputed
  from u (Wang, Zhang & Wu (2006) eq. (1) applied to u). σ is kept. An azimuth-only (1D)
  reading uses ψ_b = 0: exact for a level platform, an approximation when it rolls or pitches (the
  measured quantity is then a plane, not a ray).
"""

from dataclasses import dataclass, field
import decimal
import json
import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .bearings import Bearing, HALF_PI, SIGMA_MAX, SIGMA_MIN
from .conventions import azimuth_elevation, los_vector, wrap_angle

NS_PER_S = 1_000_000_000
#: Largest stamp a builtin_interfaces/Time can carry (sec is an int32).
MAX_STAMP_NS = (2 ** 31 - 1) * NS_PER_S
#: Largest |raw angle|, rad (about 1592 turns, 573,000 degrees). Wrapping a larger angle
#: into (−π, π] keeps fewer digits: the spacing of doubles near 1e4 is 1.8e-12 rad, near
#: 1e9 it is 1.2e-7 rad and near 1e16 it is 2 rad, so such a reading says nothing about the
#: direction; no sensor reports it.
MAX_ABS_ANGLE = 1.0e4
#: Largest UDP datagram parsed, bytes (a reading is ~100 bytes); larger ones are rejected
#: unread (``too_large``), which bounds the parse time.
MAX_DATAGRAM_BYTES = 8192
#: Longest JSON number literal converted, characters (sign, digits, point, exponent). Longer
#: literals, and exponents beyond ±:data:`MAX_EXPONENT`, are rejected before conversion:
#: building a 10^200000 integer from ``1e200000`` would take seconds.
MAX_NUMBER_CHARS = 40
MAX_EXPONENT = 400
#: Every reason :func:`parse_datagram` rejects a datagram with (counted as
#: ``rejected_<reason>`` in the station's diagnostics).
DATAGRAM_REJECTIONS = ('too_large', 'bad_json', 'not_object', 'missing_t', 'bad_t',
                       'missing_azimuth', 'bad_azimuth', 'bad_elevation', 'bad_sigma')
UNITS = ('deg', 'rad')
AZIMUTH_REFERENCES = ('enu', 'compass')
#: Tolerance on |q| − 1 for platform orientations (as for bearing messages).
QUATERNION_NORM_TOL = 1.0e-3


class ReadingError(ValueError):
    """A reading or pose is rejected; ``reason`` is a short tag counted in diagnostics."""

    def __init__(self, reason, detail=''):
        super().__init__(f'{reason}: {detail}' if detail else reason)
        self.reason = reason


class ConfigError(ValueError):
    """A station parameter is invalid; ``field`` is the parameter name."""

    def __init__(self, field_name, problem):
        super().__init__(f'{field_name}: {problem}')
        self.field = field_name
        self.problem = problem


@dataclass
class RawReading:
    """One raw DF reading, in radians but still in the sensor's reference.

    Attributes:
        stamp_ns: observation time, integer ns (> 0).
        azimuth: raw azimuth a, rad, in the sensor's reference (``enu`` or ``compass``),
            before the mounting offset.
        elevation: raw elevation, rad, or NaN when not measured.
        sigma_azimuth: σ_θ for this reading, rad, or NaN to use the station's default.
        sigma_elevation: σ_ψ for this reading, rad, or NaN to use the station's default.
    """

    stamp_ns: int
    azimuth: float
    elevation: float = float('nan')
    sigma_azimuth: float = float('nan')
    sigma_elevation: float = float('nan')


def _scale(units):
    if units not in UNITS:
        raise ValueError(f'units: {units!r} is not one of {UNITS}')
    return math.pi / 180.0 if units == 'deg' else 1.0


def raw_reading(stamp_ns, azimuth, elevation=float('nan'), units='rad',
                sigma_azimuth=float('nan'), sigma_elevation=float('nan')):
    """Build a validated :class:`RawReading`, converting ``units`` ('deg' or 'rad') to rad.

    Rejections (:class:`ReadingError` reasons): stamp ≤ 0 or beyond 2038 (``bad_stamp``);
    azimuth not finite or, in rad, beyond ±:data:`MAX_ABS_ANGLE` (``bad_azimuth``);
    elevation infinite or beyond ±:data:`MAX_ABS_ANGLE` rad (``bad_elevation``; NaN means
    "not measured"); σ given (not NaN) but, in rad, not in [SIGMA_MIN, SIGMA_MAX] =
    [1e-12, 1e3] (``bad_sigma``, the range :class:`~bearing_loc_ros.core.bearings.Bearing`
    accepts). A value that is not a number is rejected with the same reasons, never with
    another exception.
    """
    k = _scale(units)
    try:
        stamp_ns = int(stamp_ns)
    except (TypeError, ValueError, OverflowError):
        raise ReadingError('bad_stamp', f'stamp {stamp_ns!r} is not an integer') from None
    if stamp_ns <= 0 or stamp_ns > MAX_STAMP_NS:
        raise ReadingError('bad_stamp', f'stamp {stamp_ns} ns (0 means "not set")')
    az = _float(azimuth, 'bad_azimuth', 'azimuth') * k
    if not (math.isfinite(az) and abs(az) <= MAX_ABS_ANGLE):
        raise ReadingError('bad_azimuth', f'azimuth {az:.6g} rad is not finite or beyond '
                                          f'±{MAX_ABS_ANGLE:g} rad')
    el = _float(elevation, 'bad_elevation', 'elevation') * k
    if not (math.isnan(el) or abs(el) <= MAX_ABS_ANGLE):
        raise ReadingError('bad_elevation', f'elevation {el:.6g} rad is infinite or beyond '
                                            f'±{MAX_ABS_ANGLE:g} rad')
    sigmas = []
    for s in (sigma_azimuth, sigma_elevation):
        s = _float(s, 'bad_sigma', 'sigma') * k
        if not (math.isnan(s) or SIGMA_MIN <= s <= SIGMA_MAX):
            raise ReadingError('bad_sigma', f'sigma {s:.6g} rad is not in '
                                            f'[{SIGMA_MIN:g}, {SIGMA_MAX:g}] rad')
        sigmas.append(s)
    return RawReading(stamp_ns, az, el, sigmas[0], sigmas[1])


def _float(value, reason, name):
    """``float(value)``, or :class:`ReadingError` ``reason`` (never Overflow/TypeError)."""
    if isinstance(value, bool):
        raise ReadingError(reason, f'{name} must be a number, got {value!r}')
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise ReadingError(reason, f'{name} is not a float: {str(value)[:40]!r}') from None


class _BadNumber:
    """A JSON number literal refused before conversion (too long or exponent out of range)."""

    __slots__ = ('problem',)

    def __init__(self, problem):
        self.problem = problem


def _literal_problem(text):
    """Why a JSON number literal must not be converted, or '' when it is safe (cheap)."""
    if len(text) > MAX_NUMBER_CHARS:
        return f'number literal of {len(text)} characters (at most {MAX_NUMBER_CHARS})'
    return ''


def _json_int(text):
    problem = _literal_problem(text)
    return _BadNumber(problem) if problem else int(text)


def _json_float(text):
    problem = _literal_problem(text)
    if problem:
        return _BadNumber(problem)
    value = decimal.Decimal(text)  # exact and cheap: ≤ MAX_NUMBER_CHARS characters
    if value and abs(value.adjusted()) > MAX_EXPONENT:
        return _BadNumber(f'number {text} has a decimal exponent beyond ±{MAX_EXPONENT}')
    return value


def _reject_constant(name):
    raise ValueError(f'{name} is not allowed')


def _number(value, reason, name):
    """A parsed JSON number (int or Decimal) or :class:`ReadingError` ``reason``."""
    if isinstance(value, _BadNumber):
        raise ReadingError(reason, f'{name}: {value.problem}')
    if isinstance(value, bool) or not isinstance(value, (int, decimal.Decimal)):
        raise ReadingError(reason, f'{name} must be a number, got {str(value)[:40]!r}')
    return value


def _stamp_ns(t):
    """Unix seconds (int or Decimal, range-checked first) -> integer ns, exactly rounded."""
    if not 0 < t <= MAX_STAMP_NS // NS_PER_S:
        raise ReadingError('bad_t', f't {t} is not a unix time in seconds (1970 to 2038)')
    with decimal.localcontext(prec=MAX_NUMBER_CHARS + 20):  # exact: no double rounding
        stamp_ns = int(decimal.Decimal(t).scaleb(9).to_integral_value(
            rounding=decimal.ROUND_HALF_EVEN))
    if not 0 < stamp_ns <= MAX_STAMP_NS:
        raise ReadingError('bad_t', f't {t} is not a unix time in seconds (1970 to 2038)')
    return stamp_ns


def parse_datagram(data, require_t=True):
    """Parse one UDP datagram (UTF-8 JSON object) into a :class:`RawReading`.

    Format: ``{"t": unix_seconds, "azimuth_deg": a, "elevation_deg": e or null,
    "sigma_deg": s, "sigma_elevation_deg": s_e}``; ``elevation_deg``, ``sigma_deg``
    (σ_θ) and ``sigma_elevation_deg`` (σ_ψ) are optional, other keys are ignored. Angles
    are degrees in the station's ``azimuth_reference``. ``t`` is converted exactly (decimal
    arithmetic) to integer ns: t = 1700000000.123456789 -> 1700000000123456789 ns. With
    ``require_t`` False (the node re-stamps on receipt) ``t`` may be missing; stamp_ns is
    then 1 as a placeholder.

    Cost is linear in the datagram's length: a datagram longer than
    :data:`MAX_DATAGRAM_BYTES` is not parsed, and a number literal longer than
    :data:`MAX_NUMBER_CHARS` characters or with a decimal exponent beyond
    ±:data:`MAX_EXPONENT` is never converted (it makes its field invalid; in an ignored key
    it is harmless). ``t`` is range-checked before it is scaled to ns.

    Rejections (:class:`ReadingError` reasons): longer than :data:`MAX_DATAGRAM_BYTES`
    (``too_large``); not UTF-8 JSON, NaN/Infinity literals, nesting too deep (``bad_json``);
    not an object (``not_object``); ``t`` missing (``missing_t``), not a number, too long a
    literal or outside 1970-2038 (``bad_t``); ``azimuth_deg`` missing (``missing_azimuth``),
    not a number, too long a literal, or beyond ±:data:`MAX_ABS_ANGLE` rad
    (``bad_azimuth``); ``elevation_deg`` neither null nor such a number
    (``bad_elevation``); a σ not a number in [1e-12, 1e3] rad (``bad_sigma``). Nothing else
    is raised, whatever ``data`` holds.
    """
    if not isinstance(data, (bytes, bytearray, memoryview, str)):
        raise ReadingError('bad_json', f'expected bytes, got {type(data).__name__}')
    if len(data) > MAX_DATAGRAM_BYTES:
        raise ReadingError('too_large', f'{len(data)} bytes (at most {MAX_DATAGRAM_BYTES})')
    if isinstance(data, memoryview):
        data = data.tobytes()
    try:
        obj = json.loads(data, parse_float=_json_float, parse_int=_json_int,
                         parse_constant=_reject_constant)
    except (ValueError, TypeError, RecursionError) as exc:
        raise ReadingError('bad_json', str(exc).splitlines()[0][:120]) from None
    if not isinstance(obj, dict):
        raise ReadingError('not_object', f'expected a JSON object, got {type(obj).__name__}')
    if 't' in obj:
        stamp_ns = _stamp_ns(_number(obj['t'], 'bad_t', 't'))
    elif require_t:
        raise ReadingError('missing_t', 'no "t" (unix seconds)')
    else:
        stamp_ns = 1
    if 'azimuth_deg' not in obj:
        raise ReadingError('missing_azimuth', 'no "azimuth_deg"')
    az = _number(obj['azimuth_deg'], 'bad_azimuth', 'azimuth_deg')
    el = obj.get('elevation_deg')
    el = float('nan') if el is None else _number(el, 'bad_elevation', 'elevation_deg')
    sig = []
    for key in ('sigma_deg', 'sigma_elevation_deg'):
        s = obj.get(key)
        sig.append(float('nan') if s is None else _number(s, 'bad_sigma', key))
    return raw_reading(stamp_ns, az, el, 'deg', sig[0], sig[1])


@dataclass
class StationConfig:
    """A station's configuration in SI units (built and validated by :func:`station_config`).

    Attributes:
        station: station id (the namespace).
        frame_id: world frame of the published bearings.
        position: (3,) ENU position, m, or None on a moving platform (from odometry).
        position_covariance: (3, 3) station position covariance, m² (added to the odometry's
            on a moving platform).
        sigma_azimuth, sigma_elevation: default σ_θ, σ_ψ, rad.
        measures_elevation: False for a 1D (azimuth-only) station: elevations are ignored.
        azimuth_reference: 'enu' or 'compass' (module docstring).
        azimuth_offset: δ, rad, added to the raw azimuth in the sensor's reference.
        moving: True when the pose comes from a platform odometry.
        local_to_world: (3, 3) rotation taking vectors in the station's own ENU axes (true
            North and the local horizontal at the station) into the world frame's axes (the
            ENU frame of the geodetic origin), or None when no geodetic origin is set (the
            world is then a flat ENU frame and the two coincide).
    """

    station: str
    frame_id: str
    position: np.ndarray
    position_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    sigma_azimuth: float = math.radians(2.0)
    sigma_elevation: float = math.radians(2.0)
    measures_elevation: bool = False
    azimuth_reference: str = 'enu'
    azimuth_offset: float = 0.0
    moving: bool = False
    local_to_world: np.ndarray = None


def _covariance(values, name):
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return np.zeros((3, 3))
    if v.size == 3:
        cov = np.diag(v)
    elif v.size == 9:
        cov = v.reshape(3, 3)
    else:
        raise ConfigError(name, f'expected 3 (diagonal) or 9 (row-major 3x3) values in m², '
                                f'got {v.size}')
    if not np.all(np.isfinite(cov)):
        raise ConfigError(name, 'non-finite value')
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12):
        raise ConfigError(name, 'not symmetric')
    if np.min(np.linalg.eigvalsh(cov)) < -1e-9 * max(1.0, np.max(np.abs(cov))):
        raise ConfigError(name, 'not positive semi-definite (negative variance)')
    return cov


def _config_floats(values, name):
    """A parameter array as a list of floats (NaN/inf kept for the checks that follow)."""
    if isinstance(values, (str, bytes, dict)) or not hasattr(values, '__len__'):
        raise ConfigError(name, f'expected a list of numbers, got {str(values)[:40]!r}')
    try:
        return [_config_float(v, name) for v in values]
    except ConfigError:
        raise ConfigError(name, f'expected a list of numbers, got {str(values)[:60]!r}') \
            from None


def _config_float(value, name):
    """A parameter scalar as a float, or :class:`ConfigError` (never Overflow/TypeError)."""
    if isinstance(value, (bool, str, bytes)):
        raise ConfigError(name, f'expected a number, got {value!r}')
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(name, f'expected a number, got {str(value)[:40]!r}') from None


def station_config(station, frame_id='map', position=(), geodetic_position=(),
                   geodetic_origin=(), position_covariance=(), sigma_azimuth_deg=2.0,
                   sigma_elevation_deg=2.0, measures_elevation=False, azimuth_reference='enu',
                   azimuth_offset_deg=0.0, moving=False):
    """Validate station parameters (named exactly as the node's ROS parameters) -> config.

    The station position is ``position`` ([x, y, z] ENU m) or ``geodetic_position``
    ([lat_deg, lon_deg, alt_m], WGS84 ellipsoidal height) converted to ENU about
    ``geodetic_origin`` ([lat_deg, lon_deg, alt_m]) by :mod:`bearing_loc_ros.core.geodesy`;
    exactly one of them unless ``moving`` (then neither: the platform odometry gives it).
    ``position_covariance``: 3 (diagonal) or 9 (row-major) values, m², symmetric PSD.
    σ in degrees, > 0 and ≤ 180. Raises :class:`ConfigError` naming the parameter, for any
    value of any type (numbers beyond float range and wrong types included).

    With a geodetic origin, a fixed station's readings are taken to be relative to its own
    true North and local horizontal, which differ from the origin's ENU axes by the meridian
    convergence (λ − λ0) sin φ and a tilt of about distance / Earth radius (0.5 mrad per
    3 km); ``local_to_world`` = Rᵀ with R from
    :func:`bearing_loc_ros.core.geodesy.enu_axes_rotation` corrects for it. (A moving
    platform's odometry orientation is already in the world frame.)
    """
    from . import geodesy

    def geo(values, name):
        try:
            return geodesy.geodetic_triplet(values, name)
        except (ValueError, TypeError, OverflowError) as exc:
            raise ConfigError(name, str(exc).partition(': ')[2] or str(exc)) from None

    if not isinstance(station, str) or not station:
        raise ConfigError('station_id', 'empty (run the node in a namespace or set it)')
    if not isinstance(frame_id, str) or not frame_id:
        raise ConfigError('frame_id', 'must be a non-empty string')
    position = _config_floats(position, 'position')
    geodetic_position = _config_floats(geodetic_position, 'geodetic_position')
    geodetic_origin = _config_floats(geodetic_origin, 'geodetic_origin')
    position_covariance = _config_floats(position_covariance, 'position_covariance')
    sigma_azimuth_deg = _config_float(sigma_azimuth_deg, 'sigma_azimuth_deg')
    sigma_elevation_deg = _config_float(sigma_elevation_deg, 'sigma_elevation_deg')
    azimuth_offset_deg = _config_float(azimuth_offset_deg, 'azimuth_offset_deg')
    pos = None
    origin = geo(geodetic_origin, 'geodetic_origin') if len(geodetic_origin) else None
    if len(position) and len(geodetic_position):
        raise ConfigError('geodetic_position', 'give either position (ENU m) or '
                                               'geodetic_position, not both')
    if moving and (len(position) or len(geodetic_position)):
        name = 'position' if len(position) else 'geodetic_position'
        raise ConfigError(name, 'must not be set with platform_odometry (the odometry gives '
                                'the station position)')
    if len(position):
        pos = np.asarray(position, dtype=float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ConfigError('position', f'expected 3 finite values [x, y, z] in m, got '
                                          f'{list(position)}')
    elif len(geodetic_position):
        if origin is None:
            raise ConfigError('geodetic_origin', 'required with geodetic_position '
                                                 '([lat_deg, lon_deg, alt_m])')
        lla = geo(geodetic_position, 'geodetic_position')
        pos = geodesy.geodetic_to_enu(*lla, origin)
    elif not moving:
        raise ConfigError('position', 'required: set position ([x, y, z] ENU m), '
                                      'geodetic_position + geodetic_origin, or '
                                      'platform_odometry')
    local_to_world = None
    if pos is not None and origin is not None:
        lat, lon, _ = geodesy.enu_to_geodetic(pos, origin)
        local_to_world = geodesy.enu_axes_rotation(origin, lat, lon).T
    cov = _covariance(position_covariance, 'position_covariance')
    for name, val in (('sigma_azimuth_deg', sigma_azimuth_deg),
                      ('sigma_elevation_deg', sigma_elevation_deg)):
        if not (math.isfinite(val) and 0.0 < val <= 180.0):
            raise ConfigError(name, f'{val} must be > 0 and <= 180 degrees')
    if not isinstance(azimuth_reference, str) or azimuth_reference not in AZIMUTH_REFERENCES:
        raise ConfigError('azimuth_reference', f'{azimuth_reference!r} is not one of '
                                               f'{AZIMUTH_REFERENCES}')
    if not (math.isfinite(azimuth_offset_deg) and abs(azimuth_offset_deg) <= 360.0):
        raise ConfigError('azimuth_offset_deg', f'{azimuth_offset_deg} must be in '
                                                '[-360, 360]')
    return StationConfig(station=station, frame_id=frame_id, position=pos,
                         position_covariance=cov,
                         sigma_azimuth=math.radians(sigma_azimuth_deg),
                         sigma_elevation=math.radians(sigma_elevation_deg),
                         measures_elevation=bool(measures_elevation),
                         azimuth_reference=azimuth_reference,
                         azimuth_offset=math.radians(azimuth_offset_deg), moving=bool(moving),
                         local_to_world=local_to_world)


@dataclass
class PoseSample:
    """A platform pose at one instant (from nav_msgs/Odometry).

    Attributes:
        stamp_ns: integer ns.
        position: (3,) body origin in the world frame, m.
        quaternion: (4,) unit quaternion (x, y, z, w) rotating body vectors into the world.
        position_covariance: (3, 3) m².
    """

    stamp_ns: int
    position: np.ndarray
    quaternion: np.ndarray
    position_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


def pose_sample(stamp_ns, position, quaternion, position_covariance=None):
    """Validated :class:`PoseSample` (quaternion normalised).

    Rejections (:class:`ReadingError`): ``odometry_bad_stamp``, ``odometry_bad_position``
    (non-finite), ``odometry_bad_quaternion`` (NaN or |q| not within 1e-3 of 1),
    ``odometry_bad_covariance`` (non-finite or negative variances).
    """
    stamp_ns = int(stamp_ns)
    if stamp_ns <= 0:
        raise ReadingError('odometry_bad_stamp', f'stamp {stamp_ns} ns')
    p = np.asarray(position, dtype=float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise ReadingError('odometry_bad_position', 'non-finite position')
    q = np.asarray(quaternion, dtype=float).reshape(4)
    n = math.hypot(*q.tolist())  # no overflow warning for |q| near 1e308
    if not math.isfinite(n) or abs(n - 1.0) > QUATERNION_NORM_TOL:
        raise ReadingError('odometry_bad_quaternion', f'quaternion norm {n:.6g} is not 1')
    cov = np.zeros((3, 3)) if position_covariance is None else \
        np.asarray(position_covariance, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0.0):
        raise ReadingError('odometry_bad_covariance', 'non-finite or negative variance')
    return PoseSample(stamp_ns, p, q / n, cov)


class PoseBuffer:
    """A bounded, time-ordered buffer of platform poses, interpolated to bearing stamps.

    For t_i ≤ t ≤ t_{i+1}, with s = (t − t_i) / (t_{i+1} − t_i): position and position
    covariance are linear, p = (1 − s) p_i + s p_{i+1}; the orientation is the spherical
    linear interpolation (slerp, shortest arc) of q_i and q_{i+1}. A stamp outside the
    buffered interval by at most ``tolerance_ns`` gets the nearest pose (held, never
    extrapolated); further out it is rejected (``before_odometry`` / ``after_odometry``;
    ``no_odometry`` when empty). At most ``maxlen`` poses are kept (oldest dropped).

    Time must increase: a duplicate stamp is ignored; a stamp earlier than the newest one
    means the clock jumped back (bag replay restarted) and clears the buffer.
    """

    def __init__(self, maxlen=200, tolerance_ns=100_000_000):
        if int(maxlen) < 2:
            raise ValueError('maxlen: need at least 2 poses to interpolate')
        if int(tolerance_ns) < 0:
            raise ValueError('tolerance_ns: must be >= 0')
        self.maxlen = int(maxlen)
        self.tolerance_ns = int(tolerance_ns)
        self._samples = []

    def __len__(self):
        return len(self._samples)

    @property
    def interval(self):
        """(first, last) buffered stamps in ns, or None when empty."""
        if not self._samples:
            return None
        return self._samples[0].stamp_ns, self._samples[-1].stamp_ns

    def add(self, sample):
        """Append a :class:`PoseSample`; return 'ok', 'duplicate' (ignored) or 'reset'."""
        status = 'ok'
        if self._samples:
            last = self._samples[-1].stamp_ns
            if sample.stamp_ns == last:
                return 'duplicate'
            if sample.stamp_ns < last:
                self._samples.clear()
                status = 'reset'
        self._samples.append(sample)
        if len(self._samples) > self.maxlen:
            del self._samples[0]
        return status

    def clear(self):
        """Drop every buffered pose."""
        self._samples.clear()

    def interpolate(self, stamp_ns):
        """Pose at ``stamp_ns`` (class docstring) or :class:`ReadingError`."""
        if not self._samples:
            raise ReadingError('no_odometry', 'no platform pose received yet')
        t = int(stamp_ns)
        first, last = self._samples[0], self._samples[-1]
        if t <= first.stamp_ns:
            if first.stamp_ns - t > self.tolerance_ns:
                raise ReadingError('before_odometry', f'{(first.stamp_ns - t) / 1e9:.3f} s '
                                                      'before the oldest buffered pose')
            return PoseSample(t, first.position.copy(), first.quaternion.copy(),
                              first.position_covariance.copy())
        if t >= last.stamp_ns:
            if t - last.stamp_ns > self.tolerance_ns:
                raise ReadingError('after_odometry', f'{(t - last.stamp_ns) / 1e9:.3f} s '
                                                     'after the newest buffered pose')
            return PoseSample(t, last.position.copy(), last.quaternion.copy(),
                              last.position_covariance.copy())
        stamps = np.array([s.stamp_ns for s in self._samples], dtype=np.int64)
        i = int(np.searchsorted(stamps, t, side='right')) - 1
        a, b = self._samples[i], self._samples[i + 1]
        s = (t - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        pos = (1.0 - s) * a.position + s * b.position
        cov = (1.0 - s) * a.position_covariance + s * b.position_covariance
        q = Slerp([0.0, 1.0], Rotation.from_quat([a.quaternion, b.quaternion]))(s).as_quat()
        return PoseSample(t, pos, q, cov)


def to_world_bearing(reading, config, pose=None):
    """Raw reading -> world-frame :class:`Bearing` (module docstring for the conventions).

    ``pose`` (a :class:`PoseSample` at the reading's stamp) is required exactly when
    ``config.moving``. σ_θ/σ_ψ come from the reading when given, else from the config.
    Elevation is used only when ``config.measures_elevation`` and the reading has one.
    Rejections (:class:`ReadingError`): |ψ| ≥ π/2 in the sensor or world frame
    (``bad_elevation``).
    """
    a = reading.azimuth + config.azimuth_offset
    el = reading.elevation if config.measures_elevation else float('nan')
    has_el = math.isfinite(el)
    if has_el and abs(el) >= HALF_PI:
        raise ReadingError('bad_elevation', f'elevation {el} rad; |elevation| must be < pi/2')
    compass = config.azimuth_reference == 'compass'
    if config.moving:
        if pose is None:
            raise ValueError('pose: required for a station on a moving platform')
        theta_b = -a if compass else a
        u = Rotation.from_quat(pose.quaternion).apply(los_vector(theta_b, el if has_el else 0.0))
        az, el_w = (float(v) for v in azimuth_elevation(u))
        if has_el:
            el = el_w
            if abs(el) >= HALF_PI:
                raise ReadingError('bad_elevation', 'line of sight is vertical in the world')
        position = pose.position
        cov = pose.position_covariance + config.position_covariance
    else:
        az = math.pi / 2.0 - a if compass else a
        if config.local_to_world is not None:
            u = config.local_to_world @ los_vector(az, el if has_el else 0.0)
            az, el_w = (float(v) for v in azimuth_elevation(u))
            if has_el:
                el = el_w
        position = config.position
        cov = config.position_covariance
    s_az = reading.sigma_azimuth if math.isfinite(reading.sigma_azimuth) \
        else config.sigma_azimuth
    s_el = float('nan')
    if has_el:
        s_el = reading.sigma_elevation if math.isfinite(reading.sigma_elevation) \
            else config.sigma_elevation
    return Bearing(station=config.station, stamp_ns=int(reading.stamp_ns),
                   position=np.array(position, dtype=float), azimuth=float(wrap_angle(az)),
                   elevation=float(el) if has_el else float('nan'), sigma_azimuth=float(s_az),
                   sigma_elevation=float(s_el), frame_id=config.frame_id,
                   position_covariance=np.array(cov, dtype=float))
