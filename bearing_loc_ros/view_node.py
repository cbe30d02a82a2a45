"""view_node: a Foxglove WebSocket server of the package's live topics (foxglove-sdk).

Subscribes with ``raw=True`` (no deserialisation) to the package's topics as they appear in
the ROS graph and forwards the CDR bytes unchanged to Foxglove/Lichtblick clients
(:mod:`bearing_loc_ros.foxglove_view`): ``fix``, ``fix/navsat``, ``markers``,
``accuracy_map`` (transient local: sent again to every new WebSocket subscriber), ``track``,
``truth``, every ``<station>/bearing``, ``/diagnostics`` and ``/clock`` (the server time
when the node runs with ``use_sim_time``). With ``geodetic_origin`` set it also serves the
GeoJSON picture on ``/map_geojson`` and each station's position as NavSatFix on
``/<station>/navsat``.

Parameters:
  host (string, '127.0.0.1'): address to listen on. Anything but loopback exposes the
      server (no authentication) to the network: an explicit choice.
  port (int, 8765): TCP port (0 = any free port, logged).
  topics (string[], []): forward exactly these topics; empty = the package's topics
      (leaf names in foxglove_view.DEFAULT_LEAVES, plus /diagnostics and /clock).
  discovery_period (double, 1.0 s): how often the ROS graph is scanned for new topics.
  geodetic_origin (double[], []): [lat_deg, lon_deg, alt_m] of the ENU frame (WGS84).
  geojson_period (double, 0.5 s): minimum interval between GeoJSON pictures.
  ellipse_probability (double, 0.95): probability of the drawn error ellipse.
  max_backlog (int, 512): messages queued per WebSocket client before the oldest is dropped.
"""

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .foxglove_view import DEFAULT_BACKLOG, FoxgloveView, message_class, wanted_topic
from .ros_common import declare, declare_array, main_for, ParameterError


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


class ViewNode(Node):
    """The view node (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__('view', **kwargs)
        host = declare(self, 'host', '127.0.0.1', 'Address the WebSocket server listens on; '
                       'anything but loopback exposes it to the network', read_only=True)
        port = declare(self, 'port', 8765, 'TCP port (0 = any free port)', read_only=True,
                       min_value=0, max_value=65535)
        self.topics = declare_array(self, 'topics', [], 'Topics to forward (empty = the '
                                    "package's topics)", kind=str, read_only=True)
        period = declare(self, 'discovery_period', 1.0, 'Graph scan period, s',
                         read_only=True, min_value=0.05, max_value=60.0)
        origin = declare_array(self, 'geodetic_origin', [], '[lat_deg, lon_deg, alt_m] of the '
                               'ENU frame (WGS84); enables /map_geojson and station NavSatFix',
                               read_only=True)
        geo_period = declare(self, 'geojson_period', 0.5, 'Minimum interval between GeoJSON '
                             'pictures, s', read_only=True, min_value=0.0, max_value=3600.0)
        prob = declare(self, 'ellipse_probability', 0.95, 'Probability of the drawn error '
                       'ellipse', read_only=True, min_value=1e-6, max_value=1.0 - 1e-9)
        backlog = declare(self, 'max_backlog', DEFAULT_BACKLOG, 'Messages queued per client '
                          'before the oldest is dropped', read_only=True, min_value=1,
                          max_value=1_000_000)
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
                                     probability=prob, log=self.get_logger().warning)
        except Exception as exc:  # foxglove-sdk raises RuntimeError for a busy port
            raise ParameterError('port', f'cannot listen on {host}:{port}: {exc}') from None
        self._subs = {}
        self._bad_topics = set()
        self._discover()
        # Wall-clock (steady) timers: with use_sim_time a ROS-time timer would not run before
        # the first /clock message, and the topics must be found before the data flows.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._discover, clock=steady)
        self.create_timer(max(geo_period, 0.1), self._flush_geojson, clock=steady)
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

    def destroy_node(self):
        """Stop the WebSocket server, then destroy the node."""
        self.view.stop()
        return super().destroy_node()


main = main_for(ViewNode)


if __name__ == '__main__':
    main()
