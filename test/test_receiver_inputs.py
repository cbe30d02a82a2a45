"""Receiver input sources (receiver_inputs.py) against a fake KrakenSDR on loopback."""

import json
import math
import os
import time
import urllib.request

from http_fakes import LoopbackHTTP
import pytest

from bearing_loc_ros import receiver_inputs as ri
from bearing_loc_ros.core import kraken
from bearing_loc_ros.core.receiver import receiver_config

FIX = os.path.join(os.path.dirname(__file__), 'fixtures', 'kraken')


def fixture(name):
    with open(os.path.join(FIX, name), 'rb') as f:
        return f.read()


class FakeKraken(LoopbackHTTP):
    """A KrakenSDR web server on 127.0.0.1: serves ``body`` with ``status`` after ``delay``.

    ``stop()`` closes the socket (the receiver "dies"); ``start()`` binds the same port
    again. ``redirect`` answers 302 to another host.
    """

    def __init__(self, port=0):
        super().__init__(port)
        self.body, self.status, self.delay, self.redirect = b'', 200, 0.0, False
        self.requests = 0

    def respond(self, handler):
        self.requests += 1
        time.sleep(self.delay)
        if self.redirect:
            handler.send_response(302)
            handler.send_header('Location', 'http://192.0.2.1/doa.xml')
            handler.end_headers()
            return
        handler.send_response(self.status)
        handler.send_header('Content-Length', str(len(self.body)))
        handler.end_headers()
        handler.wfile.write(self.body)

    @property
    def url(self):
        return f'http://127.0.0.1:{self.port}/doa.xml'


@pytest.fixture
def fake():
    f = FakeKraken().start()
    yield f
    f.stop()


def test_http_poller_failures_and_recovery(fake):
    p = ri.HttpPoller(fake.url, 'xml', period_s=0.1, timeout_s=0.5, max_backoff_s=0.8)
    fake.body = fixture('doa_basic.xml')
    assert p.poll_once() <= 0.1
    [r] = p.drain()
    assert isinstance(r, kraken.KrakenRecord) and r.doa_deg == 75.0
    fake.body = b'<html>garbage'
    p.poll_once()
    assert p.drain()[0].reason == 'malformed_xml'
    fake.status = 500
    delays = [p.poll_once() for _ in range(4)]
    assert delays == [0.2, 0.4, 0.8, 0.8]          # backoff, capped
    assert p.snapshot()[0] == 'error' and p.counts['http_status'] == 4
    fake.status, fake.delay = 200, 0.8              # slower than the timeout
    p.poll_once()
    assert p.counts['timeout'] == 1 and p.state == 'unreachable'
    fake.delay = 0.0
    fake.body = fixture('doa_basic.xml')
    port = fake.port
    fake.stop()
    p.poll_once()
    assert p.counts['unreachable'] == 1 and p.state == 'unreachable'
    fake.port = port
    fake.start()
    assert p.poll_once() <= 0.1 and p.state == 'ok' and p.counts['recoveries'] == 1
    assert isinstance(p.drain()[-1], kraken.KrakenRecord)


def test_http_poller_refuses_redirects(fake):
    fake.redirect = True
    p = ri.HttpPoller(fake.url, 'xml', timeout_s=0.5)
    p.poll_once()
    assert p.counts['http_status'] == 1 and 'redirect refused' in p.last_error


def test_http_poller_thread_never_blocks_the_caller(fake):
    fake.delay = 0.6
    fake.body = fixture('doa_value.html')
    p = ri.HttpPoller(fake.url, 'csv', period_s=0.05, timeout_s=1.0).start()
    t0 = time.monotonic()
    assert p.drain() == []                          # returns at once
    # Causal bound, not a speed figure: drain() came back before the in-flight request could
    # have been answered, so it did not wait for the fetch thread.
    assert time.monotonic() - t0 < fake.delay
    deadline = time.monotonic() + 5.0
    got = []
    while len(got) < 2 and time.monotonic() < deadline:
        got += p.drain()
        time.sleep(0.05)
    p.stop()
    assert [r.frequency_hz for r in got[:2]] == [433.92e6, 145.5e6]
    assert p.counts['slow'] >= 1


def test_urls_are_checked():
    for bad in ('ftp://host/doa.xml', 'file:///etc/passwd', 'doa.xml', 'http:///x'):
        with pytest.raises(ValueError):
            ri.make_source('kraken_xml_http', url=bad)


def post(port, body, method='POST', length=None):
    req = urllib.request.Request(f'http://127.0.0.1:{port}/kraken', data=body, method=method)
    if length is not None:
        req.add_header('Content-Length', str(length))
    try:
        with urllib.request.urlopen(req, timeout=5) as resp:
            return resp.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_json_post_server():
    srv = ri.JsonPostServer('127.0.0.1', 0).start()
    try:
        assert post(srv.port, fixture('doa_post.json')) == 200
        assert post(srv.port, b'{"nope": 1}') == 400
        assert post(srv.port, b'x' * (ri.MAX_POST_BYTES + 1)) == 413
        assert post(srv.port, None, method='GET') == 405
        got = srv.drain()
        assert isinstance(got[0], kraken.KrakenRecord) and got[0].station_id == 'van'
        assert [e.reason for e in got[1:]] == ['missing_field', 'too_large']
    finally:
        srv.stop()
    with pytest.raises(ValueError) as e:          # port taken: a named error
        busy = ri.JsonPostServer('127.0.0.1', 0)
        try:
            ri.make_source('kraken_json_post', post_port=busy.port)
        finally:
            busy.stop()
    assert 'post_port' in str(e.value)


def test_csv_file_tail(tmp_path):
    lines = fixture('mydata.csv').decode().splitlines(keepends=True)
    path = tmp_path / 'mydata.csv'
    t = ri.CsvFileTail(path)
    t.poll()
    assert t.state == 'missing' and t.counts['missing'] == 1
    path.write_text(lines[0] + lines[1][:50])          # the second line is incomplete
    t.poll()
    assert len(t.drain()) == 1
    with open(path, 'a') as f:
        f.write(lines[1][50:] + 'garbage line\n')
    t.poll()
    got = t.drain()
    assert got[0].frequency_hz == 145.5e6 and got[1].reason == 'malformed_csv'
    path.write_text(lines[2])                          # truncated and rewritten
    t.poll()
    assert t.counts['truncated'] == 1 and t.drain()[0].stamp_ns == 1700000000500 * 10 ** 6
    os.replace(path, tmp_path / 'old.csv')             # rotated: a new file appears
    path.write_text(lines[4])
    t.poll()
    assert t.counts['reopened'] == 1
    t.poll()
    assert t.drain()[0].stamp_ns == 1700000001000 * 10 ** 6
    t.close()


def test_csv_file_paced_replay(tmp_path):
    path = tmp_path / 'mydata.csv'
    path.write_bytes(fixture('mydata.csv'))     # frames 0.5 s apart
    t = ri.CsvFileTail(path, rate=2.0)
    assert t.poll(now_s=100.0) == 2              # first frame (two channels) at once
    assert t.poll(now_s=100.2) == 0
    assert t.poll(now_s=100.25) == 2             # 0.5 s of record = 0.25 s at rate 2
    assert t.poll(now_s=101.0) == 2


def test_kraken_input_channels_and_time_filter(tmp_path):
    path = tmp_path / 'mydata.csv'
    data = fixture('mydata.csv').decode().splitlines(keepends=True)
    path.write_text(''.join(data) + data[0])     # the first line again: an old stamp
    cfg = receiver_config('hilltop', position=[0.0, 0.0, 0.0], array_heading_deg=30.0)
    ch = kraken.channel_map_from_params(['uhf', 'vhf'], [430.0, 440.0, 144.0, 146.0])
    ki = ri.KrakenInput(ri.CsvFileTail(path), cfg, ch)
    bearings, rejected = ki.poll(now_ns=None)
    assert [c for c, _ in bearings] == ['uhf', 'vhf'] * 3
    assert rejected[0][0] == 'old_time'
    uhf = bearings[0][1]
    # compass = 30 + 285 = 315 deg -> ENU 135 deg
    assert uhf.azimuth == pytest.approx(math.radians(135.0))
    assert uhf.sigma_azimuth == pytest.approx(cfg.sigma.sigma(0.91))
    state, _, values = ki.status()
    assert values['kraken_published_uhf'] == 3 and values['kraken_readings'] == 7
    only_uhf = ri.KrakenInput(ri.CsvFileTail(path), cfg,
                              kraken.channel_map_from_params(['uhf'], [430.0, 440.0]),
                              receiver_id='hilltop')
    _, rej = only_uhf.poll(None)
    assert sorted(r for r, _ in rej) == ['no_channel'] * 3 + ['old_time']
    other = ri.KrakenInput(ri.CsvFileTail(path), cfg, receiver_id='valley')
    _, rej = other.poll(None)
    assert {r for r, _ in rej} == {'other_station'}


def test_kraken_input_polled_duplicates_are_unchanged(fake):
    fake.body = fixture('doa_basic.xml')
    cfg = receiver_config('hilltop', position=[0.0, 0.0, 0.0])
    src = ri.HttpPoller(fake.url, 'xml', timeout_s=1.0)
    ki = ri.KrakenInput(src, cfg, stamp='receiver')
    for _ in range(3):
        src.poll_once()
    bearings, rejected = ki.poll(now_ns=None)
    assert len(bearings) == 1 and rejected == [] and ki.counts['unchanged'] == 2
    fake.body = json.dumps({'a': 1}).encode()
    src.poll_once()
    _, rejected = ki.poll(now_ns=None)
    assert rejected[0][0] == 'malformed_xml'


class _Source:
    """A source stub whose state the test sets (only snapshot() is used)."""

    def __init__(self):
        self.state, self.last_error = 'starting', ''

    def snapshot(self):
        return self.state, self.last_error, {}


def test_state_changes_into_and_out_of_failure_are_reported_once():
    # The station node logs these (an unreachable receiver used to appear only in
    # /diagnostics): entering a failure, changing failure, and recovering; nothing else.
    src = _Source()
    ki = ri.KrakenInput(src, receiver_config('s1', position=[0.0, 0.0, 0.0]))
    seen = []
    for state in ('starting', 'ok', 'slow', 'unreachable', 'unreachable', 'error', 'ok',
                  'ok', 'slow'):
        src.state, src.last_error = state, f'{state} detail'
        seen.append(ki.state_change())
    assert seen == [None, None, None, ('unreachable', 'unreachable detail'), None,
                    ('error', 'error detail'), ('ok', 'ok detail'), None, None]
    # A CSV file that is not there (a path typo) is a failure too.
    missing = ri.KrakenInput(ri.CsvFileTail('/nonexistent/kraken.csv'),
                             receiver_config('s1', position=[0.0, 0.0, 0.0]))
    missing.poll(now_ns=None)
    assert missing.state_change()[0] == 'missing' and missing.state_change() is None
