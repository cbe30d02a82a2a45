"""view_node: a Foxglove WebSocket server of the package's live topics (foxglove-sdk).

Subscribes with ``raw=True`` (no deserialisation) to the package's topics as they appear in
the ROS graph and forwards the CDR bytes unchanged to Foxglove/Lichtblick clients
(:mod:`bearing_loc_ros.foxglove_view`): ``fix``, ``fix/navsat``, ``markers``,
``accuracy_map`` (transient local: sent to each new WebSocket subscriber), ``track``,
``truth``, every ``<station>/bearing``, ``/diagnostics`` and ``/clock`` (the server time
when the node runs with ``use_sim_time``). With ``geodetic_origin`` set it also serves the
GeoJSON picture on ``/map_geojson`` (``<ns>/map_geojson`` per channel namespace) and each
station's position as NavSatFix on ``/<station>/navsat``. The picture and
``/view/fix_stats`` use fixes and bearings in the world frame ``frame_id`` only; the other
messages are counted and logged (at most every 10 s per reason, with the count so far) and
reported on ``/diagnostics`` (every
``diagnostics_period`` s: forwarded messages and bytes, channels, dropped, dropped by
reason, clock restarts; WARN while messages are being left out).

Parameters (all read-only; declared from the schema in core.parameters): print them with
``python -m bearing_loc_ros.core.parameters --markdown view_node``.
"""

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .core.conventions import check_frame_id
from .foxglove_view import FoxgloveView, message_class, wanted_topic
from .ros_common import declare_schema, diagnostic_status, main_for, OK, ParameterError, WARN


def subscription_qos(publishers):
    """QoS matching every publisher: reliable/transient-local only if all offer it.

    A reliable or transient-local subscription does not match a best-effort or volatile
    publisher; keep-last 1 for transient-local topics (latched maps), 10 otherwise.
    """
    reliable = bool(publishers) and all(
        p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
    latched = bool(publishers) and all(
        p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1 if latched else 10,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def _blamed(host, exc):
    """The parameter a failed listen (``exc``) is blamed on: ``host`` when it does not
    resolve, or is not an address of this machine (EADDRNOTAVAIL), else ``port`` (busy, or
    not allowed)."""
    import errno
    import socket
    if f'os error {errno.EADDRNOTAVAIL}' in str(exc) or 'requested address' in str(exc):
        return 'host'
    try:
        socket.getaddrinfo(host, None)
    except (OSError, UnicodeError):
        return 'host'
    return 'port'


class ViewNode(Node):
    """The view node (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__('view', **kwargs)
        p = declare_schema(self, 'view_node')
        host, port, self.topics = p['host'], p['port'], p['topics']
        period, origin = p['discovery_period'], p['geodetic_origin']
        geo_period, prob = p['geojson_period'], p['ellipse_probability']
        backlog = p['max_backlog']
        try:
            frame = check_frame_id(p['frame_id'])
        except ValueError as exc:
            raise ParameterError('frame_id', str(exc).partition(': ')[2]) from None
        if origin:
            from .core.gis import check_origin
            try:
                origin = check_origin(origin)
            except ValueError as exc:
                raise ParameterError('geodetic_origin', str(exc).partition(': ')[2]) from None
        sim = self.get_parameter('use_sim_time').value
        try:
            self.view = FoxgloveView(host=host, port=port, origin=origin or None, use_time=sim,
                                     backlog=backlog, geojson_period=geo_period,
                                     probability=prob, frame_id=frame,
                                     log=self.get_logger().warning)
        except Exception as exc:  # foxglove-sdk raises RuntimeError for a busy port
            raise ParameterError(_blamed(host, exc), f'cannot listen on {host}:{port}: '
                                 f'{exc}') from None
        self._subs = {}
        self._bad_topics = set()
        self._discover()
        # Wall-clock (steady) timers: with use_sim_time a ROS-time timer would not run before
        # the first /clock message, and the topics must be found before the data flows.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._discover, clock=steady)
        self.create_timer(max(geo_period, 0.1), self._flush_geojson, clock=steady)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._dropped_before = 0
        self.create_timer(p['diagnostics_period'], self._publish_diagnostics, clock=steady)
        self.get_logger().info(
            f'Foxglove WebSocket server on ws://{host}:{self.view.port} (subprotocol '
            f'foxglove.sdk.v1){"; server time from /clock" if sim else ""}')

    def _wanted(self, topic, msgtype):
        return topic in self.topics if self.topics else wanted_topic(topic, msgtype)

    def _discover(self):
        """Subscribe (raw) to every wanted topic that has appeared in the graph."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or topic in self._bad_topics or len(types) != 1:
                continue
            msgtype = types[0]
            if not self._wanted(topic, msgtype):
                continue
            try:
                cls = message_class(msgtype)
            except ValueError as exc:
                self._bad_topics.add(topic)
                self.get_logger().warning(f'{topic}: not forwarded ({exc})')
                continue
            try:
                self.view.advertise(topic, msgtype)
            except ValueError as exc:
                self._bad_topics.add(topic)
                self.get_logger().warning(f'{topic}: not forwarded ({exc})')
                continue
            qos = subscription_qos(self.get_publishers_info_by_topic(topic))
            self._subs[topic] = self.create_subscription(
                cls, topic, lambda raw, t=topic, m=msgtype: self._on_message(t, m, raw), qos,
                raw=True)
            self.get_logger().info(f'forwarding {topic} [{msgtype}]')

    def _on_message(self, topic, msgtype, raw):
        try:
            self.view.forward(topic, msgtype, raw, self.get_clock().now().nanoseconds)
        except ValueError as exc:
            self.get_logger().warning(f'{topic}: {exc}', throttle_duration_sec=10.0)

    def _flush_geojson(self):
        self.view.publish_geojson(self.get_clock().now().nanoseconds)

    def diagnostic_status(self):
        """``<node>: view``: the view's counters (FoxgloveView.stats, rejections by reason
        as ``rejected.<reason>``); WARN when messages were left out since the last one."""
        st = self.view.stats()
        values = {k: v for k, v in st.items() if k != 'rejected'}
        values.update({f'rejected.{k}': v for k, v in sorted(st['rejected'].items())})
        new = st['dropped'] - self._dropped_before
        self._dropped_before = st['dropped']
        level, message = (WARN, f'{new} message(s) left out of the map since the last report') \
            if new else (OK, 'serving')
        return diagnostic_status(f'{self.get_name()}: view', level, message, values)

    def _publish_diagnostics(self):
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostic_status()]
        self.diag_pub.publish(arr)

    def destroy_node(self):
        """Stop the WebSocket server, then destroy the node."""
        self.view.stop()
        return super().destroy_node()


main = main_for(ViewNode)


if __name__ == '__main__':
    main()
