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

Modules: :mod:`.readings` (raw readings and the errors), :mod:`.datagram` (the UDP format),
:mod:`.platform_pose` (poses and their buffer) and this one (configuration and the world
bearing); every public name is importable from here.
"""

from dataclasses import dataclass, field
import math

import numpy as np
from scipy.spatial.transform import Rotation

from .bearings import Bearing, HALF_PI
from .conventions import azimuth_elevation, check_frame_id, los_vector, wrap_angle
# Re-exported: readings, the datagram parser and the poses are part of this module's interface.
from .datagram import (DATAGRAM_REJECTIONS, MAX_DATAGRAM_BYTES, MAX_EXPONENT,  # noqa: F401
                       MAX_NUMBER_CHARS, parse_datagram)
from .platform_pose import pose_sample, PoseBuffer, PoseSample  # noqa: F401
from .readings import (AZIMUTH_REFERENCES, ConfigError, MAX_ABS_ANGLE,  # noqa: F401
                       MAX_STAMP_NS, NS_PER_S, QUATERNION_NORM_TOL, raw_reading, RawReading,
                       ReadingError, UNITS)


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
    try:
        check_frame_id(frame_id)        # the fusion node refuses a name with spaces too
    except ValueError as exc:
        raise ConfigError('frame_id', str(exc).partition(': ')[2]) from None
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
