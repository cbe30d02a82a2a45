"""The geometry of a real DF receiver: DOA + heading + position -> world-frame bearing (pure).

A receiver such as the KrakenSDR reports the direction of arrival (DOA) relative to its
antenna array, in degrees (:mod:`bearing_loc_ros.core.kraken`). Turning it into the
project's bearing (DESIGN.md: ENU azimuth θ, counter-clockwise from East, radians) takes
four steps, each a station parameter:

1. **Sense and reference of the DOA** (``sense``), with H the heading of the array front
   (degrees clockwise from true North) and D the DOA (degrees counter-clockwise from the
   array front, the XML's convention):

   * ``inverted`` (default): compass β = H + (360 − D). The KrakenSDR's DOA is
     counter-clockwise, the compass is clockwise, so the DOA is mirrored.
   * ``flipped``: β = H + 180 + D (an array mounted facing backwards whose software
     already reports clockwise angles).
   * ``plain``: β = H + D (a receiver that reports clockwise angles).

   β is then taken modulo 360 and ``heading_offset_deg`` (the calibrated bias correction,
   see :mod:`bearing_loc_ros.core.calibration`) is added.
2. **Heading H** (``heading_source``): ``fixed`` uses ``array_heading_deg``; ``gps`` uses
   the receiver's GPS heading plus ``array_heading_deg`` (the mounting angle of the array
   front relative to the vehicle's bow); ``odometry`` uses the platform odometry's yaw plus
   ``array_heading_deg``. A GPS heading (course over ground) is meaningless at low speed:
   below ``min_speed`` (m/s) the last good heading is held (counted, ``heading_held``) or,
   with ``low_speed: odometry``, the odometry yaw is used. When the receiver reports no
   speed (the CSV has none) it is derived from consecutive GPS positions. With
   ``heading_reference: magnetic`` the magnetic declination δ (degrees, East positive) is
   added: H_true = H_magnetic + δ.
3. **Compass -> ENU**: θ_local = π/2 − β (``conventions.compass_to_enu``), in the station's
   own true-North axes. With a geodetic origin, the line of sight is rotated into the
   origin's ENU axes (meridian convergence; ``geodesy.enu_axes_rotation``), as for any
   fixed station (``core.station``). An odometry heading is already in world axes.
4. **Position** (``position_source``): ``parameters`` (``position`` or
   ``geodetic_position``), ``gps`` (the record's latitude/longitude through the geodetic
   origin, at the origin's height + ``antenna_height_m``; a (0, 0) position means "no fix"
   and is rejected, ``zero_gps``), or ``odometry``.

σ_θ comes from the receiver's confidence c (and optionally its SNR) through
:class:`SigmaModel`.
"""

from collections import Counter
from dataclasses import dataclass, field
import math

import numpy as np

from .bearings import Bearing
from .conventions import azimuth_elevation, los_vector, wrap_angle_scalar
from .kraken import KrakenError

SENSES = ('inverted', 'flipped', 'plain')
HEADING_SOURCES = ('fixed', 'gps', 'odometry')
HEADING_REFERENCES = ('true', 'magnetic')
LOW_SPEED_MODES = ('hold', 'odometry')
POSITION_SOURCES = ('parameters', 'gps', 'odometry')
#: Mean Earth radius (IUGG), m: speed from consecutive GPS fixes (equirectangular).
EARTH_RADIUS_M = 6371008.8
#: Positions further apart in time than this give no derived speed, s.
SPEED_FROM_FIX_MAX_DT_S = 10.0
LN10_OVER_20 = math.log(10.0) / 20.0


def compass_bearing_deg(doa_deg, heading_deg, sense='inverted'):
    """Compass bearing β (degrees clockwise from North, [0, 360)) of a receiver DOA.

    ``inverted``: β = H + (360 − D); ``flipped``: β = H + 180 + D; ``plain``: β = H + D
    (module docstring), each modulo 360. Vectorised over ``doa_deg`` and ``heading_deg``.
    """
    d = np.asarray(doa_deg, dtype=float)
    h = np.asarray(heading_deg, dtype=float)
    if sense == 'inverted':
        b = h + (360.0 - d)
    elif sense == 'flipped':
        b = h + 180.0 + d
    elif sense == 'plain':
        b = h + d
    else:
        raise ValueError(f'sense: {sense!r} is not one of {SENSES}')
    out = np.mod(b, 360.0)
    out = np.where(out >= 360.0, 0.0, out)   # a tiny negative angle rounds to 360
    return out if out.ndim else float(out)


@dataclass
class SigmaModel:
    """Receiver confidence (and SNR) -> σ_θ, a log-linear model.

        ln σ = ln σ₁ + ln(σ₀ / σ₁) · (1 − c̃) − k · (ln 10 / 20) · (SNR − SNR_ref),

    with c̃ = clip(c, 0, 1), σ₁ = σ at full confidence (c ≥ 1), σ₀ = σ at zero confidence,
    and the SNR term used only when ``snr_slope`` k > 0 and the reading has an SNR. σ is then
    clipped to [σ_min, σ_max]. k = 1 is the Cramér-Rao slope of a bearing estimate,
    σ ∝ SNR^(−1/2) = 10^(−SNR_dB/20).

    Default σ₁ = 3°, σ₀ = 12°, k = 0: a confident KrakenSDR reading is limited by multipath
    and array mounting to a few degrees, not by thermal noise; a reading with no confidence
    is a flat or multi-peaked spectrum whose maximum may lie anywhere in the main lobe of a
    small 5-element circular array (about ±20° wide): a uniform error on ±20° has σ =
    40°/√12 ≈ 11.5°. The SNR term is off because the confidence already measures the
    spectrum's quality. ``bearing_loc calibrate`` fits σ₁, σ₀ for a site (maximum
    likelihood, :mod:`bearing_loc_ros.core.calibration`). All angles in degrees here; the
    result of :meth:`sigma` is radians.
    """

    # Dataclass fields: alike other field lists in shape only, there is no logic to share.
    sigma_conf1_deg: float = 3.0
    sigma_conf0_deg: float = 12.0
    snr_slope: float = 0.0
    snr_ref_db: float = 10.0
    sigma_min_deg: float = 0.5
    sigma_max_deg: float = 45.0

    def validate(self, prefix=''):
        """Raise ValueError naming the parameter (``prefix`` + name) unless valid."""
        for name in ('sigma_conf1_deg', 'sigma_conf0_deg', 'sigma_min_deg', 'sigma_max_deg'):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 < v <= 180.0):
                raise ValueError(f'{prefix}{name}: {v} must be > 0 and <= 180 degrees')
        if self.sigma_min_deg > self.sigma_max_deg:
            raise ValueError(f'{prefix}sigma_min_deg: {self.sigma_min_deg} is above '
                             f'sigma_max_deg {self.sigma_max_deg}')
        if not (math.isfinite(self.snr_slope) and 0.0 <= self.snr_slope <= 10.0):
            raise ValueError(f'{prefix}sigma_snr_slope: {self.snr_slope} must be in [0, 10]')
        if not (math.isfinite(self.snr_ref_db) and abs(self.snr_ref_db) <= 300.0):
            raise ValueError(f'{prefix}sigma_snr_ref_db: {self.snr_ref_db} must be finite')
        return self

    def sigma(self, confidence, snr_db=math.nan):
        """σ_θ in radians for confidence c and SNR (dB; NaN = none), vectorised."""
        c = np.clip(np.nan_to_num(np.asarray(confidence, dtype=float), nan=0.0), 0.0, 1.0)
        ln_s = (math.log(self.sigma_conf1_deg)
                + math.log(self.sigma_conf0_deg / self.sigma_conf1_deg) * (1.0 - c))
        if self.snr_slope > 0.0:
            snr = np.asarray(snr_db, dtype=float)
            ln_s = ln_s - np.where(np.isfinite(snr), self.snr_slope * LN10_OVER_20
                                   * (np.nan_to_num(snr) - self.snr_ref_db), 0.0)
        s = np.radians(np.clip(np.exp(ln_s), self.sigma_min_deg, self.sigma_max_deg))
        return s if s.ndim else float(s)


@dataclass
class ReceiverConfig:
    """A receiver station's geometry, validated (built by :func:`receiver_config`).

    Angles in degrees where the name says ``_deg`` (human-facing parameters), SI otherwise.
    ``station`` is the core :class:`~bearing_loc_ros.core.station.StationConfig` holding the
    station id, frame, fixed position, position covariance and ``local_to_world``.
    """

    # Dataclass fields: alike other field lists in shape only, there is no logic to share.
    station: object
    sense: str = 'inverted'
    heading_source: str = 'fixed'
    array_heading_deg: float = 0.0
    heading_reference: str = 'true'
    declination_deg: float = 0.0
    heading_offset_deg: float = 0.0
    min_speed: float = 1.0
    low_speed: str = 'hold'
    heading_hold_timeout_s: float = 0.0
    position_source: str = 'parameters'
    origin: tuple = None
    gps_sigma_m: float = 5.0
    antenna_height_m: float = 0.0
    min_confidence: float = 0.0
    sigma: SigmaModel = field(default_factory=SigmaModel)
    needs_odometry: bool = False


def _choice(value, choices, name):
    if value not in choices:
        raise ValueError(f'{name}: {value!r} is not one of {choices}')
    return value


def _finite(value, name, lo, hi):
    v = float(value)
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f'{name}: {v} must be in [{lo:g}, {hi:g}]')
    return v


def receiver_config(station, frame_id='map', position=(), geodetic_position=(),
                    geodetic_origin=(), position_covariance=(), sense='inverted',
                    heading_source='fixed', array_heading_deg=0.0, heading_reference='true',
                    declination_deg=0.0, heading_offset_deg=0.0, min_speed=1.0,
                    low_speed='hold', heading_hold_timeout_s=0.0, position_source='parameters',
                    gps_sigma_m=5.0, antenna_height_m=0.0, min_confidence=0.0,
                    sigma=None, prefix='kraken.'):
    """Validate a receiver station's parameters -> :class:`ReceiverConfig`.

    ``position``, ``geodetic_position``, ``geodetic_origin``, ``position_covariance`` are the
    station node's parameters of the same names (checked by
    :func:`bearing_loc_ros.core.station.station_config`; a position is required exactly
    when ``position_source`` is ``parameters``). The other names are the receiver parameters
    (module docstring), reported with ``prefix`` in errors. Raises
    :class:`~bearing_loc_ros.core.station.ConfigError` naming the parameter.
    """
    from . import geodesy
    from .station import ConfigError, station_config
    try:
        _choice(position_source, POSITION_SOURCES, 'position_source')
    except ValueError as exc:
        raise ConfigError(prefix + 'position_source', str(exc).partition(': ')[2]) from None
    given = [n for n, v in (('position', position), ('geodetic_position', geodetic_position))
             if len(v)]
    if position_source != 'parameters' and given:
        where = ("the receiver's GPS" if position_source == 'gps' else
                 'the platform odometry')
        raise ConfigError(given[0], f'must not be set with {prefix}position_source: '
                                    f'{position_source} (the position comes from {where})')
    if position_source == 'parameters' and not given:
        raise ConfigError('position', f'required with {prefix}position_source: parameters: '
                                      'set position ([x, y, z] ENU m) or geodetic_position + '
                                      f'geodetic_origin, or {prefix}position_source: gps or '
                                      'odometry')
    base = station_config(station, frame_id=frame_id, position=position,
                          geodetic_position=geodetic_position, geodetic_origin=geodetic_origin,
                          position_covariance=position_covariance,
                          moving=position_source != 'parameters')
    try:
        cfg = ReceiverConfig(
            station=base, sense=_choice(sense, SENSES, 'sense'),
            heading_source=_choice(heading_source, HEADING_SOURCES, 'heading_source'),
            array_heading_deg=_finite(array_heading_deg, 'array_heading_deg', -360., 360.),
            heading_reference=_choice(heading_reference, HEADING_REFERENCES,
                                      'heading_reference'),
            declination_deg=_finite(declination_deg, 'declination_deg', -180.0, 180.0),
            heading_offset_deg=_finite(heading_offset_deg, 'heading_offset_deg', -360., 360.),
            min_speed=_finite(min_speed, 'min_speed', 0.0, 1.0e3),
            low_speed=_choice(low_speed, LOW_SPEED_MODES, 'low_speed'),
            heading_hold_timeout_s=_finite(heading_hold_timeout_s, 'heading_hold_timeout_s',
                                           0.0, 1.0e7),
            position_source=position_source,
            gps_sigma_m=_finite(gps_sigma_m, 'gps_sigma_m', 0.0, 1.0e5),
            antenna_height_m=_finite(antenna_height_m, 'antenna_height_m', -1.0e4, 1.0e5),
            min_confidence=_finite(min_confidence, 'min_confidence', 0.0, 1.0e4),
            sigma=(sigma or SigmaModel()).validate())
    except ValueError as exc:
        name, _, problem = str(exc).partition(': ')
        raise ConfigError(prefix + name, problem) from None
    if len(geodetic_origin):
        cfg.origin = geodesy.geodetic_triplet(geodetic_origin, 'geodetic_origin')
    if position_source == 'gps' and cfg.origin is None:
        raise ConfigError('geodetic_origin', f'required with {prefix}position_source: gps')
    cfg.needs_odometry = (position_source == 'odometry' or heading_source == 'odometry'
                          or (heading_source == 'gps' and low_speed == 'odometry'))
    return cfg


class ReceiverGeometry:
    """Receiver readings (:class:`~bearing_loc_ros.core.kraken.KrakenRecord`) -> bearings.

    Holds the per-station state the conversion needs: the last good GPS heading and the
    last GPS fix (for a derived speed). ``counts`` (a Counter) counts the heading used:
    ``heading_fixed``, ``heading_gps``, ``heading_held`` (below ``min_speed``, the last good
    heading), ``heading_odometry``.
    """

    def __init__(self, config):
        self.config = config
        self.counts = Counter()
        self._good_heading = None      # (stamp_ns, heading_deg)
        self._last_fix = None          # (stamp_ns, lat_deg, lon_deg)

    # ------------------------------------------------------------------ heading

    def speed_of(self, record):
        """Ground speed, m/s: the record's, else derived from the previous GPS fix (NaN when
        unknown). Equirectangular distance, R = 6371008.8 m (error < 0.1 % below 10 km)."""
        speed = record.speed
        fix = (record.stamp_ns, record.latitude_deg, record.longitude_deg)
        prev, self._last_fix = self._last_fix, (fix if record.has_gps else self._last_fix)
        if math.isfinite(speed) or not record.has_gps or prev is None:
            return speed
        dt = (fix[0] - prev[0]) / 1e9
        if not 0.0 < dt <= SPEED_FROM_FIX_MAX_DT_S:
            return math.nan
        lat_m = math.radians(0.5 * (fix[1] + prev[1]))
        dx = math.radians(fix[2] - prev[2]) * math.cos(lat_m) * EARTH_RADIUS_M
        dy = math.radians(fix[1] - prev[1]) * EARTH_RADIUS_M
        return math.hypot(dx, dy) / dt

    def heading(self, record, pose=None):
        """(H_deg, world_axes): the array front's heading, degrees clockwise from true North.

        ``world_axes`` is True when H comes from odometry (already in the world frame's
        axes). Raises :class:`KrakenError` (``no_heading``, ``no_odometry``).
        """
        c = self.config
        if c.heading_source == 'fixed':
            self.counts['heading_fixed'] += 1
            return self._true(0.0) + c.array_heading_deg, False
        if c.heading_source == 'odometry':
            return self._odometry_heading(pose), True
        speed = self.speed_of(record)
        h = record.heading_deg
        if math.isfinite(h) and math.isfinite(speed) and speed >= c.min_speed:
            self._good_heading = (record.stamp_ns, h)
            self.counts['heading_gps'] += 1
            return self._true(h) + c.array_heading_deg, False
        if c.low_speed == 'odometry':
            return self._odometry_heading(pose), True
        held = self._good_heading
        if held is not None and (c.heading_hold_timeout_s <= 0.0 or abs(
                record.stamp_ns - held[0]) <= c.heading_hold_timeout_s * 1e9):
            self.counts['heading_held'] += 1
            return self._true(held[1]) + c.array_heading_deg, False
        raise KrakenError('no_heading', f'speed {speed:.2f} m/s below min_speed '
                                        f'{c.min_speed:g} and no good heading to hold',
                          'heading')

    def _true(self, heading_deg):
        c = self.config
        return heading_deg + (c.declination_deg if c.heading_reference == 'magnetic' else 0.0)

    def _odometry_heading(self, pose):
        if pose is None:
            raise KrakenError('no_odometry', 'no platform pose at the reading time', 'heading')
        x, y, z, w = (float(v) for v in pose.quaternion)
        yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        self.counts['heading_odometry'] += 1
        return 90.0 - math.degrees(yaw) + self.config.array_heading_deg

    # ------------------------------------------------------------------ position

    def position(self, record, pose=None):
        """(position (3,) m, covariance (3, 3) m², local_to_world or None) of the station."""
        c = self.config
        st = c.station
        if c.position_source == 'parameters':
            return st.position, st.position_covariance, st.local_to_world
        if c.position_source == 'odometry':
            if pose is None:
                raise KrakenError('no_odometry', 'no platform pose at the reading time',
                                  'position')
            return pose.position, pose.position_covariance + st.position_covariance, None
        from . import geodesy
        if not (math.isfinite(record.latitude_deg) and math.isfinite(record.longitude_deg)):
            raise KrakenError('no_gps', 'the reading carries no GPS position', 'latitude')
        if not record.has_gps:
            raise KrakenError('zero_gps', 'GPS position 0, 0 (receiver has no fix)',
                              'latitude')
        lat0, lon0, h0 = c.origin
        pos = geodesy.geodetic_to_enu(record.latitude_deg, record.longitude_deg,
                                      h0 + c.antenna_height_m, c.origin)
        rot = geodesy.enu_axes_rotation(c.origin, record.latitude_deg, record.longitude_deg).T
        cov = np.eye(3) * c.gps_sigma_m ** 2 + st.position_covariance
        return np.asarray(pos, dtype=float), cov, rot

    # ------------------------------------------------------------------ bearing

    def compass_deg(self, record, pose=None):
        """(β_deg, world_axes): compass bearing of the reading with heading and offset."""
        if record.confidence < self.config.min_confidence:
            raise KrakenError('low_confidence', f'confidence {record.confidence:g} below '
                                                f'{self.config.min_confidence:g}', 'confidence')
        h, world_axes = self.heading(record, pose)
        beta = compass_bearing_deg(record.doa_deg, h, self.config.sense)
        return float(compass_bearing_deg(0.0, beta + self.config.heading_offset_deg,
                                         'plain')), world_axes

    def to_bearing(self, record, pose=None, stamp_ns=None):
        """Reading (+ platform pose at its stamp) -> core :class:`Bearing`, azimuth-only.

        θ = π/2 − β in the station's axes, rotated into the world's (module docstring);
        σ_θ from :class:`SigmaModel`; stamp = ``stamp_ns`` or the reading's. Raises
        :class:`KrakenError` (``low_confidence``, ``no_heading``, ``no_odometry``,
        ``no_gps``, ``zero_gps``).
        """
        beta, world_axes = self.compass_deg(record, pose)
        pos, cov, rot = self.position(record, pose)
        theta = math.pi / 2.0 - math.radians(beta)
        if rot is not None and not world_axes:
            theta = float(azimuth_elevation(rot @ los_vector(theta, 0.0))[0])
        st = self.config.station
        return Bearing(station=st.station,
                       stamp_ns=int(record.stamp_ns if stamp_ns is None else stamp_ns),
                       position=np.array(pos, dtype=float), azimuth=wrap_angle_scalar(theta),
                       sigma_azimuth=self.config.sigma.sigma(record.confidence,
                                                             record.snr_db),
                       frame_id=st.frame_id, position_covariance=np.array(cov, dtype=float))
