"""Scenario model of the simulator: trajectories, stations, targets and topic names.

Pure numpy (never imports rclpy). ENU world frame, m, s of scenario time, rad. Built by
:func:`.scenario_loader.parse_scenario`, used by :func:`.simulation.simulate`, the Monte Carlo
evaluation and the planner (all re-exported from :mod:`.simulation`).
"""

from dataclasses import dataclass
import math

import numpy as np

from .bearings import MAX_ELEVATION  # noqa: F401  (largest |elevation| simulated, rad)

NS_PER_S = 1_000_000_000
#: Default simulated time of scenario start (s). Non-zero so that ROS time 0 ("clock not
#: received yet") is never a valid simulated instant and negative clock offsets stay >= 0.
DEFAULT_EPOCH = 1000.0
DEFAULT_TRUTH_RATE = 10.0
DEFAULT_FRAME = 'map'
MOTION_KINDS = ('static', 'constant_velocity', 'waypoints')
TARGET_KINDS = MOTION_KINDS + ('random_static',)
SIGMA_REPORTS = ('nominal', 'actual')


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
    """Range-dependent σ (Zong & Cui (2015) eqs. (9)-(10)): σ_ref · clip(r/r_ref, f_min, f_max).

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
    """A simulated DF station (docs/nodes.md "Scenario YAML" has every key and default).

    Angles in rad, times in s, rates in Hz, distances in m. ``sigma_el`` is NaN for a 1D
    (azimuth-only) station. ``clock_drift`` is a fraction (ppm · 1e-6).
    """

    # Dataclass fields: alike other field lists in shape only, there is no logic to share.
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
    the simulation seed (:func:`realize_targets`); Zong & Cui (2015), section 3.1.
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

    # Time conversions and lookups by name: alike other records' in shape only.
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
