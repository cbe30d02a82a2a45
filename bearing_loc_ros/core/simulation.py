"""Deterministic bearing generation from a scenario (the simulator core).

Pure numpy (never imports rclpy). The simulator node, the bag writer and the Monte Carlo
evaluation all call :func:`simulate`, so a seed gives the same bearings everywhere.
The scenario model lives in :mod:`.scenario_model` and the YAML loader in
:mod:`.scenario_loader`; both are re-exported here, so ``core.simulation`` stays the one
import path for the whole simulator.


Measurement model (Wang, Zhang & Wu (2006) eq. (1) with the additive Gaussian noise of its
eq. (6); Zong & Cui (2015) eqs. (1)-(2) and, for range-dependent σ, eqs. (9)-(10)). For
station i at s_i(t), target at X(t), observation k at the true (scenario) time t_k and
d = X(t_k) − s_i(t_k):

    θ_ik = wrap(atan2(d_y, d_x) + σ_θ(r) n_ik + o_ik a_θ),
    ψ_ik = clip(atan2(d_z, hypot(d_x, d_y)) + σ_ψ(r) m_ik + o_ik a_ψ),   (2D stations only)
    σ(r) = clip(σ_ref · clip(r / r_ref, f_min, f_max), SIGMA_MIN, π)
                       (Zong & Cui (2015) eqs. (9)-(10); σ(r) = σ_ref when no
                        ``sigma_growth`` is configured)

with r = |d|, n, m ~ N(0, 1), o_ik ~ Bernoulli(outlier) and a = ±outlier_size (random sign);
with ``outlier_size_max`` the magnitude is uniform in [outlier_size, outlier_size_max] (a
reflection 20-90° off: u = Φ(z_out)/outlier, uniform given o_ik, sets |a| = size + (max −
size)·u, so no extra random draw and the other bearings of a scenario do not change).
ψ is clipped to |ψ| ≤ π/2 − 1e-9 so a noisy elevation stays a valid bearing. The outer clip
of σ(r), rad, to the loader's SIGMA_RANGE = [SIGMA_MIN, π] = [1e-12, π] (the bounds of
``sigma_az``) keeps every σ a valid bearing σ (core.bearings accepts [1e-12, 1e3] rad): the
growth has no upper clip by default (``max_factor`` = ∞), so σ_ref · r / r_ref reached 1e4
rad, and σ_ref · f_min may fall below 1e-12 rad. A σ above π carries no information (the
wrapped noise is nearly uniform already), so the cap changes no bearing's meaning; the
clipped σ is both the one used for the noise and the one reported (``report: actual``).
Each observation is dropped with probability ``dropout``. Timing of observation k:

    t_k       = phase + k / rate                          true time (scenario seconds)
    stamp_k   = epoch + t_k + clock_offset + drift·t_k + clock_jitter·c_k   (station clock)
    publish_k = epoch + t_k + max(0, latency + latency_jitter·l_k)           (simulated clock)

c, l ~ N(0, 1); drift = clock_drift_ppm·1e-6. The truth attached to a bearing is X(t_k).
Observation times are the half-open interval [0, duration): section 4 of Wang, Zhang & Wu
(2006) (every 2 s for 100 s) gives k = 0..49. Periods are rounded to whole nanoseconds.
A duration given to :func:`simulate` (overriding the scenario's) has the scenario's bounds
(:func:`check_duration`).

Determinism: every random number comes from numpy Generators seeded with
``SeedSequence([seed, stream, index...])``: stream 0 = target j's random draws, stream 1 =
station i's survey error, stream 2 = the observations of station i of target j. Each
observation consumes one row of 8 standard normals (dropout, n, m, outlier, two signs, c, l;
uniform draws are Φ(z)), so the bearings do not depend on wall timing, on the other stations'
settings, nor (for the first k) on the duration.
"""

from dataclasses import dataclass, field
import math

import numpy as np
from scipy.special import ndtr

from .bearings import Bearing
from .conventions import azimuth_elevation, wrap_angle
# Re-exported: the scenario model and loader are part of this module's public interface.
from .scenario_loader import (GEODETIC_KEYS, GROWTH_KEYS, load_scenario,  # noqa: F401
                              MAX_TIME, MAX_TRUTH_SAMPLES, MOTION_KEYS, parse_scenario,
                              SCENARIO_KEYS, SIGMA_RANGE, STATION_KEYS, TARGET_KEYS)
from .scenario_model import (bearing_topic, DEFAULT_EPOCH, DEFAULT_FRAME,  # noqa: F401
                             DEFAULT_TRUTH_RATE, MAX_ELEVATION, MOTION_KINDS, NS_PER_S,
                             Scenario, SIGMA_REPORTS, SigmaGrowth, Station, station_position,
                             Target, TARGET_KINDS, target_position, Trajectory, truth_topic)

# Columns of the (K, 8) standard-normal block drawn per observation (the fixed order).
_C_DROP, _C_AZ, _C_EL, _C_OUT, _C_SIGN_AZ, _C_SIGN_EL, _C_CLOCK, _C_LAT = range(8)
_N_COLS = 8
_STREAM_TARGET, _STREAM_SURVEY, _STREAM_OBS = 0, 1, 2


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
    rad (σ reported in the message); kept, outlier (K,) bool; no_azimuth (K,) bool: the
    target on the station or straight above it (not observed, whatever ``kept`` says of
    dropouts).
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
    no_azimuth: np.ndarray = None


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

    # Dataclass fields: alike other field lists in shape only, there is no logic to share.
    scenario: Scenario
    seed: int
    duration: float
    targets: list
    streams: list
    bearings: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    end_ns: int = 0

    def unobserved(self):
        """{station id: scheduled observations not made because the target was on the
        station or straight above it (horizontal range <= MIN_HORIZONTAL_RANGE: no azimuth)},
        the stations with any."""
        out = {}
        for s in self.streams:
            n = int(np.count_nonzero(s.no_azimuth))
            if n:
                out[s.station] = out.get(s.station, 0) + n
        return out

    def unobserved_note(self):
        """One sentence naming :meth:`unobserved`'s counts, or '' when there are none."""
        counts = self.unobserved()
        if not counts:
            return ''
        return ('not observed (target on or straight above the station, no azimuth): '
                + ', '.join(f'{st} {n}' for st, n in counts.items()))

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
    (Zong & Cui (2015), section 3.1: sources uniform in X(−3000, 3000), Y(1000, 7000),
    Z(−500, 500) m).
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


#: Most scheduled observations (duration · Σ rate · targets, dropped ones included) of one
#: :func:`simulate` call. All are held in memory: measured ~1.5 kB each (Stream arrays +
#: BearingEvent; ``bag simulate`` builds messages while writing and adds nothing), so at most
#: ~1.5 GB (ten stations at 10 Hz for 2.7 h). With the loader's MAX_TRUTH_SAMPLES = 1e6 truth
#: samples (~0.55 kB each): seed000 for 1e5 s (1.5e5 bearings, 1e6 truth samples, 1e7 /clock
#: messages) peaked at 0.79 GB.
MAX_SIMULATED_BEARINGS = 1e6
#: Most /clock messages of one ``bag simulate`` bag ((end − epoch) · clock_rate + 2). They are
#: generated while writing (no memory per message); the bound keeps a bag below ~0.6 GB of
#: disk (~57 B per message) and ~2 min of writing (27.8 h of simulated time at 100 Hz).
MAX_CLOCK_TICKS = 1e7


def observation_times_ns(station, duration):
    """Scenario times t_k = phase + k/rate in [0, duration), integer ns (int64 array)."""
    period = station.period_ns
    phase = int(round(station.phase * NS_PER_S))
    end = int(round(duration * NS_PER_S))
    if phase >= end:
        return np.zeros(0, dtype=np.int64)
    k = np.arange((end - phase + period - 1) // period, dtype=np.int64)
    return phase + k * period


#: Horizontal range, m, below which a scheduled observation is not made (its azimuth is
#: undefined).
MIN_HORIZONTAL_RANGE = 1e-6


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
    saz_act = np.clip(station.sigma_az * f, *SIGMA_RANGE)      # σ(r), rad (module doc)
    u_out = ndtr(z[:, _C_OUT])
    outlier = u_out < station.outlier
    size = station.outlier_size
    if station.outlier_size_max is not None and station.outlier > 0.0:
        u = np.clip(u_out / station.outlier, 0.0, 1.0)
        size = size + (station.outlier_size_max - size) * u
    sign_az = np.where(z[:, _C_SIGN_AZ] >= 0.0, 1.0, -1.0)
    az = wrap_angle(az0 + saz_act * z[:, _C_AZ] + outlier * sign_az * size)
    if station.dims == 2:
        sel_act = np.clip(station.sigma_el * f, *SIGMA_RANGE)
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
    # A target on the station or straight above it has no azimuth: nothing is observed
    # (atan2(0, 0) = 0 would publish "due East" as a precise bearing).
    no_azimuth = np.hypot(d[:, 0], d[:, 1]) <= MIN_HORIZONTAL_RANGE
    kept &= ~no_azimuth
    clock_err = (station.clock_offset + station.clock_drift * t
                 + station.clock_jitter * z[:, _C_CLOCK])
    true_ns = scenario.epoch_ns + t_ns
    stamp_ns = np.maximum(true_ns + np.round(clock_err * NS_PER_S).astype(np.int64), 0)
    delay = np.maximum(0.0, station.latency + station.latency_jitter * z[:, _C_LAT])
    publish_ns = true_ns + np.round(delay * NS_PER_S).astype(np.int64)
    return Stream(station.id, target.namespace, t, true_ns, stamp_ns, publish_ns, pos, truth,
                  rng_, az0, el0, np.atleast_1d(az), el, saz_act, sel_act, saz_rep, sel_rep,
                  kept, outlier, no_azimuth)


def check_duration(scenario, duration=None):
    """The simulated duration, s, of ``simulate(scenario, duration)``: ``duration`` (None or
    0: ``scenario.duration``) checked against the bounds of a scenario's own duration, so an
    override (the simulator node's ``duration``, ``bag simulate --duration``, the Python API)
    cannot do what the loader refuses: 0 < duration <= MAX_TIME (1e7 s; every stamp stays
    within int32 ROS seconds), truth_rate · duration · targets <= MAX_TRUTH_SAMPLES (1e6) and
    duration · Σ rate · targets <= MAX_SIMULATED_BEARINGS (1e6 scheduled observations), and
    every station's first observation (its ``phase``) before the end: a station that would
    make no bearing is an error, not a silent gap in the network.

    Raises ValueError ``duration: <problem>`` (the CLI prints it as one line, exit 2).
    """
    if duration is None or duration == 0:
        duration = scenario.duration
    if isinstance(duration, bool) or not isinstance(duration, (int, float, np.number)):
        raise ValueError(f'duration: expected a number of seconds, got {duration!r}')
    try:
        duration = float(duration)
    except OverflowError:        # an integer beyond the float range
        duration = math.inf
    if not 0.0 < duration <= MAX_TIME:      # NaN fails too
        raise ValueError(f'duration: must be within (0, {MAX_TIME:g}] s (got {duration:g})')
    n_truth = scenario.truth_rate * duration * len(scenario.targets)
    if n_truth > MAX_TRUTH_SAMPLES:
        raise ValueError(f'duration: {duration:g} s gives truth_rate x duration x targets = '
                         f'{n_truth:.3g} truth samples, more than {MAX_TRUTH_SAMPLES:g}')
    n_obs = duration * sum(st.rate for st in scenario.stations) * len(scenario.targets)
    if n_obs > MAX_SIMULATED_BEARINGS:
        top = max(scenario.stations, key=lambda st: st.rate)
        raise ValueError(f'duration: {duration:g} s gives duration x rates x targets = '
                         f'{n_obs:.3g} bearings, more than the {MAX_SIMULATED_BEARINGS:g} one '
                         f'run holds in memory (the largest rate: station {top.id}, '
                         f'{top.rate:g} Hz)')
    late = [st for st in scenario.stations if st.phase >= duration]
    if late:
        raise ValueError(f'duration: {duration:g} s ends before the first observation of '
                         f'station {late[0].id} (phase {late[0].phase:g} s): it would make no '
                         f'bearing')
    return duration


def simulate(scenario, duration=None, seed=0):
    """Generate every bearing and truth sample of ``scenario`` (deterministic in ``seed``).

    Args:
        scenario: a :class:`Scenario`.
        duration: simulated seconds; None or 0 uses ``scenario.duration``. Bounded as the
            scenario's own duration (:func:`check_duration`: ValueError naming duration).
        seed: non-negative int; all randomness derives from it (module docstring).

    Returns:
        :class:`Simulation` with the kept bearings as :class:`BearingEvent` sorted by publish
        time (ties: station order, then target order), truth samples and per-stream arrays.
    """
    seed = _check_seed(seed)
    duration = check_duration(scenario, duration)
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
