"""Raw DF readings of a station: validation and conversion to radians (no ROS).

:class:`RawReading` is one reading still in the sensor's reference (azimuth, optional
elevation, optional σ, rad); :class:`ReadingError` and :class:`ConfigError` are the
rejections a station counts or reports. Re-exported from :mod:`.station`.
"""

from dataclasses import dataclass
import math

from .bearings import MAX_ABS_ANGLE, SIGMA_MAX, SIGMA_MIN  # noqa: F401 (re-export)

NS_PER_S = 1_000_000_000
#: Largest stamp a builtin_interfaces/Time can carry (sec is an int32).
MAX_STAMP_NS = (2 ** 31 - 1) * NS_PER_S
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
