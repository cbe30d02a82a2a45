"""KrakenSDR parsers (core.kraken): hand-written fixtures of every format, good and bad."""

import math
import os

import pytest

from bearing_loc_ros.core import kraken
from bearing_loc_ros.core.kraken import KrakenError

FIX = os.path.join(os.path.dirname(__file__), 'fixtures', 'kraken')


def read(name, mode='rb'):
    with open(os.path.join(FIX, name), mode) as f:
        return f.read()


def reason_of(fn, data):
    with pytest.raises(KrakenError) as info:
        fn(data)
    return info.value.reason, info.value.field


def test_xml_basic_fields():
    r = kraken.parse_xml(read('doa_basic.xml'))
    assert r.stamp_ns == 1700000000123 * 1_000_000
    assert r.station_id == 'hilltop'
    assert r.frequency_hz == pytest.approx(433.92e6, rel=1e-12)
    assert r.doa_deg == 75.0 and r.reported_deg == 75.0
    assert r.confidence == pytest.approx(0.87)
    assert r.power_db == pytest.approx(-37.5)
    assert r.snr_db == pytest.approx(18.5)
    assert (r.latitude_deg, r.longitude_deg) == (48.8566, 2.3522)
    assert (r.heading_deg, r.speed) == (30.0, 0.0)
    assert r.latency_ms == 210.0
    assert r.gps_time_ns == 1700000000000 * 1_000_000
    assert r.has_gps and r.source == 'xml'


def test_xml_without_gps_parses_but_has_no_fix():
    r = kraken.parse_xml(read('doa_no_gps.xml'))
    assert r.gps_time_ns == 0 and not r.has_gps
    assert r.confidence == pytest.approx(0.05)


@pytest.mark.parametrize('name, reason, field', [
    ('doa_missing_doa.xml', 'missing_field', 'DOA'),
    ('doa_nan.xml', 'not_finite', 'DOA'),
    ('doa_out_of_range.xml', 'out_of_range', 'DOA'),
    ('doa_wrong_root.xml', 'malformed_xml', ''),
    ('doa_truncated.xml', 'malformed_xml', ''),
    ('doa_entity_bomb.xml', 'malformed_xml', ''),
    ('doa_external_entity.xml', 'malformed_xml', ''),
])
def test_xml_rejections(name, reason, field):
    assert reason_of(kraken.parse_xml, read(name)) == (reason, field)


def test_xml_hostile_inputs():
    assert reason_of(kraken.parse_xml, b'')[0] == 'malformed_xml'
    assert reason_of(kraken.parse_xml, b'\xff\xfe\x00garbage')[0] == 'malformed_xml'
    assert reason_of(kraken.parse_xml, b'<DATA>' + b' ' * (300 * 1024) + b'</DATA>')[0] \
        == 'too_large'
    bad_time = read('doa_basic.xml').replace(b'1700000000123', b'1e40')
    assert reason_of(kraken.parse_xml, bad_time) == ('out_of_range', 'TIME')
    neg_conf = read('doa_basic.xml').replace(b'<CONF>87', b'<CONF>-3')
    assert reason_of(kraken.parse_xml, neg_conf) == ('out_of_range', 'CONF')
    text_freq = read('doa_basic.xml').replace(b'433.92', b'UHF')
    assert reason_of(kraken.parse_xml, text_freq) == ('bad_number', 'FREQUENCY')


def test_json_key_given_twice_is_malformed():
    body = b'{"tStamp": 1700000000123, "radioBearing": 10, "radioBearing": 200, ' \
           b'"conf": 0.9, "freq": 433.92}'
    assert reason_of(kraken.parse_json, body)[0] == 'malformed_json'


@pytest.mark.parametrize('garbled, field', [
    ('433_92', 'FREQUENCY'),                        # float() would read 43392
    ('\uff14\uff13\uff13.92', 'FREQUENCY'),    # full-width digits: float() reads 433.92
    ('1_700_000_000_123', 'TIME'),                  # Decimal() would read the same stamp
    ('0x1F', 'CONF')])
def test_text_numbers_are_ascii_decimals(garbled, field):
    """A field written with digit-group underscores or non-ASCII digits is garbled, not
    another number: Python's float() and Decimal() would accept it."""
    original = {'FREQUENCY': b'433.92', 'TIME': b'1700000000123', 'CONF': b'<CONF>87'}[field]
    value = garbled.encode() if field != 'CONF' else b'<CONF>' + garbled.encode()
    data = read('doa_basic.xml').replace(original, value)
    assert reason_of(kraken.parse_xml, data) == ('bad_number', field)
    line = read('mydata.csv', 'r').splitlines()[0].split(',')
    line[4] = garbled                               # the frequency column
    assert reason_of(kraken.parse_csv_line, ','.join(line)) == ('bad_number', 'frequency')


def test_csv_recording_two_channels_with_spectrum():
    lines = read('mydata.csv', 'r').splitlines()
    assert len(lines) == 6
    recs = [kraken.parse_csv_line(line) for line in lines]
    a, b = recs[0], recs[1]
    assert a.stamp_ns == b.stamp_ns == 1700000000000 * 1_000_000
    assert a.reported_deg == 285.0 and a.doa_deg == 75.0      # DOA = 360 - field 2
    assert b.reported_deg == 40.0 and b.doa_deg == 320.0
    assert a.frequency_hz == 433.92e6 and b.frequency_hz == 145.5e6
    assert a.confidence == 0.91 and a.power_db == -37.5 and math.isnan(a.snr_db)
    assert a.array_type == 'UCA' and a.station_id == 'hilltop' and a.heading_deg == 30.0
    assert math.isnan(a.speed)
    assert len(a.spectrum) == 360 and min(a.spectrum) == 0.0
    assert max(range(360), key=a.spectrum.__getitem__) == 285   # peak at the reported angle


def test_csv_html_body_and_bytes():
    out = kraken.parse_csv_text(read('doa_value.html'))
    assert [r.frequency_hz for r in out] == [433.92e6, 145.5e6]
    assert all(r.spectrum is None for r in out)
    assert kraken.parse_csv_text(b'\xff\xfe')[0].reason == 'malformed_csv'
    assert kraken.parse_csv_text('\n\n  \n') == []


def test_csv_malformed_lines_each_counted():
    out = kraken.parse_csv_text(read('malformed.csv', 'r'))
    got = [(e.reason, e.field) for e in out]
    assert got == [('malformed_csv', ''), ('bad_number', 'doa'), ('not_finite', 'confidence'),
                   ('out_of_range', 'doa'), ('malformed_csv', 'spectrum'),
                   ('out_of_range', 'ts_ms'), ('out_of_range', 'frequency'),
                   ('out_of_range', 'latitude'), ('not_finite', 'heading')]


def test_csv_same_reading_as_xml():
    """The CSV and the XML of one frame give the same DOA, frequency and confidence."""
    x = kraken.parse_xml(read('doa_basic.xml'))
    c = kraken.parse_csv_line(read('mydata.csv', 'r').splitlines()[0])
    assert c.doa_deg == x.doa_deg
    assert c.frequency_hz == pytest.approx(x.frequency_hz)


def test_json_post_body():
    r = kraken.parse_json(read('doa_post.json'))
    assert r.stamp_ns == 1700000002500 * 1_000_000 and r.station_id == 'van'
    assert r.reported_deg == 285.0 and r.doa_deg == 75.0
    assert r.frequency_hz == 433.92e6 and r.confidence == pytest.approx(0.91)
    assert (r.heading_deg, r.speed, r.snr_db, r.power_db) == (270.0, 12.5, 21.0, -37.5)
    assert r.array_type == 'UCA' and r.spectrum is None and r.has_gps
    m = kraken.parse_json(read('doa_post_mhz.json'))
    assert m.frequency_hz == pytest.approx(145.5e6) and not m.has_gps
    assert m.doa_deg == 0.0 and m.gps_time_ns == 0


# One fixture table per format, like the XML one above: the tables are data, not logic.
@pytest.mark.parametrize('name, reason, field', [
    ('doa_post_nan.json', 'malformed_json', ''),
    ('doa_post_missing.json', 'missing_field', 'radioBearing'),
    ('doa_post_array.json', 'malformed_json', ''),
    ('doa_post_bad_lat.json', 'out_of_range', 'latitude'),
])
def test_json_rejections(name, reason, field):
    assert reason_of(kraken.parse_json, read(name)) == (reason, field)


def test_json_hostile_values():
    base = b'{"tStamp": 1700000002500, "radioBearing": 10, "conf": 0.9, "freq": %s}'
    assert reason_of(kraken.parse_json, base % b'true') == ('bad_number', 'freq')
    assert reason_of(kraken.parse_json, base % b'1e400')[0] == 'not_finite'
    assert reason_of(kraken.parse_json, base % b'"UHF"') == ('bad_number', 'freq')
    assert kraken.parse_json(base % b'"433.92"').frequency_hz == pytest.approx(433.92e6)
    assert reason_of(kraken.parse_json, b'[' * 100000)[0] == 'malformed_json'
    assert reason_of(kraken.parse_json, b'{"tStamp": "x", "radioBearing": 1, "conf": 1, '
                                        b'"freq": 1e8}') == ('bad_number', 'tStamp')


@pytest.mark.parametrize('literal', [b'1e1000000000000000000', b'-1E+99999999999999999999',
                                     b'1e-1000000000000000000'])
def test_json_exponent_beyond_decimal_range_is_refused_never_raised(literal):
    """Decimal('1e1000000000000000000') raises InvalidOperation; it once escaped parse()
    and left the POST client without a reply. Refused from the text before conversion: a
    field's ``bad_number``, harmless in an ignored key; parse() returns, never raises."""
    body = read('doa_post.json')
    bad_conf = body.replace(b'"conf": 0.91', b'"conf": ' + literal)
    assert bad_conf != body
    assert reason_of(kraken.parse_json, bad_conf) == ('bad_number', 'conf')
    [err] = kraken.parse(bad_conf, 'json')
    assert isinstance(err, KrakenError) and 'exponent beyond' in str(err)
    bad_stamp = body.replace(b'"tStamp": 1700000002500', b'"tStamp": ' + literal)
    assert bad_stamp != body
    assert reason_of(kraken.parse_json, bad_stamp) == ('bad_number', 'tStamp')
    [rec] = kraken.parse(b'{"x": ' + literal + b', ' + body[1:], 'json')
    assert rec.stamp_ns == 1700000002500 * 1_000_000 and rec.doa_deg == 75.0


def test_parse_dispatch():
    assert isinstance(kraken.parse(read('doa_basic.xml'), 'xml')[0], kraken.KrakenRecord)
    assert isinstance(kraken.parse(b'{}', 'json')[0], KrakenError)
    assert len(kraken.parse(read('doa_value.html'), 'csv')) == 2
    with pytest.raises(ValueError):
        kraken.parse(b'', 'yaml')


def test_time_filter():
    tf = kraken.TimeFilter(max_age_ns=5_000_000_000, reset_ns=60_000_000_000)
    tf.check('a', 10_000_000_000)
    tf.check('b', 10_000_000_000)                   # streams are independent
    with pytest.raises(KrakenError) as e:
        tf.check('a', 10_000_000_000)
    assert e.value.reason == 'duplicate_time'
    with pytest.raises(KrakenError) as e:
        tf.check('a', 9_000_000_000)
    assert e.value.reason == 'old_time'
    with pytest.raises(KrakenError) as e:
        tf.check('a', 11_000_000_000, now_ns=17_000_000_000)
    assert e.value.reason == 'stale_time'
    tf.check('a', 11_000_000_000, now_ns=12_000_000_000)
    with pytest.raises(KrakenError) as e:           # 10 s back is not a clock restart
        tf.check('a', 1_000_000_000)
    assert e.value.reason == 'old_time' and tf.resets == 0
    tf2 = kraken.TimeFilter(reset_ns=60_000_000_000)
    tf2.check('a', 200_000_000_000)
    tf2.check('a', 100_000_000_000)
    assert tf2.resets == 1


def test_time_filter_refuses_future_stamps_without_changing_its_state():
    """One reading 30 s ahead of the node clock (a receiver clock glitch) with max_age 5 s
    once made the next 30 s of good 1 Hz readings ``old_time``; a 2037 stamp was accepted.
    Now each is ``future_time`` and every good reading passes."""
    s = 1_000_000_000
    now0 = 1_700_000_000 * s
    tf = kraken.TimeFilter(max_age_ns=5 * s, reset_ns=60 * s)
    assert tf.future_ns == kraken.MAX_FUTURE_NS == 10 * s
    out = []
    for k in range(40):
        now = now0 + k * s
        stamp = now + 30 * s if k == 5 else (2_130_000_000 * s if k == 9 else now)
        try:
            tf.check('rx', stamp, now)
            out.append('ok')
        except KrakenError as exc:
            out.append(exc.reason)
    assert out == ['ok'] * 5 + ['future_time'] + ['ok'] * 3 + ['future_time'] + ['ok'] * 30
    assert tf.resets == 0
    tf.check('rx', now0 + 50 * s + kraken.MAX_FUTURE_NS, now0 + 50 * s)   # at the limit
    tf.check('rx', now0 + 90 * s, now_ns=None)      # no node clock: no future check
    tf.check('rx', now0 + 91 * s, now_ns=0)         # node clock not started (sim time)


def test_channel_map():
    cm = kraken.channel_map_from_params(['ch_433', 'ch_145'], [433.0, 435.0, 144.0, 146.0])
    assert cm.names == ['ch_433', 'ch_145']
    assert cm.channel_of(433.92e6) == 'ch_433' and cm.channel_of(145.5e6) == 'ch_145'
    assert cm.channel_of(868e6) is None
    assert kraken.ChannelMap().channel_of(1e9) == '' and kraken.ChannelMap().names == ['']
    for names, bands in ((['a'], [1.0]), (['a', 'b'], [1.0, 3.0, 2.0, 4.0]),
                         (['a'], [5.0, 4.0]), (['a b'], [1.0, 2.0]), (['a', 'a'], [1, 2, 3, 4])):
        with pytest.raises(ValueError):
            kraken.channel_map_from_params(names, bands)
