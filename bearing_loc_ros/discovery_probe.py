"""discovery_probe: watches not-yet-trusted ``<station>/bearing`` topics in a child process.

The fusion node with ``discover`` subscribes for real only to discovered topics that have
delivered a valid bearing. Whether a newly seen topic does is found out here, in a short-lived
process of its own: rclpy and the DDS layer keep part of the reader state of every
subscription a process has made, also after it is destroyed (about 8 MiB after 200 empty
publishers came and went), and that memory goes with this process when it exits.

    python -m bearing_loc_ros.discovery_probe --namespace /ns [--qos-depth 10]
        [--qos-reliability best_effort] [--frame-id map] [--idle 3.0]

Protocol (text lines, UTF-8):

* stdin: ``watch <n> [station ...]``: the complete set of stations to watch now (``n``: a
  sequence number). Topics ``<namespace>/<station>/bearing`` not in the set are unsubscribed
  (their publishers left, or the node subscribed itself). End of input: exit.
* stdout: ``ack <n>`` once command ``n`` is applied; ``valid <station>`` (once per watch)
  when a message on the station's topic was a valid bearing: ``ros_conversions``
  ``bearing_from_cdr`` with the node's ``frame_id`` and ``Bearing.validate`` passed;
  ``idle`` right before it exits after watching nothing for ``--idle`` s.

Messages are taken raw (CDR bytes) with the node's keep-last QoS; nothing is published.
"""

import argparse
import math
import os
import queue
import subprocess
import sys
import threading
import time

from .processes import interrupt

#: Seconds with nothing to watch after which the probe exits.
IDLE_EXIT = 3.0
#: Seconds the node waits for the probe to acknowledge a command before it counts the probe
#: as hung, stops it and starts another.
ACK_TIMEOUT = 15.0
#: Restart delays after a probe failure: doubled from the first to the last per failure in
#: a row (a probe that cannot start costs the node a Python start-up per restart).
BACKOFF = (1.0, 60.0)
#: Output lines read ahead of the node at most (a flooding probe blocks on its pipe, stops
#: acknowledging and is replaced).
MAX_LINES = 10000
#: Longest protocol line read (longer output is cut into pieces, each counted as garbage).
MAX_LINE = 512
#: Name of the probe's node, followed by its process id: the simulator does not count its
#: short-lived subscriptions as the subscribers it waits for (simulator_node).
NODE_NAME_PREFIX = 'discovery_probe_'


def parse_command(line):
    """``watch <n> [station ...]`` -> (n, set of stations); None for any other line."""
    parts = line.split()
    if len(parts) < 2 or parts[0] != 'watch':
        return None
    try:
        n = int(parts[1])
    except ValueError:
        return None
    return n, set(parts[2:])


def _read_stdin(stream, out):
    """Put each line of ``stream`` into ``out``, then None at end of input."""
    try:
        for line in stream:
            out.put(line)
    except (OSError, ValueError):
        pass
    out.put(None)


class Probe:
    """The probing subscriptions of one probe process (``node``: an rclpy node).

    ``watching``: station -> subscription; ``reported``: stations already reported valid
    (each once per watch); ``emit(line)`` writes one protocol line.
    """

    def __init__(self, node, qos, frame_id, emit):
        self.node, self.qos, self.frame_id, self.emit = node, qos, frame_id, emit
        self.watching = {}
        self.reported = set()

    def watch(self, stations):
        """Subscribe to the stations' topics not watched yet, drop the others."""
        from geometry_msgs.msg import PoseWithCovarianceStamped
        for station in set(self.watching) - stations:
            self.node.destroy_subscription(self.watching.pop(station))
            self.reported.discard(station)
        for station in sorted(stations - set(self.watching)):
            self.watching[station] = self.node.create_subscription(
                PoseWithCovarianceStamped, f'{station}/bearing',
                lambda raw, s=station: self.on_message(s, raw), self.qos, raw=True)

    def on_message(self, station, raw):
        """Report ``station`` once when ``raw`` (CDR bytes) is a valid bearing."""
        from .ros_conversions import bearing_from_cdr, ConversionError
        if station in self.reported or station not in self.watching:
            return
        try:
            bearing_from_cdr(raw, station, expected_frame=self.frame_id).validate()
        except (ConversionError, ValueError):
            return
        self.reported.add(station)
        self.emit(f'valid {station}')


class ProbeProcess:
    """The fusion node's side of the probe: one child process at a time, started when there
    is something to probe, never waited on by the node.

    :meth:`update` (called from the discovery scan) tells the probe the set of candidate
    stations and returns the candidates it has reported valid. Its output is read by a
    daemon thread into a queue. A probe that exits other than after ``idle``, stops
    acknowledging (``ack_timeout`` s), or cannot be written to is stopped and reaped,
    counted in ``failures``, and started again after a back-off (:data:`BACKOFF`). Lines
    that are not protocol are counted in ``garbage``; a ``valid`` station is accepted only
    if it was asked for. Counters: ``starts``, ``failures``, ``garbage``, ``accepted``.
    ``args``: the probe's command line options (namespace, QoS, frame); ``log``: an rclpy
    logger or None; ``command``: the argv prefix (default ``python -m`` this module).
    """

    def __init__(self, args, log=None, command=None, ack_timeout=ACK_TIMEOUT,
                 backoff=BACKOFF, clock=time.monotonic):
        self.args, self.log, self.clock = list(args), log, clock
        self.command = list(command or (sys.executable, '-m', __name__))
        self.ack_timeout, self.backoff_range = float(ack_timeout), backoff
        self.proc = None
        self.starts = self.failures = self.garbage = self.accepted = 0
        self._backoff = backoff[0]
        self._not_before = -math.inf
        self._reset_process_state()

    def _reset_process_state(self):
        self._lines = None
        self._reader = None
        self._gone = threading.Event()
        self._sent = None           # the last set sent to the current probe
        self._asked = set()         # every station sent to the current probe
        self._seq = 0
        # (newest seq sent, time the oldest unacknowledged command was sent): cleared only
        # by an ack of the newest command, so no command goes untracked.
        self._unacked = None
        self._last_send = -math.inf
        self._idle = False

    @property
    def running(self):
        """True while a probe process is held (it may have exited since the last update)."""
        return self.proc is not None

    def update(self, candidates):
        """Probe ``candidates`` (a set of station names); return the sorted list of
        candidates the probe has reported valid since the last call. Never blocks."""
        candidates = set(candidates)
        asked = set(self._asked)        # a probe reaped below forgets what it was asked
        valid = self._drain()
        valid += self._check_health()
        if candidates and self.proc is None and self.clock() >= self._not_before:
            self._start()
        # The set again when it changed, and as a keep-alive while candidates wait, so that a
        # probe hanging after its last answer is found within ack_timeout.
        if self.proc is not None and (candidates != self._sent or (
                candidates and self._unacked is None
                and self.clock() - self._last_send > 0.5 * self.ack_timeout)):
            self._send(candidates)
        out = sorted(s for s in valid if s in candidates and (s in asked or s in self._asked))
        self.accepted += len(out)
        return out

    def _start(self):
        env = dict(os.environ, PYTHONUNBUFFERED='1')
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env['PYTHONPATH'] = os.pathsep.join(
            p for p in (root, os.environ.get('PYTHONPATH')) if p)
        try:
            proc = subprocess.Popen(
                self.command + self.args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                env=env, start_new_session=True)
        except OSError as exc:
            self._failed(f'cannot start the discovery probe: {exc}')
            return
        os.set_blocking(proc.stdin.fileno(), False)
        self.proc = proc
        self.starts += 1
        self._reset_process_state()
        self._lines = queue.Queue(MAX_LINES)
        self._reader = threading.Thread(target=self._read,
                                        args=(proc.stdout, self._lines, self._gone),
                                        name='discovery_probe_reader', daemon=True)
        self._reader.start()

    @staticmethod
    def _read(stream, lines, gone):
        """Reader thread: the probe's output lines, then None at its end (``gone``: set when
        the node has let go of the probe, so a full queue never holds the thread)."""
        def put(item):
            while not gone.is_set():
                try:
                    lines.put(item, timeout=0.5)
                    return True
                except queue.Full:
                    pass
            return False
        try:
            while True:
                line = stream.readline(MAX_LINE)
                if not line or not put(line):
                    break
        except (OSError, ValueError):
            pass
        put(None)

    def _drain(self):
        """Take the queued output lines; return the stations reported valid."""
        valid = []
        if self._lines is None:
            return valid
        for _ in range(MAX_LINES):
            try:
                raw = self._lines.get_nowait()
            except queue.Empty:
                break
            if raw is None:         # end of output: the probe exited (or closed stdout)
                self._lines = None
                break
            parts = raw.decode('utf-8', 'replace').split()
            if len(parts) == 2 and parts[0] == 'valid':
                valid.append(parts[1])
            elif len(parts) == 2 and parts[0] == 'ack' and parts[1].isdigit():
                if self._unacked is not None and int(parts[1]) >= self._unacked[0]:
                    self._unacked = None
            elif parts == ['idle']:
                self._idle = True
            else:
                self.garbage += 1
                self._warn(f'discovery probe: unexpected output {raw[:80]!r} ignored')
        return valid

    def _check_health(self):
        """Reap an exited probe (returning the stations it reported valid before it went);
        stop a hung one."""
        valid = []
        if self.proc is None:
            return valid
        code = self.proc.poll()
        if code is not None:
            if self._reader is not None:    # its last lines: the pipe ends with the process
                self._reader.join(timeout=0.5)
            if self._lines is not None:
                valid = self._drain()
            normal = code == 0 and self._idle
            self._close()
            if normal:
                self._backoff = self.backoff_range[0]
            else:
                self._failed(f'discovery probe exited with code {code}')
            return valid
        elif self._unacked is not None and \
                self.clock() - self._unacked[1] > self.ack_timeout:
            self._stop(kill=True)
            self._failed(f'discovery probe did not answer for {self.ack_timeout:g} s; '
                         'restarted')
        return valid

    def _send(self, stations):
        self._seq += 1
        line = f'watch {self._seq} {" ".join(sorted(stations))}\n'.encode()
        try:
            written = os.write(self.proc.stdin.fileno(), line)
        except (BlockingIOError, BrokenPipeError, OSError) as exc:
            written, err = 0, exc
        else:
            err = None
        if written != len(line):            # the pipe is full (a hung probe) or closed
            if self.proc.poll() == 0:
                return      # it exited after idle just now: _check_health reaps it
            self._stop(kill=True)
            self._failed(f'discovery probe does not read its input ({err or "pipe full"})')
            return
        self._sent = set(stations)
        self._asked |= self._sent
        now = self.clock()
        self._last_send = now
        self._unacked = (self._seq, now if self._unacked is None else self._unacked[1])

    def _failed(self, text):
        self.failures += 1
        self._not_before = self.clock() + self._backoff
        self._backoff = min(2 * self._backoff, self.backoff_range[1])
        self._warn(text)

    def _warn(self, text):
        if self.log is not None:
            self.log.warning(text, throttle_duration_sec=10.0)

    def _close(self):
        self._gone.set()
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()
            except OSError:
                pass
        self.proc = None
        self._reset_process_state()

    def _stop(self, kill=False, timeout=2.0):
        proc = self.proc
        if proc is None:
            return
        try:
            proc.stdin.close()          # end of input: the probe exits by itself
        except OSError:
            pass
        if kill:
            proc.kill()
            proc.wait()
        else:
            try:
                proc.wait(timeout=min(1.0, timeout))
            except subprocess.TimeoutExpired:
                interrupt(proc, timeout)
        self._close()

    def stop(self, timeout=2.0):
        """Stop the probe (end of input, SIGINT, then SIGKILL after ``timeout`` s) and reap
        it. Safe to call at any time, also twice."""
        self._stop(timeout=timeout)


def main(argv=None):
    """Run the probe until end of input or ``--idle`` s with nothing to watch."""
    ap = argparse.ArgumentParser(prog='python -m bearing_loc_ros.discovery_probe',
                                 description=__doc__.splitlines()[0])
    ap.add_argument('--namespace', default='/')
    ap.add_argument('--qos-depth', type=int, default=10)
    ap.add_argument('--qos-reliability', default='best_effort',
                    choices=('best_effort', 'reliable'))
    ap.add_argument('--frame-id', default='map')
    ap.add_argument('--idle', type=float, default=IDLE_EXIT)
    a = ap.parse_args(argv)

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from .ros_common import keep_last_qos

    out = sys.stdout

    def emit(line):
        out.write(line + '\n')
        out.flush()

    lines = queue.Queue()
    threading.Thread(target=_read_stdin, args=(sys.stdin, lines), daemon=True).start()
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx)
    node = rclpy.create_node(f'{NODE_NAME_PREFIX}{os.getpid()}', namespace=a.namespace,
                             context=ctx, enable_rosout=False,
                             start_parameter_services=False)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    probe = Probe(node, keep_last_qos(a.qos_depth, a.qos_reliability), a.frame_id, emit)
    idle_since = time.monotonic()
    try:
        while True:
            try:
                while True:
                    line = lines.get_nowait()
                    if line is None:
                        return 0
                    cmd = parse_command(line)
                    if cmd is not None:
                        probe.watch(cmd[1])
                        emit(f'ack {cmd[0]}')
            except queue.Empty:
                pass
            now = time.monotonic()
            if probe.watching:
                idle_since = now
            elif now - idle_since > a.idle:
                emit('idle')
                return 0
            ex.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException, BrokenPipeError):
        return 0
    finally:
        try:
            ex.shutdown()
            node.destroy_node()
        except Exception:  # noqa: B902 - the context may be gone after SIGINT
            pass
        rclpy.try_shutdown(context=ctx)


if __name__ == '__main__':
    sys.exit(main())
