"""Time alignment of bearings from asynchronous stations (DESIGN.md "Time alignment").

Pure Python/numpy: no rclpy, no wall clock. All times are integer nanoseconds on the fusion
node's clock (ROS time, so ``use_sim_time`` and bag replay with ``/clock`` work); a bearing's
time is its observation stamp ``Bearing.stamp_ns``.

Per station, bearings are kept in a :class:`StationBuffer`, sorted by stamp and bounded in
size (``buffer_size`` newest kept) and in age (stamps older than ``now − buffer_age`` are
pruned). An output epoch at time t uses at most one bearing per station, obtained by
:func:`align`:

* nearest: the buffered bearing b minimising |b.stamp − t|, provided
  |b.stamp − t| <= ``sync_tolerance`` (ties go to the earlier bearing);
* interpolated (``interpolation=True``): when two buffered bearings bracket t,
  t0 <= t <= t1 with t1 − t0 <= ``max_interpolation_gap``, the bearing at t with fraction
  a = (t − t0) / (t1 − t0) (see :func:`interpolate_bearing`); when t is not bracketed (for
  example at the newest edge of the buffer) the nearest rule above is used instead.

Interpolation assumes the azimuth, elevation and station position change linearly between
the two bearings (a target and stations moving at constant angular rate over the gap); the
gap bound keeps that model error small. Wang, Zhang & Wu (2006) eq. (1) is the measurement
model throughout.
"""

from bisect import bisect_left, bisect_right
from dataclasses import dataclass, replace

import numpy as np

from .conventions import wrap_angle

NS_PER_S = 1_000_000_000

#: How a bearing was aligned to an epoch.
NEAREST = 'nearest'
INTERPOLATED = 'interpolated'

#: Reasons a bearing is dropped on arrival (counted per station).
DUPLICATE = 'duplicate'
OUT_OF_ORDER = 'out_of_order'
TOO_LATE = 'too_late'
FROM_FUTURE = 'from_future'   # stamp > now + buffer_age (a station clock far ahead)
#: The station's position moved faster than max_station_speed since its last bearing
#: (core.fusion.stations: a GPS glitch or a bad position source).
IMPLAUSIBLE_POSITION = 'implausible_position'
DROP_REASONS = (DUPLICATE, OUT_OF_ORDER, TOO_LATE, FROM_FUTURE, IMPLAUSIBLE_POSITION)


def seconds_to_ns(seconds):
    """Seconds (float) -> integer nanoseconds, rounded to the nearest nanosecond."""
    return int(round(float(seconds) * NS_PER_S))


@dataclass(frozen=True)
class AlignmentConfig:
    """Alignment settings, integer nanoseconds (see the module docstring).

    Attributes:
        sync_tolerance_ns: largest |stamp − epoch| for the nearest rule (>= 0).
        interpolation: interpolate between bracketing bearings when possible.
        max_interpolation_gap_ns: largest t1 − t0 of a bracketing pair (> 0).
        buffer_size: bearings kept per station (>= 2 so interpolation can bracket).
        buffer_age_ns: bearings with stamp < now − buffer_age_ns are pruned (> 0).
    """

    sync_tolerance_ns: int = 50_000_000
    interpolation: bool = False
    max_interpolation_gap_ns: int = 1_000_000_000
    buffer_size: int = 50
    buffer_age_ns: int = 5_000_000_000

    def validate(self):
        """Raise ``ValueError`` naming the first invalid field; return self."""
        if self.sync_tolerance_ns < 0:
            raise ValueError('sync_tolerance: must be >= 0')
        if self.max_interpolation_gap_ns <= 0:
            raise ValueError('max_interpolation_gap: must be > 0')
        if int(self.buffer_size) < 2:
            raise ValueError('buffer_size: must be >= 2')
        if self.buffer_age_ns <= 0:
            raise ValueError('buffer_age: must be > 0')
        return self

    def replace(self, **changes):
        """A copy with ``changes`` applied (not validated)."""
        return replace(self, **changes)


def interpolate_bearing(b0, b1, t_ns):
    """Bearing at time ``t_ns`` interpolated linearly between ``b0`` and ``b1`` (same station).

    With a = (t − t0) / (t1 − t0) (t0 = b0.stamp_ns, t1 = b1.stamp_ns, t0 < t1; a is computed
    from integer nanoseconds and may lie outside [0, 1] only if the caller extrapolates):

    * azimuth, angle-aware across the ±π wrap: θ = wrap(θ0 + a · wrap(θ1 − θ0)) (rad);
    * elevation ψ = ψ0 + a (ψ1 − ψ0) when both bearings measure it (|ψ| < π/2, no wrap);
      NaN (azimuth-only) when either is azimuth-only;
    * station position p = p0 + a (p1 − p0) (m) and position covariance likewise;
    * σ = (1 − a) σ0 + a σ1. For independent errors the interpolated angle's standard
      deviation is sqrt((1 − a)² σ0² + a² σ1²) <= (1 − a) σ0 + a σ1, so the linear σ is an
      upper bound that leaves room for the model error of linear interpolation.

    The result carries stamp ``t_ns``, b0's station and frame. Measurement model:
    Wang, Zhang & Wu (2006) eq. (1). Raises ``ValueError`` if the stations or frames differ
    or t1 <= t0.
    """
    if b0.station != b1.station:
        raise ValueError(f'station: cannot interpolate {b0.station!r} with {b1.station!r}')
    if b0.frame_id != b1.frame_id:
        raise ValueError(f'frame_id: cannot interpolate {b0.frame_id!r} with {b1.frame_id!r}')
    t0, t1, t = int(b0.stamp_ns), int(b1.stamp_ns), int(t_ns)
    if t1 <= t0:
        raise ValueError('stamp_ns: interpolation needs t0 < t1')
    a = (t - t0) / (t1 - t0)
    az = wrap_angle(b0.azimuth + a * wrap_angle(b1.azimuth - b0.azimuth))
    if b0.has_elevation and b1.has_elevation:
        el = b0.elevation + a * (b1.elevation - b0.elevation)
        sel = (1.0 - a) * b0.sigma_elevation + a * b1.sigma_elevation
    else:
        el, sel = float('nan'), float('nan')
    p0, p1 = np.asarray(b0.position, dtype=float), np.asarray(b1.position, dtype=float)
    c0 = np.asarray(b0.position_covariance, dtype=float)
    c1 = np.asarray(b1.position_covariance, dtype=float)
    return replace(b0, stamp_ns=t, position=p0 + a * (p1 - p0), azimuth=float(az),
                   elevation=float(el),
                   sigma_azimuth=float((1.0 - a) * b0.sigma_azimuth + a * b1.sigma_azimuth),
                   sigma_elevation=float(sel), position_covariance=c0 + a * (c1 - c0))


class StationBuffer:
    """Bearings of one station sorted by stamp, bounded in size and age.

    Arrival rules (:meth:`classify`): a bearing whose stamp equals a buffered one is a
    duplicate; older than the newest buffered one, out of order; both are dropped, so the
    buffer only ever grows at its newest end.
    """

    def __init__(self, station, size=50, age_ns=5 * NS_PER_S):
        self.station = station
        self.size = int(size)
        self.age_ns = int(age_ns)
        self._stamps = []
        self._bearings = []

    def __len__(self):
        return len(self._bearings)

    @property
    def bearings(self):
        """The buffered bearings, oldest first (a copy of the list)."""
        return list(self._bearings)

    @property
    def newest(self):
        """The newest buffered bearing, or None."""
        return self._bearings[-1] if self._bearings else None

    @property
    def newest_stamp_ns(self):
        """Stamp of the newest buffered bearing, or None."""
        return self._stamps[-1] if self._stamps else None

    def classify(self, stamp_ns):
        """Why a bearing at ``stamp_ns`` cannot be appended: DUPLICATE, OUT_OF_ORDER or None."""
        if not self._stamps:
            return None
        i = bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            return DUPLICATE
        if stamp_ns < self._stamps[-1]:
            return OUT_OF_ORDER
        return None

    def push(self, bearing):
        """Append ``bearing`` (must pass :meth:`classify`); return the number evicted by size."""
        reason = self.classify(bearing.stamp_ns)
        if reason is not None:
            raise ValueError(f'stamp_ns: {reason} bearing for {self.station!r}')
        self._stamps.append(int(bearing.stamp_ns))
        self._bearings.append(bearing)
        evicted = max(0, len(self._bearings) - self.size)
        if evicted:
            del self._stamps[:evicted]
            del self._bearings[:evicted]
        return evicted

    def prune(self, now_ns):
        """Drop bearings with stamp < now − age; return how many were dropped."""
        k = bisect_left(self._stamps, int(now_ns) - self.age_ns)
        if k:
            del self._stamps[:k]
            del self._bearings[:k]
        return k

    def clear(self):
        """Forget every buffered bearing."""
        self._stamps.clear()
        self._bearings.clear()

    def nearest(self, t_ns, tolerance_ns, after_ns=None):
        """The bearing nearest to ``t_ns`` within ``tolerance_ns`` (ties: the earlier one).

        Only bearings stamped strictly after ``after_ns`` are candidates when it is given.
        Returns None if there is none.
        """
        lo = 0 if after_ns is None else bisect_right(self._stamps, after_ns)
        i = bisect_left(self._stamps, t_ns, lo=lo)
        best, best_d = None, None
        for j in (i - 1, i):
            if lo <= j < len(self._stamps):
                d = abs(self._stamps[j] - t_ns)
                if d <= tolerance_ns and (best_d is None or d < best_d):
                    best, best_d = self._bearings[j], d
        return best

    def bracket(self, t_ns, max_gap_ns):
        """Bearings (b0, b1) with b0.stamp <= t <= b1.stamp and t1 − t0 <= max_gap, or None.

        An exact stamp match returns (b, b).
        """
        i = bisect_left(self._stamps, t_ns)
        if i < len(self._stamps) and self._stamps[i] == t_ns:
            return self._bearings[i], self._bearings[i]
        if i == 0 or i == len(self._stamps):
            return None
        if self._stamps[i] - self._stamps[i - 1] > max_gap_ns:
            return None
        return self._bearings[i - 1], self._bearings[i]


def align(buffer, t_ns, config, after_ns=None):
    """One bearing of ``buffer`` aligned to epoch ``t_ns``: (bearing, how) or (None, None).

    ``how`` is :data:`INTERPOLATED` or :data:`NEAREST`. With ``config.interpolation`` a
    bracketing pair (:meth:`StationBuffer.bracket`) is interpolated by
    :func:`interpolate_bearing`; otherwise, or when t is not bracketed, the nearest bearing
    within ``config.sync_tolerance_ns`` stamped after ``after_ns`` is used
    (:meth:`StationBuffer.nearest`). The returned bearing is the buffered object itself for
    nearest alignment and a new one stamped t for interpolation.
    """
    if config.interpolation:
        pair = buffer.bracket(t_ns, config.max_interpolation_gap_ns)
        if pair is not None:
            b0, b1 = pair
            if b0 is b1:
                return b0, NEAREST
            return interpolate_bearing(b0, b1, t_ns), INTERPOLATED
    b = buffer.nearest(t_ns, config.sync_tolerance_ns, after_ns=after_ns)
    return (b, NEAREST) if b is not None else (None, None)
