"""The parameter schema of every node: the one source of names, types, defaults and ranges.

Each node's parameters are a tuple of :class:`Param` (:data:`SCHEMAS`). The schema feeds:

* the rclpy declarations (``ros_common.declare_schema``: ParameterDescriptor with the
  description, range and read_only flag);
* the core configuration objects (:func:`fusion_config` builds the FusionConfig of the
  fusion node and of ``bag process`` from the same values);
* the shipped parameter files (``config/<name>.yaml``) and the parameter tables of the
  documentation, both rendered by :mod:`.parameter_docs`; a test fails when any of them
  drifts from the schema.

Naming convention: SI units (metres, radians, seconds, m/s) carry no suffix
(``diagnostics_period``); other units do (``sigma_azimuth_deg``). A renamed parameter keeps
its old name for one release (:attr:`Param.deprecated`): the old name is accepted, mapped
to the new one and reported once as deprecated.

Print a node's table: ``python -m bearing_loc_ros.core.parameters --markdown fusion_node``
(``--yaml NODE`` prints its parameter file, ``--update-docs FILE`` rewrites the parameter
tables of a documentation page between its ``<!-- BEGIN/END parameters NODE -->`` markers).

No ROS imports here (core layer).
"""

from dataclasses import dataclass
import math
import sys

from .text import short_repr

BOOL = 'bool'
INTEGER = 'integer'
DOUBLE = 'double'
STRING = 'string'
DOUBLE_ARRAY = 'double_array'
STRING_ARRAY = 'string_array'
TYPES = (BOOL, INTEGER, DOUBLE, STRING, DOUBLE_ARRAY, STRING_ARRAY)
#: Python types a value of each parameter type may have (an integer is a valid double).
PY_TYPES = {BOOL: (bool,), INTEGER: (int,), DOUBLE: (float, int), STRING: (str,),
            DOUBLE_ARRAY: (list, tuple), STRING_ARRAY: (list, tuple)}


@dataclass(frozen=True)
class Param:
    """One node parameter.

    Attributes:
        name: the ROS parameter name (``group.name`` for nested YAML keys).
        type: one of :data:`TYPES` (rclpy's BOOL, INTEGER, DOUBLE, STRING, DOUBLE_ARRAY,
            STRING_ARRAY).
        default: the value when not set (``[]`` for an unset array).
        description: one sentence for the descriptor, the docs table and the YAML comment.
        unit: unit of the value ('' when dimensionless or not a number).
        min, max: inclusive numeric range (None = unbounded), checked at start-up and on
            run-time sets; ``min_open`` makes the lower bound exclusive (> min).
        choices: the allowed strings of a string parameter (empty: free text).
        read_only: True unless the parameter may change while the node runs.
        deprecated: former names, accepted for one release with a warning.
        example: value written in the shipped parameter file when it differs from the
            default; None = the default.
        commented: the example is written as a comment (the parameter stays unset).
    """

    name: str
    type: str
    default: object
    description: str
    unit: str = ''
    min: float = None
    max: float = None
    min_open: bool = False
    choices: tuple = ()
    read_only: bool = True
    deprecated: tuple = ()
    example: object = None
    commented: bool = False

    def check(self, value):
        """Raise ``ValueError('<name>: ...')`` unless ``value`` fits the type, range and
        choices; return the value (an int given for a double becomes a float)."""
        types = PY_TYPES[self.type]
        if isinstance(value, bool) and self.type != BOOL or not isinstance(value, types):
            raise ValueError(f'{self.name}: expected {self.type}, got {short_repr(value)}')
        try:
            if self.type == DOUBLE:
                value = float(value)
            if self.type in (DOUBLE_ARRAY, STRING_ARRAY):
                item = (float, int) if self.type == DOUBLE_ARRAY else (str,)
                if not all(isinstance(v, item) and not isinstance(v, bool) for v in value):
                    raise ValueError(f'{self.name}: expected {self.type}, got {short_repr(value)}')
                value = [float(v) for v in value] if self.type == DOUBLE_ARRAY else list(value)
        except OverflowError:
            raise ValueError(f'{self.name}: {str(value)[:40]} is beyond the float range') \
                from None
        if self.type == DOUBLE_ARRAY:
            for v in value:
                if not math.isfinite(v):
                    raise ValueError(f'{self.name}: every value must be finite, got {v}')
                if self.min is not None and v < self.min or self.max is not None \
                        and v > self.max:
                    raise ValueError(f'{self.name}: {v} is outside {self.range_text()}')
        if self.type == INTEGER and not -2 ** 63 <= value < 2 ** 63:
            raise ValueError(f'{self.name}: {str(value)[:40]} is beyond the int64 range')
        if self.type in (INTEGER, DOUBLE):
            if self.type == DOUBLE and not math.isfinite(value):
                raise ValueError(f'{self.name}: must be finite, got {value}')
            if self.min is not None and (value < self.min or (self.min_open
                                                              and value == self.min)):
                raise ValueError(f'{self.name}: {value} is below the minimum '
                                 f'{"(exclusive) " if self.min_open else ""}{self.min}')
            if self.max is not None and value > self.max:
                raise ValueError(f'{self.name}: {value} is above the maximum {self.max}')
        if self.choices and value not in self.choices:
            raise ValueError(f'{self.name}: {short_repr(value)} is not one of '
                             f'{list(self.choices)}')
        return value

    def range_text(self):
        """The range as the docs print it: ``[0, 60]``, ``(0, 3600]``, choices or ''."""
        if self.choices:
            return ', '.join(f'`{c}`' for c in self.choices)
        if self.min is None and self.max is None:
            return ''
        lo = '−∞' if self.min is None else _num(self.min)
        hi = '∞' if self.max is None else _num(self.max)
        return f'{"(" if self.min_open or self.min is None else "["}{lo}, {hi}' \
               f'{")" if self.max is None else "]"}'


def _num(v):
    """A bound as text: 6 significant digits, more where they would round it to another
    number (1 − 1e-9 is not 1)."""
    if not isinstance(v, float):
        return str(v)
    short = f'{v:g}'
    return short if float(short) == v else repr(v)


def _estimator_names():
    from . import registry
    return registry.names()


def _default_estimator():
    from . import registry
    return registry.default_estimator()


def _default_reference_range():
    from .estimators import DEFAULT_REFERENCE_RANGE
    return float(DEFAULT_REFERENCE_RANGE)


def _fusion_schema():
    from .planning import MODELS, SCALES
    from .tma import SPEED_REFERENCES
    P = Param
    run = dict(read_only=False)
    return (
        P('mode', STRING, 'auto', 'Fusion mode; auto = tma for a TMA estimator (tma_*), '
          'else multistation; window = stationary emitter, every bearing of the last window '
          's in one fix', choices=('auto', 'multistation', 'tma', 'window')),
        P('frame_id', STRING, 'map', 'World frame; bearings in any other frame are rejected '
          '(bad.wrong_frame)'),
        P('stations', STRING_ARRAY, [], 'Station ids; subscribes to <station>/bearing '
          'relative to the node namespace', example=['station_1', 'station_2', 'station_3'],
          **run),
        P('channels', STRING_ARRAY, [], 'Several emitters: one fusion node per channel c in '
          'this process, in namespace c (c/<station>/bearing -> c/fix); empty = one pipeline',
          example=['uhf', 'vhf'], commented=True),
        P('discover', BOOL, False, 'Also subscribe to every */bearing '
          'PoseWithCovarianceStamped topic under the namespace'),
        P('discovery_period', DOUBLE, 1.0, 'Wall-clock period of the topic discovery scan',
          's', 0.05, 3600.0),
        P('discovery_probe', BOOL, True, 'Discovery: watch a new topic in a short-lived '
          'child process until it delivers a valid bearing, and subscribe only then (false: '
          'subscribe at once; the subscriptions to publishers that never send keep memory)'),
        P('qos_depth', INTEGER, 10, 'Keep-last depth of each bearing subscription', '', 1,
          10000),
        P('qos_reliability', STRING, 'best_effort', 'QoS reliability of the bearing '
          'subscriptions: best_effort (sensor data; matches reliable and best-effort '
          'publishers) or reliable (matches reliable publishers only)',
          choices=('best_effort', 'reliable')),
        P('trigger', STRING, 'event', 'Epoch trigger: event (every live station reported) '
          'or timer (every 1/rate s, after max_latency)', choices=('event', 'timer')),
        P('rate', DOUBLE, 10.0, 'Timer epoch rate; also the housekeeping tick rate in event '
          'mode', 'Hz', 0.01, 1000.0),
        P('max_latency', DOUBLE, 0.2, 'Timer mode: epoch t is processed once now >= t + '
          'max_latency; event mode: an epoch missing a live station closes this long after '
          'its first bearing (with min_stations)', 's', 0.0, 60.0),
        P('sync_tolerance', DOUBLE, 0.05, 'Nearest alignment window |stamp - t|', 's', 0.0,
          60.0),
        P('interpolation', BOOL, False, 'Interpolate between the two bearings bracketing t '
          '(angle-aware)'),
        P('max_interpolation_gap', DOUBLE, 1.0, 'Longest gap between bracketing bearings',
          's', 1e-6, 3600.0),
        P('station_timeout', DOUBLE, 5.0, 'A station without a bearing for this long (now - '
          'its newest stamp) is stale and left out of fixes', 's', 1e-3, 3600.0),
        P('buffer_size', INTEGER, 50, 'Bearings kept per station', '', 2, 100000),
        P('buffer_age', DOUBLE, 10.0, 'Bearings older than now - buffer_age are dropped; '
          'must exceed max_latency + sync_tolerance', 's', 1e-3, 3600.0),
        P('time_jump_tolerance', DOUBLE, 0.1, 'The clock going back by more than this '
          'clears every buffer', 's', 0.0, 3600.0),
        P('future_tolerance', DOUBLE, 0.5, 'Bearings stamped later than now + this are '
          'dropped (dropped.from_future)', 's', 0.0, 3600.0),
        P('max_station_speed', DOUBLE, 1000.0, 'A bearing whose station position moved '
          'faster than this since its last accepted bearing is dropped '
          '(dropped.implausible_position: a GPS glitch, a bad position source); 0 = no check',
          'm/s', 0.0, 1e8),
        P('estimator', STRING, _default_estimator(), 'Estimator; a switch between a TMA '
          '(tma_*) and a multi-station estimator needs a restart', choices=_estimator_names(),
          **run),
        P('target_speed', DOUBLE, 0.0, 'TMA speed prior v_c (Lin et al.); required > 0 with '
          'a tma_* estimator', 'm/s', 0.0, 1e6, **run),
        P('window', DOUBLE, 120.0, 'TMA and window modes: bearings older than the newest '
          'minus window leave the fix', 's', 1e-3, 1e6),
        P('window_max_bearings', INTEGER, 400, 'Window mode: most bearings in one fix (the '
          'oldest leave first); bounds memory and CPU', '', 3, 100000),
        P('speed_reference', STRING, 'relative', 'TMA: the prior is on the relative '
          '(target - station, Lin et al.) or the ground (target) speed',
          choices=tuple(SPEED_REFERENCES)),
        P('min_stations', INTEGER, 2, 'Fewest stations in a fix', '', 2, 10000, **run),
        P('outlier_gate', DOUBLE, 0.999, 'Chi-square gate probability (1 dof per angle); '
          '1.0 disables the gate', '', 0.5, 1.0, **run),
        P('sigma_floor_deg', DOUBLE, 0.0, 'Smallest bearing sigma the fusion uses: a '
          "station's smaller claim is raised to it; 0 = none", 'deg', 0.0, 180.0, **run),
        P('station_sigma_floors', STRING_ARRAY, [], 'Per-station sigma floors '
          '"<station>:<deg>", overriding sigma_floor_deg for those stations',
          example=['station_1:2.0'], commented=True, **run),
        P('publish_low_confidence', BOOL, False, 'Also publish fixes that failed their '
          'consistency checks (low_confidence) on fix/low_confidence; never on fix'),
        P('dimension', STRING, 'auto', 'Solve: auto (3d when the bearings observe the '
          'height, else horizontal), 3d or horizontal (needs target_altitude)',
          choices=('auto', '3d', 'horizontal'), **run),
        P('target_altitude', DOUBLE_ARRAY, [], 'Target altitude [z] (world frame) of the '
          'horizontal solve; [] = not stated (azimuth-only sets then give no fix)', 'm',
          example=[0.0], commented=True, **run),
        P('target_altitude_sigma', DOUBLE, 0.0, 'Standard deviation of target_altitude; 0 '
          '= exactly known', 'm', 0.0, 1e6, **run),
        P('use_elevations', BOOL, True, 'Use measured elevations; false ignores them '
          '(ground emitters with multipath-spoiled elevations): every epoch is then solved '
          'horizontally and needs target_altitude', **run),
        P('max_iterations', INTEGER, 50, 'Iterative estimators: iteration limit', '', 1,
          100000, **run),
        P('tolerance', DOUBLE, 1e-9, 'Iterative estimators: relative step tolerance', '',
          1e-15, 1.0, **run),
        P('reference_range', DOUBLE, _default_reference_range(), 'wmle only: d_ref of '
          'sigma(d) = sigma_ref d / d_ref (Zong & Cui 2015 eqs. (9)-(10))', 'm', 1e-3, 1e9,
          **run),
        P('step_decay', DOUBLE, 1.0, 'ctls/ctls_am only: Newton step factor mu (Wang, Zhang '
          '& Wu eq. (20))', '', 1e-6, 1.0, **run),
        P('geodetic_origin', DOUBLE_ARRAY, [], 'Origin of the ENU frame [lat_deg, lon_deg, '
          'alt_m] (WGS84); enables fix/navsat', 'deg, deg, m',
          example=[48.137, 11.575, 520.0], commented=True),
        P('publish_markers', BOOL, True, 'Publish markers (built only while markers has a '
          'subscriber)'),
        P('marker_ray_length', DOUBLE, 0.0, 'Length of the bearing rays; 0 = 1.2 x the '
          'station-to-fix distance', 'm', 0.0, 1e9, **run),
        P('ellipsoid_sigma', DOUBLE, 3.0, 'Error ellipsoid marker size in standard '
          'deviations', '', 0.1, 10.0, **run),
        P('diagnostics_period', DOUBLE, 1.0, 'Wall-clock period of /diagnostics', 's', 0.01,
          3600.0),
        P('accuracy_map.enabled', BOOL, True, 'Publish the expected-accuracy OccupancyGrid on '
          'accuracy_map (multistation mode)'),
        P('accuracy_map.size', DOUBLE, 0.0, 'Side of the square map; 0 = 3 x the largest '
          'horizontal station distance from the centre, at least 100 m', 'm', 0.0, 1e8),
        P('accuracy_map.resolution', DOUBLE, 0.0, 'Cell size; 0 = size / 100; at most 2000 '
          'cells per side', 'm', 0.0, 1e7),
        P('accuracy_map.altitude', DOUBLE, 0.0, 'Target altitude (world z) of the map', 'm',
          -1e6, 1e6),
        P('accuracy_map.center', DOUBLE_ARRAY, [], '[x, y] centre of the map; [] = centroid '
          'of the live stations', 'm', -1e12, 1e12, example=[0.0, 0.0], commented=True),
        P('accuracy_map.model', STRING, 'crlb', 'Error model: CRLB or the CTLS first-order '
          'error (Wang, Zhang & Wu eqs. (30)-(32))', choices=tuple(MODELS)),
        P('accuracy_map.scale', STRING, 'linear', 'Mapping of the error (m) to cell values',
          choices=tuple(SCALES)),
        P('accuracy_map.min_error', DOUBLE, 0.0, 'Error mapped to cell value 0 (> 0 for the '
          'log scale)', 'm', 0.0, 1e9),
        P('accuracy_map.max_error', DOUBLE, 100.0, 'Error mapped to cell value 100 (and '
          'above); must exceed min_error', 'm', 1e-9, 1e9),
        P('accuracy_map.move_threshold', DOUBLE, 0.0, 'Recompute when a live station moved '
          'more than this; 0 = one cell', 'm', 0.0, 1e9),
    )


def _station_schema():
    from . import receiver_params
    from .station import UNITS
    P = Param
    return (
        P('frame_id', STRING, 'map', 'World frame of the published bearings (no spaces); must '
          'equal the fusion node frame_id'),
        P('station_id', STRING, '', 'Station id for logs and diagnostics; empty = the node '
          'namespace'),
        P('position', DOUBLE_ARRAY, [], 'Station (array phase centre) position [x, y, z] in '
          'the ENU world frame', 'm', example=[120.0, -35.5, 4.0]),
        P('geodetic_position', DOUBLE_ARRAY, [], 'Instead of position: [lat_deg, lon_deg, '
          'alt_m] (WGS84, ellipsoidal height)', 'deg, deg, m',
          example=[46.0185, 7.752, 1680.0], commented=True),
        P('geodetic_origin', DOUBLE_ARRAY, [], 'Origin of the ENU world frame [lat_deg, '
          'lon_deg, alt_m]; required with geodetic_position', 'deg, deg, m',
          example=[46.017, 7.75, 1673.0], commented=True),
        P('position_covariance', DOUBLE_ARRAY, [], 'Station position covariance: 3 '
          '(diagonal) or 9 (row-major) values; empty = zeros', 'm^2',
          example=[0.04, 0.04, 0.25]),
        P('sigma_azimuth_deg', DOUBLE, 2.0, 'Azimuth standard deviation (a datagram may '
          'override it per reading)', 'deg', 1e-6, 180.0),
        P('sigma_elevation_deg', DOUBLE, 2.0, 'Elevation standard deviation', 'deg', 1e-6,
          180.0, example=3.0),
        P('measures_elevation', BOOL, False, 'True for a 2D (azimuth + elevation) station; '
          'false ignores elevations'),
        P('azimuth_reference', STRING, 'enu', 'Raw azimuth reference: enu (CCW from East / '
          'the bow) or compass (CW from North / the bow)', choices=('enu', 'compass'),
          example='compass'),
        P('azimuth_offset_deg', DOUBLE, 0.0, 'Added to the raw azimuth in its own reference '
          'and sense before conversion', 'deg', -360.0, 360.0),
        P('input_units', STRING, 'rad', 'Units of raw_bearing x/y (UDP is always degrees)',
          choices=tuple(UNITS), example='deg'),
        P('udp_port', INTEGER, 0, 'UDP port for JSON datagrams; 0 = off', '', 0, 65535),
        P('udp_address', STRING, '127.0.0.1', 'Address to bind the UDP socket to (0.0.0.0 = '
          'all IPv4 interfaces)'),
        P('udp_stamp', STRING, 'datagram', "Stamp of a datagram's bearing: its t (unix "
          'time) or the node clock at receipt', choices=('datagram', 'receive')),
        P('platform_odometry', STRING, '', 'nav_msgs/Odometry topic of a moving platform; '
          'empty = fixed station'),
        P('odometry_tolerance', DOUBLE, 0.1, 'Readings up to this far outside the buffered '
          'odometry use the nearest pose; further out they are dropped', 's', 0.0, 60.0,
          deprecated=('odometry_tolerance_s',)),
        P('odometry_buffer_size', INTEGER, 200, 'Odometry messages kept for interpolation',
          '', 2, 100000),
        P('odometry_max_gap', DOUBLE, 2.0, 'Readings between two odometry messages further '
          'apart than this are dropped (odometry_gap), not interpolated', 's', 0.001,
          3600.0),
        P('odometry_jump', DOUBLE, 1.0, 'An odometry stamp this much or less before the '
          'newest is dropped as late (odometry_late); further back the clock jumped and the '
          'buffer is cleared', 's', 0.0, 86400.0),
        P('diagnostics_period', DOUBLE, 1.0, 'Period of the /diagnostics status', 's', 0.05,
          3600.0, deprecated=('diagnostics_period_s',)),
        P('qos_reliability', STRING, 'best_effort', 'QoS reliability of the bearing '
          'publisher: best_effort (sensor data, no retransmission) or reliable (needed by '
          'reliable subscribers)', choices=('best_effort', 'reliable')),
        P('qos_depth', INTEGER, 10, 'Keep-last depth of the bearing publisher', '', 1, 10000),
    ) + receiver_params.node_params(Param)


def _simulator_schema():
    P = Param
    return (
        P('scenario', STRING, '', 'Scenario YAML (required); a relative path is looked up in '
          'the current directory, then in the package share dir and its config/scenarios'),
        P('seed', INTEGER, 0, 'Random seed; the same seed gives the same bearings, truth and '
          'timing', '', 0, None),
        P('time_scale', DOUBLE, 1.0, 'Simulated seconds per wall second (10.0 = ten times '
          'faster than real time)', '', 0.0, 1e6, min_open=True),
        P('publish_clock', BOOL, True, 'Publish /clock (rosgraph_msgs/Clock) with the '
          'simulated time'),
        P('duration', DOUBLE, 0.0, "Simulated seconds to run; 0 = the scenario's duration",
          's', 0.0, 1e7),
        P('start_delay', DOUBLE, 5.0, 'Longest wall-clock wait for subscribers before '
          'starting (the clock is held at the epoch meanwhile); up to 10 s more while a '
          "fusion node's discovery probe hands over to the node", 's', 0.0, None),
        P('wait_for_subscribers', BOOL, True, 'Start before start_delay has passed once '
          'every bearing topic has a matched subscriber other than a discovery probe and the '
          'counts held for 1 s; while only probes subscribe, the messages due at the epoch '
          'are published'),
        P('exit_when_done', BOOL, True, 'Shut the node down once every message of the run '
          'has been published and acknowledged'),
    )


#: Messages queued per Foxglove client by default (foxglove_view.DEFAULT_BACKLOG, checked
#: equal by test_params.py; this module must not import the Foxglove SDK).
VIEW_DEFAULT_BACKLOG = 512


def _view_schema():
    P = Param
    return (
        P('host', STRING, '127.0.0.1', 'Address the WebSocket server listens on; anything but '
          'loopback exposes it (no authentication) to the network'),
        P('port', INTEGER, 8765, 'TCP port (0 = any free port, logged)', '', 0, 65535),
        P('topics', STRING_ARRAY, [], "Topics to forward (empty = the package's topics, plus "
          '/diagnostics and /clock)'),
        P('discovery_period', DOUBLE, 1.0, 'How often the ROS graph is scanned for new topics',
          's', 0.05, 60.0),
        P('geodetic_origin', DOUBLE_ARRAY, [], '[lat_deg, lon_deg, alt_m] of the ENU frame '
          '(WGS84); enables /map_geojson and the station NavSatFix topics'),
        P('frame_id', STRING, 'map', "World (ENU) frame of the fixes and bearings drawn on "
          "the map; others are counted and left out (the fusion node's frame_id)"),
        P('geojson_period', DOUBLE, 0.5, 'Minimum interval between GeoJSON pictures', 's',
          0.0, 3600.0),
        P('ellipse_probability', DOUBLE, 0.95, 'Probability of the drawn error ellipse', '',
          1e-6, 1.0 - 1e-9),
        P('max_backlog', INTEGER, VIEW_DEFAULT_BACKLOG, 'Messages queued per WebSocket client '
          'before the oldest is dropped', '', 1, 1_000_000),
        P('diagnostics_period', DOUBLE, 1.0, 'Period of the /diagnostics status (wall clock)',
          's', 0.1, 3600.0),
    )


_BUILDERS = {'fusion_node': _fusion_schema, 'station_node': _station_schema,
             'simulator_node': _simulator_schema, 'view_node': _view_schema}
#: Node executable -> its shipped parameter file under config/ (None: none shipped).
PARAMS_FILES = {'fusion_node': 'fusion.yaml', 'station_node': 'station.yaml',
                'simulator_node': None, 'view_node': None}
NODES = tuple(_BUILDERS)
_CACHE = {}


def schema(node):
    """The tuple of :class:`Param` of ``node`` ('fusion_node', 'station_node',
    'simulator_node', 'view_node'); ValueError for another name."""
    if node not in _BUILDERS:
        raise ValueError(f'node: unknown node {node!r}; choose one of {list(NODES)}')
    if node not in _CACHE:
        _CACHE[node] = _BUILDERS[node]()
    return _CACHE[node]


def param(node, name):
    """The :class:`Param` ``name`` of ``node`` (KeyError if it has none)."""
    for p in schema(node):
        if p.name == name:
            return p
    raise KeyError(name)


def defaults(node):
    """name -> default value of every parameter of ``node`` (arrays copied)."""
    return {p.name: (list(p.default) if isinstance(p.default, list) else p.default)
            for p in schema(node)}


def renamed(node):
    """Deprecated name -> current name, for ``node``."""
    return {old: p.name for p in schema(node) for old in p.deprecated}


def resolve(node, values, warn=None):
    """Parameters given by name (old names allowed) -> {current name: checked value}.

    Unknown names, wrong types and out-of-range values raise ``ValueError('<name>: ...')``;
    an old name is mapped to its current one and ``warn(text)`` called once for it; giving
    both names is an error. Missing parameters take their defaults.
    """
    old = renamed(node)
    known = {p.name: p for p in schema(node)}
    out = defaults(node)
    for name, value in values.items():
        if name in old:
            new = old[name]
            if new in values:
                raise ValueError(f'{name}: deprecated name of {new}, and both are given')
            if warn is not None:
                warn(f"parameter '{name}' is deprecated: use '{new}' (the old name will be "
                     'removed in the next release)')
            name = new
        if name not in known:
            raise ValueError(f'{name}: not a parameter of {node}{did_you_mean(node, name)}')
        out[name] = known[name].check(value)
    return out


#: Parameters every rclpy node declares itself (accepted in a parameter file, no effect on
#: this package's tools).
ROS_BUILTIN = ('use_sim_time', 'start_type_description_service')


def ros_builtin(name):
    """True for a parameter rclpy itself handles: :data:`ROS_BUILTIN` and the
    ``qos_overrides.`` names of QoS overriding."""
    return name in ROS_BUILTIN or name.startswith('qos_overrides.')


def did_you_mean(node, name):
    """`` (did you mean 'x'?)`` naming the parameter of ``node`` (current or deprecated name)
    closest to the unknown ``name`` (difflib ratio at least 0.6), or ''."""
    import difflib
    names = [p.name for p in schema(node)] + list(renamed(node))
    close = difflib.get_close_matches(name, names, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ''


def unknown_message(node, names):
    """The warning for parameters given to ``node`` that it does not have, or None.

    ``names``: the names given (command line, parameter file) that are neither ``node``'s
    parameters nor rclpy's own; ROS 2 ignores them, so a misspelt name would otherwise
    leave its parameter at the default without a word.
    """
    names = sorted(names)
    if not names:
        return None
    listed = ', '.join(f"'{n}'{did_you_mean(node, n)}" for n in names)
    return (f'ignored {len(names)} parameter{"s" if len(names) > 1 else ""} that {node} '
            f'does not have: {listed}')


#: FusionConfig fields filled from fusion node parameters of the same name.
FUSION_CONFIG_FIELDS = ('frame_id', 'trigger', 'rate', 'max_latency', 'sync_tolerance',
                        'interpolation', 'max_interpolation_gap', 'station_timeout',
                        'buffer_size', 'buffer_age', 'min_stations', 'estimator',
                        'outlier_gate', 'time_jump_tolerance', 'target_speed', 'window',
                        'speed_reference', 'future_tolerance', 'max_station_speed',
                        'window_max_bearings',
                        'sigma_floor_deg', 'station_sigma_floors')
#: Fusion node parameters that are estimator options (FusionConfig.estimator_options).
ESTIMATOR_OPTIONS = ('max_iterations', 'tolerance', 'reference_range', 'step_decay',
                     'dimension', 'target_altitude', 'target_altitude_sigma', 'use_elevations')


def markdown_table(node):
    """The Markdown parameter table of ``node`` (:func:`.parameter_docs.markdown_table`)."""
    from . import parameter_docs
    return parameter_docs.markdown_table(schema(node))


def yaml_text(node):
    """The shipped parameter file of ``node`` (:func:`.parameter_docs.yaml_text`)."""
    from . import parameter_docs
    return parameter_docs.yaml_text(node, schema(node))


def main(argv=None):
    """``python -m bearing_loc_ros.core.parameters --markdown|--yaml NODE|--update-docs FILE``
    (the renderers are in :mod:`.parameter_docs`)."""
    from . import parameter_docs
    return parameter_docs.main({node: schema(node) for node in NODES}, argv)


if __name__ == '__main__':
    sys.exit(main())
