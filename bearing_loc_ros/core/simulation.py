"""Scenario model, YAML loader and deterministic bearing generation (the simulator core).

Pure numpy (never imports rclpy). The simulator node, the bag writer and the Monte Carlo
evaluation all call :func:`simulate`, so a seed gives the same bearings everywhere.

Measurement model (seed 000 eq. (1) with the additive Gaussian noise of eq. (6); seed 003
eqs. (1)-(2) and, for range-dependent σ, eqs. (9)-(10)). For station i at s_i(t), target at
X(t), observation k at the true (scenario) time t_k and d = X(t_k) − s_i(t_k):

    θ_ik = wrap(atan2(d_y, d_x) + σ_θ(r) n_ik + o_ik a_θ),
    ψ_ik = clip(atan2(d_z, hypot(d_x, d_y)) + σ_ψ(r) m_ik + o_ik a_ψ),   (2D stations only)
    σ(r) = σ_ref · clip(r / r_ref, f_min, f_max)   (seed 003 eqs. (9)-(10); σ(r) = σ_ref
                                                    when no ``sigma_growth`` is configured)

with r = |d|, n, m ~ N(0, 1), o_ik ~ Bernoulli(outlier) and a = ±outlier_size (random sign);
with ``outlier_size_max`` the magnitude is uniform in [outlier_size, outlier_size_max] (a
reflection 20-90° off: u = Φ(z_out)/outlier, uniform given o_ik, sets |a| = size + (max −
size)·u, so no extra random draw and the other bearings of a scenario do not change).
ψ is clipped to |ψ| ≤ π/2 − 1e-9 so a noisy elevation stays a valid bearing.
Each observation is dropped with probability ``dropout``. Timing of observation k:

    t_k       = phase + k / rate                          true time (scenario seconds)
    stamp_k   = epoch + t_k + clock_offset + drift·t_k + clock_jitter·c_k   (station clock)
    publish_k = epoch + t_k + max(0, latency + latency_jitter·l_k)           (simulated clock)

c, l ~ N(0, 1); drift = clock_drift_ppm·1e-6. The truth attached to a bearing is X(t_k).
Observation times are the half-open interval [0, duration): seed 000 section 4 (every 2 s for
100 s) gives k = 0..49. Periods are rounded to whole nanoseconds.

Determinism: every random number comes from numpy Generators seeded with
``SeedSequence([seed, stream, index...])``: stream 0 = target j's random draws, stream 1 =
station i's survey error, stream 2 = the observations of station i of target j. Each
observation consumes one row of 8 standard normals (dropout, n, m, outlier, two signs, c, l;
uniform draws are Φ(z)), so the bearings do not depend on wall timing, on the other stations'
settings, nor (for the first k) on the duration.
"""

from dataclasses import dataclass, field
import math
import os
import re

import numpy as np
from scipy.special import ndtr

from .bearings import Bearing, HALF_PI
from .conventions import azimuth_elevation, wrap_angle
from .geodesy import geodetic_to_enu

NS_PER_S = 1_000_000_000
#: Largest |elevation| a simulated bearing may carry (Bearing requires |ψ| < π/2).
MAX_ELEVATION = HALF_PI - 1e-9
#: Default simulated time of scenario start (s). Non-zero so that ROS time 0 ("clock not
#: received yet") is never a valid simulated instant and negative clock offsets stay >= 0.
DEFAULT_EPOCH = 1000.0
DEFAULT_TRUTH_RATE = 10.0
DEFAULT_FRAME = 'map'
MOTION_KINDS = ('static', 'constant_velocity', 'waypoints')
TARGET_KINDS = MOTION_KINDS + ('random_static',)
SIGMA_REPORTS = ('nominal', 'actual')

_NAME_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')

# Columns of the (K, 8) standard-normal block drawn per observation (the fixed order).
_C_DROP, _C_AZ, _C_EL, _C_OUT, _C_SIGN_AZ, _C_SIGN_EL, _C_CLOCK, _C_LAT = range(8)
_N_COLS = 8
_STREAM_TARGET, _STREAM_SURVEY, _STREAM_OBS = 0, 1, 2


# --------------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Trajectory:
    """Piecewise-linear motion in the world ENU frame (m, s of scenario time).

    * ``static``: X(t) = points[0].
    * ``constant_velocity``: X(t) = points[0] + velocity · (t − times[0]) for every t.
    * ``waypoints``: linear interpolation between ``points`` at ``times`` (strictly
      increasing), holding the first point before times[0] and the last after times[-1].
    """

    kind: str
    times: np.ndarray
    points: np.ndarray
    velocity: np.ndarray

    @classmethod
    def static(cls, position):
        """A fixed point (3,), m."""
        p = np.asarray(position, dtype=float).reshape(1, 3)
        return cls('static', np.zeros(1), p, np.zeros(3))

    @classmethod
    def constant_velocity(cls, position, velocity, t0=0.0):
        """X(t) = position + velocity (t − t0); position m, velocity m/s, t0 s."""
        p = np.asarray(position, dtype=float).reshape(1, 3)
        return cls('constant_velocity', np.array([float(t0)]), p,
                   np.asarray(velocity, dtype=float).reshape(3))

    @classmethod
    def waypoints(cls, points, times):
        """Straight legs between ``points`` (K, 3) reached at ``times`` (K,) (increasing)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        ts = np.asarray(times, dtype=float).reshape(-1)
        if len(ts) != len(pts) or len(ts) < 2 or np.any(np.diff(ts) <= 0):
            raise ValueError('waypoints: need >= 2 points with strictly increasing times')
        return cls('waypoints', ts, pts, np.zeros(3))

    def position(self, t):
        """Position(s) at scenario time(s) ``t`` (s, scalar or any shape) -> (..., 3), m."""
        t = np.asarray(t, dtype=float)
        if self.kind == 'static':
            return np.broadcast_to(self.points[0], t.shape + (3,)).copy()
        if self.kind == 'constant_velocity':
            return self.points[0] + (t - self.times[0])[..., None] * self.velocity
        flat = t.reshape(-1)
        out = np.stack([np.interp(flat, self.times, self.points[:, a]) for a in range(3)],
                       axis=-1)
        return out.reshape(t.shape + (3,))

    def velocity_at(self, t):
        """Velocity (..., 3), m/s, at time(s) ``t`` (the leg's velocity; 0 when holding)."""
        t = np.asarray(t, dtype=float)
        if self.kind == 'static':
            return np.zeros(t.shape + (3,))
        if self.kind == 'constant_velocity':
            return np.broadcast_to(self.velocity, t.shape + (3,)).copy()
        legs = np.diff(self.points, axis=0) / np.diff(self.times)[:, None]
        i = np.searchsorted(self.times, t, side='right') - 1
        inside = (i >= 0) & (i < len(legs))
        return np.where(inside[..., None], legs[np.clip(i, 0, len(legs) - 1)], 0.0)


@dataclass(frozen=True)
class SigmaGrowth:
    """Range-dependent σ, seed 003 eqs. (9)-(10): σ(r) = σ_ref · clip(r/r_ref, f_min, f_max).

    ``report`` says which σ goes into the published bearing: ``nominal`` (σ_ref, what a
    station that does not know the range reports; default) or ``actual`` (σ(r), an oracle).
    """

    range_ref: float
    min_factor: float = 1e-3
    max_factor: float = math.inf
    report: str = 'nominal'

    def factor(self, r):
        """The factor clip(r / r_ref, f_min, f_max) (dimensionless) for range(s) r, m."""
        return np.clip(np.asarray(r, dtype=float) / self.range_ref, self.min_factor,
                       self.max_factor)


@dataclass(frozen=True)
class Station:
    """A simulated DF station (see README "Simulator" for every key and default).

    Angles in rad, times in s, rates in Hz, distances in m. ``sigma_el`` is NaN for a 1D
    (azimuth-only) station. ``clock_drift`` is a fraction (ppm · 1e-6).
    """

    id: str
    trajectory: Trajectory
    dims: int = 2
    sigma_az: float = 0.01
    sigma_el: float = 0.01
    rate: float = 1.0
    phase: float = 0.0
    clock_offset: float = 0.0
    clock_jitter: float = 0.0
    clock_drift: float = 0.0
    latency: float = 0.0
    latency_jitter: float = 0.0
    dropout: float = 0.0
    outlier: float = 0.0
    outlier_size: float = math.radians(10.0)
    outlier_size_max: float = None
    position_sigma: float = 0.0
    sigma_growth: SigmaGrowth = None

    @property
    def period_ns(self):
        """Observation period, integer ns (1/rate rounded to the nanosecond)."""
        return int(round(NS_PER_S / self.rate))


@dataclass(frozen=True)
class Target:
    """An emitter. ``trajectory`` is None for an unrealized ``random_static`` target.

    ``random_static``: a static point drawn uniformly in the box [box_min, box_max] (m) from
    the simulation seed (:func:`realize_targets`); seed 003 section 3.1.
    """

    namespace: str
    kind: str
    trajectory: Trajectory = None
    box_min: np.ndarray = None
    box_max: np.ndarray = None


@dataclass(frozen=True)
class Scenario:
    """A validated scenario (:func:`load_scenario` / :func:`parse_scenario`).

    ``duration`` s of simulated time, ``epoch`` s = simulated (ROS) time of scenario time 0,
    ``truth_rate`` Hz (0 = no truth stream), ``geodetic_origin`` (lat_deg, lon_deg, alt_m)
    or None, ``source`` the file the scenario came from (for messages).
    """

    stations: tuple
    targets: tuple
    duration: float
    name: str = ''
    description: str = ''
    frame_id: str = DEFAULT_FRAME
    epoch: float = DEFAULT_EPOCH
    truth_rate: float = DEFAULT_TRUTH_RATE
    geodetic_origin: tuple = None
    source: str = '<dict>'

    @property
    def epoch_ns(self):
        """Simulated time of scenario time 0, integer ns."""
        return int(round(self.epoch * NS_PER_S))

    def time_ns(self, t):
        """Scenario time t (s) -> simulated (ROS) time, integer ns: epoch + t."""
        return self.epoch_ns + int(round(float(t) * NS_PER_S))

    def station(self, station_id):
        """The station with id ``station_id`` (KeyError if none)."""
        for s in self.stations:
            if s.id == station_id:
                return s
        raise KeyError(station_id)

    def target(self, namespace):
        """The target with namespace ``namespace`` (KeyError if none)."""
        for tg in self.targets:
            if tg.namespace == namespace:
                return tg
        raise KeyError(namespace)


def target_position(target, t):
    """Target position(s) (..., 3), m, at scenario time(s) t (s); vectorised over t.

    Raises ValueError for an unrealized ``random_static`` target (use the targets of a
    :class:`Simulation`, or :func:`realize_targets`).
    """
    if target.trajectory is None:
        raise ValueError(f'target {target.namespace!r}: random_static target not realized; '
                         'use realize_targets(scenario, seed) or Simulation.targets')
    return target.trajectory.position(t)


def station_position(station, t):
    """True station position(s) (..., 3), m, at scenario time(s) t (s); vectorised over t."""
    return station.trajectory.position(t)


def bearing_topic(namespace, station_id):
    """Relative topic of a station's bearings of one target: ``<namespace>/<station>/bearing``.

    ``bearing_topic('', 'station_1') == 'station_1/bearing'`` (/station_1/bearing for a
    simulator in the root namespace), as a station node in namespace /station_1 publishes.
    """
    return '/'.join(p for p in (namespace.strip('/'), station_id, 'bearing') if p)


def truth_topic(namespace):
    """Relative topic of a target's ground truth: ``<namespace>/truth`` (``truth`` if none)."""
    return '/'.join(p for p in (namespace.strip('/'), 'truth') if p)


# --------------------------------------------------------------------------------------------
# Simulation
# --------------------------------------------------------------------------------------------

@dataclass
class BearingEvent:
    """One published bearing.

    Attributes:
        publish_ns: simulated (ROS) time at which it is published, ns (t_k + latency).
        namespace: the target's namespace (topic ``<namespace>/<station>/bearing``).
        bearing: the core Bearing; ``stamp_ns`` is the observation time as the station's
            clock reports it (offset, drift and jitter included).
        true_ns: the true observation time, ns (epoch + t_k).
        truth: target position at the true observation time (3,), m.
        outlier: True if an outlier offset was added.
    """

    publish_ns: int
    namespace: str
    bearing: Bearing
    true_ns: int
    truth: np.ndarray
    outlier: bool = False

    @property
    def topic(self):
        """Relative topic this bearing is published on."""
        return bearing_topic(self.namespace, self.bearing.station)


@dataclass
class TruthEvent:
    """Ground truth of one target at ``stamp_ns`` (= publish time, the true time), m, m/s."""

    publish_ns: int
    namespace: str
    position: np.ndarray
    velocity: np.ndarray

    @property
    def stamp_ns(self):
        """Truth is stamped with the true time, which is also its publication time."""
        return self.publish_ns

    @property
    def topic(self):
        """Relative topic of this truth sample."""
        return truth_topic(self.namespace)


@dataclass
class Stream:
    """All K scheduled observations of one target by one station, as arrays (kept or not).

    Arrays: t (K,) true scenario time s; true_ns, stamp_ns, publish_ns (K,) int64 ns;
    station_position (K, 3) published (surveyed) position m; truth (K, 3) m; range_ (K,) m;
    azimuth_true, elevation_true (K,) rad; azimuth, elevation (K,) rad (elevation NaN for 1D);
    sigma_az_actual, sigma_el_actual (K,) rad (σ used for the noise); sigma_az, sigma_el (K,)
    rad (σ reported in the message); kept, outlier (K,) bool.
    """

    station: str
    namespace: str
    t: np.ndarray
    true_ns: np.ndarray
    stamp_ns: np.ndarray
    publish_ns: np.ndarray
    station_position: np.ndarray
    truth: np.ndarray
    range_: np.ndarray
    azimuth_true: np.ndarray
    elevation_true: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray
    sigma_az_actual: np.ndarray
    sigma_el_actual: np.ndarray
    sigma_az: np.ndarray
    sigma_el: np.ndarray
    kept: np.ndarray
    outlier: np.ndarray


@dataclass
class Simulation:
    """Result of :func:`simulate`.

    Attributes:
        scenario: the scenario simulated; seed, duration (s) used.
        targets: realized targets (random_static drawn), same order as the scenario's
            (a random_static target with count > 1 is already expanded at load time).
        streams: one :class:`Stream` per (station, target), station-major.
        bearings: kept :class:`BearingEvent`, sorted by (publish_ns, station, namespace).
        truth: :class:`TruthEvent` at ``truth_rate`` over [0, duration), sorted by time.
        end_ns: simulated time at which the last message is due (>= epoch + duration).
    """

    scenario: Scenario
    seed: int
    duration: float
    targets: list
    streams: list
    bearings: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    end_ns: int = 0

    def stream(self, station_id, namespace=''):
        """The :class:`Stream` of ``station_id`` observing the target ``namespace``."""
        for s in self.streams:
            if s.station == station_id and s.namespace == namespace:
                return s
        raise KeyError((station_id, namespace))


def _rng(seed, *keys):
    """numpy Generator of the independent stream ``keys`` of ``seed`` (SeedSequence)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), *map(int, keys)]))


def _check_seed(seed):
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f'seed: must be a non-negative integer (got {seed!r})')
    return int(seed)


def realize_targets(scenario, seed=0):
    """Targets with every ``random_static`` one drawn uniformly in its box (seed stream 0).

    X_j = box_min + (box_max − box_min) · U, U ~ U[0, 1)³ from ``SeedSequence([seed, 0, j])``
    (seed 003 section 3.1: sources uniform in X(−3000, 3000), Y(1000, 7000), Z(−500, 500) m).
    """
    seed = _check_seed(seed)
    out = []
    for j, tg in enumerate(scenario.targets):
        if tg.kind == 'random_static':
            u = _rng(seed, _STREAM_TARGET, j).random(3)
            p = tg.box_min + (tg.box_max - tg.box_min) * u
            tg = Target(tg.namespace, 'random_static', Trajectory.static(p), tg.box_min,
                        tg.box_max)
        out.append(tg)
    return out


#: Most bearings one :func:`simulate` call produces (all are held in memory, ~1 kB each).
MAX_SIMULATED_BEARINGS = 1e8


def observation_times_ns(station, duration):
    """Scenario times t_k = phase + k/rate in [0, duration), integer ns (int64 array)."""
    period = station.period_ns
    phase = int(round(station.phase * NS_PER_S))
    end = int(round(duration * NS_PER_S))
    if phase >= end:
        return np.zeros(0, dtype=np.int64)
    k = np.arange((end - phase + period - 1) // period, dtype=np.int64)
    return phase + k * period


def _simulate_stream(scenario, station, i, target, j, duration, seed, survey):
    """Arrays of every scheduled observation of target j by station i (model in module doc)."""
    t_ns = observation_times_ns(station, duration)
    t = t_ns / NS_PER_S
    K = len(t)
    z = _rng(seed, _STREAM_OBS, i, j).standard_normal((K, _N_COLS))
    pos = station_position(station, t) + survey
    truth = target_position(target, t)
    d = truth - station_position(station, t)
    rng_ = np.linalg.norm(d, axis=-1)
    az0, el0 = azimuth_elevation(d)
    if station.sigma_growth is not None:
        f = station.sigma_growth.factor(rng_)
    else:
        f = np.ones(K)
    saz_act = station.sigma_az * f
    u_out = ndtr(z[:, _C_OUT])
    outlier = u_out < station.outlier
    size = station.outlier_size
    if station.outlier_size_max is not None and station.outlier > 0.0:
        u = np.clip(u_out / station.outlier, 0.0, 1.0)
        size = size + (station.outlier_size_max - size) * u
    sign_az = np.where(z[:, _C_SIGN_AZ] >= 0.0, 1.0, -1.0)
    az = wrap_angle(az0 + saz_act * z[:, _C_AZ] + outlier * sign_az * size)
    if station.dims == 2:
        sel_act = station.sigma_el * f
        sign_el = np.where(z[:, _C_SIGN_EL] >= 0.0, 1.0, -1.0)
        el = np.clip(el0 + sel_act * z[:, _C_EL] + outlier * sign_el * size,
                     -MAX_ELEVATION, MAX_ELEVATION)
    else:
        sel_act = np.full(K, np.nan)
        el = np.full(K, np.nan)
    if station.sigma_growth is not None and station.sigma_growth.report == 'actual':
        saz_rep, sel_rep = saz_act, sel_act
    else:
        saz_rep, sel_rep = np.full(K, station.sigma_az), np.full(K, station.sigma_el)
    kept = ~(ndtr(z[:, _C_DROP]) < station.dropout)
    clock_err = (station.clock_offset + station.clock_drift * t
                 + station.clock_jitter * z[:, _C_CLOCK])
    true_ns = scenario.epoch_ns + t_ns
    stamp_ns = np.maximum(true_ns + np.round(clock_err * NS_PER_S).astype(np.int64), 0)
    delay = np.maximum(0.0, station.latency + station.latency_jitter * z[:, _C_LAT])
    publish_ns = true_ns + np.round(delay * NS_PER_S).astype(np.int64)
    return Stream(station.id, target.namespace, t, true_ns, stamp_ns, publish_ns, pos, truth,
                  rng_, az0, el0, np.atleast_1d(az), el, saz_act, sel_act, saz_rep, sel_rep,
                  kept, outlier)


def simulate(scenario, duration=None, seed=0):
    """Generate every bearing and truth sample of ``scenario`` (deterministic in ``seed``).

    Args:
        scenario: a :class:`Scenario`.
        duration: simulated seconds; None or 0 uses ``scenario.duration``.
        seed: non-negative int; all randomness derives from it (module docstring).

    Returns:
        :class:`Simulation` with the kept bearings as :class:`BearingEvent` sorted by publish
        time (ties: station order, then target order), truth samples and per-stream arrays.
    """
    seed = _check_seed(seed)
    if duration is None or duration == 0:
        duration = scenario.duration
    duration = float(duration)
    if not math.isfinite(duration) or duration <= 0:
        raise ValueError(f'duration: must be > 0 s (got {duration})')
    n_obs = duration * sum(st.rate for st in scenario.stations) * len(scenario.targets)
    if duration * NS_PER_S >= 2 ** 63 or n_obs > MAX_SIMULATED_BEARINGS:
        raise ValueError(f'duration: {duration:g} s gives ~{n_obs:.3g} bearings, more than the '
                         f'{MAX_SIMULATED_BEARINGS:.0e} one run holds in memory')
    targets = realize_targets(scenario, seed)
    streams, events = [], []
    for i, st in enumerate(scenario.stations):
        survey = st.position_sigma * _rng(seed, _STREAM_SURVEY, i).standard_normal(3)
        cov = np.eye(3) * st.position_sigma ** 2
        for j, tg in enumerate(targets):
            s = _simulate_stream(scenario, st, i, tg, j, duration, seed, survey)
            streams.append(s)
            for k in np.flatnonzero(s.kept):
                b = Bearing(station=st.id, stamp_ns=int(s.stamp_ns[k]),
                            position=s.station_position[k].copy(),
                            azimuth=float(s.azimuth[k]), elevation=float(s.elevation[k]),
                            sigma_azimuth=float(s.sigma_az[k]),
                            sigma_elevation=float(s.sigma_el[k]),
                            frame_id=scenario.frame_id, position_covariance=cov.copy())
                events.append((int(s.publish_ns[k]), i, j, int(s.true_ns[k]),
                               BearingEvent(int(s.publish_ns[k]), tg.namespace, b,
                                            int(s.true_ns[k]), s.truth[k].copy(),
                                            bool(s.outlier[k]))))
    events.sort(key=lambda e: e[:4])
    bearings = [e[-1] for e in events]
    truth = []
    if scenario.truth_rate > 0:
        period = int(round(NS_PER_S / scenario.truth_rate))
        end = int(round(duration * NS_PER_S))
        t_ns = np.arange(0, end, period, dtype=np.int64)
        per_target = [(tg.namespace, target_position(tg, t_ns / NS_PER_S),
                       tg.trajectory.velocity_at(t_ns / NS_PER_S)) for tg in targets]
        for k, tk in enumerate(t_ns):
            for ns, p, v in per_target:
                truth.append(TruthEvent(scenario.epoch_ns + int(tk), ns, p[k].copy(),
                                        v[k].copy()))
    end_ns = scenario.time_ns(duration)
    if bearings:
        end_ns = max(end_ns, bearings[-1].publish_ns)
    return Simulation(scenario, seed, duration, targets, streams, bearings, truth, end_ns)


# --------------------------------------------------------------------------------------------
# Loader
# --------------------------------------------------------------------------------------------

SCENARIO_KEYS = ('name', 'description', 'frame_id', 'duration', 'epoch', 'truth_rate',
                 'geodetic_origin', 'station_defaults', 'stations', 'targets')
MOTION_KEYS = ('position', 'geodetic', 'velocity', 'waypoints', 'speed', 'times',
               'start_time')
STATION_KEYS = ('id', 'dims', 'sigma_az', 'sigma_az_deg', 'sigma_el', 'sigma_el_deg', 'rate',
                'phase', 'clock_offset', 'clock_jitter', 'clock_drift_ppm', 'latency',
                'latency_jitter', 'dropout', 'outlier', 'outlier_size', 'outlier_size_deg',
                'outlier_size_max', 'outlier_size_max_deg', 'position_sigma',
                'sigma_growth') + MOTION_KEYS
TARGET_KEYS = ('namespace', 'kind', 'box_min', 'box_max', 'count') + MOTION_KEYS
GROWTH_KEYS = ('range_ref', 'min_factor', 'max_factor', 'report')
GEODETIC_KEYS = ('lat_deg', 'lon_deg', 'alt')


class _Src:
    """Formats loader errors as ``<file>: <key path>: <problem>``."""

    def __init__(self, source):
        self.source = source

    def error(self, key, problem):
        return ValueError(f'{self.source}: {key}: {problem}')


def _mapping(src, value, key, allowed):
    if not isinstance(value, dict):
        raise src.error(key or 'scenario', f'expected a mapping, got {type(value).__name__}')
    for k in value:
        if k not in allowed:
            raise src.error(f'{key}.{k}' if key else str(k),
                            f'unknown key (allowed: {", ".join(allowed)})')
    return value


def _float(src, d, key, where, default=None, lo=None, hi=None, lo_open=False,
           required=False):
    if key not in d or d[key] is None:
        if required:
            raise src.error(f'{where}{key}', 'required key is missing')
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise src.error(f'{where}{key}', f'expected a number, got {v!r}')
    try:
        v = float(v)
    except OverflowError:        # an integer beyond the float range
        v = math.inf
    if not math.isfinite(v):
        raise src.error(f'{where}{key}', f'must be finite (got {v})')
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise src.error(f'{where}{key}', f'must be {">" if lo_open else ">="} {lo} (got {v})')
    if hi is not None and v > hi:
        raise src.error(f'{where}{key}', f'must be <= {hi} (got {v})')
    return v


def _angle(src, d, key, where, default, lo=0.0, lo_open=True):
    """A radian value given as ``key`` (rad) or ``key_deg`` (degrees), not both."""
    if key in d and f'{key}_deg' in d:
        raise src.error(f'{where}{key}_deg', f'give either {key} (rad) or {key}_deg, not both')
    if f'{key}_deg' in d:
        v = _float(src, d, f'{key}_deg', where, lo=lo, lo_open=lo_open)
        return default if v is None else math.radians(v)
    return _float(src, d, key, where, default, lo=lo, lo_open=lo_open)


def _vec(src, value, key, n=3):
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in value)):
        raise src.error(key, f'expected a list of {n} numbers, got {value!r}')
    try:
        v = np.array(value, dtype=float)
    except OverflowError:        # an integer beyond the float range
        v = np.array([math.inf])
    if not np.all(np.isfinite(v)):
        raise src.error(key, f'non-finite value in {str(value)[:80]}')
    return v


def _geodetic(src, value, key):
    g = _mapping(src, value, key, GEODETIC_KEYS)
    lat = _float(src, g, 'lat_deg', f'{key}.', lo=-90.0, hi=90.0, required=True)
    lon = _float(src, g, 'lon_deg', f'{key}.', lo=-180.0, hi=360.0, required=True)
    alt = _float(src, g, 'alt', f'{key}.', default=0.0)
    return lat, lon, alt


def _motion(src, d, where, origin, allow_random=False):
    """Parse the motion keys of a station or target into a Trajectory (or None for random)."""
    has = {k for k in MOTION_KEYS if k in d}
    if 'position' in has and 'geodetic' in has:
        raise src.error(f'{where}geodetic', 'give either position (ENU m) or geodetic')
    if 'waypoints' in has:
        bad = has & {'position', 'geodetic', 'velocity'}
        if bad:
            raise src.error(f'{where}{sorted(bad)[0]}', 'not allowed together with waypoints')
        pts_raw = d['waypoints']
        if not isinstance(pts_raw, (list, tuple)) or len(pts_raw) < 2:
            raise src.error(f'{where}waypoints', 'expected a list of at least 2 [x, y, z]')
        pts = np.array([_vec(src, p, f'{where}waypoints[{k}]') for k, p in enumerate(pts_raw)])
        legs = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        if 'speed' in has and 'times' in has:
            raise src.error(f'{where}times', 'give either speed or times, not both')
        if 'times' in has:
            if 'start_time' in has:
                raise src.error(f'{where}start_time', 'not allowed together with times')
            times = d['times']
            if not isinstance(times, (list, tuple)) or len(times) != len(pts):
                raise src.error(f'{where}times', f'expected {len(pts)} times (one per waypoint)')
            ts = np.array([_float(src, {'t': x}, 't', f'{where}times[{k}]', required=True)
                           for k, x in enumerate(times)])
            if np.any(np.diff(ts) <= 0):
                raise src.error(f'{where}times', 'must be strictly increasing')
            return Trajectory.waypoints(pts, ts)
        if 'speed' not in has:
            raise src.error(f'{where}speed', 'required with waypoints (or give times)')
        sp = d['speed']
        if isinstance(sp, (list, tuple)):
            if len(sp) != len(legs):
                raise src.error(f'{where}speed', f'expected {len(legs)} speeds (one per leg)')
            speeds = np.array([_float(src, {'v': x}, 'v', f'{where}speed[{k}]', lo=0.0,
                                      lo_open=True, required=True) for k, x in enumerate(sp)])
        else:
            speeds = np.full(len(legs), _float(src, d, 'speed', where, lo=0.0, lo_open=True))
        k0 = np.flatnonzero(legs <= 0)
        if len(k0):
            raise src.error(f'{where}waypoints[{k0[0] + 1}]', 'repeats the previous waypoint')
        t0 = _float(src, d, 'start_time', where, 0.0)
        return Trajectory.waypoints(pts, t0 + np.concatenate([[0.0], np.cumsum(legs / speeds)]))
    for k in ('speed', 'times', 'start_time'):
        if k in has:
            raise src.error(f'{where}{k}', 'only allowed with waypoints')
    if 'geodetic' in has:
        if origin is None:
            raise src.error(f'{where}geodetic', 'needs a scenario-level geodetic_origin')
        lat, lon, alt = _geodetic(src, d['geodetic'], f'{where}geodetic')
        try:
            p = geodetic_to_enu(lat, lon, alt, origin).reshape(3)
        except ValueError as exc:
            raise src.error(f'{where}geodetic', str(exc)) from None
    elif 'position' in has:
        p = _vec(src, d['position'], f'{where}position')
    elif allow_random:
        return None
    else:
        raise src.error(f'{where}position', 'required (or geodetic, or waypoints)')
    if 'velocity' in has:
        return Trajectory.constant_velocity(p, _vec(src, d['velocity'], f'{where}velocity'))
    return Trajectory.static(p)


def _station(src, raw, k, defaults, origin):
    where = f'stations[{k}].'
    _mapping(src, raw, f'stations[{k}]', STATION_KEYS)
    d = dict(defaults)
    for base in ('sigma_az', 'sigma_el', 'outlier_size', 'outlier_size_max'):
        if base in raw or f'{base}_deg' in raw:
            d.pop(base, None)
            d.pop(f'{base}_deg', None)
    d.update(raw)
    sid = d.get('id')
    if not isinstance(sid, str) or not _NAME_RE.match(sid):
        raise src.error(f'{where}id', f'expected a ROS name token ([A-Za-z_][A-Za-z0-9_]*), '
                        f'got {sid!r}')
    dims = d.get('dims', 2)
    if dims not in (1, 2) or isinstance(dims, bool):
        raise src.error(f'{where}dims', f'must be 1 (azimuth only) or 2 (got {dims!r})')
    sigma_az = _angle(src, d, 'sigma_az', where, 0.01)
    sigma_el = _angle(src, d, 'sigma_el', where, sigma_az) if dims == 2 else math.nan
    growth = None
    if d.get('sigma_growth') is not None:
        gw = f'{where}sigma_growth'
        g = _mapping(src, d['sigma_growth'], gw, GROWTH_KEYS)
        report = g.get('report', 'nominal')
        if report not in SIGMA_REPORTS:
            raise src.error(f'{gw}.report', f'must be one of {SIGMA_REPORTS} (got {report!r})')
        fmin = _float(src, g, 'min_factor', f'{gw}.', 1e-3, lo=0.0, lo_open=True)
        fmax = _float(src, g, 'max_factor', f'{gw}.', math.inf, lo=fmin)
        growth = SigmaGrowth(_float(src, g, 'range_ref', f'{gw}.', lo=0.0, lo_open=True,
                                    required=True), fmin, fmax, report)
    outlier_size = _angle(src, d, 'outlier_size', where, math.radians(10.0), lo_open=False)
    size_max = None
    if 'outlier_size_max' in d or 'outlier_size_max_deg' in d:
        size_max = _angle(src, d, 'outlier_size_max', where, None, lo_open=False)
        if not outlier_size <= size_max <= math.pi:
            raise src.error(f'{where}outlier_size_max', 'must be in [outlier_size, 180 deg]')
    rate = _float(src, d, 'rate', where, 1.0, lo=0.0, lo_open=True)
    if rate > 1e6:
        raise src.error(f'{where}rate', f'must be <= 1e6 Hz (got {rate})')
    return Station(
        id=sid, trajectory=_motion(src, d, where, origin), dims=dims, sigma_az=sigma_az,
        sigma_el=sigma_el, rate=rate, phase=_float(src, d, 'phase', where, 0.0, lo=0.0),
        clock_offset=_float(src, d, 'clock_offset', where, 0.0),
        clock_jitter=_float(src, d, 'clock_jitter', where, 0.0, lo=0.0),
        clock_drift=_float(src, d, 'clock_drift_ppm', where, 0.0) * 1e-6,
        latency=_float(src, d, 'latency', where, 0.0, lo=0.0),
        latency_jitter=_float(src, d, 'latency_jitter', where, 0.0, lo=0.0),
        dropout=_float(src, d, 'dropout', where, 0.0, lo=0.0, hi=1.0),
        outlier=_float(src, d, 'outlier', where, 0.0, lo=0.0, hi=1.0),
        outlier_size=outlier_size, outlier_size_max=size_max,
        position_sigma=_float(src, d, 'position_sigma', where, 0.0, lo=0.0),
        sigma_growth=growth)


def _namespace(src, value, key):
    if value is None:
        return ''
    if not isinstance(value, str):
        raise src.error(key, f'expected a string, got {value!r}')
    ns = value.strip('/')
    if ns and not all(_NAME_RE.match(p) for p in ns.split('/')):
        raise src.error(key, f'not a valid ROS namespace: {value!r}')
    return ns


def _targets(src, raw, k, origin):
    where = f'targets[{k}].'
    _mapping(src, raw, f'targets[{k}]', TARGET_KEYS)
    ns = _namespace(src, raw.get('namespace', ''), f'{where}namespace')
    kind = raw.get('kind')
    if kind is not None and kind not in TARGET_KINDS:
        raise src.error(f'{where}kind', f'must be one of {TARGET_KINDS} (got {kind!r})')
    count = raw.get('count', 1)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise src.error(f'{where}count', f'must be an integer >= 1 (got {count!r})')
    if kind == 'random_static' or ('box_min' in raw or 'box_max' in raw):
        if kind not in (None, 'random_static'):
            raise src.error(f'{where}box_min', 'only allowed with kind random_static')
        extra = [m for m in MOTION_KEYS if m in raw]
        if extra:
            raise src.error(f'{where}{extra[0]}', 'not allowed for a random_static target')
        lo = _vec(src, raw.get('box_min'), f'{where}box_min')
        hi = _vec(src, raw.get('box_max'), f'{where}box_max')
        if np.any(hi < lo):
            raise src.error(f'{where}box_max', 'must be >= box_min on every axis')
        names = [ns] if count == 1 else [f'{ns}_{m}' if ns else f'source_{m}'
                                         for m in range(count)]
        return [Target(n, 'random_static', None, lo, hi) for n in names]
    if count != 1:
        raise src.error(f'{where}count', 'only allowed for random_static targets')
    traj = _motion(src, raw, where, origin)
    if kind is not None and kind != traj.kind:
        raise src.error(f'{where}kind', f'{kind!r} does not match the motion keys given '
                        f'(they describe a {traj.kind} target)')
    return [Target(ns, traj.kind, traj)]


def parse_scenario(data, source='<dict>'):
    """Validate a scenario mapping (the parsed YAML) and return a :class:`Scenario`.

    Raises ValueError ``'<source>: <key path>: <problem>'`` naming the offending key, e.g.
    ``config/scenarios/x.yaml: stations[1].sigma_az: must be > 0.0 (got -1.0)``.
    """
    src = _Src(source)
    _mapping(src, data, '', SCENARIO_KEYS)
    name = data.get('name', '')
    description = data.get('description', '')
    for key, v in (('name', name), ('description', description)):
        if not isinstance(v, str):
            raise src.error(key, f'expected a string, got {v!r}')
    frame_id = data.get('frame_id', DEFAULT_FRAME)
    if not isinstance(frame_id, str) or not frame_id:
        raise src.error('frame_id', f'expected a non-empty string, got {frame_id!r}')
    duration = _float(src, data, 'duration', '', lo=0.0, lo_open=True, required=True)
    epoch = _float(src, data, 'epoch', '', DEFAULT_EPOCH, lo=0.0)
    truth_rate = _float(src, data, 'truth_rate', '', DEFAULT_TRUTH_RATE, lo=0.0)
    origin = None
    if data.get('geodetic_origin') is not None:
        origin = _geodetic(src, data['geodetic_origin'], 'geodetic_origin')
    defaults = data.get('station_defaults') or {}
    _mapping(src, defaults, 'station_defaults',
             tuple(k for k in STATION_KEYS if k != 'id' and k not in MOTION_KEYS))
    raw_st = data.get('stations')
    if not isinstance(raw_st, list) or not raw_st:
        raise src.error('stations', 'expected a non-empty list of stations')
    stations = tuple(_station(src, r, k, defaults, origin) for k, r in enumerate(raw_st))
    seen = set()
    for k, s in enumerate(stations):
        if s.id in seen:
            raise src.error(f'stations[{k}].id', f'duplicate station id {s.id!r}')
        seen.add(s.id)
        if epoch + s.clock_offset < 0:
            raise src.error(f'stations[{k}].clock_offset',
                            f'epoch + clock_offset must be >= 0 s (ROS time cannot be negative;'
                            f' got {epoch + s.clock_offset})')
    raw_tg = data.get('targets')
    if not isinstance(raw_tg, list) or not raw_tg:
        raise src.error('targets', 'expected a non-empty list of targets')
    targets = tuple(t for k, r in enumerate(raw_tg) for t in _targets(src, r, k, origin))
    seen = set()
    for t in targets:
        if t.namespace in seen:
            raise src.error('targets', f'duplicate target namespace {t.namespace!r}')
        seen.add(t.namespace)
    return Scenario(stations=stations, targets=targets, duration=duration, name=name,
                    description=description, frame_id=frame_id, epoch=epoch,
                    truth_rate=truth_rate, geodetic_origin=origin, source=source)


def load_scenario(path):
    """Read and validate a scenario YAML file (format: README "Simulator").

    Raises ValueError naming the file and the offending key (or the YAML syntax error).
    """
    import yaml
    path = os.fspath(path)
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise ValueError(f'{path}: cannot read scenario ({exc.strerror or exc})') from None
    except UnicodeDecodeError:
        raise ValueError(f'{path}: not a UTF-8 text file (a YAML scenario is expected)') \
            from None
    except yaml.YAMLError as exc:
        msg = ' '.join(str(exc).split())
        raise ValueError(f'{path}: invalid YAML ({msg})') from None
    if data is None:
        raise ValueError(f'{path}: empty scenario file')
    return parse_scenario(data, source=path)
