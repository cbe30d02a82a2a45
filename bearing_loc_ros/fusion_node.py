"""fusion_node: time-aligns the stations' bearings and publishes fixes.

Wiring only: parameters (core.parameters schema) -> the fusion pipeline
(:func:`bearing_loc_ros.core.fusion.make_core`: buffers, alignment, epochs, estimator,
outlier gate, counters), messages <-> core objects (``ros_conversions``), the node clock
(so ``use_sim_time`` with ``/clock`` and bag replay work) -> publications.

Topics (relative, so namespaces and remapping work):

* in: ``<station>/bearing`` geometry_msgs/PoseWithCovarianceStamped per station (the
  ``stations`` parameter, plus topics found by discovery), keep-last ``qos_depth``, best
  effort by default (``qos_reliability``; it matches reliable and best-effort publishers).
  Losses are counted per station: the middleware's message-lost events
  (``lost.message_lost``) and gaps in the publication sequence numbers of a single
  publisher (``lost.sequence_gap``: the network, or the keep-last queue overflowing while
  the node was busy);
* out: ``fix`` (PoseWithCovarianceStamped), ``fix/navsat`` (sensor_msgs/NavSatFix, with a
  ``geodetic_origin``), ``fix/low_confidence`` (PoseWithCovarianceStamped, with
  ``publish_low_confidence``: fixes that failed their consistency checks, core.robust;
  never on ``fix``), ``markers`` (visualization_msgs/MarkerArray), ``/diagnostics``
  (diagnostic_msgs/DiagnosticArray); TMA mode: ``track`` (nav_msgs/Odometry, target position
  and velocity); multi-station mode: ``accuracy_map`` (nav_msgs/OccupancyGrid, transient
  local, core.display.AccuracyMap, recomputed only when the live station set changes).

Parameters: ``python -m bearing_loc_ros.core.parameters --markdown fusion_node``.
"""

from functools import partial
import re
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.duration import Duration
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import NavSatFix
from visualization_msgs.msg import MarkerArray

from . import fusion_channels
from .core.display import AccuracyMap, AccuracyMapConfig
from .core.fusion import FusionConfig, make_core, MODE_MULTISTATION, MODE_TMA
from .core.fusion.gating import LOW_CONFIDENCE
from .ros_common import declare_schema, keep_last_qos, main_for, ParameterError, \
    topics_under_namespace
from .ros_conversions import (bearing_from_msg, ConversionError, diagnostic_array,
                              fix_markers_msg, fix_to_msg, fix_to_navsat, occupancy_grid_msg,
                              track_to_msg)

BEARING_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
#: A station id: one or more ROS name tokens separated by '/' (the topic namespace).
STATION_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')
#: New subscriptions made per discovery scan at most (the executor stays responsive when
#: many publishers appear at once; the rest are taken on the next scans).
MAX_NEW_PER_SCAN = 16
#: Run-time parameters that change only the display (the others change the core).
RUNTIME_DISPLAY = ('marker_ray_length', 'ellipsoid_sigma')
MAP_PREFIX = 'accuracy_map.'


def _parameter_error(exc):
    """A core ValueError ('field: problem' or 'options.field: problem') as ParameterError."""
    text = str(exc)
    head, _, rest = text.partition(':')
    name = head.replace('options.', '') if rest and ' ' not in head else 'estimator'
    return ParameterError(name, rest.strip() if rest else text)


def _check_station_name(name):
    if not STATION_RE.match(name):
        raise ParameterError('stations', f'{name!r} is not a valid station id (ROS name '
                             'tokens separated by /)')


def _check_stations(names):
    """Valid, distinct station ids (ParameterError naming the first problem)."""
    seen = set()
    for s in names:
        _check_station_name(s)
        if s in seen:
            raise ParameterError('stations', f'{s!r} is listed twice')
        seen.add(s)


class FusionNode(Node):
    """Fuses bearings from many stations into fixes; see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('fusion', **kwargs)
        p = declare_schema(self, 'fusion_node')
        self.channel_host = None
        if p['channels']:     # this node only hosts one fusion node per channel
            try:
                self.channel_host = fusion_channels.ChannelHost(
                    self, p['channels'], p, lambda ns, overrides: FusionNode(
                        context=self.context, namespace=ns, parameter_overrides=overrides,
                        use_global_arguments=False))
            except ValueError as exc:
                raise _parameter_error(exc) from None
            return
        self.frame_id = p['frame_id']
        self.stations_param = list(p['stations'])
        _check_stations(self.stations_param)
        self.geodetic_origin = None
        if p['geodetic_origin']:
            from .core.geodesy import geodetic_triplet
            try:
                self.geodetic_origin = geodetic_triplet(p['geodetic_origin'], 'geodetic_origin')
            except ValueError as exc:
                raise ParameterError('geodetic_origin', str(exc).partition(': ')[2]) from None
        try:
            self.core = make_core(FusionConfig.from_parameters(p), self.stations_param,
                                  p['mode'])
            self.accuracy_map = (AccuracyMap(AccuracyMapConfig(**{
                k[len(MAP_PREFIX):]: (tuple(v) if isinstance(v, list) else v)
                for k, v in p.items() if k.startswith(MAP_PREFIX) and k != MAP_PREFIX +
                'enabled'})) if p['accuracy_map.enabled'] else None)
        except ValueError as exc:
            raise _parameter_error(exc) from None
        self.config = self.core.config
        self.mode = self.core.mode
        self.ray_length = p['marker_ray_length']
        self.ellipsoid_sigma = p['ellipsoid_sigma']
        self.discover = p['discover']
        self.qos_reliability = p['qos_reliability']
        self.bearing_qos = keep_last_qos(p['qos_depth'], p['qos_reliability'])
        self._subs = {}            # station -> Subscription
        self.incompatible_qos = {}  # station -> incompatible publishers seen (QoS events)
        self._discovered = set()   # stations found by discovery (not in the parameter)
        self._seq = {}             # station -> last publication sequence number
        self._single_publisher = {}  # station -> exactly one publisher (sequence gaps valid)
        for s in self.stations_param:
            self._subscribe(s)

        pub = self.create_publisher
        self.fix_pub = pub(PoseWithCovarianceStamped, 'fix', 10)
        self.navsat_pub = (pub(NavSatFix, 'fix/navsat', 10)
                           if self.geodetic_origin is not None else None)
        self.marker_pub = pub(MarkerArray, 'markers', 10) if p['publish_markers'] else None
        # Fixes that failed their consistency checks (core.robust): never on fix; here only
        # when asked for.
        self.low_confidence_pub = (pub(PoseWithCovarianceStamped, 'fix/low_confidence', 10)
                                   if p['publish_low_confidence'] else None)
        self.diag_pub = pub(DiagnosticArray, '/diagnostics', 10)
        self.track_pub = pub(Odometry, 'track', 10) if self.mode == MODE_TMA else None
        self.map_pub = None
        self.accuracy_maps = 0          # maps published
        self.accuracy_map_ms = None     # wall time of the last map computation
        self._geometry_seen = None
        if self.accuracy_map is not None and self.mode == MODE_MULTISTATION:
            self.map_pub = pub(OccupancyGrid, 'accuracy_map', keep_last_qos(1, latched=True))

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._tick_timer = self.create_timer(self.core.tick_period_ns / 1e9, self._on_tick)
        # On /clock jumping back (a bag looping, a simulation restart) tick the core at once,
        # so its buffers are cleared at the jump rather than at the next timer period.
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True), post_callback=lambda jump: self._on_tick())
        self.create_timer(p['diagnostics_period'], self._publish_diagnostics, clock=steady)
        if self.discover:
            self.create_timer(p['discovery_period'], self._discover, clock=steady)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.fixes_published = 0
        self._log_events()
        if not self.stations_param and not self.discover:
            self.get_logger().error(
                'no stations: set stations:=[...] or discover:=true (the node idles until '
                'the stations parameter is set)')
        self.get_logger().info(
            f'fusion ({self.mode}): estimator {self.config.estimator}, trigger '
            f'{self.config.trigger}, {"interpolated" if self.config.interpolation else "nearest"}'
            f' alignment, stations {self.stations_param or "none"}'
            f'{" + discovery" if self.discover else ""}, frame {self.frame_id}')

    # ------------------------------------------------------------------ run-time parameters
    def _validate_parameters(self, params):
        """On-set callback: validate only (no side effects)."""
        try:
            self._parameter_changes(params)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _parameter_changes(self, params):
        values = {prm.name: prm.value for prm in params}
        config = self.core.config.parameter_changes(values)
        display = {k: v for k, v in values.items() if k in RUNTIME_DISPLAY}
        stations = list(values['stations'] or []) if 'stations' in values else None
        _check_stations(stations or ())
        if config:
            try:
                self.core.check_config(**config)
            except ValueError as exc:
                raise _parameter_error(exc) from None
        return config, display, stations

    def _apply_parameters(self, params):
        """Post-set callback: apply the (already validated) changes."""
        config, display, stations = self._parameter_changes(params)
        if config:
            self.config = self.core.reconfigure(**config)
            self.get_logger().info('reconfigured: ' + ', '.join(
                f'{k}={v}' for k, v in config.items()))
        self.ray_length = display.get('marker_ray_length', self.ray_length)
        self.ellipsoid_sigma = display.get('ellipsoid_sigma', self.ellipsoid_sigma)
        if stations is not None:
            for s in stations:
                self._subscribe(s)
            for s in set(self.stations_param) - set(stations):
                self._unsubscribe(s)
            self.stations_param = stations

    # ------------------------------------------------------------------ stations
    def _subscribe(self, station, wait=True):
        """Subscribe to ``<station>/bearing``; ``wait=False`` (discovered): the station is
        not waited for before it delivered a valid bearing."""
        if station in self._subs:
            return
        self.core.add_station(station, wait=wait)
        events = SubscriptionEventCallbacks(
            incompatible_qos=partial(self._on_incompatible_qos, station),
            message_lost=partial(self._on_message_lost, station))
        self._subs[station] = self.create_subscription(
            PoseWithCovarianceStamped, f'{station}/bearing', partial(self._on_bearing, station),
            self.bearing_qos, event_callbacks=events)
        self._single_publisher[station] = False

    def _unsubscribe(self, station):
        sub = self._subs.pop(station, None)
        if sub is not None:
            self.destroy_subscription(sub)
        self._discovered.discard(station)
        self._seq.pop(station, None)
        self._single_publisher.pop(station, None)
        self.incompatible_qos.pop(station, None)
        self.core.remove_station(station)

    def _discover(self):
        """Subscribe to new */bearing topics under the namespace (at most
        MAX_NEW_PER_SCAN per scan); drop discovered stations whose publishers are gone once
        they are not alive (waiting: at once; alive: after station_timeout, when stale)."""
        found = topics_under_namespace(self, '/bearing', BEARING_TYPE, STATION_RE)
        new = 0
        for station, name in found.items():
            if new < MAX_NEW_PER_SCAN and station not in self._subs \
                    and self.count_publishers(name) > 0:
                self._discovered.add(station)
                self._subscribe(station, wait=False)
                new += 1
                self.get_logger().info(f'discovered station {station} ({name})')
        for station in list(self._discovered):
            topic = f'{self.get_namespace().rstrip("/")}/{station}/bearing'
            gone = station not in found or self.count_publishers(topic) == 0
            if gone and self.core.station_state(station) != 'alive':
                self._unsubscribe(station)
                self.get_logger().info(f'station {station} left (no publisher on {topic})')

    def _count_publishers(self):
        """Refresh which stations have exactly one publisher (sequence gaps are counted for
        those only: several publishers interleave their sequence numbers)."""
        ns = self.get_namespace().rstrip('/')
        for station in self._subs:
            one = self.count_publishers(f'{ns}/{station}/bearing') == 1
            if one != self._single_publisher.get(station):
                self._seq.pop(station, None)     # a new baseline after the change
            self._single_publisher[station] = one

    def _on_message_lost(self, station, info):
        """The middleware reports messages of ``station`` lost (for example a sequence gap
        seen by a best-effort reader)."""
        self.core.count_lost(station, 'message_lost', int(info.total_count_change))

    def _on_incompatible_qos(self, station, info):
        """A publisher on <station>/bearing cannot match (typically best-effort vs reliable)."""
        self.incompatible_qos[station] = int(info.total_count)
        self.get_logger().warning(
            f'{station}/bearing: {info.total_count} publisher(s) with incompatible QoS (policy '
            f'{info.last_policy_kind}); a best-effort publisher needs qos_reliability:='
            'best_effort here, or a reliable publisher', throttle_duration_sec=10.0)

    # ------------------------------------------------------------------ data path
    def now_ns(self):
        """Node-clock time in ns, or None while ROS time has not started (no /clock yet)."""
        t = self.get_clock().now().nanoseconds
        return t if t > 0 else None

    def _on_bearing(self, station, msg, info):
        # Per-message path (N calls per epoch): the fix is published before anything else.
        # ``info``: rclpy's message info (two-argument callback), for the sequence numbers.
        now = self.now_ns()
        seq = info.get('publication_sequence_number')
        if seq is not None:
            last = self._seq.get(station)
            if last is not None and seq > last + 1 and self._single_publisher.get(station):
                self.core.count_lost(station, 'sequence_gap', seq - last - 1)
            self._seq[station] = seq
        try:
            bearing = bearing_from_msg(msg, station, expected_frame=self.frame_id)
        except ConversionError as exc:
            self.core.count_bad_message(station, exc.reason, now)
            # Throttled per station and reason on the node clock, suppressed ones counted.
            self.core.registry.warn_throttled(station, exc.reason,
                                              f'{station}: rejected bearing ({exc})',
                                              now if now is not None else 0)
            self._log_events()
            return
        # Before the first /clock message ROS time is 0: the bearing's stamp stands in.
        epochs = self.core.add_bearing(bearing, now if now is not None else bearing.stamp_ns)
        if epochs:
            self._publish_epochs(epochs)
        if self.core.has_events:
            self._log_events()

    def _on_tick(self):
        now = self.now_ns()
        if now is None:
            return
        epochs = self.core.tick(now)
        if epochs:
            self._publish_epochs(epochs)
        if self.core.has_events:
            self._log_events()
        if self.map_pub is not None and self.core.geometry_version != self._geometry_seen:
            self._geometry_seen = self.core.geometry_version
            self.publish_accuracy_map(now)

    def _log_events(self):
        log = self.get_logger()
        for level, text in self.core.drain_events():
            # rclpy binds a severity to each call site: one call per severity.
            if level == 'warn':
                log.warning(text)
            else:
                log.info(text)

    def _publish_epochs(self, epochs):
        """Publish the epochs' fixes first (the latency-critical output), then the rest."""
        fixes = [ep for ep in epochs if ep.ok]
        for ep in fixes:
            self.fix_pub.publish(fix_to_msg(ep.position, ep.covariance, ep.stamp_ns,
                                            self.frame_id))
            self.fixes_published += 1
        log = self.get_logger()
        for ep in epochs:
            if self.low_confidence_pub is not None and ep.reason == LOW_CONFIDENCE \
                    and ep.position is not None:
                self.low_confidence_pub.publish(fix_to_msg(ep.position, ep.covariance,
                                                           ep.stamp_ns, self.frame_id))
            if not ep.ok:
                log.debug(f'epoch {ep.stamp_ns / 1e9:.3f}: no fix ({ep.reason}'
                          f'{": " + ep.detail if ep.detail else ""})')
        # Markers cost ~0.5-1.5 ms per fix at N = 10: built only when someone listens.
        markers = self.marker_pub is not None and self.marker_pub.get_subscription_count() > 0
        for ep in fixes:
            if self.track_pub is not None and ep.velocity is not None:
                self.track_pub.publish(track_to_msg(ep.position, ep.velocity,
                                                    ep.state_covariance, ep.stamp_ns,
                                                    self.frame_id))
            if self.navsat_pub is not None:
                try:
                    self.navsat_pub.publish(fix_to_navsat(ep.position, ep.covariance,
                                                          ep.stamp_ns, self.geodetic_origin,
                                                          self.frame_id))
                except ValueError as exc:
                    log.warning(f'fix/navsat: {exc}', throttle_duration_sec=5.0)
            if markers:
                self.marker_pub.publish(fix_markers_msg(
                    ep, self.frame_id, self.ray_length, self.ellipsoid_sigma,
                    int(self.config.station_timeout * 1e9)))
            if ep.rejected:
                log.info(f'epoch {ep.stamp_ns / 1e9:.3f}: outlier bearing(s) from '
                         f'{", ".join(b.station for b in ep.rejected)} rejected',
                         throttle_duration_sec=5.0)

    def destroy_node(self):
        """Destroy the channel nodes this node hosts (if any), then the node."""
        if self.channel_host is not None:
            self.channel_host.destroy()
        return super().destroy_node()

    def publish_accuracy_map(self, now_ns):
        """Publish the expected-accuracy OccupancyGrid when core.display.AccuracyMap says the
        live station geometry changed (run from the tick, never per bearing)."""
        t0 = time.perf_counter()
        try:
            out = self.accuracy_map.update(self.core.geometry())
        except ValueError as exc:
            self.get_logger().warning(f'accuracy_map: {exc}', throttle_duration_sec=10.0)
            return
        if out is None:
            return
        grid, data = out
        self.map_pub.publish(occupancy_grid_msg(grid, data, now_ns, self.frame_id))
        self.accuracy_maps += 1
        self.accuracy_map_ms = 1e3 * (time.perf_counter() - t0)
        self.get_logger().info(
            f'accuracy_map: {len(self.accuracy_map.stations)} live station(s), '
            f'{grid.width}x{grid.height} cells of {grid.resolution:g} m, '
            f'{self.accuracy_map_ms:.1f} ms')

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self):
        now = self.now_ns() or 0
        self._count_publishers()
        entries = self.core.diagnostics(now)
        entries[0].values.update(fixes_published=self.fixes_published, mode=self.mode,
                                 qos_reliability=self.qos_reliability,
                                 discovered_stations=len(self._discovered))
        if not self._subs and not self.discover:
            entries[0].level = 'error'
            entries[0].message = ('no stations: set stations:=[...] or discover:=true')
        if self.map_pub is not None:
            entries[0].values.update(accuracy_maps=self.accuracy_maps, accuracy_map_ms=(
                'n/a' if self.accuracy_map_ms is None else f'{self.accuracy_map_ms:.1f}'))
        for d in entries[1:]:
            if d.hardware_id in self.incompatible_qos:
                d.values['incompatible_qos_publishers'] = self.incompatible_qos[d.hardware_id]
        self.diag_pub.publish(diagnostic_array(
            entries, self.get_fully_qualified_name().lstrip('/'), now))


main = main_for(FusionNode)


if __name__ == '__main__':
    main()
