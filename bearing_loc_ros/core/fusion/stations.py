"""The station registry: per-station buffers, arrival checks, states and the clock.

:class:`StationRegistry` owns everything the fusion pipeline knows about its stations and
its clock, and nothing about estimation:

* arrival checks of a bearing (the first that applies): no usable station id, invalid
  fields (``invalid_bearing``: Bearing.validate's rules, a 3-coordinate position, a finite
  (3, 3) position covariance with a non-negative diagonal, m²), another frame
  (``wrong_frame``), ``duplicate`` (same stamp as a buffered bearing of its station),
  ``out_of_order`` (older than the station's newest), ``too_late`` (stamp < last epoch −
  sync_tolerance, or older than now − buffer_age), ``from_future`` (stamp > now +
  future_tolerance); such bearings are counted, never raised. A station whose buffer holds
  bearings stamped after now (a clock that was ahead) and that then sends
  :data:`FUTURE_RECOVERY` consecutive in-order-with-now bearings refused as out of order
  has those future bearings evicted (``evicted_future``), so one forged stamp cannot block
  its station for longer than future_tolerance;
* the station state machine: ``waiting`` (no bearing yet), ``alive``, ``stale`` (now − its
  newest stamp > station_timeout). Only stations added with ``wait=True`` (configured
  ones) are waited for while ``waiting``; a discovered station counts once it delivered a
  valid bearing;
* the clock offset of each station: the median of (stamp − now) over its last
  :data:`OFFSET_WINDOW` valid bearings; when a station's bearings are refused because
  their stamps are further from now than buffer_age, a warning naming the likely cause is
  logged once (use_sim_time set on one side only, an unsynchronised clock);
* throttled warnings: a per-message warning (invalid bearings, bad station ids) is emitted
  at most once per :data:`WARN_THROTTLE_NS` of node time per station and kind, with the
  number suppressed in between (``warnings_suppressed``);
* the clock: "now" (integer ns on the node clock) going back by more than
  ``time_jump_tolerance`` clears every buffer and the epoch history (a bag looping, a
  simulation reset), reported as an event and to the ``on_time_jump`` listener;
* the geometry hook: ``geometry_version`` increments whenever the live station geometry
  changes.

Cost: O(1) amortised per bearing (only the bearing's station buffer is pruned on arrival,
every buffer before an epoch; states are rescanned only when one may have changed).

One module (about 500 lines) on purpose: the registry's buffers, arrival checks, states and
clock hints change together on every bearing.
"""

from collections import Counter, deque
from dataclasses import dataclass, field
import math
import numbers
import statistics

import numpy as np

from ..alignment import (FROM_FUTURE, IMPLAUSIBLE_POSITION, OUT_OF_ORDER, seconds_to_ns,
                         StationBuffer, TOO_LATE)

NS_PER_S = 1_000_000_000

#: Station states.
WAITING = 'waiting'
ALIVE = 'alive'
STALE = 'stale'

#: Rejection reasons of bearings given to the pipeline that break the contract.
INVALID_BEARING = 'invalid_bearing'
WRONG_FRAME = 'wrong_frame'

#: A station moving more than this (m) counts as a geometry change (planning hook).
GEOMETRY_MOVE_TOLERANCE_M = 1.0
#: Consecutive out-of-order arrivals, each stamped no later than now, that evict the
#: station's buffered bearings stamped after now.
FUTURE_RECOVERY = 3
#: A station position may move max_station_speed × the time since its last accepted
#: bearing plus this many metres, plus 3 × the RMS of its stated position σ (GPS noise).
POSITION_JUMP_SLACK_M = 10.0
#: stand_in_now counts a station's stamp while it sent a bearing among the last this many
#: × (stations) bearings to reach the arrival checks.
RECENT_ARRIVALS_PER_STATION = 4
#: Consecutive dropped bearings at one new position (within the same allowance of each
#: other) after which the station is taken to have moved there (a relocated station).
RELOCATION_RUN = 3
#: Valid bearings per station over which the clock offset (stamp − now) is a median.
OFFSET_WINDOW = 9
#: A per-message warning of one station and kind is logged at most once per this, ns.
WARN_THROTTLE_NS = 5 * NS_PER_S
#: Offsets (s) beyond which a sim-time / wall-time mix-up is the likely cause (~11 days).
SIM_TIME_OFFSET_S = 1e6


@dataclass
class StationStats:
    """Per-station state and counters (diagnostics)."""

    station: str
    state: str = WAITING
    received: int = 0
    accepted: int = 0
    used: int = 0
    outliers: int = 0
    evicted: int = 0
    bad: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)
    last_stamp_ns: int = None
    position: tuple = None       # (x, y, z) m at the last geometry change
    since_ns: int = None
    wait: bool = True            # waited for while 'waiting' (configured, not discovered)
    evicted_future: int = 0      # buffered bearings stamped after now, evicted
    offsets: deque = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    clock_warning: str = None    # set while its stamps are far off the node clock
    lost: Counter = field(default_factory=Counter)   # losses reported by the transport
    _future_run: int = 0
    _stray_warning: bool = False  # clock_warning is about one stray stamp, not the clock
    anchor: tuple = None         # ((x, y, z), stamp ns) of the last accepted bearing
    seen_stamp_ns: int = None    # stamp of its newest bearing to reach the arrival checks
    seen_at: int = 0             # the registry's arrival count then (stand_in_now)
    _relocation: tuple = None    # ((x, y, z), stamp ns, count) of dropped far positions

    def clock_offset_s(self):
        """Median of (stamp − now) over the last OFFSET_WINDOW valid bearings, s (None
        without any)."""
        return statistics.median(self.offsets) / NS_PER_S if self.offsets else None


def clock_hint(offset_s, stray_s=None):
    """The likely cause of a station's stamps being ``offset_s`` (median of stamp − now, s)
    off the node clock, as one sentence for the log and /diagnostics. ``stray_s``: the
    dropped stamp's own offset, s, when the median is within the buffer (the station's
    clock is fine and one stamp is far off: a corrupted or forged stamp)."""
    if stray_s is not None:
        side, cause = (('behind', 'delivered late, or a corrupted stamp?') if stray_s < 0
                       else ('ahead of', 'a corrupted stamp?'))
        return (f'a stamp {abs(stray_s):.3g} s {side} the node clock, while its recent '
                f'stamps are within {abs(offset_s):.3g} s of it: {cause}')
    side = 'behind' if offset_s < 0 else 'ahead of'
    cause = ('is use_sim_time set on one side only?' if abs(offset_s) > SIM_TIME_OFFSET_S
             else 'is the station clock synchronised (NTP/PTP)?')
    return f'stamps are {abs(offset_s):.3g} s {side} the node clock: {cause}'


def bearing_problem(b):
    """None when Bearing ``b`` is valid, else the problem text (counted as invalid_bearing).

    The field rules are :meth:`Bearing.validate`'s (one place; ~2 µs on its scalar fast
    path). It checks values, not the position's shape, so a position that is not exactly 3
    coordinates is refused here too (it would break the (N, 3) arrays of an epoch).
    """
    stamp = b.stamp_ns
    if type(stamp) is not int:
        if isinstance(stamp, bool) or not isinstance(stamp, numbers.Real) \
                or not math.isfinite(stamp) or stamp != int(stamp):
            return f'stamp_ns: must be an integer number of ns, got {stamp!r}'[:120]
    if not -2 ** 63 <= stamp < 2 ** 63:
        return 'stamp_ns: outside the int64 range of a ROS time'
    try:
        b.validate()
    except (TypeError, ValueError) as exc:
        return str(exc)
    problem = _position_covariance_problem(b.position_covariance)
    if problem is not None:
        return problem
    if np.shape(b.position) != (3,):
        return f'position: expected 3 coordinates, got shape {np.shape(b.position)}'
    return None


#: Relative tolerance of the symmetry and positive semi-definiteness of a station position
#: covariance: the rounding of a sender's arithmetic, single precision included (float32 ε
#: = 1.2e-7: a singular covariance built in float32 has λ_min down to a few 1e-7 λ_max);
#: a real violation is of order 1.
COVARIANCE_TOL = 1e-6


def covariance3_problem(v):
    """None when the 9 numbers ``v`` (a 3 × 3 station position covariance, m², row-major)
    are a covariance, else the problem text.

    A covariance is finite, symmetric (|c_ij − c_ji| ≤ tol · max|c|) and positive
    semi-definite (smallest eigenvalue ≥ −tol · largest), tol = :data:`COVARIANCE_TOL`.
    One that is not would make a station's gate distance d² = r² / (σ² + gᵀ C g) negative
    or undefined and switch its outlier gate off. The all-zero matrix (a surveyed station)
    is accepted without an eigenvalue computation.
    """
    if not all(map(math.isfinite, v)) or v[0] < 0.0 or v[4] < 0.0 or v[8] < 0.0:
        return 'non-finite or negative variance'
    if not any(v):
        return None
    scale = max(map(abs, v))
    tol = COVARIANCE_TOL * scale
    if abs(v[1] - v[3]) > tol or abs(v[2] - v[6]) > tol or abs(v[5] - v[7]) > tol:
        return 'not symmetric'
    lam = np.linalg.eigvalsh(np.array(v, dtype=float).reshape(3, 3))
    if lam[0] < -COVARIANCE_TOL * max(lam[2], 0.0) or not lam[2] > 0.0:
        return f'not positive semi-definite (eigenvalues {lam[0]:.3g} … {lam[2]:.3g} m²)'
    return None


def _position_covariance_problem(pcov):
    """None for a (3, 3) station position covariance of numbers that is a covariance
    (:func:`covariance3_problem`, the rule of ros_conversions.bearing_from_msg), else the
    problem text."""
    try:
        c = (pcov if type(pcov) is np.ndarray else np.asarray(pcov, dtype=float))
        v = c.ravel().tolist() if c.shape == (3, 3) else None
    except (TypeError, ValueError):
        v = None
    if v is None or not all(isinstance(x, (float, int)) for x in v):
        return 'position_covariance: expected a (3, 3) array of numbers, m²'
    problem = covariance3_problem(v)
    return None if problem is None else f'position_covariance: {problem}'


class StationRegistry:
    """Stations, their buffers and states, and the pipeline clock (module docstring).

    ``last_epoch_ns`` (the time of the newest epoch, set by the pipeline) makes bearings
    that no future epoch could use ``too_late``. ``on_time_jump(now_ns)`` is called after a
    backward time jump cleared the buffers.
    """

    def __init__(self, config, stations=(), on_time_jump=None):
        self._buffers = {}
        self._stats = {}
        self.last_epoch_ns = None
        self.last_now_ns = None
        self.first_now_ns = None
        self.events = []
        self.bad_messages = 0
        self.dropped = Counter()
        self.time_jumps = 0
        self._arrivals = 0               # bearings that reached the arrival checks
        self.geometry_version = 0
        self._on_time_jump = on_time_jump
        self._next_check_ns = None    # earliest now at which a station state may change
        self._scan_now_ns = None      # now of the last full state scan
        self._expected = None         # cached event-trigger station list (None: recompute)
        self.open_since_ns = None     # now at which the pending epoch got its first bearing
        self.repeat_stamp_ns = None   # a pending station's previous newest stamp (it reported
        #                               again before the pending epoch closed)
        self.warnings_suppressed = 0
        self._warned = {}             # (station, kind) -> [last emitted now, suppressed]
        self.event_blocker = None     # station the event trigger last found missing
        self.apply_config(config)
        for s in stations:
            self.add_station(s)

    def apply_config(self, config):
        """Take the timing and buffer settings of ``config`` (buffers are kept, resized)."""
        old = getattr(self, 'align', None)
        self.config = config
        self.align = config.alignment()
        self.timeout_ns = seconds_to_ns(config.station_timeout)
        self._jump_tolerance_ns = seconds_to_ns(config.time_jump_tolerance)
        self.max_latency_ns = seconds_to_ns(config.max_latency)
        self.future_ns = seconds_to_ns(config.future_tolerance)
        self.max_speed = float(config.max_station_speed)
        if old is not None and self.align != old:
            for buf in self._buffers.values():
                buf.size, buf.age_ns = self.align.buffer_size, self.align.buffer_age_ns
        self._next_check_ns = None
        self._expected = None

    # ----------------------------------------------------------------- stations
    @property
    def stations(self):
        """Known station ids, in the order they were added."""
        return list(self._stats)

    def __contains__(self, station):
        return station in self._stats

    def add_station(self, station, wait=True):
        """Register ``station`` (idempotent); it is 'waiting' until its first bearing.

        ``wait``: the event trigger waits for it while it is 'waiting' (at most
        station_timeout); False for a discovered station, which counts only once it has
        delivered a valid bearing (a publisher without data never blocks an epoch).
        """
        if station not in self._stats:
            self._stats[station] = StationStats(station, since_ns=self.last_now_ns,
                                                wait=bool(wait))
            self._buffers[station] = StationBuffer(station, self.align.buffer_size,
                                                   self.align.buffer_age_ns)
            self.events.append(('info', f'station {station} added'))
            self._expected = None
            self._next_check_ns = None     # its waiting period must be scheduled
        return self._stats[station]

    def remove_station(self, station):
        """Forget ``station`` (its buffer and counters); True when it was known."""
        if self._stats.pop(station, None) is None:
            return False
        self._buffers.pop(station, None)
        for key in [k for k in self._warned if k[0] == station]:
            del self._warned[key]
        self._expected = None
        self.geometry_version += 1
        self.events.append(('info', f'station {station} removed'))
        return True

    def stats(self, station):
        """The :class:`StationStats` of ``station``."""
        return self._stats[station]

    def all_stats(self):
        """(station, StationStats) pairs in the order the stations were added."""
        return self._stats.items()

    def buffer(self, station):
        """The StationBuffer of ``station``."""
        return self._buffers[station]

    def live_stations(self):
        """Stations currently alive."""
        return [s for s, st in self._stats.items() if st.state == ALIVE]

    def stale_stations(self):
        """Stations currently stale."""
        return [s for s, st in self._stats.items() if st.state == STALE]

    def clock_disagreements(self, now):
        """Station -> one sentence, for the stations whose clock offset (median of stamp −
        now, :meth:`StationStats.clock_offset_s`) differs from the median of the stations'
        offsets by more than ``sync_tolerance`` ahead, or by more than the larger of
        ``sync_tolerance`` and ``max_latency`` behind (behind is also what a longer transport
        delay looks like, which the event trigger waits for up to ``max_latency``). Only the
        stations that sent within ``station_timeout`` count, and at least three: of two, the
        data cannot say which one is off. Their bearings are matched to other observation
        cycles than the other stations' (a shared transport delay cancels in the
        difference)."""
        offsets = {}
        for s, st in self._stats.items():
            v = st.clock_offset_s()
            if v is not None and st.seen_stamp_ns is not None \
                    and abs(now + v * NS_PER_S - st.seen_stamp_ns) <= self.timeout_ns:
                offsets[s] = v
        if len(offsets) < 3:
            return {}
        ref = statistics.median(offsets.values())
        tol = self.align.sync_tolerance_ns / NS_PER_S
        late = max(tol, self.max_latency_ns / NS_PER_S)
        out = {}
        for s, v in offsets.items():
            d = v - ref
            if d > tol or -d > late:
                cause = ('its clock is ahead' if d > 0 else
                         'its clock is behind, or its bearings take that much longer to '
                         'arrive')
                out[s] = (f'stamps are {abs(d):.3g} s {"ahead of" if d > 0 else "behind"} '
                          f'the other stations\' (sync_tolerance {tol:.3g} s): {cause}; a '
                          'clock offset matches its bearings to other cycles (synchronise '
                          'it: NTP/PTP, or use trigger timer with max_latency above the '
                          'offset)')
        return out

    def state_at(self, st, now):
        """State of StationStats ``st`` at ``now`` (ns) from its newest stamp."""
        if st.last_stamp_ns is None:
            return WAITING
        if now - st.last_stamp_ns > self.timeout_ns:
            return STALE
        return ALIVE

    def geometry(self):
        """Station -> (position (3,) m, σ_θ rad, σ_ψ rad or NaN) of every live station, from
        its newest bearing (``geometry_version`` says when this changed)."""
        out = {}
        for s in self.live_stations():
            b = self._buffers[s].newest
            if b is not None:
                out[s] = (np.asarray(b.position, dtype=float).copy(), float(b.sigma_azimuth),
                          float(b.sigma_elevation))
        return out

    # ----------------------------------------------------------------- inputs
    def warn_throttled(self, station, kind, text, now):
        """Queue warning ``text`` unless one of the same ``station`` and ``kind`` was queued
        less than WARN_THROTTLE_NS of node time ago (then count it as suppressed); the next
        one emitted says how many were suppressed. True when queued."""
        key = (station, kind)
        entry = self._warned.get(key)
        if entry is not None and now is not None and entry[0] is not None \
                and entry[0] <= now < entry[0] + WARN_THROTTLE_NS:
            entry[1] += 1
            self.warnings_suppressed += 1
            return False
        if entry is not None and entry[1]:
            text += f' ({entry[1]} similar warning(s) suppressed)'
        if len(self._warned) > 4 * len(self._stats) + 64:   # bounded: forget the oldest
            self._warned.pop(next(iter(self._warned)))
        self._warned[key] = [now, 0]
        self.events.append(('warn', text))
        return True

    def count_lost(self, station, kind, n):
        """Count ``n`` messages of ``station`` lost in transport (``kind``: for example
        ``message_lost`` from the middleware, ``sequence_gap`` from publication sequence
        numbers); a station that is not known is ignored."""
        st = self._stats.get(station)
        if st is not None and n > 0:
            st.lost[kind] += int(n)

    def count_bad(self, station, reason, now_ns=None, first_warning=None):
        """Count a message of ``station`` refused with ``reason``; log ``first_warning`` the
        first time this station is refused for that reason."""
        st = self.add_station(station)
        st.received += 1
        if first_warning and not st.bad[reason]:
            self.events.append(('warn', first_warning))
        st.bad[reason] += 1
        self.bad_messages += 1
        if now_ns is not None:
            self.advance(int(now_ns), station)

    def stand_in_now(self, bearing):
        """A stand-in for the node clock while ROS time has not started (simulated time
        before the first /clock), ns: the lower median of this bearing's stamp and the
        newest stamp that reached the arrival checks from every other station that sent one
        among the last :data:`RECENT_ARRIVALS_PER_STATION` × (stations) such bearings. One
        station's stamp alone (the bearing's own, as before) let a stamp a day ahead become
        "now", so the next honest bearing looked like the clock jumping back and cleared
        every buffer, every cycle; among the stations' stamps a minority far ahead is
        outvoted and dropped as ``from_future``. A station that went silent leaves the
        median after that many bearings of the others, so it cannot hold "now" back. With
        one station it is the bearing's stamp.
        """
        recent = self._arrivals - RECENT_ARRIVALS_PER_STATION * max(len(self._stats), 1)
        stamps = [st.seen_stamp_ns for name, st in self._stats.items()
                  if st.seen_stamp_ns is not None and name != bearing.station
                  and st.seen_at > recent]
        stamps.append(int(bearing.stamp_ns))
        stamps.sort()
        return stamps[(len(stamps) - 1) // 2]

    def check_station_id(self, bearing, now):
        """True when the bearing's station id is a non-empty string; otherwise count it as
        a bad message of no station and return False."""
        if isinstance(bearing.station, str) and bearing.station:
            return True
        self.bad_messages += 1
        self.warn_throttled('', 'station_id', f'bearing with station id '
                            f'{bearing.station!r:.60} dropped (must be a non-empty string)', now)
        self.advance(now)
        return False

    def accept(self, bearing, now):
        """Arrival checks and buffering of one bearing at ``now`` (ns); True if buffered.

        The station id must have passed :meth:`check_station_id`.
        """
        st = self.add_station(bearing.station)
        self.advance(now, bearing.station)
        st.received += 1
        detail = bearing_problem(bearing)
        if detail is not None:
            st.bad[INVALID_BEARING] += 1
            self.bad_messages += 1
            self.warn_throttled(bearing.station, INVALID_BEARING,
                                f'{bearing.station}: invalid bearing ({detail})', now)
            return False
        if bearing.frame_id != self.config.frame_id:
            st.bad[WRONG_FRAME] += 1
            self.bad_messages += 1
            return False
        stamp = int(bearing.stamp_ns)
        st.offsets.append(stamp - now)
        self._arrivals += 1
        st.seen_stamp_ns, st.seen_at = stamp, self._arrivals
        buf = self._buffers[bearing.station]
        reason = buf.classify(stamp)
        if reason == OUT_OF_ORDER and stamp <= now and buf.newest_stamp_ns > now:
            st._future_run += 1
            if st._future_run >= FUTURE_RECOVERY:
                reason = self._evict_future(st, buf, stamp, now)
        else:
            st._future_run = 0
        if reason is None and self._is_too_late(stamp, now):
            reason = TOO_LATE
        if reason is None and stamp > now + self.future_ns:
            reason = FROM_FUTURE
        pos = bearing.position
        # Python floats: ~1 µs instead of ~5 µs of numpy on 3-vectors, per bearing.
        pos = tuple(pos.tolist() if type(pos) is np.ndarray else (float(v) for v in pos))
        if reason is None and self.max_speed > 0.0:
            reason = self._position_jump(st, bearing, pos, stamp, now)
        if reason is not None:
            st.dropped[reason] += 1
            self.dropped[reason] += 1
            if reason in (TOO_LATE, FROM_FUTURE) \
                    and abs(stamp - now) > self.align.buffer_age_ns:
                median = st.clock_offset_s()
                systematic = abs(median) * NS_PER_S > self.align.buffer_age_ns
                # Said once; again when a stray stamp turns out to be a clock step (the
                # median of the recent stamps follows it).
                if st.clock_warning is None or (systematic and st._stray_warning):
                    st._stray_warning = not systematic
                    st.clock_warning = clock_hint(median, None if systematic
                                                  else (stamp - now) / NS_PER_S)
                    # Throttled: a station alternating between far-off and good stamps sets
                    # the warning again after every good bearing. (Stray stamps apart: a
                    # clock step first taken for one is still said.)
                    kind = 'clock_stray' if st._stray_warning else 'clock'
                    self.warn_throttled(bearing.station, kind, f'{bearing.station}: '
                                        f'{st.clock_warning} (its bearings are dropped as '
                                        f'{reason})', now)
            return False
        st.clock_warning = None
        last = self.last_epoch_ns
        if self.open_since_ns is None and (last is None or stamp > last):
            self.open_since_ns = now
        newest = buf.newest_stamp_ns
        if newest is not None and (last is None or newest > last) and newest <= now:
            # A station reports again before the pending epoch closed: a new cycle began.
            rep = self.repeat_stamp_ns
            self.repeat_stamp_ns = newest if rep is None or newest > rep else rep
        st.evicted += buf.push(bearing)
        st.accepted += 1
        st.last_stamp_ns = stamp
        st.anchor, st._relocation = (pos, stamp), None
        if st.position is None or math.dist(pos, st.position) > GEOMETRY_MOVE_TOLERANCE_M:
            st.position = pos
            self.geometry_version += 1
        self._set_state(st, self.state_at(st, now))
        if st.state == ALIVE:
            due = stamp + self.timeout_ns
            if self._next_check_ns is not None and due < self._next_check_ns:
                self._next_check_ns = due
        return True

    def _allowance_m(self, bearing, dt_ns):
        """How far a station may move in ``dt_ns``: max_station_speed × |dt| +
        POSITION_JUMP_SLACK_M + 3 × the RMS σ of its stated position covariance, m."""
        c = bearing.position_covariance
        var = 0.0 if c is None else float(c[0][0]) + float(c[1][1]) + float(c[2][2])
        return (self.max_speed * abs(dt_ns) / NS_PER_S + POSITION_JUMP_SLACK_M
                + 3.0 * math.sqrt(max(var, 0.0)))

    def _position_jump(self, st, bearing, pos, stamp, now):
        """IMPLAUSIBLE_POSITION when the station's position moved faster than
        max_station_speed since its last accepted bearing (a teleporting station: a GPS
        glitch, a bad position source), else None. RELOCATION_RUN dropped bearings in a row
        at one new position (within the allowance of each other) are taken as a relocated
        station: the last of them is accepted, with a warning."""
        if st.anchor is None:
            return None
        p0, t0 = st.anchor
        moved = math.dist(pos, p0)
        if moved <= self._allowance_m(bearing, stamp - t0):
            return None
        run = st._relocation
        if run is not None and math.dist(pos, run[0]) <= self._allowance_m(bearing,
                                                                           stamp - run[1]):
            run = (pos, stamp, run[2] + 1)
        else:
            run = (pos, stamp, 1)
        st._relocation = run
        if run[2] >= RELOCATION_RUN:
            self.events.append(('warn', f'{bearing.station}: position moved {moved:.0f} m '
                                        f'and stayed there for {RELOCATION_RUN} bearings: '
                                        'taken as a relocated station'))
            return None
        self.warn_throttled(bearing.station, IMPLAUSIBLE_POSITION,
                            f'{bearing.station}: position moved {moved:.0f} m in '
                            f'{abs(stamp - t0) / NS_PER_S:.3g} s, faster than '
                            f'max_station_speed {self.max_speed:g} m/s: bearing dropped '
                            '(implausible_position)', now)
        return IMPLAUSIBLE_POSITION

    def _evict_future(self, st, buf, stamp, now):
        """Evict ``buf``'s bearings stamped after now (a clock that was ahead, or a forged
        stamp); return the arrival's reason at ``stamp`` afterwards."""
        kept = [b for b in buf.bearings if b.stamp_ns <= now]
        n = len(buf) - len(kept)
        buf.clear()
        for b in kept:
            buf.push(b)
        st.evicted_future += n
        st._future_run = 0
        st.last_stamp_ns = buf.newest_stamp_ns
        self.events.append(('warn', f'{st.station}: {n} buffered bearing(s) stamped after now '
                                    'evicted (its clock was ahead)'))
        return buf.classify(stamp)

    def epoch_done(self, t, now):
        """The pipeline processed an epoch at ``t`` (ns) at ``now``: the next pending epoch
        opens at ``now`` if a station already has a bearing after t."""
        self.last_epoch_ns = t
        self.repeat_stamp_ns = None
        self.open_since_ns = None
        for buf in self._buffers.values():
            n = buf.newest_stamp_ns
            if n is not None and n > t:
                self.open_since_ns = now
                break

    def _is_too_late(self, stamp, now):
        if stamp < now - self.align.buffer_age_ns:
            return True
        return (self.last_epoch_ns is not None
                and stamp < self.last_epoch_ns - self.align.sync_tolerance_ns)

    # ----------------------------------------------------------------- clock and states
    def advance(self, now, station=None):
        """Time-jump detection, pruning and station states at ``now`` (ns).

        Cost O(1) amortised per call: only ``station``'s buffer is pruned here (every buffer
        is pruned before an epoch, :meth:`prune_all`, and on ticks), and the station states
        are rescanned only when one may have timed out. Buffers are always pruned at the
        newest now seen, so the result is the same as pruning every buffer on every call.
        """
        if self.first_now_ns is None:
            self.first_now_ns = now
            for st in self._stats.values():
                st.since_ns = now if st.since_ns is None else st.since_ns
        last = self.last_now_ns
        if last is not None and now < last - self._jump_tolerance_ns:
            self._reset_time(now, last)
        elif last is None or now > last:
            # A small backward step (within the tolerance) keeps the newest now.
            self.last_now_ns = now
        if station is None:
            self.prune_all()
        else:
            self._buffers[station].prune(self.last_now_ns)
        if (self._next_check_ns is None or now > self._next_check_ns
                or now < self._scan_now_ns):
            self._update_states(now)

    def prune_all(self):
        """Drop the bearings older than the newest now − buffer_age from every buffer."""
        for buf in self._buffers.values():
            buf.prune(self.last_now_ns)

    def _reset_time(self, now, last):
        self.time_jumps += 1
        for buf in self._buffers.values():
            buf.clear()
        for st in self._stats.values():
            st.last_stamp_ns = None
            st.anchor = st._relocation = st.seen_stamp_ns = None
            st.state = WAITING
            st.since_ns = now
        self.last_epoch_ns = None
        self.open_since_ns = None
        self.repeat_stamp_ns = None
        self.first_now_ns = now
        self.last_now_ns = now
        self._next_check_ns = None
        self._expected = None
        self.geometry_version += 1
        self.events.append(('warn', f'time jumped back from {last / NS_PER_S:.3f} s to '
                                    f'{now / NS_PER_S:.3f} s: buffers cleared'))
        if self._on_time_jump is not None:
            self._on_time_jump(now)

    def _set_state(self, st, new):
        if new != st.state:
            if new == STALE:
                self.events.append(('warn', f'station {st.station} stale: no bearing for '
                                            f'more than {self.config.station_timeout} s'))
            elif new == ALIVE:
                self.events.append(('info', f'station {st.station} alive'
                                    + (' again' if st.state == STALE else '')))
            st.state = new
            self._expected = None
            self.geometry_version += 1

    def _update_states(self, now):
        """Full scan: every station's state at ``now``, and the next time one may change
        (an alive station timing out, or a waiting one no longer waited for)."""
        nxt = None
        for st in self._stats.values():
            self._set_state(st, self.state_at(st, now))
            if st.state == ALIVE:
                due = st.last_stamp_ns + self.timeout_ns
            elif st.state == WAITING and st.since_ns is not None and st.since_ns >= now - \
                    self.timeout_ns:
                due = st.since_ns + self.timeout_ns
            else:
                continue
            nxt = due if nxt is None or due < nxt else nxt
        self._next_check_ns = nxt if nxt is not None else now + 1000 * NS_PER_S
        self._scan_now_ns = now
        self._expected = None

    def expected_stations(self, now):
        """Stations an event epoch waits for: the live ones, plus the configured ones
        (``wait``) that have not reported yet but were added (or the clock reset) less than
        station_timeout ago."""
        if self._expected is None:
            self._expected = [
                s for s, st in self._stats.items()
                if st.state == ALIVE or (st.state == WAITING and st.wait
                                         and st.since_ns is not None
                                         and now - st.since_ns <= self.timeout_ns)]
        return self._expected
