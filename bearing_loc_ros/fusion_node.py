"""fusion_node: time-aligns the stations' bearings and publishes fixes.

Wiring only: parameters (core.parameters schema) -> the fusion pipeline
(:func:`bearing_loc_ros.core.fusion.make_core`: buffers, alignment, epochs, estimator,
outlier gate, counters), messages <-> core objects (``ros_conversions``), the node clock
(so ``use_sim_time`` with ``/clock`` and bag replay work) -> publications. The subscriptions
(discovery, loss counting, QoS events) and the publishers are ``fusion_wiring``'s.

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

from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.duration import Duration
from rclpy.node import Node

from . import fusion_channels
from .core.display import AccuracyMap, AccuracyMapConfig
from .core.fusion import FusionConfig, make_core
from .core.fusion.config import check_station_ids
from .core.warmup import cache_note, warm_up
from .discovery_probe import ProbeProcess
from .fusion_wiring import BearingInputs, FusionOutputs
from .ros_common import core_parameter_error, declare_schema, keep_last_qos, log_events, \
    main_for, ParameterError
from .ros_conversions import bearing_from_cdr, bearing_from_msg, ConversionError
from .spin import LeanExecutor

#: Run-time parameters that change only the display (the others change the core).
RUNTIME_DISPLAY = ('marker_ray_length', 'ellipsoid_sigma')


def _check_stations(names):
    """Valid, distinct station ids (ParameterError naming the first problem)."""
    try:
        check_station_ids(names)
    except ValueError as exc:
        raise core_parameter_error(exc, 'stations') from None


class FusionNode(Node):
    """Fuses bearings from many stations into fixes; see the module docstring."""

    #: Publication state, kept by FusionOutputs (read by tests and tools).
    map_pub = property(lambda self: self.outputs.map_pub)
    accuracy_maps = property(lambda self: self.outputs.accuracy_maps)
    fixes_published = property(lambda self: self.outputs.fixes_published)

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
                raise core_parameter_error(exc, 'estimator') from None
            self.add_on_set_parameters_callback(self._refuse_on_channel_host)
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
            self.accuracy_map = (AccuracyMap(AccuracyMapConfig.from_parameters(p))
                                 if p['accuracy_map.enabled'] else None)
        except ValueError as exc:
            raise core_parameter_error(exc, 'estimator') from None
        self.config = self.core.config
        self.mode = self.core.mode
        # The one-fix numerics are compiled (or loaded from the cache) now, not on a fix.
        warm_seconds = warm_up()
        self.discover = p['discover']
        self.qos_reliability = p['qos_reliability']
        self.bearing_qos = keep_last_qos(p['qos_depth'], p['qos_reliability'])
        probe = None
        if self.discover and p['discovery_probe']:
            probe = ProbeProcess(
                ['--namespace', self.get_namespace(), '--qos-depth', str(p['qos_depth']),
                 '--qos-reliability', p['qos_reliability'], '--frame-id', self.frame_id],
                log=self.get_logger())
        self.inputs = BearingInputs(self, self.core, self.bearing_qos, self._on_bearing,
                                    probe)
        # The inputs' bookkeeping under the node's former names (read by tests and tools).
        self._subs, self._seq = self.inputs.subs, self.inputs.seq
        self._single_publisher = self.inputs.single_publisher
        self.incompatible_qos = self.inputs.incompatible_qos
        for s in self.stations_param:
            self.inputs.subscribe(s)
        self.outputs = FusionOutputs(self, p, self.mode, self.frame_id, self.geodetic_origin,
                                     self.accuracy_map)
        self._geometry_seen = None

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._tick_timer = self.create_timer(self.core.tick_period_ns / 1e9, self._on_tick)
        # On /clock jumping back (a bag looping, a simulation restart) tick the core at once,
        # so its buffers are cleared at the jump rather than at the next timer period.
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True), post_callback=lambda jump: self._on_tick())
        self.create_timer(p['diagnostics_period'], self._publish_diagnostics, clock=steady)
        if self.discover:
            self.create_timer(p['discovery_period'], self.inputs.discover, clock=steady)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._log_events()
        floored = sorted(set(self.config.sigma_floors()[1]) - set(self.stations_param))
        if floored and not self.discover:
            self.get_logger().warning(
                f'station_sigma_floors names {", ".join(floored)}, not in stations: no effect '
                'unless such a station is added')
        if not self.stations_param and not self.discover:
            self.get_logger().error(
                'no stations: set stations:=[...] or discover:=true (the node idles until '
                'the stations parameter is set)')
        self.get_logger().info(
            f'fusion ({self.mode}): estimator {self.config.estimator}, trigger '
            f'{self.config.trigger}, {"interpolated" if self.config.interpolation else "nearest"}'
            f' alignment, stations {self.stations_param or "none"}'
            f'{" + discovery" if self.discover else ""}, frame {self.frame_id}; one-fix '
            f'numerics ready in {warm_seconds:.1f} s{cache_note()}')

    # ------------------------------------------------------------------ run-time parameters
    def _refuse_on_channel_host(self, params):
        """A channel host runs no pipeline: a run-time change here would be accepted and do
        nothing (``use_sim_time`` too: the channel nodes took it at start-up), so it is
        refused with the nodes that take it."""
        names = [x.name for x in params]
        where = ', '.join(n.get_fully_qualified_name()
                          for n in self.channel_host.nodes.values())
        return SetParametersResult(successful=False, reason=(
            f'{", ".join(names)}: this node only hosts the fusion nodes of channels; set '
            f'parameters on {where}'))

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
                raise core_parameter_error(exc, 'estimator') from None
        return config, display, stations

    def _apply_parameters(self, params):
        """Post-set callback: apply the (already validated) changes."""
        config, display, stations = self._parameter_changes(params)
        if config:
            self.config = self.core.reconfigure(**config)
            self.get_logger().info('reconfigured: ' + ', '.join(
                f'{k}={v}' for k, v in config.items()))
        out = self.outputs
        out.ray_length = display.get('marker_ray_length', out.ray_length)
        out.ellipsoid_sigma = display.get('ellipsoid_sigma', out.ellipsoid_sigma)
        if stations is not None:
            self.inputs.set_stations(stations, self.stations_param)
            self.stations_param = stations

    # ------------------------------------------------------------------ data path
    def now_ns(self):
        """Node-clock time in ns, or None while ROS time has not started (no /clock yet)."""
        t = self.get_clock().now().nanoseconds
        return t if t > 0 else None

    def _on_bearing(self, station, msg, info):
        # Per-message path (N calls per epoch): the fix is published before anything else.
        # ``msg``: the CDR bytes of the raw subscription (or a message object);
        # ``info``: rclpy's message info (two-argument callback), for the sequence numbers.
        now = self.now_ns()
        self.inputs.count_sequence(station, info)
        try:
            if type(msg) is bytes:
                bearing = bearing_from_cdr(msg, station, expected_frame=self.frame_id)
            else:
                bearing = bearing_from_msg(msg, station, expected_frame=self.frame_id)
        except ConversionError as exc:
            self.core.count_bad_message(station, exc.reason, now)
            # Throttled per station and reason on the node clock, suppressed ones counted.
            self.core.registry.warn_throttled(station, exc.reason,
                                              f'{station}: rejected bearing ({exc})',
                                              now if now is not None else 0)
            self._log_events()
            return
        # Before the first /clock message ROS time is 0 (now None): the core's stand-in.
        epochs = self.core.add_bearing(bearing, now)
        if epochs:
            self._publish_epochs(epochs)
            self.core.settle()
        if self.core.has_events:
            self._log_events()

    def _on_tick(self):
        now = self.now_ns()
        if now is None:
            return
        epochs = self.core.tick(now)
        if epochs:
            self._publish_epochs(epochs)
            self.core.settle()
        if self.core.has_events:
            self._log_events()
        if self.map_pub is not None and (self.core.geometry_version != self._geometry_seen
                                         or self.accuracy_map.pending):
            # pending: stations moved while a recomputation was not due; retried each tick.
            self._geometry_seen = self.core.geometry_version
            self.outputs.publish_accuracy_map(self.core.geometry(), now)

    def _log_events(self):
        log_events(self.get_logger(), self.core.drain_events())

    def _publish_epochs(self, epochs):
        """Publish the epochs' fixes first (the latency-critical output), then the rest."""
        self.outputs.publish_epochs(epochs, self.config.station_timeout)

    def destroy_node(self):
        """Destroy the channel nodes this node hosts (if any), then the node."""
        if self.channel_host is not None:
            self.channel_host.destroy()
        if getattr(self, 'inputs', None) is not None:
            self.inputs.stop_probe()
            self.inputs.destroy_events()
        if getattr(self, 'outputs', None) is not None:
            self.outputs.destroy_events()
        return super().destroy_node()

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self):
        now = self.now_ns() or 0
        self.inputs.poll_events()
        self.outputs.poll_events()
        self.inputs.count_publishers()
        entries = self.core.diagnostics(now)
        entries[0].values.update(fixes_published=self.fixes_published, mode=self.mode,
                                 qos_reliability=self.qos_reliability,
                                 discovered_stations=len(self.inputs.discovered),
                                 **self.inputs.probe_diagnostics())
        if not self._subs and not self.discover:
            entries[0].level = 'error'
            entries[0].message = ('no stations: set stations:=[...] or discover:=true')
        self.outputs.publish_diagnostics(entries, now, self.incompatible_qos)


# Spun by spin.LeanExecutor: at 10 stations x 10 Hz rclpy's per-callback Tasks cost the
# node as much as its own per-bearing work (docs/benchmarks.md).
main = main_for(FusionNode, executor=LeanExecutor)


if __name__ == '__main__':
    main()
