"""Fuzzing the station's UDP datagram parser (core.station.parse_datagram).

Property, for any input: parse_datagram either returns a RawReading whose values are valid
(stamp in (0, 2038], finite azimuth within ±MAX_ABS_ANGLE rad, elevation NaN or within that
bound, σ NaN or within the Bearing range) and equal to what the datagram says, or raises
ReadingError with one of the documented reasons. Nothing else escapes (OverflowError,
RecursionError, a stall on ``1e200000``...).

Hypothesis runs derandomised (the same examples every run) with no example database, and a
fixed example budget that keeps this file to a few seconds. A watchdog turns a parse that
hangs into a failure instead of a stuck suite; it bounds at seconds what takes microseconds,
so it never fires on a slow machine (bench/bench_fuzz_inputs.py measures the parse times).
"""

import contextlib
import decimal
import json
import math
import signal

from hypothesis import example, given, HealthCheck, settings, strategies as st

from bearing_loc_ros.core.bearings import SIGMA_MAX, SIGMA_MIN
from bearing_loc_ros.core.station import (DATAGRAM_REJECTIONS, MAX_ABS_ANGLE,
                                          MAX_DATAGRAM_BYTES, MAX_STAMP_NS, parse_datagram,
                                          ReadingError)

FUZZ = settings(max_examples=400, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck))
HANG_S = 10
FIELDS = ('t', 'azimuth_deg', 'elevation_deg', 'sigma_deg', 'sigma_elevation_deg')
REASON_OF = {'t': 'bad_t', 'azimuth_deg': 'bad_azimuth', 'elevation_deg': 'bad_elevation',
             'sigma_deg': 'bad_sigma', 'sigma_elevation_deg': 'bad_sigma'}


@contextlib.contextmanager
def watchdog(seconds=HANG_S):
    """Raise TimeoutError if the body runs for more than ``seconds`` (a hang, not slowness)."""
    def expired(signum, frame):
        raise TimeoutError(f'no answer after {seconds} s')
    old = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def check(data, require_t=True):
    """Parse ``data``; assert the property; return the reading or the rejection reason."""
    try:
        with watchdog():
            r = parse_datagram(data, require_t=require_t)
    except ReadingError as exc:
        assert exc.reason in DATAGRAM_REJECTIONS, exc.reason
        assert str(exc).startswith(exc.reason)
        return exc.reason
    assert 0 < r.stamp_ns <= MAX_STAMP_NS
    assert math.isfinite(r.azimuth) and abs(r.azimuth) <= MAX_ABS_ANGLE
    assert math.isnan(r.elevation) or abs(r.elevation) <= MAX_ABS_ANGLE
    for s in (r.sigma_azimuth, r.sigma_elevation):
        assert math.isnan(s) or SIGMA_MIN <= s <= SIGMA_MAX
    return r


# ------------------------------------------------------------------ strategies

def _digits(n):
    return st.text('0123456789', min_size=n, max_size=n)


@st.composite
def number_literals(draw):
    """JSON number literals, from ordinary to hostile (long, huge/tiny exponents, -0)."""
    kind = draw(st.sampled_from(['int', 'float', 'long', 'exp', 'frac']))
    if kind == 'int':
        return str(draw(st.integers(-10 ** 12, 10 ** 12)))
    if kind == 'float':
        return repr(draw(st.floats(allow_nan=False, allow_infinity=False)))
    sign = draw(st.sampled_from(['', '-']))
    lead = str(draw(st.integers(1, 9)))
    if kind == 'long':
        return sign + lead + draw(_digits(draw(st.integers(30, 1200))))
    if kind == 'exp':
        exp = draw(st.one_of(st.integers(-1000, 1000), st.integers(-10 ** 7, 10 ** 7),
                             st.just(999990), st.just(200000)))
        return f'{sign}{lead}e{exp}'
    return f'{sign}0.{draw(_digits(draw(st.integers(0, 80))))}1'


values = st.one_of(
    number_literals(),
    st.sampled_from(['null', 'true', 'false', 'NaN', 'Infinity', '-Infinity', '"10"', '[]',
                     '{}', '[1]', '{"a": 1}', '[' * 50 + ']' * 50]),
)


@st.composite
def datagrams(draw):
    """JSON objects with the format's keys (each maybe missing) holding hostile literals."""
    parts = [f'"{k}": {draw(values)}' for k in FIELDS if draw(st.booleans()) or k != 't']
    parts += [f'"{k}": {draw(values)}' for k in draw(st.lists(st.sampled_from(['x', 'id']),
                                                              max_size=2))]
    draw(st.randoms(use_true_random=False)).shuffle(parts)
    return ('{' + ', '.join(parts) + '}').encode()


json_trees = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(
        st.sampled_from(FIELDS + ('x',)), c, max_size=5),
    max_leaves=20)


# ------------------------------------------------------------------ properties

@FUZZ
@given(st.binary(max_size=300))
def test_arbitrary_bytes(data):
    check(data)


@FUZZ
@given(json_trees)
def test_arbitrary_json(tree):
    check(json.dumps(tree).encode())


@FUZZ
@given(datagrams(), st.booleans())
@example(b'{"t": 1e200000, "azimuth_deg": 1}', True)  # stalled the node 1.9 s
@example(b'{"t": 1e999990, "azimuth_deg": 1}', True)  # 31 s
@example(b'{"t": 1700000000, "azimuth_deg": 1' + b'0' * 400 + b'}', True)  # OverflowError
@example(b'{"t": 1700000000, "azimuth_deg": 1e300}', True)  # published as 0.0
def test_hostile_numbers(data, require_t):
    """Accepted values equal the literal's (in rad); rejections name the field's reason."""
    got = check(data, require_t)
    obj = json.loads(data, parse_float=str, parse_int=str, parse_constant=str)
    if isinstance(got, str):
        if got in ('missing_t', 'missing_azimuth', 'bad_json'):
            assert got != 'missing_t' or 't' not in obj
            assert got != 'missing_azimuth' or 'azimuth_deg' not in obj
            return
        assert got in {REASON_OF[k] for k in obj if k in REASON_OF}
        return
    az = float(decimal.Decimal(obj['azimuth_deg']))
    assert got.azimuth == math.radians(az) or \
        math.isclose(got.azimuth, math.radians(az), rel_tol=1e-15)
    if not require_t:
        assert got.stamp_ns == 1                    # t is not read when re-stamping
    elif 't' in obj:
        assert got.stamp_ns == int(decimal.Decimal(obj['t']).scaleb(9).to_integral_value(
            rounding=decimal.ROUND_HALF_EVEN))


@FUZZ
@given(st.binary(min_size=1, max_size=40), st.integers(0, 60), st.integers(0, 2))
def test_mutated_valid_datagrams(noise, where, how):
    """Bytes inserted into, overwritten in, or cut out of a valid datagram."""
    base = b'{"t": 1700000000.25, "azimuth_deg": 12.5, "elevation_deg": 3, "sigma_deg": 1}'
    i = min(where, len(base))
    data = (base[:i] + noise + base[i:], base[:i] + noise + base[i + len(noise):],
            base[:i] + base[i + len(noise):])[how]
    check(data)


def test_the_repros_and_size_limit_are_counted_by_reason():
    assert check(b'{"t": 1e200000, "azimuth_deg": 1}') == 'bad_t'
    assert check(b'{"t": 1e999990, "azimuth_deg": 1}') == 'bad_t'
    assert check(b'{"t": 1, "azimuth_deg": ' + b'9' * 400 + b'}') == 'bad_azimuth'
    assert check(b'{"t": 1, "azimuth_deg": 1e300}') == 'bad_azimuth'
    padded = b'{"t": 1, "azimuth_deg": 1}'.ljust(MAX_DATAGRAM_BYTES)
    assert check(padded).azimuth == math.radians(1.0)
    assert check(padded + b' ') == 'too_large'
