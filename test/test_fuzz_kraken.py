"""Fuzzing the KrakenSDR receiver parsers (core.kraken.parse: XML, CSV, JSON).

Inputs: arbitrary bytes, and the shipped fixtures mutated (bytes inserted, overwritten or cut;
each number replaced by a hostile literal: 400 digits, 1e200000, NaN, -0, 1e-999990).
Property: parse returns a list whose items are KrakenRecords with finite, in-range values or
KrakenErrors with a documented reason; nothing else escapes, and no input stalls (the number
literals are the ones that froze the UDP parser). Hypothesis runs derandomised with no
example database and a fixed budget.
"""

import math
import os
import re

from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
import pytest

from bearing_loc_ros.core import kraken

FUZZ = settings(max_examples=200, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck))
FIXTURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'fixtures', 'kraken')
REASONS = ('malformed_xml', 'malformed_csv', 'malformed_json', 'missing_field', 'bad_number',
           'not_finite', 'out_of_range', 'too_large')
HOSTILE_NUMBERS = ('1' + '0' * 400, '1e200000', '1e999990', '-1e999990', '1e-999990', 'NaN',
                   '-0', '0.' + '0' * 60 + '1', '9' * 30, 'Infinity', '1e308', '-5e-324')
NUMBER = re.compile(rb'-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?')


def _fixtures():
    out = []
    for name in sorted(os.listdir(FIXTURES)):
        fmt = name.rpartition('.')[2]
        if fmt in kraken.FORMATS:
            with open(os.path.join(FIXTURES, name), 'rb') as f:
                out.append((fmt, f.read()))
    return out


SEEDS = _fixtures()


def check(data, fmt):
    items = kraken.parse(data, fmt)
    assert isinstance(items, list)
    for item in items:
        if isinstance(item, kraken.KrakenError):
            assert item.reason in REASONS, item
            continue
        assert isinstance(item, kraken.KrakenRecord)
        assert 0 < item.stamp_ns <= kraken.MAX_STAMP_NS
        assert kraken.FREQ_MIN_HZ <= item.frequency_hz <= kraken.FREQ_MAX_HZ
        assert 0.0 <= item.doa_deg <= 360.0 and math.isfinite(item.reported_deg)
        assert math.isfinite(item.confidence) and item.confidence >= 0.0
        for v in (item.power_db, item.snr_db, item.latitude_deg, item.longitude_deg,
                  item.heading_deg, item.speed, item.latency_ms):
            assert not math.isinf(v)
    return items


def test_seeds_exist():
    assert {fmt for fmt, _ in SEEDS} == set(kraken.FORMATS)


@FUZZ
@given(st.binary(max_size=400), st.sampled_from(kraken.FORMATS))
def test_arbitrary_bytes(data, fmt):
    check(data, fmt)


@FUZZ
@given(st.sampled_from(SEEDS), st.binary(min_size=1, max_size=20), st.integers(0, 4000),
       st.integers(0, 2))
def test_mutated_fixtures(seed, noise, where, how):
    fmt, base = seed
    i = where % (len(base) + 1)
    data = (base[:i] + noise + base[i:], base[:i] + noise + base[i + len(noise):],
            base[:i] + base[i + len(noise):])[how]
    check(data, fmt)


@FUZZ
@given(st.sampled_from(SEEDS), st.integers(0, 200), st.sampled_from(HOSTILE_NUMBERS))
def test_hostile_number_literals(seed, which, literal):
    fmt, base = seed
    spans = [m.span() for m in NUMBER.finditer(base)]
    if not spans:
        return
    a, b = spans[which % len(spans)]
    check(base[:a] + literal.encode() + base[b:], fmt)


@pytest.mark.parametrize('fmt, base', SEEDS)
def test_every_number_of_every_fixture_hostile(fmt, base):
    """Each number of each fixture replaced in turn by each hostile literal."""
    for a, b in (m.span() for m in NUMBER.finditer(base[:3000])):
        for literal in HOSTILE_NUMBERS[:3]:
            check(base[:a] + literal.encode() + base[b:], fmt)


# ------------------------------------------------------------ the station node's receiver path

NODE_REASONS = REASONS + ('duplicate_time', 'old_time', 'stale_time', 'zero_gps', 'no_gps',
                          'no_heading', 'no_odometry', 'low_confidence', 'no_channel',
                          'other_station', 'no_clock', 'invalid_bearing')
HOSTILE_FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                           st.floats(-400.0, 400.0), st.sampled_from([0.0, -0.0, 1e308]))


def _receiver(kind):
    from bearing_loc_ros.core.receiver_params import receiver_from_params
    p = {'position': [1.0, 2.0, 3.0], 'kraken.channels': ['a', 'b'],
         'kraken.channel_bands_mhz': [100.0, 200.0, 400.0, 500.0],
         'kraken.min_confidence': 0.1, 'kraken.max_age': 5.0}
    if kind == 'vehicle':
        p = {'geodetic_origin': [48.1, 11.5, 500.0], 'kraken.heading_source': 'gps',
             'kraken.position_source': 'gps', 'kraken.heading_hold_timeout': 2.0}
    return receiver_from_params('st', p)


@FUZZ
@given(st.sampled_from(['fixed', 'vehicle']), st.lists(st.tuples(
    st.integers(-10 ** 4, 10 ** 4), HOSTILE_FLOATS, HOSTILE_FLOATS, HOSTILE_FLOATS,
    HOSTILE_FLOATS, HOSTILE_FLOATS, st.sampled_from([150.0, 450.0, 300.0, 0.0])),
    min_size=1, max_size=8))
def test_receiver_path_never_raises_and_publishes_only_valid_bearings(kind, readings):
    """Readings with hostile DOA, heading, confidence and GPS values, through the text
    format and the node's KrakenInput (channels, time filter, geometry, confidence -> σ):
    each is a valid bearing that converts to a message, or a rejection with a known
    reason; nothing raises."""
    from bearing_loc_ros.receiver_inputs import _Source, KrakenInput
    from bearing_loc_ros.ros_conversions import bearing_from_msg, bearing_to_msg
    cfg, channels = _receiver(kind)
    src = _Source()
    t0 = 1_700_000_000_000
    for dt, doa, heading, conf, lat, lon, mhz in readings:
        rec = kraken.KrakenRecord(
            (t0 + dt) * 10 ** 6, 'st', mhz * 1e6, doa, doa, conf, -40.0, latitude_deg=lat,
            longitude_deg=lon, heading_deg=heading, source='csv')
        try:
            src._put([kraken.parse_csv_line(kraken.csv_line(rec, spectrum=False))])
        except kraken.KrakenError as exc:
            src._put([exc])
    ki = KrakenInput(src, cfg, channels, 'receiver', 5.0)
    bearings, rejected = ki.poll(t0 * 10 ** 6)
    assert len(bearings) + len(rejected) == len(readings)
    assert {r for r, _ in rejected} <= set(NODE_REASONS), rejected
    for ch, b in bearings:
        assert ch in channels.names
        back = bearing_from_msg(bearing_to_msg(b), 'st')
        assert math.isfinite(back.azimuth) and abs(back.azimuth) <= math.pi
        assert 0.0 < back.sigma_azimuth < math.pi and np.all(np.isfinite(back.position))
