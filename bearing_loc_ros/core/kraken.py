"""KrakenSDR DoA receiver output: parsers for its three formats (pure, no I/O, no ROS).

The KrakenSDR DoA software reports each processed frame in three formats; each parser here
returns one validated :class:`KrakenRecord` per reading or raises :class:`KrakenError` whose
``reason`` is a short tag the station node counts in ``/diagnostics``.

* XML (``doa.xml``, served over HTTP on port 8081 by default): root ``<DATA>`` with
  ``STATION_ID``, ``TIME`` (unix epoch, ms), ``GPS_TIME`` (ms, 0 without GPS), ``FREQUENCY``
  (MHz), ``LOCATION/LATITUDE``, ``LOCATION/LONGITUDE`` (deg), ``LOCATION/HEADING`` (deg),
  ``LOCATION/SPEED``, ``DOA`` (deg, counter-clockwise from the array front), ``PWR``
  (max(−100, p) + 100, so p = PWR − 100 dB), ``CONF`` (int(confidence × 100)), ``LATENCY``,
  ``PROCESSING_TIME`` (ms), ``ADC_OVERDRIVE``, ``NUM_CORRELATED_SOURCES``, ``SNR_DB``. Only
  the first channel is written. Parsed with defusedxml: a document with a DTD, entity
  declarations or external references is refused (``malformed_xml``).
* "Kraken App" CSV (``DOA_value.html`` and the recording file): one line per channel, fields
  separated by a comma and a space: ``ts_ms, 360 − DOA, confidence, power_dB, frequency_Hz,
  array_type, latency_ms, station_id, lat, lon, heading, heading2, GPS, r1, r2, r3, r4``
  followed by the 360-value DoA spectrum (dB, minimum shifted to 0). The second field is
  clockwise from the array front, so DOA = 360 − field.
* JSON (POSTed by the receiver): keys ``station_id``, ``tStamp`` (ms), ``gps_timestamp``
  (ms), ``latitude``, ``longitude``, ``gpsBearing`` (deg), ``speed``, ``radioBearing`` (deg,
  clockwise from the array front, as the CSV's second field), ``conf``, ``power`` (dB),
  ``freq``, ``antType``, ``latency``, ``processing_time``, ``doaArray``, ``adc_overdrive``,
  ``num_corr_sources``, ``snr_db``. ``freq`` is taken as MHz when below 10⁵ and as Hz
  otherwise (the receiver tunes 24 MHz to 1.77 GHz, so the two readings cannot be confused).

Normalisation: every record carries ``doa_deg`` in the XML's sense (counter-clockwise from
the array front, [0, 360]); the DOA sense options of :mod:`bearing_loc_ros.core.receiver` act
on it, so one station configuration gives the same bearing from any of the three formats.
The confidence is on the CSV/JSON scale (XML CONF / 100). Times are integer nanoseconds.

Rejection reasons: ``malformed_xml``, ``malformed_csv``, ``malformed_json``,
``missing_field``, ``bad_number`` (not a number), ``not_finite`` (NaN/inf),
``out_of_range``, ``too_large`` (document over the size limit); :class:`TimeFilter` adds
``duplicate_time``, ``old_time`` (earlier than the last accepted), ``stale_time``
(older than the allowed age) and ``future_time`` (ahead of the node clock), and the station
``unset_clock`` (:data:`MIN_RECEIVER_TIME_NS`); the error's ``field`` names the offending
field.

One module (about 500 lines) on purpose: the three format parsers share the field checks
and the record type, and the time filter and channel map apply to their records.
"""

from dataclasses import dataclass
import decimal
import json
import math
import re
from xml.etree.ElementTree import ParseError

from defusedxml import DefusedXmlException
from defusedxml.ElementTree import fromstring as _xml_fromstring

from .datagram import (BadNumber, json_decimal, MAX_EXPONENT, reject_json_constant,
                       unique_json_object)

NS_PER_MS = 1_000_000
#: Largest stamp a builtin_interfaces/Time can carry (sec is an int32), ns.
MAX_STAMP_NS = (2 ** 31 - 1) * 1_000_000_000
#: Documents longer than this are refused before parsing (a real doa.xml is < 1 KiB, a JSON
#: body with its 360-value spectrum < 8 KiB).
MAX_DOCUMENT_BYTES = 256 * 1024
#: Frequencies accepted, Hz (any DF receiver; the KrakenSDR tunes 24 MHz - 1.77 GHz).
FREQ_MIN_HZ = 1.0e3
FREQ_MAX_HZ = 1.0e11
#: JSON ``freq`` below this is read as MHz, at or above as Hz (module docstring).
JSON_MHZ_BELOW = 1.0e5
#: A reading stamped more than this after the node clock is refused (``future_time``) by
#: the station's :class:`TimeFilter`, ns: the receiver's clock is wrong (a reading cannot
#: come from the future), and accepting it would make every later reading look old.
MAX_FUTURE_NS = 10 * 1_000_000_000
#: A receiver ``TIME`` before 2000-01-01T00:00:00Z (unix ns) is an unset clock (a board
#: without a real-time clock that booted before its GPS or NTP time came): such a reading is
#: refused (``unset_clock``) where the bearing would carry it as its stamp.
MIN_RECEIVER_TIME_NS = 946_684_800 * 1_000_000_000
CSV_FIXED_FIELDS = 17
SPECTRUM_LEN = 360
FORMATS = ('xml', 'csv', 'json')


class KrakenError(ValueError):
    """A receiver document or reading is rejected.

    Attributes: ``reason`` (tag counted in diagnostics), ``field`` (offending field or '').
    """

    def __init__(self, reason, detail='', field=''):
        super().__init__(f'{reason}: {detail}' if detail else reason)
        self.reason = reason
        self.field = field


@dataclass
class KrakenRecord:
    """One reading of one receiver channel, validated, in the receiver's own units.

    Attributes:
        stamp_ns: observation time (receiver ``TIME``/``ts_ms``/``tStamp``), integer ns.
        station_id: the receiver's station id ('' when it sends none).
        frequency_hz: channel frequency, Hz.
        doa_deg: DOA, degrees counter-clockwise from the array front, in [0, 360].
        reported_deg: the angle exactly as the format carries it (XML ``DOA``; CSV field 2
            and JSON ``radioBearing``, which are 360 − DOA).
        confidence: receiver confidence (CSV/JSON value; XML CONF / 100), ≥ 0.
        power_db: channel power, dB (NaN when absent).
        snr_db: signal-to-noise ratio, dB (NaN when absent; the CSV has none).
        latitude_deg, longitude_deg: receiver GPS position, degrees (NaN when absent; 0, 0
            when the receiver has no fix).
        heading_deg: receiver heading, degrees clockwise from North (NaN when absent).
        speed: receiver ground speed as reported (m/s), NaN when absent.
        latency_ms: receiver processing latency, ms (NaN when absent).
        gps_time_ns: receiver GPS time, ns (0 without GPS).
        array_type: 'UCA', 'ULA', ... ('' when absent).
        source: 'xml', 'csv' or 'json'.
        spectrum: the 360-value DoA spectrum (tuple of floats) or None.
    """

    stamp_ns: int
    station_id: str
    frequency_hz: float
    doa_deg: float
    reported_deg: float
    confidence: float
    power_db: float = math.nan
    snr_db: float = math.nan
    latitude_deg: float = math.nan
    longitude_deg: float = math.nan
    heading_deg: float = math.nan
    speed: float = math.nan
    latency_ms: float = math.nan
    gps_time_ns: int = 0
    array_type: str = ''
    source: str = 'xml'
    spectrum: tuple = None

    @property
    def has_gps(self):
        """True when the record carries a GPS position other than the (0, 0) "no fix"."""
        lat, lon = self.latitude_deg, self.longitude_deg
        return math.isfinite(lat) and math.isfinite(lon) and not (lat == 0.0 and lon == 0.0)


# ------------------------------------------------------------------------------ fields

#: A number written in text (XML, CSV): ASCII decimal digits with an optional sign, point and
#: exponent, or nan/inf (refused as not finite). Python's float() and Decimal() also take
#: digit-group underscores ("1_75" = 175) and non-ASCII digits ("１２"): a receiver never
#: writes those, so such a field is garbled and refused, not read as another number.
_NUMBER_TEXT = re.compile(r'[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf(?:inity)?)',
                          re.ASCII | re.IGNORECASE)


def _number_text(text, name):
    """``text`` stripped when it is a number in :data:`_NUMBER_TEXT`'s grammar, else
    KrakenError ``bad_number``."""
    text = text.strip()
    if not _NUMBER_TEXT.fullmatch(text):
        raise KrakenError('bad_number', f'{name}: {text[:40]!r} is not a number', name)
    return text


def _float(value, name, lo=-math.inf, hi=math.inf):
    """A finite float within [lo, hi] from text or a JSON number, else KrakenError."""
    if isinstance(value, bool) or value is None:
        raise KrakenError('bad_number', f'{name}: {value!r} is not a number', name)
    if isinstance(value, BadNumber):
        raise KrakenError('bad_number', f'{name}: {value.problem}', name)
    if isinstance(value, str):
        x = float(_number_text(value, name))
    elif isinstance(value, (int, float, decimal.Decimal)):
        try:
            x = float(value)
        except OverflowError:
            x = math.inf
    else:
        raise KrakenError('bad_number', f'{name}: {type(value).__name__} is not a number', name)
    if not math.isfinite(x):
        raise KrakenError('not_finite', f'{name}: {x}', name)
    if not lo <= x <= hi:
        raise KrakenError('out_of_range', f'{name}: {x:g} is outside [{lo:g}, {hi:g}]', name)
    return x


def _stamp_ms(value, name, allow_zero=False):
    """Unix milliseconds (text or number) -> integer ns, exactly (decimal arithmetic)."""
    if isinstance(value, bool) or value is None:
        raise KrakenError('bad_number', f'{name}: {value!r} is not a number', name)
    if isinstance(value, BadNumber):
        raise KrakenError('bad_number', f'{name}: {value.problem}', name)
    try:
        d = decimal.Decimal(_number_text(value, name) if isinstance(value, str) else value)
    except (decimal.InvalidOperation, ValueError, TypeError):
        raise KrakenError('bad_number', f'{name}: {str(value)[:40]!r} is not a number',
                          name) from None
    if not d.is_finite():
        raise KrakenError('not_finite', f'{name}: {d}', name)
    ns = -1
    # compare before converting: int() of a huge exponent (1e999990) would take seconds
    if -1 < d <= MAX_STAMP_NS // NS_PER_MS + 1:
        try:
            ns = int((d * NS_PER_MS).to_integral_value(rounding=decimal.ROUND_HALF_EVEN))
        except (ArithmeticError, ValueError):
            ns = -1
    if ns == 0 and allow_zero:
        return 0
    if ns <= 0 or ns > MAX_STAMP_NS:
        raise KrakenError('out_of_range', f'{name}: {str(d)[:40]} is not a unix time in ms',
                          name)
    return ns


def _optional(value, convert, *args):
    """NaN for an absent or empty field, else ``convert(value, *args)``."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return math.nan
    return convert(value, *args)


def _text(value, name, max_len=128):
    text = '' if value is None else str(value).strip()
    if len(text) > max_len or any(ord(ch) < 32 for ch in text):
        raise KrakenError('out_of_range', f'{name}: not a short printable text', name)
    return text


def _angle(value, name):
    return _float(value, name, 0.0, 360.0)


def _common(stamp_ns, station_id, frequency_hz, doa_deg, reported_deg, confidence, **kw):
    return KrakenRecord(stamp_ns=stamp_ns, station_id=station_id, frequency_hz=frequency_hz,
                        doa_deg=doa_deg, reported_deg=reported_deg, confidence=confidence, **kw)


def _position(lat, lon, heading, speed):
    return dict(latitude_deg=_optional(lat, _float, 'latitude', -90.0, 90.0),
                longitude_deg=_optional(lon, _float, 'longitude', -180.0, 180.0),
                heading_deg=_optional(heading, _float, 'heading', -360.0, 360.0),
                speed=_optional(speed, _float, 'speed', 0.0, 1.0e4))


def _check_size(data, fmt):
    if len(data) > MAX_DOCUMENT_BYTES:
        raise KrakenError('too_large', f'{fmt} document of {len(data)} bytes (limit '
                                       f'{MAX_DOCUMENT_BYTES})')


# ------------------------------------------------------------------------------ XML

XML_REQUIRED = ('TIME', 'FREQUENCY', 'DOA', 'CONF')


def parse_xml(data):
    """Parse one KrakenSDR ``doa.xml`` document (bytes or str) -> :class:`KrakenRecord`.

    Field mapping (module docstring): stamp = TIME ms; frequency = FREQUENCY MHz × 10⁶;
    doa_deg = reported_deg = DOA; confidence = CONF / 100; power_db = PWR − 100; GPS fields
    from ``LOCATION``. Required: TIME, FREQUENCY, DOA, CONF (``missing_field``); the others
    are NaN when absent. Raises :class:`KrakenError`.
    """
    _check_size(data, 'XML')
    try:
        root = _xml_fromstring(data, forbid_dtd=True)
    except DefusedXmlException as exc:
        raise KrakenError('malformed_xml', f'refused: {type(exc).__name__}') from None
    except (ParseError, ValueError, TypeError, LookupError) as exc:   # LookupError: encoding
        raise KrakenError('malformed_xml', (str(exc).splitlines() or [''])[0][:120]) from None
    if root.tag != 'DATA':
        raise KrakenError('malformed_xml', f'root element is <{str(root.tag)[:40]}>, '
                                           'expected <DATA>')

    def get(path):
        el = root.find(path)
        return None if el is None else (el.text or '')

    for name in XML_REQUIRED:
        if get(name) is None:
            raise KrakenError('missing_field', f'<{name}>', name)
    pwr = _optional(get('PWR'), _float, 'PWR', 0.0, 1.0e3)
    reported = _angle(get('DOA'), 'DOA')
    return _common(
        _stamp_ms(get('TIME'), 'TIME'), _text(get('STATION_ID'), 'STATION_ID'),
        _float(get('FREQUENCY'), 'FREQUENCY', FREQ_MIN_HZ / 1e6, FREQ_MAX_HZ / 1e6) * 1e6,
        reported, reported, _float(get('CONF'), 'CONF', 0.0, 1.0e6) / 100.0,
        power_db=pwr - 100.0, snr_db=_optional(get('SNR_DB'), _float, 'SNR_DB', -300., 300.),
        latency_ms=_optional(get('LATENCY'), _float, 'LATENCY', 0.0, 1.0e9),
        gps_time_ns=_gps_time(get('GPS_TIME'), 'GPS_TIME'), source='xml',
        **_position(get('LOCATION/LATITUDE'), get('LOCATION/LONGITUDE'),
                    get('LOCATION/HEADING'), get('LOCATION/SPEED')))


def _gps_time(value, name):
    if value is None or (isinstance(value, str) and not value.strip()):
        return 0
    return _stamp_ms(value, name, allow_zero=True)


# ------------------------------------------------------------------------------ CSV

def parse_csv_line(line):
    """Parse one "Kraken App" CSV line (str) -> :class:`KrakenRecord`.

    Fields (module docstring) split on ',' with surrounding blanks stripped: stamp = field 1
    (ms); doa_deg = 360 − field 2; confidence = field 3; power_db = field 4; frequency =
    field 5 (Hz); array type, latency (ms), station id, lat, lon, heading = fields 6-11;
    fields 12-17 are not used; then either nothing or exactly 360 spectrum values
    (``malformed_csv`` otherwise). Raises :class:`KrakenError`.
    """
    if not isinstance(line, str):
        raise KrakenError('malformed_csv', f'expected text, got {type(line).__name__}')
    _check_size(line, 'CSV')
    f = [v.strip() for v in line.strip().split(',')]
    if len(f) < CSV_FIXED_FIELDS:
        raise KrakenError('malformed_csv', f'{len(f)} fields, expected at least '
                                           f'{CSV_FIXED_FIELDS}')
    extra = len(f) - CSV_FIXED_FIELDS
    spectrum = None
    if extra:
        if extra != SPECTRUM_LEN:
            raise KrakenError('malformed_csv', f'{extra} spectrum values, expected '
                                               f'{SPECTRUM_LEN}', 'spectrum')
        spectrum = tuple(_float(v, 'spectrum') for v in f[CSV_FIXED_FIELDS:])
    reported = _angle(f[1], 'doa')
    doa = 0.0 if reported == 0.0 else 360.0 - reported
    return _common(
        _stamp_ms(f[0], 'ts_ms'), _text(f[7], 'station_id'),
        _float(f[4], 'frequency', FREQ_MIN_HZ, FREQ_MAX_HZ), doa, reported,
        _float(f[2], 'confidence', 0.0, 1.0e4),
        power_db=_optional(f[3], _float, 'power', -1.0e3, 1.0e3),
        latency_ms=_optional(f[6], _float, 'latency', 0.0, 1.0e9),
        array_type=_text(f[5], 'array_type', 16), source='csv', spectrum=spectrum,
        **_position(f[8], f[9], f[10], None))


def parse_csv_text(text):
    """Parse a ``DOA_value.html`` body (one CSV line per channel).

    Returns a list with, per non-blank line, a :class:`KrakenRecord` or the
    :class:`KrakenError` that line raised (one bad channel does not hide the others).
    A body that is not UTF-8 text gives a single ``malformed_csv`` error.
    """
    if isinstance(text, (bytes, bytearray)):
        try:
            text = bytes(text).decode('utf-8')
        except UnicodeDecodeError:
            return [KrakenError('malformed_csv', 'not UTF-8 text')]
    if len(text) > MAX_DOCUMENT_BYTES * 16:
        return [KrakenError('too_large', f'CSV body of {len(text)} characters')]
    out = []
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            out.append(parse_csv_line(line))
        except KrakenError as exc:
            out.append(exc)
    return out


# ------------------------------------------------------------------------------ JSON

JSON_REQUIRED = ('tStamp', 'radioBearing', 'conf', 'freq')


def _json_number(text):
    """A JSON float literal -> exact Decimal, or a BadNumber (exponent beyond ±400, read
    from the text before any conversion: ``1e1000000000000000000`` is never converted)."""
    return json_decimal(text, max_chars=None, max_exponent=MAX_EXPONENT)


def parse_json(data):
    """Parse one KrakenSDR JSON body (bytes or str, a JSON object) -> :class:`KrakenRecord`.

    stamp = tStamp ms; doa_deg = 360 − radioBearing; confidence = conf; power_db = power;
    frequency = freq (MHz below 10⁵, else Hz); GPS fields from latitude, longitude,
    gpsBearing, speed. Required: tStamp, radioBearing, conf, freq. NaN/Infinity literals and
    a key given twice are refused (``malformed_json``). A number with a decimal exponent
    beyond ±400 is refused before it is converted: in a field it is a ``bad_number``, in an
    ignored key harmless.
    A ``doaArray`` of 360 numbers becomes the spectrum; any other doaArray is ignored.
    Raises :class:`KrakenError`.
    """
    _check_size(data, 'JSON')
    try:
        obj = json.loads(data, parse_float=_json_number, parse_constant=reject_json_constant,
                         object_pairs_hook=unique_json_object)
    except (ValueError, TypeError, RecursionError) as exc:
        raise KrakenError('malformed_json', str(exc).splitlines()[0][:120]) from None
    except ArithmeticError as exc:   # decimal's errors: a last resort, literals are checked
        raise KrakenError('malformed_json', f'a number cannot be converted '
                                            f'({type(exc).__name__})') from None
    if not isinstance(obj, dict):
        raise KrakenError('malformed_json', f'expected an object, got {type(obj).__name__}')
    for name in JSON_REQUIRED:
        if obj.get(name) is None:
            raise KrakenError('missing_field', f'"{name}"', name)
    freq = _float(obj['freq'], 'freq', FREQ_MIN_HZ / 1e6, FREQ_MAX_HZ)
    if freq < JSON_MHZ_BELOW:
        freq *= 1e6
    if not FREQ_MIN_HZ <= freq <= FREQ_MAX_HZ:
        raise KrakenError('out_of_range', f'freq: {freq:g} Hz', 'freq')
    reported = _angle(obj['radioBearing'], 'radioBearing')
    spectrum = None
    arr = obj.get('doaArray')
    if isinstance(arr, list) and len(arr) == SPECTRUM_LEN:
        spectrum = tuple(_float(v, 'doaArray') for v in arr)
    return _common(
        _stamp_ms(obj['tStamp'], 'tStamp'), _text(obj.get('station_id'), 'station_id'), freq,
        0.0 if reported == 0.0 else 360.0 - reported, reported,
        _float(obj['conf'], 'conf', 0.0, 1.0e4),
        power_db=_optional(obj.get('power'), _float, 'power', -1.0e3, 1.0e3),
        snr_db=_optional(obj.get('snr_db'), _float, 'snr_db', -300.0, 300.0),
        latency_ms=_optional(obj.get('latency'), _float, 'latency', 0.0, 1.0e9),
        gps_time_ns=_gps_time(obj.get('gps_timestamp'), 'gps_timestamp'),
        array_type=_text(obj.get('antType'), 'antType', 16), source='json', spectrum=spectrum,
        **_position(obj.get('latitude'), obj.get('longitude'), obj.get('gpsBearing'),
                    obj.get('speed')))


def parse(data, fmt):
    """Parse one document of format ``fmt`` ('xml', 'csv' or 'json') -> list of results.

    Each item is a :class:`KrakenRecord` or a :class:`KrakenError` (CSV bodies may hold one
    line per channel; XML and JSON give exactly one item). Never raises for bad data: an
    arithmetic error escaping a parser (none is known) becomes ``malformed_<fmt>``.
    """
    if fmt not in FORMATS:
        raise ValueError(f'fmt: {fmt!r} is not one of {FORMATS}')
    try:
        if fmt == 'csv':
            return parse_csv_text(data)
        return [parse_xml(data) if fmt == 'xml' else parse_json(data)]
    except KrakenError as exc:
        return [exc]
    except (ArithmeticError, RecursionError) as exc:
        return [KrakenError(f'malformed_{fmt}', f'{type(exc).__name__} while parsing')]


# ------------------------------------------------------------------------------ time, channels

class TimeFilter:
    """Per-stream check of reading times: refuse future, stale, duplicate and out-of-order
    stamps.

    A stream is one (station, channel) pair; all times are integer ns on one clock (unix
    time for receiver stamps). ``check(key, stamp_ns, now_ns)`` raises :class:`KrakenError`
    with reason ``future_time`` (when ``future_ns`` > 0, default :data:`MAX_FUTURE_NS`,
    and ``now_ns`` > 0 is given: stamp − now > future_ns), ``stale_time`` (when
    ``max_age_ns`` > 0 and ``now_ns`` is given: now − stamp > max_age), ``duplicate_time``
    (same stamp as the last accepted reading of the stream: a poll that saw the same frame
    again) or ``old_time`` (earlier than the last accepted), else records the stamp. A
    rejected reading changes nothing, so a reading stamped in the future cannot make the
    later good ones look old. A stamp more than ``reset_ns`` earlier than the last accepted
    one means the receiver's clock (or a replayed file) restarted: the stream is reset and
    the reading accepted (counted in ``resets``).
    """

    def __init__(self, max_age_ns=0, reset_ns=0, future_ns=MAX_FUTURE_NS):
        self.max_age_ns = int(max_age_ns)
        self.reset_ns = int(reset_ns)
        self.future_ns = int(future_ns)
        self.resets = 0
        self._last = {}

    def check(self, key, stamp_ns, now_ns=None):
        """Accept (record) or reject ``stamp_ns`` for stream ``key`` (class docstring)."""
        if (self.future_ns > 0 and now_ns is not None and now_ns > 0
                and stamp_ns - now_ns > self.future_ns):
            raise KrakenError('future_time', f'{(stamp_ns - now_ns) / 1e9:.3f} s after the '
                                             'node clock', 'TIME')
        if self.max_age_ns > 0 and now_ns is not None and now_ns - stamp_ns > self.max_age_ns:
            raise KrakenError('stale_time', f'{(now_ns - stamp_ns) / 1e9:.3f} s old', 'TIME')
        last = self._last.get(key)
        if last is not None:
            if stamp_ns == last:
                raise KrakenError('duplicate_time', f'{stamp_ns} ns seen already', 'TIME')
            if stamp_ns < last:
                if self.reset_ns > 0 and last - stamp_ns > self.reset_ns:
                    self.resets += 1
                else:
                    raise KrakenError('old_time', f'{(last - stamp_ns) / 1e9:.3f} s before '
                                                  'the last accepted reading', 'TIME')
        self._last[key] = stamp_ns


class ChannelMap:
    """Frequency bands -> channel names (several emitters on one receiver).

    ``bands`` maps a channel name to (low_hz, high_hz), low < high; a reading belongs to
    the first band (in the given order) with low ≤ f ≤ high. Bands must not overlap (an
    ambiguous reading could then go to two emitters). With no bands, every frequency is the
    single unnamed channel ''.
    """

    def __init__(self, bands=()):
        self.bands = []
        for name, (lo, hi) in dict(bands).items():
            if not name or not str(name).replace('_', '').replace('/', '').isalnum():
                raise ValueError(f'channels: {name!r} is not a valid channel name (letters, '
                                 'digits, _ and /)')
            lo, hi = float(lo), float(hi)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
                raise ValueError(f'channel {name}: band [{lo:g}, {hi:g}] Hz must have '
                                 '0 <= low < high')
            for other, olo, ohi in self.bands:
                if lo <= ohi and olo <= hi:
                    raise ValueError(f'channel {name}: band overlaps channel {other}')
            self.bands.append((str(name), lo, hi))

    @property
    def names(self):
        """Channel names in order ([''] when no band is configured)."""
        return [b[0] for b in self.bands] or ['']

    def channel_of(self, frequency_hz):
        """Channel name of a frequency (Hz), '' without bands, None when in no band."""
        if not self.bands:
            return ''
        for name, lo, hi in self.bands:
            if lo <= frequency_hz <= hi:
                return name
        return None


def channel_map_from_params(names, bands_mhz):
    """:class:`ChannelMap` from the node parameters ``channels`` (names) and
    ``channel_bands_mhz`` (flat [low1, high1, low2, high2, ...] in MHz). ValueError when the
    lengths disagree or a band is invalid.
    """
    names = [str(n) for n in names]
    bands_mhz = [float(v) for v in bands_mhz]
    if len(set(names)) != len(names):
        raise ValueError(f'channels: duplicate names in {names}')
    if len(bands_mhz) != 2 * len(names):
        raise ValueError(f'channel_bands_mhz: expected {2 * len(names)} values (low, high in '
                         f'MHz per channel), got {len(bands_mhz)}')
    return ChannelMap({n: (bands_mhz[2 * k] * 1e6, bands_mhz[2 * k + 1] * 1e6)
                       for k, n in enumerate(names)})


def csv_line(record, spectrum=True):
    """One "Kraken App" CSV line (no newline) for ``record``: the inverse of
    :func:`parse_csv_line` (field 2 = 360 − doa_deg; a NaN value is written as an empty
    field, which parses back to NaN; the spectrum only when the record has one and
    ``spectrum`` is true). Used to write recordings for tests, simulations and examples."""
    def num(v):
        return '' if not math.isfinite(v) else repr(float(v))

    ms = decimal.Decimal(int(record.stamp_ns)) / NS_PER_MS
    reported = 0.0 if record.doa_deg in (0.0, 360.0) else 360.0 - record.doa_deg
    fields = [format(ms, 'f'), repr(reported),
              repr(float(record.confidence)), num(record.power_db),
              repr(float(record.frequency_hz)), record.array_type or 'UCA',
              num(record.latency_ms), record.station_id, num(record.latitude_deg),
              num(record.longitude_deg), num(record.heading_deg), num(record.heading_deg),
              'GPS', '0', '0', '0', '0']
    if spectrum and record.spectrum is not None:
        fields += [repr(float(v)) for v in record.spectrum]
    return ', '.join(fields)
