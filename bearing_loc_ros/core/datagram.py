"""The UDP JSON datagram of a DF station, parsed in time linear in its size (no ROS).

Format and rejections: :func:`parse_datagram`. No number literal is ever converted to a
big integer or decimal. Re-exported from :mod:`.station`.
"""

import decimal
import json

from .readings import MAX_STAMP_NS, NS_PER_S, raw_reading, ReadingError

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
    not a number, too long a literal, or beyond ±:data:`.readings.MAX_ABS_ANGLE` rad
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
