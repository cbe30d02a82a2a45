"""Settings of the fusion pipeline (:class:`FusionConfig`) and their validation.

Units: seconds, Hz, metres, m/s; angles are not configured here (each bearing carries its
own σ). Every check raises ``ValueError('<field>: <problem>')`` naming the field, which the
node reports as ``parameter '<field>': <problem>`` and ``bag process`` as one line.
"""

from dataclasses import dataclass, field, replace
import math
import numbers
import re

from .. import parameters as _parameters
from .. import registry as _registry
from ..alignment import AlignmentConfig, seconds_to_ns
from ..conventions import check_frame_id
from ..tma import SPEED_REFERENCES

NS_PER_S = 1_000_000_000

#: Epoch triggers.
TRIGGER_EVENT = 'event'
TRIGGER_TIMER = 'timer'
TRIGGERS = (TRIGGER_EVENT, TRIGGER_TIMER)

#: Fusion modes (the node's ``mode`` parameter; ``auto`` follows the estimator).
MODE_MULTISTATION = _registry.MODE_MULTISTATION
MODE_TMA = _registry.MODE_TMA
#: Stationary emitter: every bearing of the window in one fix (core.fusion.window); it runs
#: the multi-station estimators.
MODE_WINDOW = 'window'


def _estimator_options(values):
    """Estimator options of node parameter values: ``target_altitude`` [] (the node's "not
    stated") becomes None and [z] becomes z (m); ValueError for more than one value."""
    out = dict(values)
    z = out.get('target_altitude')
    if z is not None and not isinstance(z, (numbers.Real, str, bytes)):
        # A list from a parameter file, array('d') from a run-time parameter change.
        z = list(z)
        if len(z) > 1:
            raise ValueError(f'target_altitude: expected [] (not stated) or [z] (m), got {z}')
        out['target_altitude'] = float(z[0]) if z else None
    return out


#: A station id: one or more ROS name tokens separated by '/' (the topic namespace).
STATION_ID_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')


def check_station_ids(names):
    """The station ids ``names`` as a list, each a valid ROS name path (STATION_ID_RE) listed
    once; ``ValueError('stations: ...')`` naming the first problem."""
    names = list(names)
    seen = set()
    for s in names:
        if not STATION_ID_RE.match(s):
            raise ValueError(f'stations: {s!r} is not a valid station id (ROS name tokens '
                             'separated by /)')
        if s in seen:
            raise ValueError(f'stations: {s!r} is listed twice')
        seen.add(s)
    return names


#: Defaults: the fusion node's parameter schema (core.parameters), the one place they live.
_DEFAULTS = _parameters.defaults('fusion_node')


def _seconds(name, value, positive=False):
    v = float(value)
    if not math.isfinite(v) or v < 0.0 or (positive and v == 0.0):
        raise ValueError(f'{name}: must be {"> 0" if positive else ">= 0"} seconds, got {value}')
    return v


@dataclass(frozen=True)
class FusionConfig:
    """Settings of the fusion pipeline (the fusion node's parameters; seconds, Hz, metres).

    Defaults are those of the fusion node's parameter schema (core.parameters);
    ``estimator_options`` defaults to {} (each estimator's own defaults apply).

    Attributes:
        frame_id: world frame; bearings in another frame are rejected (``wrong_frame``).
        trigger: ``event`` or ``timer`` (:mod:`.triggers`).
        rate: timer epoch rate, Hz (also the node's housekeeping tick rate in event mode).
        max_latency: timer mode: epoch t_k is processed once now >= t_k + max_latency;
            event mode: an epoch still missing a live station's bearing is processed once
            max_latency has passed since its first bearing arrived, with >= min_stations
            stations, s.
        sync_tolerance: nearest alignment window |stamp − t|, s.
        interpolation: interpolate between bracketing bearings.
        max_interpolation_gap: longest bracketing gap t1 − t0, s.
        station_timeout: a station is stale when now − (its newest stamp) > this, s.
        buffer_size: bearings kept per station. buffer_age: their maximum age, s.
        min_stations: fewest stations in a fix (>= 2).
        estimator: a name of the estimator registry (core.registry.names()).
        estimator_options: keyword options for it (each estimator gets the ones it accepts,
            core.registry.scoped_options).
        outlier_gate: χ² gate probability in [0.5, 1]; 1 disables gating.
        time_jump_tolerance: "now" going back by more than this (s) clears the buffers.
        future_tolerance: bearings stamped later than now + this (s) are dropped
            (``from_future``): a station clock ahead, or a forged stamp.
        max_station_speed: a bearing whose station position moved faster than this (m/s)
            since the station's last accepted bearing is dropped
            (``implausible_position``); 0 disables the check.
        target_speed: TMA speed prior v_c, m/s (Lin et al.; required > 0 for a TMA
            estimator, 0 = unset).
        window: TMA and window modes, s: bearings older than the newest minus this leave
            the sums (TMA) or the fix (window).
        window_max_bearings: window mode: most bearings in one fix (oldest leave first).
        speed_reference: TMA prior on 'relative' (|v_t − v_o|, Lin et al.) or 'ground'
            (|v_t|) speed.
    """

    frame_id: str = _DEFAULTS['frame_id']
    trigger: str = _DEFAULTS['trigger']
    rate: float = _DEFAULTS['rate']
    max_latency: float = _DEFAULTS['max_latency']
    sync_tolerance: float = _DEFAULTS['sync_tolerance']
    interpolation: bool = _DEFAULTS['interpolation']
    max_interpolation_gap: float = _DEFAULTS['max_interpolation_gap']
    station_timeout: float = _DEFAULTS['station_timeout']
    buffer_size: int = _DEFAULTS['buffer_size']
    buffer_age: float = _DEFAULTS['buffer_age']
    min_stations: int = _DEFAULTS['min_stations']
    estimator: str = _DEFAULTS['estimator']
    estimator_options: dict = field(default_factory=dict)
    outlier_gate: float = _DEFAULTS['outlier_gate']
    time_jump_tolerance: float = _DEFAULTS['time_jump_tolerance']
    future_tolerance: float = _DEFAULTS['future_tolerance']
    max_station_speed: float = _DEFAULTS['max_station_speed']
    target_speed: float = _DEFAULTS['target_speed']
    window: float = _DEFAULTS['window']
    speed_reference: str = _DEFAULTS['speed_reference']
    window_max_bearings: int = _DEFAULTS['window_max_bearings']
    sigma_floor_deg: float = _DEFAULTS['sigma_floor_deg']
    station_sigma_floors: tuple = ()

    def __post_init__(self):
        # a parameter array arrives as a list: one canonical (hashable) form
        object.__setattr__(self, 'station_sigma_floors', tuple(self.station_sigma_floors))

    def sigma_floors(self):
        """(global floor, {station: floor}) in rad, from ``sigma_floor_deg`` and
        ``station_sigma_floors`` ("<station>:<deg>"); ValueError naming the field."""
        g = float(self.sigma_floor_deg)
        if not (math.isfinite(g) and 0.0 <= g <= 180.0):
            raise ValueError(f'sigma_floor_deg: must be in [0, 180] deg, got {g}')
        out = {}
        for item in self.station_sigma_floors:
            name, sep, deg = str(item).rpartition(':')
            try:
                v = float(deg)
            except ValueError:
                v = math.nan
            if not sep or not name or not (math.isfinite(v) and 0.0 <= v <= 180.0):
                raise ValueError(f'station_sigma_floors: expected "<station>:<deg>" with deg '
                                 f'in [0, 180], got {item!r}')
            if not STATION_ID_RE.match(name):
                raise ValueError(f'station_sigma_floors: {name!r} is not a valid station id '
                                 f'(ROS name tokens separated by /), in {item!r}')
            if name in out:
                raise ValueError(f'station_sigma_floors: {name!r} is given twice')
            out[name] = math.radians(v)
        return math.radians(g), out

    def validate(self):
        """Raise ``ValueError`` naming the first invalid field; return self."""
        check_frame_id(self.frame_id)
        if self.trigger not in TRIGGERS:
            raise ValueError(f'trigger: {self.trigger!r} is not one of {list(TRIGGERS)}')
        if not (math.isfinite(float(self.rate)) and 0.0 < float(self.rate) <= 1000.0):
            raise ValueError(f'rate: must be in (0, 1000] Hz, got {self.rate}')
        _seconds('max_latency', self.max_latency)
        _seconds('sync_tolerance', self.sync_tolerance)
        _seconds('max_interpolation_gap', self.max_interpolation_gap, positive=True)
        _seconds('station_timeout', self.station_timeout, positive=True)
        _seconds('buffer_age', self.buffer_age, positive=True)
        _seconds('time_jump_tolerance', self.time_jump_tolerance)
        _seconds('future_tolerance', self.future_tolerance)
        v = float(self.max_station_speed)
        if not (math.isfinite(v) and 0.0 <= v <= 1e8):
            raise ValueError(f'max_station_speed: must be in [0, 1e8] m/s (0 = no check), '
                             f'got {self.max_station_speed}')
        if int(self.buffer_size) < 2:
            raise ValueError(f'buffer_size: must be >= 2, got {self.buffer_size}')
        if float(self.buffer_age) <= float(self.max_latency) + float(self.sync_tolerance):
            raise ValueError('buffer_age: must exceed max_latency + sync_tolerance, or the '
                             'bearings of an epoch are pruned before it is processed')
        if int(self.min_stations) < 2:
            raise ValueError(f'min_stations: must be >= 2, got {self.min_stations}')
        if not isinstance(self.estimator_options, dict):
            raise ValueError('estimator_options: must be a dict')
        _seconds('window', self.window, positive=True)
        if self.speed_reference not in SPEED_REFERENCES:
            raise ValueError(f'speed_reference: {self.speed_reference!r} is not one of '
                             f'{list(SPEED_REFERENCES)}')
        v = float(self.target_speed)
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f'target_speed: must be finite and >= 0 m/s, got {v}')
        if _registry.mode_of(self.estimator) == MODE_TMA:
            if v <= 0.0:
                raise ValueError(f'target_speed: must be > 0 m/s for the TMA estimator '
                                 f'{self.estimator} (the speed prior of Lin et al.)')
            it = self.estimator_options.get('max_iterations', 1)
            if int(it) != it or it < 1:
                raise ValueError(f'max_iterations: must be an integer >= 1, got {it}')
        else:
            _registry.check(self.estimator, self.estimator_options)
            opts = self.estimator_options
            if opts.get('dimension') == 'horizontal' and opts.get('target_altitude') is None:
                raise ValueError('target_altitude: required when dimension is horizontal '
                                 '(m, world frame)')
            if not bool(opts.get('use_elevations', True)):      # (checked a bool above)
                if opts.get('dimension') == '3d':
                    raise ValueError('use_elevations: false leaves nothing to observe the '
                                     'height; dimension 3d needs elevations')
                if opts.get('target_altitude') is None:
                    raise ValueError('target_altitude: required when use_elevations is false '
                                     '(every epoch is solved horizontally; m, world frame)')
        if int(self.window_max_bearings) < 3:
            raise ValueError(f'window_max_bearings: must be >= 3, got '
                             f'{self.window_max_bearings}')
        g = float(self.outlier_gate)
        if not 0.5 <= g <= 1.0:
            raise ValueError(f'outlier_gate: probability must be in [0.5, 1], got {g}')
        self.sigma_floors()
        return self

    @classmethod
    def from_parameters(cls, values=None):
        """The validated config of fusion node parameter values (name -> value; missing
        names take the schema defaults): the fields of the same name
        (core.parameters.FUSION_CONFIG_FIELDS) and the estimator options
        (core.parameters.ESTIMATOR_OPTIONS). The node and ``bag process`` both build their
        config here. ValueError naming the field."""
        v = _parameters.defaults('fusion_node')
        v.update(values or {})
        return cls(estimator_options=_estimator_options(
                       {k: v[k] for k in _parameters.ESTIMATOR_OPTIONS}),
                   **{k: v[k] for k in _parameters.FUSION_CONFIG_FIELDS}).validate()

    def parameter_changes(self, values):
        """Field changes (for :meth:`replace`) that fusion node parameter values (name ->
        value) make: fields of the same name, and ``estimator_options`` when an estimator
        option changes; other names are ignored."""
        changes = {k: v for k, v in values.items() if k in _parameters.FUSION_CONFIG_FIELDS}
        options = dict(self.estimator_options)
        options.update(_estimator_options(
            {k: v for k, v in values.items() if k in _parameters.ESTIMATOR_OPTIONS}))
        if options != self.estimator_options:
            changes['estimator_options'] = options
        return changes

    def replace(self, **changes):
        """A copy with ``changes`` applied (validate it before use)."""
        return replace(self, **changes)

    def alignment(self):
        """The :class:`AlignmentConfig` (integer ns) of these settings."""
        return AlignmentConfig(
            sync_tolerance_ns=seconds_to_ns(self.sync_tolerance),
            interpolation=bool(self.interpolation),
            max_interpolation_gap_ns=seconds_to_ns(self.max_interpolation_gap),
            buffer_size=int(self.buffer_size), buffer_age_ns=seconds_to_ns(self.buffer_age))

    @property
    def period_ns(self):
        """Timer period 1 / rate, integer ns."""
        return max(1, int(round(NS_PER_S / float(self.rate))))
