"""station_node: raw direction-finding readings -> world-frame bearings on ``bearing``.

Runs on a station computer (``ros2 run bearing_loc_ros station_node --ros-args
-r __ns:=/station_1 -p position:=[0.0,0.0,2.0]``). Inputs:

* ``raw_bearing`` (geometry_msgs/Vector3Stamped): x = azimuth, y = elevation (NaN = none), in
  the sensor's reference (``azimuth_reference``) and units (``input_units``); header.stamp =
  observation time.
* UDP (``udp_port`` > 0): one JSON object per datagram, ``{"t": unix_s, "azimuth_deg": a,
  "elevation_deg": e | null, "sigma_deg": s}``; read non-blocking from a steady-clock timer,
  so the executor never blocks.
* ``platform_odometry`` (nav_msgs/Odometry topic, optional): the station is on a moving
  platform; readings are in the body frame and rotated into the world frame with the pose
  interpolated to each reading's stamp.
* A KrakenSDR receiver (``input``: ``kraken_xml_http``, ``kraken_csv_http``,
  ``kraken_json_post`` or ``kraken_csv_file``, parameters ``kraken.*``): it replaces the
  raw topic and UDP. The source runs in a worker thread or is read non-blocking
  (:mod:`bearing_loc_ros.receiver_inputs`); a steady-clock timer drains it through
  :class:`~bearing_loc_ros.receiver_inputs.KrakenInput` (parsing, channel bands, time
  checks, heading and position: :mod:`bearing_loc_ros.core.receiver`).

Outputs: ``bearing`` (geometry_msgs/PoseWithCovarianceStamped, DESIGN.md contract) — or,
with ``kraken.channels``, ``/<channel>/<station>/bearing`` per channel (the simulator's
target namespace scheme) — and ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, every
``diagnostics_period``; a receiver input adds its state and ``kraken_*`` counters, WARN
while the receiver is unreachable, slow, failing or its file missing).

The node is thin: parameters (declared from the schema in core.parameters; print them with
``python -m bearing_loc_ros.core.parameters --markdown station_node``) ->
:func:`bearing_loc_ros.core.station.station_config`,
messages/datagrams -> core readings (:mod:`bearing_loc_ros.ros_conversions`,
:func:`~bearing_loc_ros.core.station.parse_datagram`), the core computes the bearing
(:func:`~bearing_loc_ros.core.station.to_world_bearing`), the node publishes it. Bad
parameters exit with code 1 and a message naming the parameter; bad readings are counted by
reason, logged (throttled) and never stop the node.
"""

import errno
import socket

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from . import ros_common as rcm
from .core.receiver_params import receiver_from_params
from .core.simulation import bearing_topic
from .core.station import (ConfigError, parse_datagram, PoseBuffer, ReadingError,
                           station_config, to_world_bearing)
from .core.station_report import StationCounters
from .core.udp import udp_drops
from .receiver_inputs import FAILED_STATES, KrakenInput, make_source
from .ros_conversions import (bearing_to_msg, ConversionError, pose_from_odometry,
                              raw_reading_from_msg)

#: Period of the non-blocking UDP poll (s, steady clock) and datagrams read per poll.
UDP_POLL_PERIOD_S = 0.01
UDP_MAX_PER_POLL = 256
LOG_THROTTLE_S = 5.0
#: Period of the receiver input drain (s, steady clock).
KRAKEN_POLL_PERIOD_S = 0.02
#: Receiver source states reported as WARN in /diagnostics.
KRAKEN_WARN_STATES = ('unreachable', 'error', 'missing', 'slow')

#: Inputs accept best-effort and reliable publishers. Bearings are published with the
#: sensor-data profile by default (best effort, keep-last ``qos_depth``, volatile: on a
#: lossy link a retransmitted bearing arrives too late for its epoch and delays the next
#: ones); ``qos_reliability:=reliable`` for reliable subscribers. OUTPUT_QOS (best effort)
#: is a subscriber profile that matches the bearing publisher of either setting.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                       reliability=ReliabilityPolicy.BEST_EFFORT)
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                        reliability=ReliabilityPolicy.BEST_EFFORT)


class StationNode(Node):
    """One DF station: raw readings (topic and/or UDP) -> ``bearing``; see module docstring."""

    #: Counters, kept by core.station_report.StationCounters (read by tests and tools).
    published = property(lambda self: self.counters.published)
    last_stamp_ns = property(lambda self: self.counters.last_stamp_ns)

    def __init__(self, **kwargs):
        super().__init__('station_node', **kwargs)
        self._sock = None
        self.kraken = None
        p = rcm.declare_schema(self, 'station_node')
        station = p['station_id'] or rcm.station_id_from_namespace(self.get_namespace())
        self.receiver_config, self.channels = None, None
        try:
            if p['input']:
                self.receiver_config, self.channels = receiver_from_params(station, p)
                self.config = self.receiver_config.station
            else:
                self.config = station_config(
                    station, frame_id=p['frame_id'], position=p['position'],
                    geodetic_position=p['geodetic_position'],
                    geodetic_origin=p['geodetic_origin'],
                    position_covariance=p['position_covariance'],
                    sigma_azimuth_deg=p['sigma_azimuth_deg'],
                    sigma_elevation_deg=p['sigma_elevation_deg'],
                    measures_elevation=p['measures_elevation'],
                    azimuth_reference=p['azimuth_reference'],
                    azimuth_offset_deg=p['azimuth_offset_deg'],
                    moving=bool(p['platform_odometry']))
        except ConfigError as exc:
            raise rcm.ParameterError(exc.field, exc.problem) from None
        if p['input'] and p['udp_port']:
            raise rcm.ParameterError('udp_port', f"must be 0 with input {p['input']} (a "
                                                 'receiver input replaces UDP and raw_bearing)')
        needs_odometry = (self.receiver_config.needs_odometry if p['input']
                          else self.config.moving)
        if needs_odometry and not p['platform_odometry']:
            raise rcm.ParameterError('platform_odometry', 'required by kraken.heading_source, '
                                     'kraken.low_speed or kraken.position_source odometry')
        self.input_units = p['input_units']
        self.restamp_udp = p['udp_stamp'] == 'receive'
        self.counters = StationCounters()
        self.rejected, self.received = self.counters.rejected, self.counters.received
        self.sources = []
        self.bearing_qos = rcm.keep_last_qos(p['qos_depth'], p['qos_reliability'])

        self.pubs = {ch: self.create_publisher(
            PoseWithCovarianceStamped, '/' + bearing_topic(ch, station) if ch else 'bearing',
            self.bearing_qos) for ch in (self.channels.names if self.channels else [''])}
        self.pub = self.pubs.get('')
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        if not p['input']:
            self.raw_sub = self.create_subscription(Vector3Stamped, 'raw_bearing',
                                                    self._on_raw, INPUT_QOS)
            self.sources.append(f'topic {self.raw_sub.topic_name} ({self.input_units})')
        self.poses = None
        if p['platform_odometry']:
            self.poses = PoseBuffer(p['odometry_buffer_size'],
                                    int(round(p['odometry_tolerance'] * 1e9)),
                                    int(round(p['odometry_max_gap'] * 1e9)),
                                    int(round(p['odometry_jump'] * 1e9)))
            self.odom_sub = self.create_subscription(Odometry, p['platform_odometry'],
                                                     self._on_odometry, INPUT_QOS)
            self.sources.append(f'odometry {self.odom_sub.topic_name}')
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if p['input']:
            self._open_receiver(p)
            self.create_timer(KRAKEN_POLL_PERIOD_S, self._poll_kraken, clock=steady)
        if p['udp_port']:
            self._open_udp(p['udp_address'], p['udp_port'])
            self.create_timer(UDP_POLL_PERIOD_S, self._poll_udp, clock=steady)
            self.sources.append(f"udp {p['udp_address']}:{p['udp_port']} "
                                f"(stamp: {p['udp_stamp']})")
            if self.restamp_udp is False and self.get_parameter('use_sim_time').value:
                self.get_logger().warning(
                    'use_sim_time is true but udp_stamp is "datagram": UDP stamps are wall '
                    '(unix) time and will not match /clock; set udp_stamp:=receive')
        self.create_timer(p['diagnostics_period'], self._publish_diagnostics, clock=steady)
        c = self.config
        where = 'moving platform' if c.moving else f'position {c.position.tolist()} m'
        if self.receiver_config is not None and c.moving:
            where = f'position from {self.receiver_config.position_source}'
        self.get_logger().info(
            f"station '{c.station}' in frame '{c.frame_id}', {where}, "
            f"{'2D' if c.measures_elevation else '1D'}, reference {c.azimuth_reference}, "
            f"inputs: {'; '.join(self.sources)}")

    # ------------------------------------------------------------------ inputs

    def _open_receiver(self, p):
        """Start the receiver input ``p['input']`` (ParameterError naming a bad kraken.*)."""
        mode = p['input']
        try:
            source = make_source(mode, url=p['kraken.url'],
                                 poll_period_s=1.0 / p['kraken.poll_rate'],
                                 timeout_s=p['kraken.timeout'],
                                 post_address=p['kraken.post_address'],
                                 post_port=p['kraken.post_port'], file_path=p['kraken.file'],
                                 file_from_start=p['kraken.file_from_start'],
                                 file_rate=p['kraken.file_rate'])
        except ValueError as exc:
            name, _, problem = str(exc).partition(': ')
            raise rcm.ParameterError('kraken.' + name, problem) from None
        source.log = self.get_logger().warning     # the source's throttled warnings
        self.kraken = KrakenInput(source, self.receiver_config, self.channels,
                                  p['kraken.stamp'], p['kraken.max_age'],
                                  p['kraken.receiver_id']).start()
        where = {'kraken_json_post': f"{p['kraken.post_address']}:"
                                     f"{getattr(source, 'port', p['kraken.post_port'])}",
                 'kraken_csv_file': p['kraken.file']}.get(mode, p['kraken.url'])
        names = self.channels.names
        self.sources.append(f'{mode} {where} (stamp: {p["kraken.stamp"]}'
                            + (f', channels {", ".join(names)}' if names != [''] else '')
                            + ')')

    def _poll_kraken(self):
        """Drain the receiver input: publish its bearings, count its rejections."""
        now = self.get_clock().now().nanoseconds
        pose_at = self.poses.interpolate if self.poses is not None else None
        bearings, rejected = self.kraken.poll(now, pose_at)
        change = self.kraken.state_change()
        if change is not None:
            state, error = change
            if error.startswith(f'{state}: '):     # 'unreachable: <why>' says it once
                error = error[len(state) + 2:]
            # Throttled: a receiver flapping between ok and unreachable.
            if state in FAILED_STATES:
                self.get_logger().warning(f'receiver {state}: {error} (retrying; counts in '
                                          '/diagnostics)', throttle_duration_sec=10.0)
            else:
                self.get_logger().info(f'receiver {state} again', throttle_duration_sec=10.0)
        self.received['kraken'] += len(bearings) + len(rejected)
        for channel, b in bearings:
            try:
                msg = bearing_to_msg(b)
            except ValueError as exc:
                self._reject('invalid_bearing', 'receiver', exc)
                continue
            self.pubs[channel].publish(msg)
            self.counters.count_published(b.stamp_ns)
        for reason, detail in rejected:
            self._reject(reason, 'receiver', detail)

    def _open_udp(self, address, port):
        try:
            infos = socket.getaddrinfo(address, port, type=socket.SOCK_DGRAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise rcm.ParameterError('udp_address', f'{address!r}: {exc}') from None
        family, stype, proto, _, sockaddr = infos[0]
        sock = socket.socket(family, stype, proto)
        try:
            sock.setblocking(False)
            sock.bind(sockaddr)
        except OSError as exc:
            sock.close()
            if exc.errno == errno.EADDRNOTAVAIL:
                raise rcm.ParameterError('udp_address', f'cannot bind {address}:{port}: not '
                                                        'an address of this machine') from None
            raise rcm.ParameterError('udp_port', f'cannot bind {address}:{port}: '
                                                 f'{exc.strerror or exc}') from None
        self._sock = sock

    def _on_raw(self, msg):
        self.received['raw_bearing'] += 1
        try:
            reading = raw_reading_from_msg(msg, self.input_units)
        except ConversionError as exc:
            self._reject(exc.reason, 'raw_bearing', exc)
            return
        self._process(reading, 'raw_bearing')

    def _poll_udp(self):
        for _ in range(UDP_MAX_PER_POLL):
            try:
                data, sender = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. ICMP errors surfaced on the socket; keep going
                self.get_logger().warning(f'UDP receive error: {exc}',
                                          throttle_duration_sec=LOG_THROTTLE_S)
                return
            self.received['udp'] += 1
            try:
                reading = parse_datagram(data, require_t=not self.restamp_udp,
                                         elevation=self.config.measures_elevation)
            except ReadingError as exc:
                self._reject(exc.reason, f'udp from {sender[0]}:{sender[1]}', exc)
                continue
            if self.restamp_udp:
                now = self.get_clock().now().nanoseconds
                if now <= 0:
                    self._reject('no_clock', 'udp', 'node clock is 0 (no /clock yet?)')
                    continue
                reading.stamp_ns = now
            self._process(reading, 'udp')

    def _on_odometry(self, msg):
        self.received['odometry'] += 1
        try:
            pose = pose_from_odometry(msg, self.config.frame_id)
        except ConversionError as exc:
            self._reject(exc.reason, 'odometry', exc)
            return
        status = self.poses.add(pose)
        if status == 'duplicate':
            self._reject('odometry_duplicate', 'odometry', 'same stamp as the previous pose')
        elif status == 'late':
            self._reject('odometry_late', 'odometry', 'stamped before the newest pose by at '
                         f'most odometry_jump ({self.poses.jump_ns / 1e9:g} s)')
        elif status == 'reset':
            self.received['odometry_resets'] += 1
            self.get_logger().warning('odometry time jumped backwards by more than '
                                      'odometry_jump: pose buffer cleared',
                                      throttle_duration_sec=LOG_THROTTLE_S)

    # ------------------------------------------------------------------ processing

    def _process(self, reading, source):
        try:
            pose = self.poses.interpolate(reading.stamp_ns) if self.config.moving else None
            msg = bearing_to_msg(to_world_bearing(reading, self.config, pose))
        except ReadingError as exc:
            self._reject(exc.reason, source, exc)
            return
        except ValueError as exc:  # the finished bearing failed validation
            self._reject('invalid_bearing', source, exc)
            return
        self.pub.publish(msg)
        self.counters.count_published(reading.stamp_ns)

    def _reject(self, reason, source, detail):
        self.rejected[reason] += 1
        text = str(detail)
        if text.startswith(reason + ': '):
            text = text[len(reason) + 2:]
        self.get_logger().warning(f'rejected {source} input ({reason}): {text}',
                                  throttle_duration_sec=LOG_THROTTLE_S)

    # ------------------------------------------------------------------ diagnostics

    def diagnostic_status(self):
        """The station's DiagnosticStatus: WARN when inputs were rejected since last report."""
        values = {'station': self.config.station, 'frame_id': self.config.frame_id,
                  'sources': '; '.join(self.sources)}
        extra, receiver, drops = {}, None, None
        if self.kraken is not None:
            state, last_error, kvalues = self.kraken.status()
            extra.update(kvalues)
            if state in KRAKEN_WARN_STATES:
                receiver = f'receiver {state}' + (f' ({last_error})' if last_error else '')
        if self._sock is not None:  # datagrams the kernel discarded: the queue was full
            drops = udp_drops(self._sock)
            extra['udp_dropped_by_kernel'] = 'unsupported' if drops is None else drops
        level, message, values = self.counters.report(values, extra, receiver, drops)
        return rcm.diagnostic_status(f'{self.get_name()}: {self.config.station}',
                                     rcm.WARN if level == 'warn' else rcm.OK, message, values,
                                     hardware_id=self.config.station)

    def _publish_diagnostics(self):
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostic_status()]
        self.diag_pub.publish(arr)

    def destroy_node(self):
        """Stop the receiver input, close the UDP socket, then destroy the node."""
        if self.kraken is not None:
            self.kraken.stop()
            self.kraken = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        return super().destroy_node()


main = rcm.main_for(StationNode)

if __name__ == '__main__':
    main()
