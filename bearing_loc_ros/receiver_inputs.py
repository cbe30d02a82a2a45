"""Station inputs for KrakenSDR receivers: HTTP polling, JSON POST, recorded CSV (no rclpy).

The I/O never blocks the caller (a ROS timer): network reads run in worker threads that put
parsed results in bounded queues; the node's timer drains them. Each source keeps counters
and a state for ``/diagnostics`` and recovers by itself:

* :class:`HttpPoller`: GET the receiver's ``doa.xml`` (``fmt='xml'``) or ``DOA_value.html``
  (``fmt='csv'``) every ``period_s`` from the one URL the user configured, with a timeout;
  redirects are refused (no other host is ever contacted) and environment proxies ignored.
  After a failure the next attempt waits period·2^k (k consecutive failures, at most
  ``max_backoff_s``); the first success resets it (state ``ok``, ``recoveries`` counted).
* :class:`JsonPostServer`: an HTTP server (stdlib ``http.server``, one thread per request)
  bound to ``127.0.0.1`` by default, accepting the receiver's JSON POST on any path; 200 for
  a parsed reading, 400 with the rejection reason, 413 over the size limit, 405 for other
  methods.
* :class:`CsvFileTail`: a recorded "Kraken App" CSV file read from the start (or its end)
  and followed while it grows (tail); a truncated or replaced file is read again from the
  start, a missing one is waited for. ``rate`` > 0 replays the lines at ``rate`` × their
  recorded pace.

:class:`KrakenInput` ties one source to the receiver geometry (:mod:`..core.receiver`) and
the channel map (:mod:`..core.kraken`): records -> per-channel core bearings, with every
rejection counted by reason.
"""

from collections import Counter, deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
import os
import threading
import time
import urllib.error
import urllib.parse
import urllib.request

from .core import kraken
from .core.kraken import KrakenError
from .core.receiver import ReceiverGeometry

MODES = ('kraken_xml_http', 'kraken_csv_http', 'kraken_json_post', 'kraken_csv_file')
STAMPS = ('receiver', 'receive')
QUEUE_SIZE = 1000
MAX_POST_BYTES = 64 * 1024
#: Lines read from a file per poll (the node polls every few tens of ms).
FILE_LINES_PER_POLL = 500


class _Source:
    """Shared state of an input source: a bounded result queue and counters (thread-safe)."""

    def __init__(self, queue_size=QUEUE_SIZE):
        self._lock = threading.Lock()
        self._queue = deque()
        self._queue_size = int(queue_size)
        self.counts = Counter()
        self.state = 'starting'
        self.last_error = ''

    def _put(self, items):
        with self._lock:
            for item in items:
                if len(self._queue) >= self._queue_size:
                    self._queue.popleft()
                    self.counts['queue_overflow'] += 1
                self._queue.append(item)

    def _count(self, key, n=1):
        with self._lock:
            self.counts[key] += n

    def drain(self, max_items=1000):
        """Up to ``max_items`` queued results (KrakenRecord or KrakenError), oldest first."""
        out = []
        with self._lock:
            while self._queue and len(out) < max_items:
                out.append(self._queue.popleft())
        return out

    def snapshot(self):
        """(state, last_error, counters dict) for diagnostics."""
        with self._lock:
            return self.state, self.last_error, dict(self.counts)


#: Source states that mean the receiver cannot be read (logged when entered and left).
FAILED_STATES = ('unreachable', 'error', 'missing')


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, req, fp, code, msg, headers, newurl):
        raise urllib.error.HTTPError(req.full_url, code, 'redirect refused (only the '
                                     'configured URL is polled)', headers, fp)


def check_url(url):
    """The URL if it is http(s)://host[:port]/path, else ValueError naming the problem."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ('http', 'https') or not parts.hostname:
        raise ValueError(f'{url!r} is not an http:// or https:// URL with a host')
    return url


class HttpPoller(_Source):
    """Poll one receiver URL in a worker thread (module docstring)."""

    def __init__(self, url, fmt, period_s=0.5, timeout_s=2.0, max_backoff_s=10.0,
                 queue_size=QUEUE_SIZE):
        super().__init__(queue_size)
        self.url = check_url(url)
        if fmt not in ('xml', 'csv'):
            raise ValueError(f'fmt: {fmt!r} is not xml or csv')
        self.fmt = fmt
        self.period_s = float(period_s)
        self.timeout_s = float(timeout_s)
        self.max_backoff_s = max(float(max_backoff_s), self.period_s)
        self.failures = 0
        self.last_ok = None
        self._opener = urllib.request.build_opener(urllib.request.ProxyHandler({}),
                                                   _NoRedirect())
        self._stop = threading.Event()
        self._thread = None

    def start(self):
        """Start the worker thread (daemon: it never keeps the process alive)."""
        self._thread = threading.Thread(target=self._run, name='kraken-http', daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout=None):
        """Ask the worker to stop and wait for it (at most the HTTP timeout + 1 s)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(self.timeout_s + 1.0 if timeout is None else timeout)

    def _fail(self, key, detail):
        with self._lock:
            self.counts[key] += 1
            self.failures += 1
            self.state = 'unreachable' if key in ('unreachable', 'timeout') else 'error'
            self.last_error = f'{key}: {detail}'[:200]

    def poll_once(self):
        """One GET + parse; returns the delay before the next one (s)."""
        t0 = time.monotonic()
        self._count('requests')
        try:
            with self._opener.open(self.url, timeout=self.timeout_s) as resp:
                body = resp.read(kraken.MAX_DOCUMENT_BYTES + 1)
        except urllib.error.HTTPError as exc:
            self._fail('http_status', f'HTTP {exc.code} {exc.reason}')
        except urllib.error.URLError as exc:
            reason = exc.reason
            key = 'timeout' if isinstance(reason, TimeoutError) else 'unreachable'
            self._fail(key, str(reason))
        except TimeoutError as exc:
            self._fail('timeout', str(exc) or 'timed out')
        except (OSError, ValueError) as exc:   # reset connections, bad status lines
            self._fail('http_error', f'{type(exc).__name__}: {exc}')
        else:
            elapsed = time.monotonic() - t0
            with self._lock:
                if self.failures:
                    self.counts['recoveries'] += 1
                self.failures = 0
                self.state = 'ok'
                self.last_ok = time.monotonic()
                if elapsed > max(self.period_s, 0.5 * self.timeout_s):
                    self.counts['slow'] += 1
                    self.state = 'slow'
            if len(body) > kraken.MAX_DOCUMENT_BYTES:
                self._put([KrakenError('too_large', f'body over {kraken.MAX_DOCUMENT_BYTES} '
                                                    'bytes')])
            else:
                self._put(kraken.parse(body, self.fmt))
        if self.failures:
            return min(self.period_s * 2 ** min(self.failures, 20), self.max_backoff_s)
        return max(0.0, self.period_s - (time.monotonic() - t0))

    def _run(self):
        while not self._stop.is_set():
            delay = self.poll_once()
            self._stop.wait(delay)


class _PostHandler(BaseHTTPRequestHandler):
    server_version = 'bearing_loc'
    timeout = 5.0            # a stalled client cannot hold a thread longer

    def log_message(self, *args):   # silence the default stderr access log
        pass

    def _reply(self, code, text):
        body = (text + '\n').encode('utf-8')
        self.send_response(code)
        self.send_header('Content-Type', 'text/plain; charset=utf-8')
        self.send_header('Content-Length', str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_POST(self):   # noqa: N802 (http.server naming)
        src = self.server.source
        src._count('requests')
        try:
            length = int(self.headers.get('Content-Length', ''))
        except ValueError:
            length = -1
        if length < 0:
            src._put([KrakenError('malformed_json', 'no Content-Length')])
            self._reply(411, 'length required')
            return
        if length > src.max_body:
            src._put([KrakenError('too_large', f'{length} bytes')])
            self._reply(413, 'too large')
            return
        data = self.rfile.read(length)
        result = kraken.parse(data, 'json')[0]
        src._put([result])
        if isinstance(result, KrakenError):
            self._reply(400, result.reason)
        else:
            self._reply(200, 'ok')

    def do_GET(self):   # noqa: N802
        self._reply(405, 'POST a JSON reading')

    do_PUT = do_DELETE = do_GET


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True


class JsonPostServer(_Source):
    """Accept the receiver's JSON POSTs on ``address:port`` (module docstring)."""

    def __init__(self, address='127.0.0.1', port=8081, max_body=MAX_POST_BYTES,
                 queue_size=QUEUE_SIZE):
        super().__init__(queue_size)
        self.address = address
        self.max_body = int(max_body)
        self._httpd = _Server((address, int(port)), _PostHandler)   # OSError if not bindable
        self._httpd.source = self
        self._thread = None
        self.state = 'listening'

    @property
    def port(self):
        """The bound port (the actual one when 0 was asked)."""
        return self._httpd.server_address[1]

    def start(self):
        """Serve in a daemon thread."""
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={
            'poll_interval': 0.2}, name='kraken-post', daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout=2.0):
        """Stop serving and close the socket."""
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join(timeout)
        self._httpd.server_close()


class CsvFileTail(_Source):
    """Read a "Kraken App" CSV recording and follow it while it grows (module docstring).

    Non-blocking: :meth:`poll` reads what is there (at most ``FILE_LINES_PER_POLL`` lines);
    an incomplete last line is kept until its newline arrives. ``rate`` > 0 releases each
    reading when ``rate`` × (steady time since the first) reaches its recorded offset.
    """

    def __init__(self, path, from_start=True, rate=0.0, queue_size=QUEUE_SIZE):
        super().__init__(queue_size)
        self.path = os.fspath(path)
        self.from_start = bool(from_start)
        self.rate = float(rate)
        self._f = None
        self._ino = None
        self._partial = ''
        self._first = None        # (steady s, stamp ns) of the first released record
        self._held = deque()

    def close(self):
        """Close the file."""
        if self._f is not None:
            self._f.close()
            self._f = None

    stop = close

    def start(self):
        """Nothing to start (polled by the caller)."""
        return self

    def _open(self, at_start):
        try:
            f = open(self.path, 'r', encoding='utf-8', errors='replace', newline='')
        except OSError as exc:
            if self.state != 'missing':
                self._count('missing')
            self.state, self.last_error = 'missing', f'{exc.strerror}: {self.path}'
            return False
        self._f, self._ino = f, os.fstat(f.fileno()).st_ino
        if not at_start:
            f.seek(0, os.SEEK_END)
        self._partial = ''
        self.state = 'reading'
        return True

    def _check_replaced(self):
        try:
            st = os.stat(self.path)
        except OSError:
            return
        if st.st_ino != self._ino:
            self._count('reopened')
            self.close()
        elif st.st_size < self._f.tell():
            self._count('truncated')
            self._f.seek(0)
            self._partial = ''

    def _read_lines(self):
        if self._f is None and not self._open(self.from_start or self._ino is not None):
            return []
        self._check_replaced()
        if self._f is None and not self._open(True):
            return []
        lines = []
        while len(lines) < FILE_LINES_PER_POLL:
            chunk = self._f.readline()
            if not chunk:
                break
            if not chunk.endswith('\n'):
                self._partial += chunk
                break
            lines.append(self._partial + chunk)
            self._partial = ''
        return lines

    def poll(self, now_s=None):
        """Read new lines, parse them, queue the results that are due; return how many."""
        for line in self._read_lines():
            if line.strip():
                self._count('lines')
                try:
                    self._held.append(kraken.parse_csv_line(line))
                except KrakenError as exc:
                    self._held.append(exc)
        now_s = time.monotonic() if now_s is None else now_s
        due = []
        while self._held:
            item = self._held[0]
            if self.rate > 0.0 and isinstance(item, kraken.KrakenRecord):
                if self._first is None:
                    self._first = (now_s, item.stamp_ns)
                offset = (item.stamp_ns - self._first[1]) / 1e9 / self.rate
                if now_s - self._first[0] < offset:
                    break
            due.append(self._held.popleft())
        self._put(due)
        return len(due)


def make_source(mode, url='', poll_period_s=0.5, timeout_s=2.0, post_address='127.0.0.1',
                post_port=8081, file_path='', file_from_start=True, file_rate=0.0):
    """The source object of an input ``mode`` (one of :data:`MODES`); ValueError naming the
    parameter (``url``, ``post_port``, ``file``) when it cannot be built."""
    if mode in ('kraken_xml_http', 'kraken_csv_http'):
        try:
            check_url(url)
        except ValueError as exc:
            raise ValueError(f'url: {exc}') from None
        return HttpPoller(url, 'xml' if mode == 'kraken_xml_http' else 'csv', poll_period_s,
                          timeout_s)
    if mode == 'kraken_json_post':
        try:
            return JsonPostServer(post_address, post_port)
        except (OSError, OverflowError) as exc:
            raise ValueError(f'post_port: cannot listen on {post_address}:{post_port} '
                             f'({getattr(exc, "strerror", None) or exc})') from None
    if mode == 'kraken_csv_file':
        if not file_path:
            raise ValueError('file: required with input kraken_csv_file')
        return CsvFileTail(file_path, file_from_start, file_rate)
    raise ValueError(f'input: {mode!r} is not one of {MODES}')


class KrakenInput:
    """One receiver source + its geometry and channels -> per-channel core bearings.

    ``poll(now_ns, pose_at)`` drains the source and returns ``(bearings, rejections)``:
    ``bearings`` a list of (channel, :class:`~bearing_loc_ros.core.bearings.Bearing`),
    ``rejections`` a list of (reason, detail). Steps per reading: parse errors are rejected
    with their reason; ``receiver_id`` (when set) must equal the reading's station id
    (``other_station``); the frequency picks the channel (``no_channel`` when in no band);
    the stamp is the receiver's ``TIME`` (``stamp='receiver'``) or the node clock on
    receipt (``'receive'``); :class:`~bearing_loc_ros.core.kraken.TimeFilter` refuses
    duplicate, out-of-order and (``max_age_s`` > 0) stale stamps per (station, channel) —
    a polled document seen again is counted as ``unchanged``, not rejected; the platform
    pose (``pose_at(stamp_ns)``, only when the geometry needs odometry) and
    :meth:`ReceiverGeometry.to_bearing` finish the bearing.
    """

    def __init__(self, source, config, channels=None, stamp='receiver', max_age_s=0.0,
                 receiver_id='', reset_s=60.0):
        if stamp not in STAMPS:
            raise ValueError(f'stamp: {stamp!r} is not one of {STAMPS}')
        self.source = source
        self.geometry = ReceiverGeometry(config)
        self.channels = channels or kraken.ChannelMap()
        self.stamp = stamp
        self.receiver_id = receiver_id
        self.times = kraken.TimeFilter(int(max_age_s * 1e9), int(reset_s * 1e9))
        self.counts = Counter()
        self.published = Counter()
        self._reported_state = None

    def start(self):
        """Start the source's worker (if it has one)."""
        self.source.start()
        return self

    def stop(self):
        """Stop the source (joins its thread, closes sockets and files)."""
        self.source.stop()

    def poll(self, now_ns, pose_at=None, max_items=1000):
        """Drain the source (class docstring); never raises for bad data."""
        if isinstance(self.source, CsvFileTail):
            self.source.poll()
        bearings, rejected = [], []
        for item in self.source.drain(max_items):
            self.counts['readings'] += 1
            try:
                if isinstance(item, KrakenError):
                    raise item
                channel, b = self._bearing(item, now_ns, pose_at)
            except KrakenError as exc:
                if exc.reason == 'duplicate_time' and isinstance(self.source, HttpPoller):
                    self.counts['unchanged'] += 1
                    continue
                rejected.append((exc.reason, str(exc)))
                continue
            except ValueError as exc:   # pose interpolation (ReadingError) or bad bearing
                rejected.append((getattr(exc, 'reason', 'invalid_bearing'), str(exc)))
                continue
            self.published[channel] += 1
            bearings.append((channel, b))
        return bearings, rejected

    def _bearing(self, rec, now_ns, pose_at):
        if self.receiver_id and rec.station_id != self.receiver_id:
            raise KrakenError('other_station', f'station id {rec.station_id!r}, expected '
                                               f'{self.receiver_id!r}', 'station_id')
        channel = self.channels.channel_of(rec.frequency_hz)
        if channel is None:
            raise KrakenError('no_channel', f'{rec.frequency_hz / 1e6:.6f} MHz is in no '
                                            'configured channel band', 'frequency')
        own = self.stamp == 'receiver'
        self.times.check((rec.station_id, channel), rec.stamp_ns, now_ns if own else None)
        stamp = rec.stamp_ns if own else int(now_ns)
        if stamp <= 0:
            raise KrakenError('no_clock', 'node clock is 0 (no /clock yet?)')
        pose = None
        if self.geometry.config.needs_odometry:
            pose = pose_at(stamp) if pose_at is not None else None
        b = self.geometry.to_bearing(rec, pose, stamp_ns=stamp)
        return channel, b.validate()

    def state_change(self):
        """(state, last error) when the source's state moved into or out of a failure
        (:data:`FAILED_STATES`: unreachable, error, a missing file) since the last call, else
        None: what the node logs (the counters stay in /diagnostics)."""
        state, last_error, _ = self.source.snapshot()
        failed = state in FAILED_STATES
        was = self._reported_state in FAILED_STATES
        if state == self._reported_state or (not failed and not was):
            self._reported_state = state
            return None
        self._reported_state = state
        return state, last_error

    def status(self):
        """(state, message, values) for the station's DiagnosticStatus: state is the
        source's (``ok``/``slow``/``unreachable``/``error``/``listening``/``reading``/
        ``missing``/``starting``); values hold every counter, prefixed ``kraken_``."""
        state, last_error, counts = self.source.snapshot()
        values = {'kraken_state': state, 'kraken_last_error': last_error}
        values.update({f'kraken_source_{k}': v for k, v in sorted(counts.items())})
        values.update({f'kraken_{k}': v for k, v in sorted(self.counts.items())})
        values.update({f'kraken_{k}': v for k, v in sorted(self.geometry.counts.items())})
        values.update({f'kraken_published_{c or "bearing"}': v
                       for c, v in sorted(self.published.items())})
        if self.times.resets:
            values['kraken_time_resets'] = self.times.resets
        return state, last_error, values
