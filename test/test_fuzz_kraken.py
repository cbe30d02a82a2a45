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
