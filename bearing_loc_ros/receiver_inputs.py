"""Station inputs for KrakenSDR receivers: HTTP polling, JSON POST, recorded CSV (no rclpy).

The I/O never blocks the caller (a ROS timer): network reads run in worker threads that put
parsed results in bounded queues; the node's timer drains them. Each source keeps counters
and a state for ``/diagnostics`` and recovers by itself:

* :class:`HttpPoller`: GET the receiver's ``doa.xml`` (``fmt='xml'``) or ``DOA_value.html``
  (``fmt='csv'``) every ``period_s`` from the one URL the user configured, with a timeout;
  redirects are refused (no other host is ever contacted) and environment proxies ignored.
  After a failure (connection, timeout, HTTP status, a reply that is not HTTP) the next
  attempt waits period·2^k (k consecutive failures, at most ``max_backoff_s``); the first
  success resets it (state ``ok``, ``recoveries`` counted). Nothing stops the polling
  thread: an unexpected error is counted (``internal_error``), logged and retried.
* :class:`JsonPostServer`: an HTTP server (stdlib ``http.server``, one thread per request)
  bound to ``127.0.0.1`` by default, accepting the receiver's JSON POST on any path; 200 for
  a parsed reading, 400 with the rejection reason (``truncated_body`` when the client sent
  less than its Content-Length), 411 without a Content-Length, 413 over the size limit, 405
  for other methods. Clients that disconnect are counted, not reported with a traceback. At
  most :data:`MAX_POST_CONNECTIONS` connections are served at once (more are closed at
  once, ``connections_refused``) and each at most :data:`POST_DEADLINE_S` (then it is shut
  down, ``slow_clients``): clients that trickle bytes cannot hold threads without end.
* :class:`CsvFileTail`: a recorded "Kraken App" CSV file read from the start (or its end)
  and followed while it grows (tail); a truncated or replaced file is read again from the
  start, a missing one is waited for. Lines end with LF, CR LF or a lone CR; a line over
  :data:`MAX_LINE_BYTES` is skipped to its end (one ``too_large``). ``rate`` > 0 replays
  the lines at ``rate`` × their recorded pace (:data:`MAX_REPLAY_GAP_S`).

:class:`KrakenInput` ties one source to the receiver geometry (:mod:`..core.receiver`) and
the channel map (:mod:`..core.kraken`): records -> per-channel core bearings, with every
rejection counted by reason.
"""

from collections import Counter, deque
import codecs
import errno
import http.client
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
import logging
import math
import os
import socket
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request

from .core import kraken
from .core.kraken import KrakenError
from .core.receiver import ReceiverGeometry
from .log_throttle import Throttle

MODES = ('kraken_xml_http', 'kraken_csv_http', 'kraken_json_post', 'kraken_csv_file')
STAMPS = ('receiver', 'receive')
QUEUE_SIZE = 1000
MAX_POST_BYTES = 64 * 1024
#: Default TCP port of the JSON POST listener (the station parameter kraken.post_port).
POST_PORT = 8082
#: Connections the JSON POST listener serves at once (a receiver posts one reading at a
#: time); a further one is closed unread and counted ``connections_refused``.
MAX_POST_CONNECTIONS = 16
#: Longest a POST connection may last, s (a reading takes milliseconds); a client still
#: sending then, a byte at a time within the per-read timeout, is shut down
#: (``slow_clients``).
POST_DEADLINE_S = 10.0
#: Lines read from a file per poll (the node polls every few tens of ms).
FILE_LINES_PER_POLL = 500
#: Longest line of a recorded CSV file, bytes (the document limit of the parsers; a real
#: line with its 360-value spectrum is < 4 KiB). A longer one is skipped to its end and
#: counted once as ``too_large``, so memory stays bounded whatever the file holds.
MAX_LINE_BYTES = kraken.MAX_DOCUMENT_BYTES
#: Replay (``rate`` > 0): a reading stamped before the previous one, or more than this many
#: seconds of recorded time after it, is released at once and the pace restarts from it
#: (counted ``replay_jumps``): a gap in the recording, a clock jump or a bad stamp never
#: holds the replay.
MAX_REPLAY_GAP_S = 60.0
#: A source logs one kind of problem at most once per this many seconds (steady clock).
LOG_THROTTLE_S = 10.0
_READ_BYTES = 256 * 1024
#: Marks, in a file's queue of held lines, where a reopened or truncated file restarts.
_RESTART = object()


def _line_end(buf, start):
    """(first index, index after) of the first line end (LF, CR LF or CR) in ``buf`` at or
    after ``start``, or None. A CR LF cut between two reads ends the line at the CR and
    leaves a blank line (skipped)."""
    lf = buf.find(b'\n', start)
    cr = buf.find(b'\r', start, len(buf) if lf < 0 else lf)
    if cr >= 0:
        return cr, cr + 2 if buf[cr + 1:cr + 2] == b'\n' else cr + 1
    return None if lf < 0 else (lf, lf + 1)


class _Source:
    """Shared state of an input source: a bounded result queue and counters (thread-safe).

    ``log`` (a callable taking one line of text; Python logging by default, the node sets
    its own logger) receives the source's warnings, at most one per kind every
    :data:`LOG_THROTTLE_S` s.
    """

    def __init__(self, queue_size=QUEUE_SIZE):
        self._lock = threading.Lock()
        self._queue = deque()
        self._queue_size = int(queue_size)
        self.counts = Counter()
        self.state = 'starting'
        self.last_error = ''
        self.log = logging.getLogger(__name__).warning
        self._throttle = Throttle(LOG_THROTTLE_S)

    def _warn(self, kind, text):
        """Log ``text`` unless a ``kind`` warning was logged less than LOG_THROTTLE_S ago."""
        if self._throttle.allow(kind) is None:
            return
        try:
            self.log(text)
        except Exception:   # noqa: BLE001 - a broken logger must not stop an input
            pass

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
    """The URL if it is http(s)://host[:port]/path (port 1-65535 when given), else
    ValueError naming the problem."""
    try:
        parts = urllib.parse.urlsplit(url)
        port = parts.port
    except ValueError as exc:   # a port that is not a number in 0-65535, a bad IPv6 host
        raise ValueError(f'{url!r} is not a valid URL ({exc})') from None
    if parts.scheme not in ('http', 'https') or not parts.hostname:
        raise ValueError(f'{url!r} is not an http:// or https:// URL with a host')
    if port == 0:
        raise ValueError(f'{url!r}: port 0 cannot be polled (a port is 1 to 65535)')
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
            self.last_error = f'{key}: {" ".join(str(detail).split())}'[:200]   # one line

    def poll_once(self):
        """One GET + parse; returns the delay before the next one (s)."""
        t0 = time.monotonic()
        self._count('requests')
        try:
            with self._opener.open(self.url, timeout=self.timeout_s) as resp:
                body = resp.read(kraken.MAX_DOCUMENT_BYTES + 1)
                announced = (resp.headers.get('Content-Length') or '').strip()
            if announced.isascii() and announced.isdigit() and len(body) < min(
                    int(announced), kraken.MAX_DOCUMENT_BYTES + 1):
                raise http.client.IncompleteRead(body[:40], int(announced) - len(body))
        except urllib.error.HTTPError as exc:
            self._fail('http_status', f'HTTP {exc.code} {exc.reason}')
        except urllib.error.URLError as exc:
            reason = exc.reason
            key = 'timeout' if isinstance(reason, TimeoutError) else 'unreachable'
            self._fail(key, str(reason))
        except TimeoutError as exc:
            self._fail('timeout', str(exc) or 'timed out')
        except (OSError, ValueError, http.client.HTTPException) as exc:
            # reset connections; replies that are not HTTP (BadStatusLine), cut short
            # (IncompleteRead) or with too many headers
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
            try:
                delay = self.poll_once()
            except Exception as exc:   # noqa: BLE001 - last resort: the thread keeps polling
                detail = f'{type(exc).__name__}: {exc}'
                self._fail('internal_error', detail)
                self._warn('internal_error', f'receiver poll of {self.url} failed: '
                                             f'{detail[:200]} (retrying)')
                delay = min(self.period_s * 2 ** min(self.failures, 20), self.max_backoff_s)
            self._stop.wait(delay)


class _PostHandler(BaseHTTPRequestHandler):
    server_version = 'bearing_loc'
    timeout = 5.0            # a stalled client cannot hold a thread longer

    def log_message(self, *args):   # silence the default stderr access log
        pass

    def log_error(self, fmt, *args):
        """http.server's own errors (a client silent within its headers, a malformed
        request line): counted and logged as :meth:`_Server.handle_error` does."""
        kind = 'client_disconnects' if fmt.startswith('Request timed out') else \
            'request_errors'
        src = self.server.source
        src._count(kind)
        src._warn(kind, f'JSON POST listener: request from {self.client_address[0]}: '
                        f'{(fmt % args)[:120]} (counted as {kind})')

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
        text = (self.headers.get('Content-Length') or '').strip()
        length = int(text) if text.isascii() and text.isdigit() else -1
        if length < 0:
            src._put([KrakenError('malformed_json', 'no Content-Length' if not text else
                                  f'Content-Length {text[:20]!r} is not a byte count')])
            self._reply(411, 'length required')
            return
        if length > src.max_body:
            src._put([KrakenError('too_large', f'{length} bytes')])
            self._reply(413, 'too large')
            return
        try:
            data = self.rfile.read(length)
        except OSError as exc:      # the client went silent (timeout) or reset
            data, why = b'', type(exc).__name__
        else:
            why = f'{len(data)} of {length} bytes'
        if len(data) < length:
            src._put([KrakenError('truncated_body', f'body shorter than its Content-Length '
                                                    f'({why})')])
            self.close_connection = True
            self._reply(400, 'truncated_body')
            return
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

    def server_activate(self):
        super().server_activate()
        self._open = {}                 # connection socket -> steady time it was accepted
        self._open_lock = threading.Lock()

    def process_request(self, request, client_address):
        """Serve the connection in a thread, unless :data:`MAX_POST_CONNECTIONS` are open."""
        with self._open_lock:
            full = len(self._open) >= self.source.max_connections
            if not full:
                self._open[request] = time.monotonic()
        if full:
            src = self.source
            src._count('connections_refused')
            src._warn('connections_refused', f'JSON POST listener: {len(self._open)} '
                      f'connections open, one from {client_address[0]} closed '
                      f'(counted as connections_refused)')
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:       # no thread (e.g. the thread limit): the slot is free
            with self._open_lock:
                self._open.pop(request, None)
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._open_lock:
                self._open.pop(request, None)

    def service_actions(self):
        """Every poll of serve_forever: shut down connections open longer than the
        deadline (their thread's blocked read then returns and the thread ends)."""
        limit = time.monotonic() - self.source.deadline_s
        with self._open_lock:
            late = [r for r, t in self._open.items() if t < limit]
            for r in late:
                self._open[r] = math.inf        # shut down once
        for r in late:
            self.source._count('slow_clients')
            self.source._warn('slow_clients', f'JSON POST listener: a connection open longer '
                              f'than {self.source.deadline_s:g} s shut down (counted as '
                              f'slow_clients)')
            try:
                r.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def handle_error(self, request, client_address):
        """A request failed: count it and log one throttled line (no traceback). A client
        that disconnected or went silent is ``client_disconnects``, anything else
        ``request_errors``."""
        exc = sys.exc_info()[1]
        src = self.source
        kind = ('client_disconnects' if isinstance(exc, (ConnectionError, TimeoutError))
                else 'request_errors')
        src._count(kind)
        src._warn(kind, f'JSON POST listener: request from {client_address[0]} failed: '
                        f'{type(exc).__name__}: {str(exc)[:120]} (counted as {kind})')


class _Server6(_Server):
    address_family = socket.AF_INET6


class JsonPostServer(_Source):
    """Accept the receiver's JSON POSTs on ``address:port`` (module docstring).

    ``address`` is a host name or an IPv4/IPv6 address. Raises OSError when it does not
    resolve or cannot be bound (``errno`` EADDRNOTAVAIL: not an address of this machine),
    or the port is taken.
    """

    def __init__(self, address='127.0.0.1', port=POST_PORT, max_body=MAX_POST_BYTES,
                 queue_size=QUEUE_SIZE, max_connections=MAX_POST_CONNECTIONS,
                 deadline_s=POST_DEADLINE_S):
        super().__init__(queue_size)
        self.address = address
        self.max_body = int(max_body)
        self.max_connections = int(max_connections)
        self.deadline_s = float(deadline_s)
        family = socket.getaddrinfo(address, int(port), type=socket.SOCK_STREAM)[0][0]
        server = _Server6 if family == socket.AF_INET6 else _Server
        self._httpd = server((address, int(port)), _PostHandler)   # OSError if not bindable
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


#: Bytes at the start of a followed file compared at every poll to notice a rewrite in
#: place (a recorder that truncates and writes a new recording to the same file).
_HEAD_BYTES = 256


class CsvFileTail(_Source):
    """Read a "Kraken App" CSV recording and follow it while it grows (module docstring).

    Non-blocking: :meth:`poll` reads what is there (at most ``FILE_LINES_PER_POLL`` lines,
    and nothing while ``queue_size`` parsed lines wait for their replay time). The file is
    read as bytes: a line ends at LF, CR LF or a lone CR, and each line is decoded as UTF-8
    (a line that is not is ``malformed_csv``); an incomplete last line is kept until its end
    arrives, up to :data:`MAX_LINE_BYTES` (then it is skipped to its end, one
    ``too_large``). ``rate`` > 0 releases each reading ``(stamp − previous stamp) / rate``
    seconds (steady clock) after the previous one; a reading stamped before the previous
    one or more than :data:`MAX_REPLAY_GAP_S` after it is released at once and the pace
    restarts from it (``replay_jumps``), and so does the first reading of a reopened or
    truncated file.
    """

    def __init__(self, path, from_start=True, rate=0.0, queue_size=QUEUE_SIZE):
        super().__init__(queue_size)
        self.path = os.fspath(path)
        self.from_start = bool(from_start)
        self.rate = float(rate)
        self._f = None
        self._ino = None
        self._buf = b''           # bytes read after the last line end
        self._head = b''          # the file's first bytes, to notice a rewrite in place
        self._skip = False        # skipping to the end of a line (too long, or cut at open)
        self._pace = None         # (steady s, stamp ns) of the last released record
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

    def _restart(self):
        """Read from the file's current position as a new file: no partial line, and the
        replay pace restarts at the next reading."""
        self._buf, self._skip = b'', False
        self._held.append(_RESTART)

    def _open(self, at_start):
        try:
            f = open(self.path, 'rb')
        except OSError as exc:
            if self.state != 'missing':
                self._count('missing')
            self.state, self.last_error = 'missing', f'{exc.strerror}: {self.path}'
            return False
        self._f, self._ino = f, os.fstat(f.fileno()).st_ino
        self._head = b''
        self._restart()
        if not at_start:
            end = f.seek(0, os.SEEK_END)
            if end:   # the recorder may be inside a line: skip to its end
                f.seek(end - 1)
                self._skip = f.read(1) not in (b'\n', b'\r')
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
        elif st.st_size < self._f.tell() or not self._same_head():
            # Made shorter, or rewritten in place (its first bytes changed) even when the
            # new text is already longer than what was read: read again from its start.
            self._count('truncated')
            self._f.seek(0)
            self._head = b''
            self._restart()

    def _same_head(self):
        """True while the file's first bytes (up to :data:`_HEAD_BYTES`) are those seen
        before; the kept copy grows with the file until it is that long."""
        try:
            head = os.pread(self._f.fileno(), _HEAD_BYTES, 0)
        except OSError:
            return True
        if not head.startswith(self._head):
            return False
        self._head = head
        return True

    @staticmethod
    def _decode(line):
        if line.startswith(codecs.BOM_UTF8):
            line = line[len(codecs.BOM_UTF8):]
        try:
            return line.decode('utf-8')
        except UnicodeDecodeError:
            return KrakenError('malformed_csv', 'not UTF-8 text')

    def _read_lines(self):
        """New complete lines: str, '' for a blank one, or a KrakenError (not UTF-8, too
        long); at most FILE_LINES_PER_POLL."""
        if self._f is None and not self._open(self.from_start or self._ino is not None
                                              or self.state == 'missing'):
            return []
        self._check_replaced()
        if self._f is None and not self._open(True):
            return []
        lines, buf, start = [], self._buf, 0
        while len(lines) < FILE_LINES_PER_POLL:
            end = _line_end(buf, start)
            if end is not None:
                if self._skip:
                    self._skip = False
                else:
                    lines.append(self._decode(buf[start:end[0]]))
                start = end[1]
                continue
            buf, start = (b'' if self._skip else buf[start:]), 0
            if len(buf) > MAX_LINE_BYTES:
                lines.append(KrakenError('too_large', f'CSV line longer than {MAX_LINE_BYTES} '
                                                      'bytes (skipped to its end)'))
                buf, self._skip = b'', True
            data = self._f.read(_READ_BYTES)
            if not data:
                break
            buf += data
        self._buf = buf[start:]
        return lines

    def poll(self, now_s=None):
        """Read new lines, parse them, queue the results that are due; return how many.

        ``now_s``: steady clock, s (default ``time.monotonic()``), for ``rate`` > 0.
        """
        if len(self._held) < self._queue_size:
            for line in self._read_lines():
                if isinstance(line, KrakenError):
                    self._count('lines')
                    self._held.append(line)
                elif line.strip():
                    self._count('lines')
                    try:
                        self._held.append(kraken.parse_csv_line(line))
                    except KrakenError as exc:
                        self._held.append(exc)
        now_s = time.monotonic() if now_s is None else now_s
        due = []
        while self._held:
            item = self._held[0]
            if item is _RESTART:
                self._held.popleft()
                self._pace = None
                continue
            if self.rate > 0.0 and isinstance(item, kraken.KrakenRecord):
                if self._pace is None:
                    self._pace = (now_s, item.stamp_ns)
                else:
                    gap_s = (item.stamp_ns - self._pace[1]) / 1e9
                    if 0.0 <= gap_s <= MAX_REPLAY_GAP_S:
                        release = self._pace[0] + gap_s / self.rate
                        if now_s < release:
                            break
                        self._pace = (release, item.stamp_ns)
                    else:
                        self._count('replay_jumps')
                        self._pace = (now_s, item.stamp_ns)
            due.append(self._held.popleft())
        self._put(due)
        return len(due)


def make_source(mode, url='', poll_period_s=0.5, timeout_s=2.0, post_address='127.0.0.1',
                post_port=POST_PORT, file_path='', file_from_start=True, file_rate=0.0):
    """The source object of an input ``mode`` (one of :data:`MODES`); ValueError naming the
    parameter (``url``, ``post_address``, ``post_port``, ``file``) when it cannot be built:
    ``post_address`` when the address does not resolve or is not one of this machine's,
    ``post_port`` when the port is taken or not allowed."""
    if mode in ('kraken_xml_http', 'kraken_csv_http'):
        try:
            check_url(url)
        except ValueError as exc:
            raise ValueError(f'url: {exc}') from None
        return HttpPoller(url, 'xml' if mode == 'kraken_xml_http' else 'csv', poll_period_s,
                          timeout_s)
    if mode == 'kraken_json_post':
        where = f'{post_address}:{post_port}'
        try:
            return JsonPostServer(post_address, post_port)
        except (socket.gaierror, UnicodeError) as exc:
            raise ValueError(f'post_address: {post_address!r} does not resolve '
                             f'({getattr(exc, "strerror", None) or exc})') from None
        except OverflowError as exc:
            raise ValueError(f'post_port: cannot listen on {where} ({exc})') from None
        except OSError as exc:
            name = 'post_address' if exc.errno == errno.EADDRNOTAVAIL else 'post_port'
            why = ('not an address of this machine' if name == 'post_address' else
                   exc.strerror or str(exc))
            raise ValueError(f'{name}: cannot listen on {where} ({why})') from None
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
    the stamp is the receiver's ``TIME`` (``stamp='receiver'``; a ``TIME`` before
    ``min_time_ns``, by default 2000-01-01, is an unset receiver clock, ``unset_clock``; 0
    turns the check off, as for a recorded log) or the node clock on receipt (``'receive'``);
    :class:`~bearing_loc_ros.core.kraken.TimeFilter` refuses
    duplicate and out-of-order stamps per (station, channel) — a polled document seen
    again is counted as ``unchanged``, not rejected — and, with ``stamp='receiver'`` and
    ``now_ns`` given, ``TIME`` more than
    :data:`~bearing_loc_ros.core.kraken.MAX_FUTURE_NS` after ``now_ns`` (``future_time``)
    or (``max_age_s`` > 0) more than ``max_age_s`` before it (``stale_time``); the
    platform pose (``pose_at(stamp_ns)``, only when the geometry needs odometry) and
    :meth:`ReceiverGeometry.to_bearing` finish the bearing. ``max_age_s`` > 0 with
    ``stamp='receive'`` is a ValueError: the receiver's clock is then not comparable with
    the node's, and a reading stamped on receipt has no age.
    """

    def __init__(self, source, config, channels=None, stamp='receiver', max_age_s=0.0,
                 receiver_id='', reset_s=60.0, min_time_ns=kraken.MIN_RECEIVER_TIME_NS):
        if stamp not in STAMPS:
            raise ValueError(f'stamp: {stamp!r} is not one of {STAMPS}')
        if stamp == 'receive' and max_age_s > 0.0:
            raise ValueError(f'max_age: {max_age_s:g} s applies only with stamp receiver')
        self.source = source
        self.geometry = ReceiverGeometry(config)
        self.channels = channels or kraken.ChannelMap()
        self.stamp = stamp
        self.receiver_id = receiver_id
        self.times = kraken.TimeFilter(int(max_age_s * 1e9), int(reset_s * 1e9),
                                       kraken.MAX_FUTURE_NS)
        self.min_time_ns = int(min_time_ns)
        self._unset = {}            # (station, channel) -> the last TIME refused as unset
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
        if own and rec.stamp_ns < self.min_time_ns:
            # Before the stream's time checks: the stamps that follow once the clock is set
            # are then neither old nor a reset. The same frame polled again is a duplicate
            # (counted as unchanged for a polled source), not another refusal.
            key = (rec.station_id, channel)
            if self._unset.get(key) == rec.stamp_ns:
                raise KrakenError('duplicate_time', f'{rec.stamp_ns} ns seen already', 'TIME')
            self._unset[key] = rec.stamp_ns
            raise KrakenError('unset_clock', f'TIME {rec.stamp_ns / 1e9:.3f} s is before '
                                             '2000-01-01: the receiver clock is not set',
                              'TIME')
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
