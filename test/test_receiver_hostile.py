"""Receiver inputs (receiver_inputs.py) against hostile peers and files, on loopback.

A receiver that answers with something that is not HTTP, a JSON client that sends less
than it announced or hangs up, recorded files with CR line ends, invalid UTF-8, a line with
no end, replaced files and absurd stamps during a paced replay: each is counted by reason
and the input keeps working. Nothing here asserts on durations; waits are for a state,
with a generous deadline.
"""

import inspect
import os
import select
import socket
import struct
import threading
import time

import pytest

from bearing_loc_ros import receiver_inputs as ri
from bearing_loc_ros.core import kraken
from bearing_loc_ros.core.receiver import receiver_config

FIX = os.path.join(os.path.dirname(__file__), 'fixtures', 'kraken')
GOOD_XML = open(os.path.join(FIX, 'doa_basic.xml'), 'rb').read()
GOOD_JSON = open(os.path.join(FIX, 'doa_post.json'), 'rb').read()
LINE0 = open(os.path.join(FIX, 'mydata.csv'), encoding='utf-8').read().splitlines()[0]
FIELDS = [f.strip() for f in LINE0.split(',')][:kraken.CSV_FIXED_FIELDS]
T0_MS = 1_700_000_000_000


def csv_line(t_ms, station='hilltop', end='\n'):
    """A valid "Kraken App" CSV line (no spectrum) stamped ``t_ms``."""
    f = list(FIELDS)
    f[0], f[7] = str(t_ms), station
    return ', '.join(f) + end


def wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()


# ------------------------------------------------------------------ HTTP polling

class RawServer:
    """A TCP server on 127.0.0.1 that answers each connection with ``replies[k]`` (raw
    bytes; the last one repeats), after reading the request."""

    def __init__(self, replies):
        self.replies = list(replies)
        self.served = 0
        self.sock = socket.socket()
        self.sock.bind(('127.0.0.1', 0))
        self.sock.listen(16)
        self.url = f'http://127.0.0.1:{self.sock.getsockname()[1]}/doa.xml'
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            with c:
                try:
                    c.settimeout(5.0)
                    c.recv(65536)
                    c.sendall(self.replies[min(self.served, len(self.replies) - 1)])
                except OSError:
                    pass
                self.served += 1

    def close(self):
        self.sock.close()


def http_ok(body):
    return b'HTTP/1.1 200 OK\r\nContent-Length: %d\r\n\r\n' % len(body) + body


BAD_REPLIES = {
    'not HTTP (BadStatusLine)': b'SSH-2.0-OpenSSH_9.6\r\n',
    'cut short (IncompleteRead)': b'HTTP/1.1 200 OK\r\nContent-Length: 500\r\n\r\n<DATA>',
    'bad chunks (IncompleteRead)': (b'HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n'
                                    b'ZZZ\r\nabc\r\n0\r\n\r\n'),
    'too many headers (HTTPException)': (b'HTTP/1.1 200 OK\r\n' + b''.join(
        b'X-%d: a\r\n' % i for i in range(200)) + b'\r\n'),
}


@pytest.mark.parametrize('reply', list(BAD_REPLIES))
def test_a_reply_that_is_not_http_is_counted_and_polling_recovers(reply):
    """http.client's own exceptions once escaped poll_once and ended the polling thread for
    good, while the diagnostics still said ok."""
    srv = RawServer([BAD_REPLIES[reply], http_ok(GOOD_XML)])
    p = ri.HttpPoller(srv.url, 'xml', period_s=0.05, timeout_s=2.0, max_backoff_s=0.1)
    try:
        p.poll_once()
        state, last_error, counts = p.snapshot()
        assert state == 'error' and counts['http_error'] == 1, (state, last_error)
        assert last_error.startswith('http_error: ') and last_error.isprintable()  # one line
        assert p.drain() == []
        p.poll_once()
        assert p.state == 'ok' and p.counts['recoveries'] == 1
        [rec] = p.drain()
        assert isinstance(rec, kraken.KrakenRecord) and rec.doa_deg == 75.0
    finally:
        srv.close()


class _Response:
    def __init__(self, body):
        self.body = body
        self.headers = {'Content-Length': str(len(body))}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def read(self, n=-1):
        return self.body


class _FlakyOpener:
    """Raises an error no handler expects on the first ``fail`` calls, then serves XML."""

    def __init__(self, fail):
        self.fail, self.calls = fail, 0

    def open(self, url, timeout=None):
        self.calls += 1
        if self.calls <= self.fail:
            raise RuntimeError('unexpected failure inside the HTTP stack')
        return _Response(GOOD_XML)


def test_the_polling_thread_survives_any_error_counts_and_logs_it_once():
    p = ri.HttpPoller('http://127.0.0.1:9/doa.xml', 'xml', period_s=0.01, timeout_s=1.0,
                      max_backoff_s=0.02)
    p._opener = _FlakyOpener(fail=3)
    logged = []
    p.log = logged.append
    p.start()
    try:
        assert wait_for(lambda: p.snapshot()[2].get('recoveries')), p.snapshot()
        assert p._thread.is_alive()
        state, _, counts = p.snapshot()
        assert state == 'ok' and counts['internal_error'] == 3
        assert isinstance(p.drain()[0], kraken.KrakenRecord)
        assert len(logged) == 1 and 'RuntimeError' in logged[0]     # throttled
    finally:
        p.stop()


@pytest.mark.parametrize('url', ['http://127.0.0.1:abc/doa.xml', 'http://127.0.0.1:99999/x',
                                 'http://127.0.0.1:0/doa.xml', 'http://127.0.0.1:-1/doa.xml',
                                 'http://[::1/doa.xml'])
def test_a_bad_port_in_the_url_is_a_start_up_error(url):
    with pytest.raises(ValueError) as e:
        ri.make_source('kraken_xml_http', url=url)
    assert str(e.value).startswith('url: ')
    ri.make_source('kraken_xml_http', url='http://127.0.0.1:8081/doa.xml')
    ri.make_source('kraken_xml_http', url='http://[::1]/doa.xml')


# ------------------------------------------------------------------ JSON POST

def raw_post(port, head, body=b'', shutdown=False, timeout=10.0):
    """Send ``head`` + ``body`` and return the reply's status line (b'' when the server
    closed without one)."""
    with socket.create_connection(('127.0.0.1', port), timeout=timeout) as c:
        c.sendall(b'POST /kraken HTTP/1.1\r\nHost: x\r\n' + head + b'\r\n' + body)
        if shutdown:
            c.shutdown(socket.SHUT_WR)
        try:
            return c.recv(4096).split(b'\r\n')[0]
        except OSError:
            return b''


@pytest.fixture
def server():
    srv = ri.JsonPostServer('127.0.0.1', 0).start()
    srv.logged = []
    srv.log = srv.logged.append
    yield srv
    srv.stop()


def test_post_listener_default_port_is_the_documented_one():
    assert ri.POST_PORT == 8082
    assert inspect.signature(ri.JsonPostServer).parameters['port'].default == ri.POST_PORT
    assert inspect.signature(ri.make_source).parameters['post_port'].default == ri.POST_PORT


def test_post_with_a_huge_exponent_gets_a_reply_and_is_counted(server):
    """Decimal('1e1000000000000000000') once raised in the request thread: no reply, a
    traceback, nothing counted."""
    bad_conf = GOOD_JSON.replace(b'"conf": 0.91', b'"conf": 1e1000000000000000000')
    ignored = b'{"x": 1e1000000000000000000, ' + GOOD_JSON[1:]
    for body in (bad_conf, ignored):
        assert raw_post(server.port, b'Content-Length: %d\r\n' % len(body), body) in (
            b'HTTP/1.0 400 Bad Request', b'HTTP/1.0 200 OK')
    bad, good = server.drain()
    assert bad.reason == 'bad_number' and bad.field == 'conf'
    assert isinstance(good, kraken.KrakenRecord)


def test_a_body_shorter_than_its_content_length_is_a_counted_rejection(server, monkeypatch):
    head = b'Content-Length: %d\r\n' % (len(GOOD_JSON) + 100)
    # the client closes its side: the server sees the end of the body early
    assert raw_post(server.port, head, GOOD_JSON, shutdown=True) == b'HTTP/1.0 400 Bad Request'
    # the client stops sending and waits: the server gives up after its timeout
    monkeypatch.setattr(ri._PostHandler, 'timeout', 0.3)
    assert raw_post(server.port, head, GOOD_JSON) == b'HTTP/1.0 400 Bad Request'
    assert [e.reason for e in server.drain()] == ['truncated_body', 'truncated_body']
    # a Content-Length that is not plain digits is no length ('1_1' is 11 to Python's int)
    assert raw_post(server.port, b'Content-Length: 1_1\r\n', b'{"a": 12345}') == \
        b'HTTP/1.0 411 Length Required'


def test_clients_that_hang_up_are_counted_without_a_traceback(server, capfd):
    for _ in range(5):
        c = socket.create_connection(('127.0.0.1', server.port), timeout=5.0)
        c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
        c.sendall(b'POST / HTTP/1.1\r\nContent-Length: 100\r\n\r\n{"tStamp"')
        c.close()                                   # reset: nobody reads the reply
    assert wait_for(lambda: server.snapshot()[2].get('client_disconnects', 0) >= 5), \
        server.snapshot()
    assert 'Traceback' not in capfd.readouterr().err
    assert len(server.logged) == 1 and 'client_disconnects' in server.logged[0]
    assert raw_post(server.port, b'Content-Length: %d\r\n' % len(GOOD_JSON), GOOD_JSON) == \
        b'HTTP/1.0 200 OK'                          # still serving


def test_a_client_silent_within_its_headers_is_counted(server, monkeypatch):
    # http.server handles that timeout itself: it was counted nowhere.
    monkeypatch.setattr(ri._PostHandler, 'timeout', 0.3)
    with socket.create_connection(('127.0.0.1', server.port), timeout=5.0) as c:
        c.sendall(b'POST / HTTP/1.1\r\nContent-Len')
        assert wait_for(lambda: server.snapshot()[2].get('client_disconnects', 0) == 1), \
            server.snapshot()
    assert len(server.logged) == 1 and 'timed out' in server.logged[0]


def test_post_connections_are_capped_and_a_trickling_client_is_cut(monkeypatch):
    """Each connection held a thread for as long as its client sent a byte within the read
    timeout: idle or trickling clients could open threads without end."""
    srv = ri.JsonPostServer('127.0.0.1', 0, max_connections=2, deadline_s=0.6).start()
    srv.logged = []
    srv.log = srv.logged.append
    try:
        idle = [socket.create_connection(('127.0.0.1', srv.port), timeout=5.0)
                for _ in range(2)]
        assert wait_for(lambda: len(srv._httpd._open) == 2)
        with socket.create_connection(('127.0.0.1', srv.port), timeout=5.0) as third:
            assert third.recv(10) == b''                        # closed unread
        assert srv.snapshot()[2]['connections_refused'] == 1
        for c in idle:
            c.close()
        assert wait_for(lambda: not srv._httpd._open)
        with socket.create_connection(('127.0.0.1', srv.port), timeout=5.0) as slow:
            slow.setblocking(False)
            sent = 0
            with pytest.raises(OSError):
                for byte in b'POST / HTTP/1.1\r\nX-Padding: ' + b'x' * 100:
                    slow.sendall(bytes([byte]))           # a byte every 0.05 s: within the
                    sent += 1                             # 5 s read timeout, never idle
                    if select.select([slow], [], [], 0.05)[0] and slow.recv(1) == b'':
                        raise ConnectionResetError('closed by the server')
            assert sent < 117                             # cut before it was done
        assert wait_for(lambda: srv.snapshot()[2].get('slow_clients') == 1), srv.snapshot()
        assert raw_post(srv.port, b'Content-Length: %d\r\n' % len(GOOD_JSON), GOOD_JSON) == \
            b'HTTP/1.0 200 OK'                                  # still serving
        assert any('connections_refused' in line for line in srv.logged)
        assert any('slow_clients' in line for line in srv.logged)
    finally:
        srv.stop()


def test_a_connection_whose_thread_cannot_start_frees_its_slot(monkeypatch):
    """The slot was taken before the thread started: a failed start (the thread limit) kept
    it for ever, and after max_connections such failures every client was refused."""
    import socketserver
    srv = ri.JsonPostServer('127.0.0.1', 0, max_connections=1).start()
    srv.log = lambda text: None
    try:
        def no_thread(self, request, client_address):
            raise RuntimeError("can't start new thread")
        with monkeypatch.context() as m:
            m.setattr(socketserver.ThreadingMixIn, 'process_request', no_thread)
            with socket.create_connection(('127.0.0.1', srv.port), timeout=5.0) as c:
                assert c.recv(10) == b''                    # dropped, and counted
            assert wait_for(lambda: srv.snapshot()[2].get('request_errors') == 1)
        assert not srv._httpd._open
        assert raw_post(srv.port, b'Content-Length: %d\r\n' % len(GOOD_JSON), GOOD_JSON) == \
            b'HTTP/1.0 200 OK'
    finally:
        srv.stop()


def test_unbindable_post_address_names_post_address(monkeypatch):
    with pytest.raises(ValueError) as e:            # TEST-NET-1: never this machine's
        ri.make_source('kraken_json_post', post_address='192.0.2.1', post_port=0)
    assert str(e.value).startswith('post_address: ')

    def no_such_host(*args, **kwargs):
        raise socket.gaierror(socket.EAI_NONAME, 'Name or service not known')
    monkeypatch.setattr(ri.socket, 'getaddrinfo', no_such_host)
    with pytest.raises(ValueError) as e:
        ri.make_source('kraken_json_post', post_address='not_a_host', post_port=0)
    assert str(e.value).startswith('post_address: ') and 'not_a_host' in str(e.value)


# ------------------------------------------------------------------ recorded CSV files

def poll_until_quiet(tail, now_s=None, polls=50):
    """Poll ``polls`` times (a file input is polled forever); return the queued results."""
    for _ in range(polls):
        tail.poll(now_s)
    return tail.drain(10 ** 6)


@pytest.mark.parametrize('end', ['\n', '\r\n', '\r'])
def test_every_line_end_is_a_line_end(tmp_path, end):
    """Lines ending in a lone CR were never complete: nothing was read, and the file was
    taken as truncated and read again at every poll."""
    path = tmp_path / 'mydata.csv'
    path.write_bytes(''.join(csv_line(T0_MS + 1000 * i, 'Zürich', end)
                             for i in range(20)).encode())
    t = ri.CsvFileTail(path)
    got = poll_until_quiet(t)
    assert [r.stamp_ns for r in got] == [(T0_MS + 1000 * i) * 10 ** 6 for i in range(20)]
    assert all(r.station_id == 'Zürich' for r in got)
    assert t.counts['lines'] == 20 and 'truncated' not in t.counts


def test_a_lone_cr_inside_a_file_does_not_loop_it(tmp_path):
    path = tmp_path / 'mydata.csv'
    good = [csv_line(T0_MS + 1000 * i) for i in range(23)]
    path.write_bytes((''.join(good[:3]) + 'junk\rjunk\n' + ''.join(good[3:])).encode())
    t = ri.CsvFileTail(path)
    got = poll_until_quiet(t)
    assert [getattr(r, 'reason', 'record') for r in got] == \
        ['record'] * 3 + ['malformed_csv'] * 2 + ['record'] * 20
    assert 'truncated' not in t.counts
    with open(path, 'ab') as f:                     # followed on: appended lines are read
        f.write(csv_line(T0_MS + 99_000).encode())
    [r] = poll_until_quiet(t)
    assert r.stamp_ns == (T0_MS + 99_000) * 10 ** 6 and 'truncated' not in t.counts


def test_a_file_rewritten_in_place_is_read_again_from_its_start(tmp_path):
    # The new recording is already longer than what was read: before, the tail went on
    # from its old offset, losing the new file's first lines (or cutting one in two).
    path = tmp_path / 'mydata.csv'
    path.write_bytes(''.join(csv_line(T0_MS + 1000 * i) for i in range(10)).encode())
    t = ri.CsvFileTail(path)
    assert len(poll_until_quiet(t)) == 10
    with open(path, 'r+b') as f:                    # same inode, truncated and rewritten
        f.truncate(0)
        f.write(''.join(csv_line(T0_MS + 500_000 + 1000 * i, 'valley')
                        for i in range(30)).encode())
    got = poll_until_quiet(t)
    assert [r.stamp_ns for r in got] == [(T0_MS + 500_000 + 1000 * i) * 10 ** 6
                                         for i in range(30)]
    assert t.counts['truncated'] == 1 and 'reopened' not in t.counts


def test_a_file_missing_at_start_up_is_read_from_its_start(tmp_path):
    # Also without file_from_start: it was opened at its end when it appeared.
    path = tmp_path / 'later.csv'
    t = ri.CsvFileTail(path, from_start=False)
    assert poll_until_quiet(t) == [] and t.state == 'missing'
    path.write_bytes(''.join(csv_line(T0_MS + 1000 * i) for i in range(6)).encode())
    assert len(poll_until_quiet(t)) == 6


def test_a_line_that_is_not_utf8_is_malformed_and_the_others_are_read(tmp_path):
    path = tmp_path / 'mydata.csv'
    path.write_bytes(b'\xef\xbb\xbf' + csv_line(T0_MS).encode()
                     + csv_line(T0_MS + 1000, 'h\xe9lltop').encode('latin-1')
                     + b'\xff\xfe\x00garbage\n' + csv_line(T0_MS + 2000).encode())
    got = poll_until_quiet(ri.CsvFileTail(path))
    assert [r.reason if isinstance(r, kraken.KrakenError) else r.station_id
            for r in got] == ['hilltop', 'malformed_csv', 'malformed_csv', 'hilltop']
    assert 'not UTF-8' in str(got[1])


def test_a_line_without_end_is_capped_and_skipped(tmp_path):
    """A 300 MB line without a newline was kept whole in memory (631 MB)."""
    path = tmp_path / 'mydata.csv'
    chunk = b'A' * (1 << 20)
    with open(path, 'wb') as f:
        f.write(csv_line(T0_MS).encode())
        for _ in range(8):
            f.write(chunk)
    t = ri.CsvFileTail(path)
    got = poll_until_quiet(t, polls=3)
    assert [getattr(r, 'reason', 'record') for r in got] == ['record', 'too_large']
    assert len(t._buf) <= ri.MAX_LINE_BYTES + ri._READ_BYTES
    with open(path, 'ab') as f:                     # more of the same line: still one
        f.write(chunk)
        f.write(b'\r\n' + csv_line(T0_MS + 1000).encode())
    [r] = poll_until_quiet(t, polls=3)
    assert r.stamp_ns == (T0_MS + 1000) * 10 ** 6
    assert t.counts['lines'] == 3


def test_paced_replay_restarts_with_a_replaced_or_truncated_file(tmp_path):
    """The pace was anchored at the first reading ever released: after the file was
    replaced by the next day's recording, its lines were due a day later."""
    path = tmp_path / 'mydata.csv'
    path.write_text(''.join(csv_line(T0_MS + 100 * i) for i in range(3)))
    t = ri.CsvFileTail(path, rate=1.0)
    assert t.poll(now_s=100.0) == 1
    assert t.poll(now_s=100.2) == 2
    day = T0_MS + 86_400_000
    os.replace(path, tmp_path / 'old.csv')
    path.write_text(''.join(csv_line(day + 100 * i) for i in range(3)))
    assert t.poll(now_s=100.3) == 1 and t.counts['reopened'] == 1
    assert t.poll(now_s=100.35) == 0                # then at the recorded pace again
    assert t.poll(now_s=100.4) == 1
    with open(path, 'w') as f:                      # truncated and rewritten: a day back
        f.write(csv_line(T0_MS))
    assert t.poll(now_s=100.45) == 0 and t.counts['truncated'] == 1
    assert t.poll(now_s=100.5) == 2                 # the last old line, then the new one
    assert 'replay_jumps' not in t.counts           # the restarts are not gaps
    assert [r.stamp_ns // 10 ** 6 for r in t.drain()] == \
        [T0_MS, T0_MS + 100, T0_MS + 200, day, day + 100, day + 200, T0_MS]


def test_paced_replay_never_waits_for_an_absurd_stamp(tmp_path):
    """One line stamped far in the future held every later line for good."""
    path = tmp_path / 'mydata.csv'
    far = T0_MS + 10 ** 9                           # 11.6 days later
    stamps = [T0_MS, T0_MS + 1000, far, T0_MS + 2000, T0_MS + 3000]
    path.write_text(''.join(csv_line(s) for s in stamps))
    t = ri.CsvFileTail(path, rate=1.0)
    assert t.poll(now_s=100.0) == 1
    assert t.poll(now_s=100.5) == 0
    assert t.poll(now_s=101.0) == 3                 # t0 + 1 s, far, and back: at once
    assert t.counts['replay_jumps'] == 2
    assert t.poll(now_s=101.5) == 0                 # the pace restarted at t0 + 2 s
    assert t.poll(now_s=102.0) == 1
    assert [r.stamp_ns // 10 ** 6 for r in t.drain()] == stamps
    gap = T0_MS + 3000 + int(1000 * ri.MAX_REPLAY_GAP_S) + 1   # just over the limit, then
    with open(path, 'a') as f:                                # one at it: waited for
        f.write(csv_line(gap) + csv_line(gap + int(1000 * ri.MAX_REPLAY_GAP_S)))
    assert t.poll(now_s=103.0) == 1 and t.counts['replay_jumps'] == 3
    assert t.poll(now_s=103.0 + ri.MAX_REPLAY_GAP_S - 0.5) == 0
    assert t.poll(now_s=103.0 + ri.MAX_REPLAY_GAP_S) == 1


def test_paced_replay_reads_no_further_than_its_queue(tmp_path):
    path = tmp_path / 'mydata.csv'
    path.write_text(''.join(csv_line(T0_MS + 1000 * i) for i in range(1200)))
    t = ri.CsvFileTail(path, rate=1.0, queue_size=10)
    for _ in range(5):
        t.poll(now_s=100.0)
    assert t.counts['lines'] == ri.FILE_LINES_PER_POLL


# ------------------------------------------------------------------ KrakenInput

class _Queue(ri._Source):
    def __init__(self, items):
        super().__init__()
        self._put(items)


def test_receiver_stamps_in_the_future_are_rejected_and_do_not_poison_the_stream():
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0])
    now = (T0_MS + 5000) * 10 ** 6
    recs = [kraken.parse_json(GOOD_JSON.replace(b'1700000002500', str(ms).encode()))
            for ms in (T0_MS, 2_130_000_000_000, T0_MS + 30_000 + 5000, T0_MS + 1000)]
    ki = ri.KrakenInput(_Queue(recs), cfg, stamp='receiver', max_age_s=60.0)
    bearings, rejected = ki.poll(now)
    assert [b.stamp_ns // 10 ** 6 for _, b in bearings] == [T0_MS, T0_MS + 1000]
    assert [r for r, _ in rejected] == ['future_time', 'future_time']
    assert ki.times.resets == 0


def test_a_receiver_clock_reset_to_1970_is_refused_not_published():
    # A receiver board without a real-time clock reboots: its TIME restarts near 1970 until
    # GPS or NTP sets it. Those bearings would carry a 1970 stamp (the fusion drops them as
    # too old); they are refused, and the stream carries on once the clock is set again.
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0])
    now = (T0_MS + 5000) * 10 ** 6
    times = (T0_MS, 12_000, 13_000, T0_MS + 2000, T0_MS + 3000)
    recs = [kraken.parse_json(GOOD_JSON.replace(b'1700000002500', str(ms).encode()))
            for ms in times]
    ki = ri.KrakenInput(_Queue(recs), cfg, stamp='receiver')
    bearings, rejected = ki.poll(now)
    assert [b.stamp_ns // 10 ** 6 for _, b in bearings] == [T0_MS, T0_MS + 2000, T0_MS + 3000]
    assert [r for r, _ in rejected] == ['unset_clock'] * 2
    assert 'before 2000-01-01' in rejected[0][1] and ki.times.resets == 0
    # The same unset frame polled again is a duplicate (a poller counts it as unchanged),
    # not one more refusal.
    ki = ri.KrakenInput(_Queue(recs[1:2] * 3), cfg, stamp='receiver')
    _, rejected = ki.poll(now)
    assert [r for r, _ in rejected] == ['unset_clock', 'duplicate_time', 'duplicate_time']
    # Stamped on receipt, the receiver's clock does not matter (its jump back is a reset).
    ki = ri.KrakenInput(_Queue(recs), cfg, stamp='receive')
    bearings, rejected = ki.poll(now)
    assert len(bearings) == 5 and rejected == [] and ki.times.resets == 1


def test_max_age_with_receive_stamps_is_refused():
    cfg = receiver_config('rx', position=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match='^max_age: '):
        ri.KrakenInput(_Queue([]), cfg, stamp='receive', max_age_s=5.0)
    ri.KrakenInput(_Queue([]), cfg, stamp='receive')


# ------------------------------------------------------------------ the user docs

SOURCE_KEYS = ('requests', 'timeout', 'unreachable', 'http_status', 'http_error',
               'internal_error', 'slow', 'recoveries', 'client_disconnects', 'request_errors',
               'connections_refused', 'slow_clients',
               'lines', 'missing', 'reopened', 'truncated', 'replay_jumps', 'queue_overflow')
REASONS = ('future_time', 'stale_time', 'truncated_body', 'no_clock', 'too_large',
           'malformed_csv', 'bad_number', 'unset_clock')


def test_every_counter_and_reason_of_the_inputs_is_documented():
    """receivers.md named ``kraken_source_timeouts`` (the key is ``_timeout``) and left out
    http_error, queue_overflow and the file counters."""
    here = os.path.dirname(os.path.abspath(__file__))
    with open(os.path.join(here, '..', 'docs', 'receivers.md'), encoding='utf-8') as f:
        text = f.read()
    src = inspect.getsource(ri)
    for key in SOURCE_KEYS:
        assert f"'{key}'" in src, key                      # a counter the code keeps
        assert f'`kraken_source_{key}`' in text, key
    assert 'kraken_source_timeouts' not in text and '`kraken_time_resets`' in text
    for reason in REASONS:
        assert f'`{reason}`' in text, reason
