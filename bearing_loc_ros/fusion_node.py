"""fusion_node: time-aligns the stations' bearings and publishes fixes (DESIGN.md).

A thin rclpy shell around :class:`bearing_loc_ros.core.fusion.FusionCore` (the whole
per-epoch pipeline: buffers, alignment, epochs, estimator, outlier gate, counters). The node
only converts messages (``ros_conversions``), feeds the core the node-clock time (so
``use_sim_time`` with ``/clock`` and bag replay work) and publishes what it returns.

Topics (relative, so namespaces and remapping work):

* in: ``<station>/bearing`` geometry_msgs/PoseWithCovarianceStamped per station (the
  ``stations`` parameter, plus topics found by discovery), reliable, keep-last ``qos_depth``;
* out: ``fix`` (PoseWithCovarianceStamped), ``fix/navsat`` (sensor_msgs/NavSatFix, only with a
  ``geodetic_origin``), ``markers`` (visualization_msgs/MarkerArray), ``/diagnostics``
  (diagnostic_msgs/DiagnosticArray); TMA mode: ``track`` (nav_msgs/Odometry, position and
  velocity of the target, :func:`track_to_msg`); multi-station mode: ``accuracy_map``
  (nav_msgs/OccupancyGrid, transient local, the expected error of the live station set from
  core.planning.occupancy_error_map, recomputed only when that set changes).

Parameters, QoS, diagnostics keys and examples: README "Fusion node".
"""

from functools import partial
import re
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.duration import Duration
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from .core import estimators
from .core.fusion import (error_ellipsoid, FusionConfig, LEVEL_ERROR, LEVEL_OK, LEVEL_WARN,
                          make_core, MODE_MULTISTATION, MODE_TMA, MODES,
                          ray_endpoints, TMA_ESTIMATORS)
from .core.planning import GridSpec, MODELS, occupancy_error_map, SCALES, Stations
from .ros_common import (declare, declare_array, diagnostic_status, ERROR, main_for, OK,
                         ParameterError, WARN)
from .ros_conversions import (bearing_from_msg, ConversionError, fix_to_msg, fix_to_navsat,
                              ns_to_time)

BEARING_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
#: A station id: one or more ROS name tokens separated by '/' (the topic namespace).
STATION_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')
#: Parameters that may change at run time (everything else is read-only), and the core
#: configuration field each one maps to. Estimator options go to FusionConfig.estimator_options.
RUNTIME_CONFIG = ('estimator', 'min_stations', 'outlier_gate', 'target_speed')
ESTIMATOR_OPTIONS = ('max_iterations', 'tolerance', 'reference_range', 'step_decay')
RUNTIME_DISPLAY = ('marker_ray_length', 'ellipsoid_sigma')
LEVELS = {LEVEL_OK: OK, LEVEL_WARN: WARN, LEVEL_ERROR: ERROR}
#: Rotational (co)variance of the unknown orientation and angular velocity in ``track``, rad².
UNKNOWN_ROTATION_VARIANCE = 1e6
#: Accuracy map: automatic size = this × the largest horizontal station distance from the
#: centre, at least AUTO_MIN_SIZE m; automatic resolution = size / AUTO_CELLS.
AUTO_SIZE_FACTOR = 3.0
AUTO_MIN_SIZE = 100.0
AUTO_CELLS = 100
MAX_MAP_CELLS = 2000


def track_to_msg(position, velocity, state_covariance, stamp_ns, frame_id):
    """TMA target state -> nav_msgs/Odometry (the ``track`` topic).

    header.frame_id = child_frame_id = ``frame_id`` (the world frame): the velocity is
    expressed in the world frame, and nav_msgs/Odometry defines the twist in
    child_frame_id, so both name the world frame. pose.pose.position = position (3,) m,
    orientation identity; pose.covariance[0..2, 0..2] = state_covariance[:3, :3] (m²);
    twist.twist.linear = velocity (3,) m/s, twist.covariance[0..2, 0..2] =
    state_covariance[3:, 3:] (m²/s²); the rotational blocks (orientation, angular velocity:
    not estimated) get variance UNKNOWN_ROTATION_VARIANCE. The position-velocity
    cross-covariance (state_covariance[:3, 3:], m²/s) has no field in Odometry and is
    dropped. Belongs in ros_conversions (kept here while that module is being edited).
    """
    C = np.asarray(state_covariance, dtype=float)
    msg = Odometry()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = frame_id
    p, v = msg.pose.pose.position, msg.twist.twist.linear
    p.x, p.y, p.z = (float(x) for x in position)
    v.x, v.y, v.z = (float(x) for x in velocity)
    msg.pose.pose.orientation.w = 1.0
    for block, target in ((C[:3, :3], msg.pose), (C[3:, 3:], msg.twist)):
        cov = np.zeros((6, 6))
        cov[:3, :3] = block
        cov[3, 3] = cov[4, 4] = cov[5, 5] = UNKNOWN_ROTATION_VARIANCE
        target.covariance = cov.ravel().tolist()
    return msg


def _parameter_error(exc):
    """A core ValueError ('field: problem' or 'options.field: problem') as ParameterError."""
    text = str(exc)
    head, _, rest = text.partition(':')
    name = head.replace('options.', '') if rest and ' ' not in head else 'estimator'
    return ParameterError(name, rest.strip() if rest else text)


class FusionNode(Node):
    """Fuses bearings from many stations into fixes; see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('fusion', **kwargs)
        p = self._declare_parameters()
        self.frame_id = p['frame_id']
        self.stations_param = list(p['stations'])
        self.geodetic_origin = None
        if p['geodetic_origin']:
            from .core.geodesy import geodetic_triplet
            try:
                self.geodetic_origin = geodetic_triplet(p['geodetic_origin'], 'geodetic_origin')
            except ValueError as exc:
                raise ParameterError('geodetic_origin', str(exc).partition(': ')[2]) from None
        for s in self.stations_param:
            self._check_station_name(s)
        if p['mode'] != 'auto' and p['mode'] not in MODES:
            raise ParameterError('mode', f'{p["mode"]!r} is not one of '
                                 f'{["auto"] + sorted(MODES)}')
        self.config = FusionConfig(
            frame_id=self.frame_id, trigger=p['trigger'], rate=p['rate'],
            max_latency=p['max_latency'], sync_tolerance=p['sync_tolerance'],
            interpolation=p['interpolation'], max_interpolation_gap=p['max_interpolation_gap'],
            station_timeout=p['station_timeout'], buffer_size=p['buffer_size'],
            buffer_age=p['buffer_age'], min_stations=p['min_stations'],
            estimator=p['estimator'],
            estimator_options={k: p[k] for k in ESTIMATOR_OPTIONS},
            outlier_gate=p['outlier_gate'], time_jump_tolerance=p['time_jump_tolerance'],
            target_speed=p['target_speed'], window=p['window'],
            speed_reference=p['speed_reference'])
        try:
            self.core = make_core(self.config, self.stations_param, p['mode'])
        except ValueError as exc:
            raise _parameter_error(exc) from None
        self.mode = self.core.mode
        self.ray_length = p['marker_ray_length']
        self.ellipsoid_sigma = p['ellipsoid_sigma']
        self.publish_markers = p['publish_markers']
        self.discover = p['discover']

        reliability = (ReliabilityPolicy.BEST_EFFORT if p['qos_reliability'] == 'best_effort'
                       else ReliabilityPolicy.RELIABLE)
        self.bearing_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=p['qos_depth'],
                                      reliability=reliability,
                                      durability=DurabilityPolicy.VOLATILE)
        self._subs = {}            # station -> Subscription
        self.incompatible_qos = {}  # station -> incompatible publishers seen (QoS events)
        self._discovered = set()   # stations found by discovery (not in the parameter)
        for s in self.stations_param:
            self._subscribe(s)

        self.fix_pub = self.create_publisher(PoseWithCovarianceStamped, 'fix', 10)
        self.navsat_pub = (self.create_publisher(NavSatFix, 'fix/navsat', 10)
                           if self.geodetic_origin is not None else None)
        self.marker_pub = (self.create_publisher(MarkerArray, 'markers', 10)
                           if self.publish_markers else None)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.track_pub = (self.create_publisher(Odometry, 'track', 10)
                          if self.mode == MODE_TMA else None)

        #: Planning hook: callables f(node, geometry, now_ns) run when the live station
        #: geometry changes (core.geometry(): station -> (position, σ_θ, σ_ψ)); a later task
        #: registers an accuracy-map publisher (core.planning) here.
        self.geometry_hooks = []
        self._geometry_seen = None
        self.map_config = p['accuracy_map']
        self.map_pub = None
        self.accuracy_maps = 0          # maps published
        self.accuracy_map_ms = None     # wall time of the last map computation
        self.accuracy_map_last = None   # (grid, OccupancyErrorMap or None) last published
        self._map_key = None            # (station names, positions) of the last map
        if self.map_config['enabled'] and self.mode == MODE_MULTISTATION:
            latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.map_pub = self.create_publisher(OccupancyGrid, 'accuracy_map', latched)
            self.geometry_hooks.append(FusionNode.publish_accuracy_map)

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._tick_timer = self.create_timer(self.core.tick_period_ns / 1e9, self._on_tick)
        # On /clock jumping back (a bag looping, a simulation restart) tick the core at once,
        # so its buffers are cleared at the jump rather than at the next timer period.
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True), post_callback=self._on_time_jump)
        self._diag_timer = self.create_timer(p['diagnostics_period'], self._publish_diagnostics,
                                             clock=steady)
        self._discovery_timer = (self.create_timer(p['discovery_period'], self._discover,
                                                   clock=steady) if self.discover else None)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.fixes_published = 0
        self._log_events()
        self.get_logger().info(
            f'fusion ({self.mode}): estimator {self.config.estimator}, trigger '
            f'{self.config.trigger}, {"interpolated" if self.config.interpolation else "nearest"}'
            f' alignment, stations {self.stations_param or "none"}'
            f'{" + discovery" if self.discover else ""}, frame {self.frame_id}')

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self):
        ro = dict(read_only=True)
        p = {}
        p['mode'] = declare(self, 'mode', 'auto', 'Fusion mode: auto (tma for tma_* '
                            'estimators, else multistation), ' + ', '.join(sorted(MODES)),
                            **ro)
        p['frame_id'] = declare(self, 'frame_id', 'map', 'World frame; bearings in another '
                                'frame are rejected (counted as bad.wrong_frame)', **ro)
        p['stations'] = declare_array(self, 'stations', [], 'Station ids; subscribes to '
                                      '<station>/bearing relative to the node namespace',
                                      kind=str)
        p['discover'] = declare(self, 'discover', False, 'Also subscribe to any */bearing '
                                'PoseWithCovarianceStamped topic under the namespace', **ro)
        p['discovery_period'] = declare(self, 'discovery_period', 1.0, 'Wall seconds between '
                                        'topic discovery scans', min_value=0.05,
                                        max_value=3600.0, **ro)
        p['qos_depth'] = declare(self, 'qos_depth', 10, 'Keep-last depth of the bearing '
                                 'subscriptions', min_value=1, max_value=10000, **ro)
        p['qos_reliability'] = declare(self, 'qos_reliability', 'reliable', 'reliable or '
                                       'best_effort (best_effort also matches best-effort '
                                       'publishers)', **ro)
        if p['qos_reliability'] not in ('reliable', 'best_effort'):
            raise ParameterError('qos_reliability', f'{p["qos_reliability"]!r} is not '
                                 'reliable or best_effort')
        p['trigger'] = declare(self, 'trigger', 'event', 'Epoch trigger: event (all live '
                               'stations reported) or timer (every 1/rate s after '
                               'max_latency)', **ro)
        p['rate'] = declare(self, 'rate', 10.0, 'Timer epoch rate (and tick rate), Hz',
                            min_value=0.01, max_value=1000.0, **ro)
        p['max_latency'] = declare(self, 'max_latency', 0.2, 'Timer mode: wait this long for '
                                   'late bearings before an epoch is processed, s',
                                   min_value=0.0, max_value=60.0, **ro)
        p['sync_tolerance'] = declare(self, 'sync_tolerance', 0.05, 'Nearest alignment: '
                                      'largest |stamp - epoch|, s', min_value=0.0,
                                      max_value=60.0, **ro)
        p['interpolation'] = declare(self, 'interpolation', False, 'Interpolate between '
                                     'bracketing bearings (angle-aware)', **ro)
        p['max_interpolation_gap'] = declare(self, 'max_interpolation_gap', 1.0, 'Longest '
                                             'gap between bracketing bearings, s',
                                             min_value=1e-6, max_value=3600.0, **ro)
        p['station_timeout'] = declare(self, 'station_timeout', 5.0, 'A station is stale '
                                       'after this long without a bearing, s',
                                       min_value=1e-3, max_value=3600.0, **ro)
        p['buffer_size'] = declare(self, 'buffer_size', 50, 'Bearings buffered per station',
                                   min_value=2, max_value=100000, **ro)
        p['buffer_age'] = declare(self, 'buffer_age', 10.0, 'Bearings older than this are '
                                  'dropped from the buffers, s', min_value=1e-3,
                                  max_value=3600.0, **ro)
        p['time_jump_tolerance'] = declare(self, 'time_jump_tolerance', 0.1, 'The clock '
                                           'going back more than this clears the buffers, s',
                                           min_value=0.0, max_value=3600.0, **ro)
        p['estimator'] = declare(self, 'estimator', estimators.DEFAULT_ESTIMATOR,
                                 'Estimator: ' + ', '.join(sorted(estimators.ESTIMATORS))
                                 + '; single moving station (TMA): '
                                 + ', '.join(sorted(TMA_ESTIMATORS)))
        p['target_speed'] = declare(self, 'target_speed', 0.0, 'TMA speed prior v_c, m/s '
                                    '(required > 0 for tma_* estimators; seed 001)',
                                    min_value=0.0, max_value=1e6)
        p['window'] = declare(self, 'window', 120.0, 'TMA: bearings of the last window '
                              'seconds are used', min_value=1e-3, max_value=1e6, **ro)
        p['speed_reference'] = declare(self, 'speed_reference', 'relative', 'TMA: the speed '
                                       'prior is on the relative (target - station, seed '
                                       '001) or ground (target) velocity', **ro)
        p['min_stations'] = declare(self, 'min_stations', 2, 'Fewest stations in a fix',
                                    min_value=2, max_value=10000)
        p['outlier_gate'] = declare(self, 'outlier_gate', 0.999, 'chi-square gate '
                                    'probability (1 dof per angle); 1.0 disables the gate',
                                    min_value=0.5, max_value=1.0)
        p['max_iterations'] = declare(self, 'max_iterations', 50, 'Iterative estimators: '
                                      'iteration limit', min_value=1, max_value=100000)
        p['tolerance'] = declare(self, 'tolerance', 1e-9, 'Iterative estimators: relative '
                                 'step tolerance', min_value=1e-15, max_value=1.0)
        p['reference_range'] = declare(self, 'reference_range', float(
            estimators.DEFAULT_REFERENCE_RANGE), 'wmle: reference range d_ref, m',
            min_value=1e-3, max_value=1e9)
        p['step_decay'] = declare(self, 'step_decay', 1.0, 'ctls/ctls_am: Newton step '
                                  'factor mu (seed 000 eq. (20))', min_value=1e-6,
                                  max_value=1.0)
        p['geodetic_origin'] = declare_array(self, 'geodetic_origin', [], '[lat_deg, lon_deg, '
                                             'alt_m] (WGS84) of the ENU frame; enables '
                                             'fix/navsat', kind=float, read_only=True)
        p['publish_markers'] = declare(self, 'publish_markers', True, 'Publish markers', **ro)
        p['marker_ray_length'] = declare(self, 'marker_ray_length', 0.0, 'Length of the '
                                         'bearing rays, m; 0 = 1.2 x the distance to the fix',
                                         min_value=0.0, max_value=1e9)
        p['ellipsoid_sigma'] = declare(self, 'ellipsoid_sigma', 3.0, 'Error ellipsoid '
                                       'marker size in standard deviations',
                                       min_value=0.1, max_value=10.0)
        p['diagnostics_period'] = declare(self, 'diagnostics_period', 1.0, 'Wall seconds '
                                          'between /diagnostics messages', min_value=0.01,
                                          max_value=3600.0, **ro)
        p['accuracy_map'] = self._declare_map_parameters()
        return p

    def _declare_map_parameters(self):
        ro = dict(read_only=True)
        m = {}
        m['enabled'] = declare(self, 'accuracy_map.enabled', True, 'Publish the expected-'
                               'accuracy OccupancyGrid on accuracy_map (multistation mode)',
                               **ro)
        m['size'] = declare(self, 'accuracy_map.size', 0.0, 'Side of the square map, m; 0 = '
                            f'{AUTO_SIZE_FACTOR:g} x the largest horizontal station distance '
                            f'from the centre (at least {AUTO_MIN_SIZE:g} m)', min_value=0.0,
                            max_value=1e8, **ro)
        m['resolution'] = declare(self, 'accuracy_map.resolution', 0.0, 'Cell size, m; 0 = '
                                  f'size / {AUTO_CELLS}', min_value=0.0, max_value=1e7, **ro)
        m['altitude'] = declare(self, 'accuracy_map.altitude', 0.0, 'Target altitude of the '
                                'map (world z), m', min_value=-1e6, max_value=1e6, **ro)
        m['center'] = declare_array(self, 'accuracy_map.center', [], '[x, y] centre of the '
                                    'map, m; [] = centroid of the live stations', kind=float,
                                    read_only=True)
        m['model'] = declare(self, 'accuracy_map.model', 'crlb', 'Error model: '
                             + ', '.join(MODELS), **ro)
        m['scale'] = declare(self, 'accuracy_map.scale', 'linear', 'Cell value scale: '
                             + ', '.join(SCALES), **ro)
        m['min_error'] = declare(self, 'accuracy_map.min_error', 0.0, 'Error mapped to cell '
                                 'value 0, m', min_value=0.0, max_value=1e9, **ro)
        m['max_error'] = declare(self, 'accuracy_map.max_error', 100.0, 'Error mapped to cell '
                                 'value 100 (and above), m', min_value=1e-9, max_value=1e9,
                                 **ro)
        m['move_threshold'] = declare(self, 'accuracy_map.move_threshold', 0.0, 'Recompute '
                                      'when a station moved more than this, m; 0 = one cell',
                                      min_value=0.0, max_value=1e9, **ro)
        if m['model'] not in MODELS:
            raise ParameterError('accuracy_map.model', f'{m["model"]!r} is not one of '
                                 f'{list(MODELS)}')
        if m['scale'] not in SCALES:
            raise ParameterError('accuracy_map.scale', f'{m["scale"]!r} is not one of '
                                 f'{list(SCALES)}')
        if not m['max_error'] > m['min_error']:
            raise ParameterError('accuracy_map.max_error', 'must exceed accuracy_map.min_error')
        if m['scale'] == 'log' and m['min_error'] <= 0.0:
            raise ParameterError('accuracy_map.min_error', 'must be > 0 m for the log scale')
        if m['center'] and len(m['center']) != 2:
            raise ParameterError('accuracy_map.center', 'expected [] or [x, y]')
        if m['size'] > 0.0 and m['resolution'] > 0.0 and \
                m['size'] / m['resolution'] > MAX_MAP_CELLS:
            raise ParameterError('accuracy_map.resolution', f'size / resolution exceeds '
                                 f'{MAX_MAP_CELLS} cells per side')
        return m

    @staticmethod
    def _check_station_name(name):
        if not STATION_RE.match(name):
            raise ParameterError('stations', f'{name!r} is not a valid station id (ROS name '
                                 'tokens separated by /)')

    def _validate_parameters(self, params):
        """On-set callback: validate only (no side effects)."""
        try:
            self._parameter_changes(params)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _parameter_changes(self, params):
        config, display, stations = {}, {}, None
        options = dict(self.core.config.estimator_options)
        for prm in params:
            if prm.name in RUNTIME_CONFIG:
                config[prm.name] = prm.value
            elif prm.name in ESTIMATOR_OPTIONS:
                options[prm.name] = prm.value
            elif prm.name in RUNTIME_DISPLAY:
                display[prm.name] = prm.value
            elif prm.name == 'stations':
                stations = list(prm.value or [])
                for s in stations:
                    self._check_station_name(s)
        if options != self.core.config.estimator_options:
            config['estimator_options'] = options
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
            self.core.reconfigure(**config)
            self.config = self.core.config
            self.get_logger().info('reconfigured: ' + ', '.join(
                f'{k}={v}' for k, v in config.items()))
        if 'marker_ray_length' in display:
            self.ray_length = display['marker_ray_length']
        if 'ellipsoid_sigma' in display:
            self.ellipsoid_sigma = display['ellipsoid_sigma']
        if stations is not None:
            for s in stations:
                if s not in self._subs:
                    self._subscribe(s)
            for s in set(self.stations_param) - set(stations):
                self._unsubscribe(s)
            self.stations_param = stations

    # ------------------------------------------------------------------ stations
    def _subscribe(self, station):
        if station in self._subs:
            return
        self.core.add_station(station)
        events = SubscriptionEventCallbacks(
            incompatible_qos=partial(self._on_incompatible_qos, station))
        self._subs[station] = self.create_subscription(
            PoseWithCovarianceStamped, f'{station}/bearing', partial(self._on_bearing, station),
            self.bearing_qos, event_callbacks=events)

    def _unsubscribe(self, station):
        sub = self._subs.pop(station, None)
        if sub is not None:
            self.destroy_subscription(sub)
        self._discovered.discard(station)
        self.core.remove_station(station)

    def _namespace_prefix(self):
        ns = self.get_namespace()
        return ns if ns.endswith('/') else ns + '/'

    def _discover(self):
        """Subscribe to new */bearing topics under the namespace; drop vanished ones."""
        prefix = self._namespace_prefix()
        found = set()
        for name, types in self.get_topic_names_and_types():
            if (not name.startswith(prefix) or not name.endswith('/bearing')
                    or BEARING_TYPE not in types):
                continue
            station = name[len(prefix):-len('/bearing')]
            if not station or not STATION_RE.match(station):
                continue
            found.add(station)
            if station not in self._subs and self.count_publishers(name) > 0:
                self._discovered.add(station)
                self._subscribe(station)
                self.get_logger().info(f'discovered station {station} ({name})')
        for station in list(self._discovered):
            topic = prefix + station + '/bearing'
            gone = station not in found or self.count_publishers(topic) == 0
            if gone and self.core.station_state(station) != 'alive':
                self._unsubscribe(station)
                self.get_logger().info(f'station {station} left (no publisher on {topic})')

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

    def _on_bearing(self, station, msg):
        # The per-message path (N calls per epoch): no logging, no allocation beyond the
        # conversion unless something happened; the fix is published before anything else.
        now = self.now_ns()
        try:
            bearing = bearing_from_msg(msg, station, expected_frame=self.frame_id)
        except ConversionError as exc:
            self.core.count_bad_message(station, exc.reason, now)
            self.get_logger().warning(f'{station}: rejected bearing ({exc})',
                                      throttle_duration_sec=5.0)
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
        version = self.core.geometry_version
        if self.geometry_hooks and version != self._geometry_seen:
            self._geometry_seen = version
            geometry = self.core.geometry()
            for hook in self.geometry_hooks:
                hook(self, geometry, now)

    def _on_time_jump(self, jump):
        self._on_tick()

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
        fixes = []
        for ep in epochs:
            if not ep.ok:
                continue
            if not (np.all(np.isfinite(ep.position)) and np.all(np.isfinite(ep.covariance))):
                continue    # the core never returns these; belt and braces
            self.fix_pub.publish(fix_to_msg(ep.position, ep.covariance, ep.stamp_ns,
                                            self.frame_id))
            self.fixes_published += 1
            fixes.append(ep)
        for ep in epochs:
            if not ep.ok:
                self.get_logger().debug(f'epoch {ep.stamp_ns / 1e9:.3f}: no fix ({ep.reason}'
                                        f'{": " + ep.detail if ep.detail else ""})')
        # Markers cost ~0.5-1.5 ms per fix at N = 10: built only when someone listens.
        markers = (self.marker_pub is not None
                   and self.marker_pub.get_subscription_count() > 0)
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
                    self.get_logger().warning(f'fix/navsat: {exc}', throttle_duration_sec=5.0)
            if markers:
                self.marker_pub.publish(self.markers(ep))
            if ep.rejected:
                self.get_logger().info(
                    f'epoch {ep.stamp_ns / 1e9:.3f}: outlier bearing(s) from '
                    f'{", ".join(b.station for b in ep.rejected)} rejected')

    def markers(self, ep):
        """MarkerArray of an epoch: rays (used green, rejected red), fix sphere, ellipsoid."""
        stamp = ns_to_time(ep.stamp_ns)
        life = Duration(seconds=self.config.station_timeout).to_msg()
        out = MarkerArray()
        rays = Marker(type=Marker.LINE_LIST, action=Marker.ADD, ns='bearings', id=0,
                      lifetime=life)
        rays.header.stamp, rays.header.frame_id = stamp, self.frame_id
        rays.pose.orientation.w = 1.0
        rays.scale.x = 0.002 * max(1.0, self._scene_size(ep))
        green, red = ColorRGBA(r=0.1, g=0.8, b=0.2, a=0.9), ColorRGBA(r=0.9, g=0.1, b=0.1, a=0.9)
        for group, color in ((ep.bearings, green), (ep.rejected, red)):
            if not group:
                continue
            pos = np.array([b.position for b in group])
            if self.ray_length > 0.0:
                length = self.ray_length
            else:
                length = 1.2 * np.linalg.norm(pos - ep.position, axis=1)
            seg = ray_endpoints(pos, [b.azimuth for b in group], [b.elevation for b in group],
                                length)
            for a, b in seg:
                rays.points += [Point(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                                Point(x=float(b[0]), y=float(b[1]), z=float(b[2]))]
                rays.colors += [color, color]
        out.markers.append(rays)
        x, y, z = (float(v) for v in ep.position)
        diam, q = error_ellipsoid(ep.covariance, self.ellipsoid_sigma)
        size = 0.01 * self._scene_size(ep)
        for mid, ns, scale, quat, color in (
                (1, 'fix', (size, size, size), (0.0, 0.0, 0.0, 1.0),
                 ColorRGBA(r=0.1, g=0.3, b=1.0, a=1.0)),
                (2, 'ellipsoid', diam, q, ColorRGBA(r=0.2, g=0.5, b=1.0, a=0.3))):
            m = Marker(type=Marker.SPHERE, action=Marker.ADD, ns=ns, id=mid, lifetime=life,
                       color=color)
            m.header.stamp, m.header.frame_id = stamp, self.frame_id
            m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, z
            o = m.pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in quat)
            m.scale.x, m.scale.y, m.scale.z = (max(float(v), 1e-6) for v in scale)
            out.markers.append(m)
        return out

    @staticmethod
    def _scene_size(ep):
        pos = np.array([b.position for b in ep.bearings] + [ep.position])
        return float(max(1.0, np.max(np.ptp(pos, axis=0))))

    # ------------------------------------------------------------------ accuracy map
    def map_grid(self, positions):
        """GridSpec of the accuracy map for live station positions (N, 3), m.

        Centre: ``accuracy_map.center`` or the stations' horizontal centroid; side
        ``accuracy_map.size`` or AUTO_SIZE_FACTOR x the largest horizontal distance of a
        station from the centre (>= AUTO_MIN_SIZE); cells of ``accuracy_map.resolution``
        (or side / AUTO_CELLS), at ``accuracy_map.altitude``.
        """
        m = self.map_config
        pos = np.asarray(positions, dtype=float).reshape(-1, 3)
        c = np.asarray(m['center'], dtype=float) if m['center'] else pos[:, :2].mean(axis=0)
        size = m['size']
        if size <= 0.0:
            reach = float(np.max(np.hypot(*(pos[:, :2] - c).T))) if len(pos) else 0.0
            size = max(AUTO_MIN_SIZE, AUTO_SIZE_FACTOR * reach)
        res = m['resolution'] if m['resolution'] > 0.0 else size / AUTO_CELLS
        n = max(1, min(MAX_MAP_CELLS, int(round(size / res))))
        half = 0.5 * n * res
        return GridSpec(float(c[0] - half), float(c[1] - half), float(res), n, n,
                        float(m['altitude']))

    def _map_changed(self, names, positions):
        if self._map_key is None:
            return True
        old_names, old_pos = self._map_key
        if names != old_names:
            return True
        if not names:
            return False
        thr = self.map_config['move_threshold']
        if thr <= 0.0 and self.accuracy_map_last is not None:
            thr = self.accuracy_map_last[0].resolution
        return bool(np.max(np.linalg.norm(positions - old_pos, axis=1)) > thr)

    def publish_accuracy_map(self, geometry, now_ns):
        """Geometry hook: publish the expected-accuracy OccupancyGrid of the live stations.

        Runs from the housekeeping tick only when core.geometry_version changed, and
        recomputes only when the set of live stations changed or one of them moved more
        than ``accuracy_map.move_threshold``: never per bearing. ε = sqrt(trace P) per cell
        (core.planning.occupancy_error_map, model ``accuracy_map.model``, σ from each
        station's newest bearing), cell value = error_to_occupancy(ε, min_error, max_error,
        scale) (README "Fusion node"). No live station: every cell −1 (unknown) on the last
        grid.
        """
        names = sorted(geometry)
        positions = np.array([geometry[s][0] for s in names]).reshape(-1, 3)
        if not self._map_changed(names, positions):
            return
        m = self.map_config
        t0 = time.perf_counter()
        if names:
            sel = np.array([geometry[s][2] for s in names], dtype=float)
            try:
                stations = Stations.from_arrays(
                    positions, [geometry[s][1] for s in names], sel,
                    has_elevation=np.isfinite(sel), names=names)
                grid = self.map_grid(positions)
                om = occupancy_error_map(stations, grid, m['model'], m['scale'],
                                         m['min_error'], m['max_error'])
            except ValueError as exc:
                self.get_logger().warning(f'accuracy_map: {exc}', throttle_duration_sec=10.0)
                return
            data = om.data
        elif self.accuracy_map_last is not None:
            grid, om = self.accuracy_map_last[0], None
            data = np.full(grid.width * grid.height, -1, dtype=np.int8)
        else:
            return
        self._map_key = (names, positions)
        msg = OccupancyGrid()
        msg.header.stamp = ns_to_time(now_ns)
        msg.header.frame_id = self.frame_id
        msg.info.map_load_time = msg.header.stamp
        msg.info.resolution = float(grid.resolution)
        msg.info.width, msg.info.height = grid.width, grid.height
        o = msg.info.origin
        o.position.x, o.position.y, o.position.z = grid.origin_x, grid.origin_y, grid.altitude
        o.orientation.w = 1.0
        msg.data = data.tolist()
        self.map_pub.publish(msg)
        self.accuracy_maps += 1
        self.accuracy_map_last = (grid, om)
        self.accuracy_map_ms = 1e3 * (time.perf_counter() - t0)
        self.get_logger().info(
            f'accuracy_map: {len(names)} live station(s), {grid.width}x{grid.height} cells of '
            f'{grid.resolution:g} m, {self.accuracy_map_ms:.1f} ms')

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self):
        now = self.now_ns()
        if now is None:
            now = 0
        arr = DiagnosticArray()
        arr.header.stamp = ns_to_time(now)
        name = self.get_fully_qualified_name().lstrip('/')
        for d in self.core.diagnostics(now):
            values = dict(d.values)
            if d.name == 'fusion':
                values['fixes_published'] = self.fixes_published
                values['mode'] = self.mode
                if self.map_pub is not None:
                    values['accuracy_maps'] = self.accuracy_maps
                    values['accuracy_map_ms'] = (f'{self.accuracy_map_ms:.1f}'
                                                 if self.accuracy_map_ms is not None
                                                 else 'n/a')
            elif d.hardware_id in self.incompatible_qos:
                values['incompatible_qos_publishers'] = self.incompatible_qos[d.hardware_id]
            arr.status.append(diagnostic_status(f'{name}: {d.name}', LEVELS[d.level],
                                                d.message, values, d.hardware_id))
        self.diag_pub.publish(arr)


main = main_for(FusionNode)


if __name__ == '__main__':
    main()
