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


class BadNumber:
    """A JSON number literal refused before conversion (too long or exponent out of range).

    ``problem`` says why (text). It stands in for the number in the parsed object, so the
    field that holds it is invalid while an ignored key that holds it is harmless.
    """

    __slots__ = ('problem',)

    def __init__(self, problem):
        self.problem = problem


#: Exponent digits (leading zeros stripped) beyond which the exponent is not even converted
#: to an int: it is then far beyond any limit.
_MAX_EXPONENT_DIGITS = 12


def literal_exponent(text):
    """Decimal exponent of a JSON number literal, read from its text without converting it.

    ``text`` matches JSON's number grammar (``-?digits[.digits][e[+-]digits]``). Returns the
    power of ten of its leading non-zero digit (what ``Decimal(text).adjusted()`` gives:
    ``'123.4e2'`` -> 4, ``'0.001'`` -> -3), or None when the literal is zero. An exponent
    written with more than 12 digits gives ±10¹² (beyond any limit) without conversion.
    Cost linear in ``len(text)``; never raises for JSON literals.
    """
    mantissa, _, exp = text.lower().partition('e')
    digits = exp.lstrip('+-').lstrip('0')
    e = 10 ** _MAX_EXPONENT_DIGITS if len(digits) > _MAX_EXPONENT_DIGITS else int(digits or 0)
    if exp.startswith('-'):
        e = -e
    whole, _, frac = mantissa.lstrip('+-').partition('.')
    whole = whole.lstrip('0')
    if whole:
        return e + len(whole) - 1
    significant = frac.lstrip('0')
    if not significant:
        return None
    return e - (len(frac) - len(significant)) - 1


def json_decimal(text, max_chars=MAX_NUMBER_CHARS, max_exponent=MAX_EXPONENT):
    """A JSON number literal (with a fraction or exponent) -> exact Decimal, or BadNumber.

    Refused before any conversion (a :class:`BadNumber` saying why): more than
    ``max_chars`` characters (None: no length limit), or a decimal exponent
    (:func:`literal_exponent`) beyond ±``max_exponent``. A zero is Decimal zero with its
    sign, whatever its exponent. Use as ``json.loads(..., parse_float=json_decimal)``.
    """
    if max_chars is not None and len(text) > max_chars:
        return BadNumber(f'number literal of {len(text)} characters (at most {max_chars})')
    exponent = literal_exponent(text)
    if exponent is None:
        return decimal.Decimal(text.lower().partition('e')[0])
    if abs(exponent) > max_exponent:
        return BadNumber(f'number {text[:40]} has a decimal exponent beyond ±{max_exponent}')
    return decimal.Decimal(text)  # exact and cheap: the exponent is small


def _json_int(text):
    if len(text) > MAX_NUMBER_CHARS:
        return BadNumber(f'number literal of {len(text)} characters (at most '
                         f'{MAX_NUMBER_CHARS})')
    return int(text)


def reject_json_constant(name):
    """``parse_constant`` of json.loads: NaN, Infinity and -Infinity are not JSON numbers."""
    raise ValueError(f'{name} is not allowed')


def _number(value, reason, name):
    """A parsed JSON number (int or Decimal) or :class:`ReadingError` ``reason``."""
    if isinstance(value, BadNumber):
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


def unique_json_object(pairs):
    """A JSON object's dict; ValueError when a key is given twice (json keeps the last one
    silently: ``{"azimuth_deg": 10, "azimuth_deg": 200}`` would be 200 without a word)."""
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen = set()
        dup = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise ValueError(f'duplicate key {dup[:40]!r}')
    return obj


def parse_datagram(data, require_t=True, elevation=True):
    """Parse one UDP datagram (UTF-8 JSON object) into a :class:`RawReading`.

    Format: ``{"t": unix_seconds, "azimuth_deg": a, "elevation_deg": e or null,
    "sigma_deg": s, "sigma_elevation_deg": s_e}``; ``elevation_deg``, ``sigma_deg``
    (σ_θ) and ``sigma_elevation_deg`` (σ_ψ) are optional, other keys are ignored. Angles
    are degrees in the station's ``azimuth_reference``. ``t`` is converted exactly (decimal
    arithmetic) to integer ns: t = 1700000000.123456789 -> 1700000000123456789 ns. With
    ``require_t`` False (the node re-stamps on receipt) ``t`` is not read (it may be missing
    or anything); stamp_ns is then 1 as a placeholder. With ``elevation`` False (an
    azimuth-only station) ``elevation_deg`` and ``sigma_elevation_deg`` are not read either:
    a field the station ignores does not reject the datagram.

    Cost is linear in the datagram's length: a datagram longer than
    :data:`MAX_DATAGRAM_BYTES` is not parsed, and a number literal longer than
    :data:`MAX_NUMBER_CHARS` characters or with a decimal exponent beyond
    ±:data:`MAX_EXPONENT` is never converted (it makes its field invalid; in an ignored key
    it is harmless); the exponent is read from the literal's text (:func:`literal_exponent`)
    before any conversion. ``t`` is range-checked before it is scaled to ns.

    Rejections (:class:`ReadingError` reasons): longer than :data:`MAX_DATAGRAM_BYTES`
    (``too_large``); not UTF-8 JSON, NaN/Infinity literals, nesting too deep, a key given
    twice in one object (``bad_json``);
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
        obj = json.loads(data, parse_float=json_decimal, parse_int=_json_int,
                         parse_constant=reject_json_constant, object_pairs_hook=unique_json_object)
    except (ValueError, TypeError, RecursionError) as exc:
        raise ReadingError('bad_json', str(exc).splitlines()[0][:120]) from None
    except ArithmeticError as exc:   # decimal's errors: a last resort, literals are checked
        raise ReadingError('bad_json', f'a number cannot be converted '
                                       f'({type(exc).__name__})') from None
    if not isinstance(obj, dict):
        raise ReadingError('not_object', f'expected a JSON object, got {type(obj).__name__}')
    if not require_t:
        stamp_ns = 1
    elif 't' in obj:
        stamp_ns = _stamp_ns(_number(obj['t'], 'bad_t', 't'))
    else:
        raise ReadingError('missing_t', 'no "t" (unix seconds)')
    if 'azimuth_deg' not in obj:
        raise ReadingError('missing_azimuth', 'no "azimuth_deg"')
    az = _number(obj['azimuth_deg'], 'bad_azimuth', 'azimuth_deg')
    el = obj.get('elevation_deg') if elevation else None
    el = float('nan') if el is None else _number(el, 'bad_elevation', 'elevation_deg')
    sig = []
    for key in ('sigma_deg', 'sigma_elevation_deg') if elevation else ('sigma_deg',):
        s = obj.get(key)
        sig.append(float('nan') if s is None else _number(s, 'bad_sigma', key))
    if not elevation:
        sig.append(float('nan'))
    return raw_reading(stamp_ns, az, el, 'deg', sig[0], sig[1])
