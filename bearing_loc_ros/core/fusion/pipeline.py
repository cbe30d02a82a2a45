"""The fusion pipeline: a station registry and a mode strategy, composed; counters; replay.

:class:`FusionCore` takes bearings (:class:`~bearing_loc_ros.core.bearings.Bearing`) and
"now" times (integer ns on the node clock) and returns :class:`Epoch` results; it never
reads a clock, never sleeps and uses no randomness, so the same sequence of
:meth:`FusionCore.add_bearing` / :meth:`FusionCore.tick` calls gives the same fixes live (the
fusion node), offline over a bag (``bearing_loc bag process``, via :func:`replay`) and in
benchmarks. It is made of:

* a :class:`~.stations.StationRegistry` (buffers, arrival checks, station states, clock);
* a strategy: :class:`~.multistation.MultiStationStrategy` (mode ``multistation``) or
  :class:`~.single_station.TmaStrategy` (mode ``tma``), which turns buffered bearings into
  epochs;
* the fix counters and diagnostics (this module).
"""

from collections import Counter, deque

from .. import registry as _registry
from ..alignment import DROP_REASONS, INTERPOLATED, NEAREST, seconds_to_ns
from ..conventions import stamp_text
from .config import FusionConfig, MODE_MULTISTATION, MODE_TMA, MODE_WINDOW, NS_PER_S
from .multistation import MultiStationStrategy
from .results import DiagnosticEntry, LEVEL_OK, LEVEL_WARN, NO_FIX_REASONS, NOT_CONVERGED, \
    ESTIMATOR_ERROR
from .single_station import TmaStrategy
from .window import WindowStrategy
from .stations import ALIVE, StationRegistry, STALE, WAITING

#: Fusion modes: name -> strategy class; the node's ``mode`` parameter picks one
#: (``auto``: the estimator's mode, core.registry.mode_of).
MODES = {MODE_MULTISTATION: MultiStationStrategy, MODE_TMA: TmaStrategy,
         MODE_WINDOW: WindowStrategy}
#: Window (ns) over which the fix rate is measured.
RATE_WINDOW_NS = 5 * NS_PER_S


class FusionCore:
    """The fusion pipeline of one mode (module docstring).

    Usage (the node and ``bag process`` do exactly this)::

        core = make_core(FusionConfig(...), stations=['station_1', 'station_2'])
        epochs = core.add_bearing(bearing, now_ns)   # on every accepted message
        epochs += core.tick(now_ns)                 # every core.tick_period_ns
        core.settle()                               # after publishing epochs (optional)
        core.count_bad_message(station, reason, now_ns)   # messages that failed conversion
        core.drain_events()                         # [(level, text)] to log
        core.diagnostics(now_ns)                    # [DiagnosticEntry] to publish

    ``mode`` is ``multistation`` (default) or ``tma``; the configured estimator must belong
    to it (ValueError otherwise: switching needs a restart with the other mode).
    """

    def __init__(self, config=None, stations=(), mode=MODE_MULTISTATION):
        if mode not in MODES:
            raise ValueError(f'mode: {mode!r} is not one of {["auto"] + sorted(MODES)}')
        self.mode = mode
        config = self._check_mode((config if config is not None else FusionConfig()).validate())
        self.config = config
        self.registry = StationRegistry(config, on_time_jump=self._on_time_jump)
        self.strategy = MODES[mode](self.registry)
        self._fix_times = deque()
        self.epochs = 0
        self.fixes = 0
        self.no_fix = Counter()
        self.outliers = 0
        self.iterations = 0
        self.last_fix_stamp_ns = None
        self.last_epoch = None
        for s in stations:
            self.registry.add_station(s)

    # ----------------------------------------------------------------- configuration
    @property
    def tick_period_ns(self):
        """How often the owner should call :meth:`tick` (1 / rate), ns."""
        return self.config.period_ns

    @property
    def quiet_horizon_ns(self):
        """Time after the last arrival beyond which ticks no longer change anything but the
        no-fix counts of empty timer epochs, ns: every buffered bearing has aged out
        (``buffer_age``, the ``window`` in window mode), its epochs were due (``max_latency``)
        and its station is stale (``station_timeout``), counted from its stamp, which may
        lie up to ``future_tolerance`` after its arrival; plus two periods."""
        c = self.config
        return seconds_to_ns(max(c.buffer_age, c.window, c.max_latency, c.station_timeout)
                             + c.future_tolerance) + 2 * c.period_ns

    def check_config(self, **changes):
        """Validate ``changes`` to the configuration without applying them (ValueError).

        An estimator of another mode is refused for that reason first (a tma_* estimator in
        multi-station mode used to be refused for its missing target_speed)."""
        new = self.config.replace(**changes)
        if new.estimator in _registry.names():
            self._check_mode(new)
        return self._check_mode(new.validate())

    def _check_mode(self, config):
        mode = _registry.mode_of(config.estimator)
        # The window mode (a stationary emitter) runs the multi-station estimators.
        if mode != (MODE_MULTISTATION if self.mode == MODE_WINDOW else self.mode):
            raise ValueError(f'estimator: {config.estimator} is a {mode} estimator but the '
                             f'fusion runs in mode {self.mode}; switching between tma_* and '
                             'multi-station estimators needs a restart')
        return config

    def reconfigure(self, **changes):
        """Apply validated ``changes`` (buffer bounds take effect at once; buffers are kept)."""
        new = self.check_config(**changes)
        self.config = new
        self.registry.apply_config(new)
        self.strategy.reconfigure(new)
        return new

    # ----------------------------------------------------------------- stations
    @property
    def stations(self):
        """Known station ids, in the order they were added."""
        return self.registry.stations

    def add_station(self, station, wait=True):
        """Register ``station`` (idempotent); it is 'waiting' until its first bearing.
        ``wait=False`` (a discovered station): never waited for before its first valid
        bearing (:meth:`StationRegistry.add_station`)."""
        return self.registry.add_station(station, wait=wait)

    def remove_station(self, station):
        """Forget ``station`` (its buffer, counters and the strategy's state of it)."""
        if self.registry.remove_station(station):
            self.strategy.station_removed(station)

    def station_stats(self, station):
        """The :class:`~.stations.StationStats` of ``station``."""
        return self.registry.stats(station)

    def station_state(self, station):
        """'waiting', 'alive' or 'stale' (as of the last call that passed a now)."""
        return self.registry.stats(station).state

    def live_stations(self):
        """Stations currently alive."""
        return self.registry.live_stations()

    def geometry(self):
        """Planning hook: station -> (position (3,), σ_θ, σ_ψ or NaN) of every live station
        (empty in TMA mode); ``geometry_version`` increments whenever it changes (a station
        joins, goes stale, comes back, is removed or moves more than 1 m)."""
        return self.strategy.geometry()

    # Read-only views of the registry's counters, one property each on purpose: the node and
    # the diagnostics read them from the pipeline without reaching into its parts.
    @property
    def geometry_version(self):
        """Counter of live-geometry changes (see :meth:`geometry`)."""
        return self.registry.geometry_version

    @property
    def bad_messages(self):
        """Messages refused (conversion, invalid fields, wrong frame, not tracked...)."""
        return self.registry.bad_messages

    @property
    def dropped(self):
        """Counter of dropped bearings by arrival reason (duplicate, too_late...)."""
        return self.registry.dropped

    @property
    def time_jumps(self):
        """Backward time jumps that cleared the buffers."""
        return self.registry.time_jumps

    # ----------------------------------------------------------------- inputs
    def count_bad_message(self, station, reason, now_ns=None):
        """Count a message of ``station`` rejected before reaching the core (conversion)."""
        self.registry.count_bad(station, reason, now_ns)

    def count_lost(self, station, kind, n):
        """Count ``n`` messages of ``station`` lost in transport, by ``kind`` (diagnostics
        ``lost.<kind>``, per station and in total)."""
        self.registry.count_lost(station, kind, n)

    def add_bearing(self, bearing, now_ns):
        """Ingest one bearing received at node-clock time ``now_ns``; return new Epochs.

        ``now_ns`` None: ROS time has not started (simulated time before the first /clock);
        :meth:`StationRegistry.stand_in_now` stands in. Bad bearings are counted (registry
        arrival checks, the strategy's refusal), never raised; an accepted bearing may
        complete epochs (event trigger, TMA).
        """
        reg = self.registry
        now = int(now_ns) if now_ns is not None else reg.stand_in_now(bearing)
        if not reg.check_station_id(bearing, now):
            return []
        refusal = self.strategy.refusal(bearing.station)
        if refusal is not None:
            reg.count_bad(bearing.station, refusal[0], now, first_warning=refusal[1])
            return []
        if not reg.accept(bearing, now):
            return []
        return self._record(self.strategy.on_bearing(bearing, now), now)

    def tick(self, now_ns):
        """Clock tick at node-clock time ``now_ns``: prune, update states, run due epochs."""
        now = int(now_ns)
        self.registry.advance(now)
        return self._record(self.strategy.on_tick(now), now)

    def settle(self):
        """Finish the work deferred past the epochs just returned (the station trust's update
        from the last fix, core.station_trust). The node calls it once the fix is published,
        off the latency path; without the call it happens before the trust is next read, so
        the results are the same either way (offline replay does not call it)."""
        trust = getattr(self.strategy, 'trust', None)
        if trust is not None:
            trust.settle()

    @property
    def has_events(self):
        """True when log events are pending (a cheap test before :meth:`drain_events`)."""
        return bool(self.registry.events)

    def drain_events(self):
        """Return and forget the pending log events: list of (level 'info'|'warn', text)."""
        ev, self.registry.events = self.registry.events, []
        return ev

    # ----------------------------------------------------------------- counters
    def _record(self, epochs, now):
        """Count ``epochs`` (the strategy's results at ``now``) and advance the epoch time."""
        reg = self.registry
        for ep in epochs:
            reg.epoch_done(ep.stamp_ns, now)
            self.epochs += 1
            for b in ep.rejected:
                reg.stats(b.station).outliers += 1
                self.outliers += 1
            if ep.ok:
                self.fixes += 1
                self.iterations += ep.iterations
                self.last_fix_stamp_ns = ep.stamp_ns
                self._fix_times.append(now)
                while self._fix_times and self._fix_times[0] <= now - RATE_WINDOW_NS:
                    self._fix_times.popleft()
                for b in ep.bearings:
                    reg.stats(b.station).used += 1
            else:
                self.no_fix[ep.reason] += 1
            self.last_epoch = ep
        return epochs

    def _on_time_jump(self, now):
        self._fix_times.clear()
        self.strategy.reset(now)

    def fix_rate(self, now_ns):
        """Fixes per second over the last RATE_WINDOW_NS (or since start), node clock."""
        now = int(now_ns)
        first = self.registry.first_now_ns
        first = first if first is not None else now
        window = min(RATE_WINDOW_NS, now - first)
        if window <= 0:
            return 0.0
        n = sum(1 for t in self._fix_times if now - window < t <= now)
        return n * NS_PER_S / window

    def diagnostics(self, now_ns):
        """Diagnostic entries (overall first, then one per station) at ``now_ns``.

        Overall keys: estimator, trigger, alignment, epochs, fixes, fix_rate_hz,
        converged_fraction, mean_iterations, rejected_bearings, bad_messages,
        dropped.<reason>, no_fix.<reason>, time_jumps, live_stations, stale_stations,
        waiting_stations, last_fix_stamp, warnings_suppressed, lost.<kind> (totals),
        clock_warnings, and the strategy's (TMA: tracked_station, window_bearings,
        target_speed, speed_reference). Station keys: state, received, accepted, used,
        outliers, evicted, evicted_future, bad.<reason>, dropped.<reason>, lost.<kind>,
        last_stamp, age_s, clock_offset_s (median stamp − now), clock_warning.

        Before any station delivered a bearing the overall level is OK ("waiting for
        data") for station_timeout after the start, then WARN; a station whose stamps are
        far off the node clock is WARN with the likely cause (:func:`.stations.clock_hint`),
        and so is one whose clock offset differs from the other stations'
        (:meth:`.stations.StationRegistry.clock_disagreements`).
        """
        now = int(now_ns)
        reg = self.registry
        states = {s: reg.state_at(st, now) for s, st in reg.all_stats()}
        live = [s for s, v in states.items() if v == ALIVE]
        stale = [s for s, v in states.items() if v == STALE]
        waiting = [s for s, v in states.items() if v == WAITING]
        lost = Counter()
        for _, st in reg.all_stats():
            lost.update(st.lost)
        clock = {s: st.clock_warning for s, st in reg.all_stats() if st.clock_warning}
        for s, text in reg.clock_disagreements(now).items():
            clock.setdefault(s, text)
        non_conv = self.no_fix[NOT_CONVERGED] + self.no_fix[ESTIMATOR_ERROR]
        attempts = self.fixes + non_conv
        values = {
            'estimator': self.config.estimator,
            'trigger': self.config.trigger,
            'alignment': INTERPOLATED if reg.align.interpolation else NEAREST,
            'epochs': self.epochs,
            'fixes': self.fixes,
            'fix_rate_hz': f'{self.fix_rate(now):.3f}',
            'converged_fraction': (f'{self.fixes / attempts:.4f}' if attempts else 'n/a'),
            'mean_iterations': (f'{self.iterations / self.fixes:.2f}' if self.fixes else 'n/a'),
            'rejected_bearings': self.outliers,
            'bad_messages': reg.bad_messages,
            'time_jumps': reg.time_jumps,
            'live_stations': ','.join(live),
            'stale_stations': ','.join(stale),
            'waiting_stations': ','.join(waiting),
            'warnings_suppressed': reg.warnings_suppressed,
            'clock_warnings': ','.join(clock),
            'last_fix_stamp': (stamp_text(self.last_fix_stamp_ns)
                               if self.last_fix_stamp_ns is not None else 'none'),
        }
        for r in DROP_REASONS:
            values[f'dropped.{r}'] = reg.dropped[r]
        for r in NO_FIX_REASONS:
            values[f'no_fix.{r}'] = self.no_fix[r]
        for k, n in sorted(lost.items()):
            values[f'lost.{k}'] = n
        values.update(self.strategy.diagnostic_values())
        if not any(st.accepted or st.last_stamp_ns is not None for _, st in reg.all_stats()) \
                and not self.epochs:
            first = reg.first_now_ns
            idle = 0.0 if first is None else (now - first) / NS_PER_S
            level = LEVEL_OK if idle <= self.config.station_timeout else LEVEL_WARN
            msg = 'waiting for data' + (f': no bearing accepted in {idle:.1f} s'
                                        if level != LEVEL_OK else '')
        else:
            level, msg = self.strategy.overall_status(live, stale, self.fixes, self.last_epoch)
        if clock:
            level = LEVEL_WARN if level == LEVEL_OK else level
            s0 = next(iter(clock))
            msg += f'; {s0}: {clock[s0]}'
        out = [DiagnosticEntry('fusion', level, msg, values)]
        for s, st in reg.all_stats():
            off = st.clock_offset_s()
            sv = {'state': states[s], 'received': st.received, 'accepted': st.accepted,
                  'used': st.used, 'outliers': st.outliers, 'evicted': st.evicted,
                  'evicted_future': st.evicted_future,
                  'clock_offset_s': 'n/a' if off is None else f'{off:.3f}',
                  'last_stamp': (stamp_text(st.last_stamp_ns)
                                 if st.last_stamp_ns is not None else 'none'),
                  'age_s': (f'{(now - st.last_stamp_ns) / NS_PER_S:.3f}'
                            if st.last_stamp_ns is not None else 'n/a')}
            for r, n in sorted(st.bad.items()):
                sv[f'bad.{r}'] = n
            for r in DROP_REASONS:
                sv[f'dropped.{r}'] = st.dropped[r]
            for k, n in sorted(st.lost.items()):
                sv[f'lost.{k}'] = n
            lvl = LEVEL_OK if states[s] == ALIVE else LEVEL_WARN
            msg = (states[s] if not st.bad
                   else f'{states[s]}, {sum(st.bad.values())} bad message(s)')
            if s in clock:
                sv['clock_warning'] = clock[s]
                lvl, msg = LEVEL_WARN, f'{msg}; {clock[s]}'
            out.append(DiagnosticEntry(f'station {s}', lvl, msg, sv, hardware_id=s))
        return out


def make_core(config, stations=(), mode='auto'):
    """The fusion core of ``mode`` (``auto``: the estimator's mode) for ``config``.

    The one place that maps configuration to a pipeline, for the node, ``bag process`` and
    the benchmarks. ValueError naming the field for an unknown mode or an estimator of
    another mode.
    """
    config = config if config is not None else FusionConfig()
    if mode == 'auto':
        mode = _registry.mode_of(config.estimator)
    return FusionCore(config, stations=stations, mode=mode)


def replay(core, items):
    """Run ``core`` over time-ordered arrivals exactly as the node would; yield Epochs.

    ``items`` is an iterable of (now_ns, bearing) in arrival order (bearing may be None for
    a pure clock update, for example a /clock message). Before each arrival, :meth:`tick` is
    called at every multiple of ``core.tick_period_ns`` up to now (the node's timer). A
    backward jump of now restarts the tick grid. Live and replayed fixes are identical when
    every bearing arrived before its epoch was due (now >= t + max_latency in timer mode).

    A gap without arrivals longer than :meth:`FusionCore.quiet_horizon_ns` (a forward jump
    of the clock, such as from simulated to wall time: 1e10 periods) is ticked through that
    horizon after the last arrival, by which time every buffered bearing has aged out, its
    epochs are formed and its stations are stale; then, like rcl's timer after a clock jump,
    once at the last multiple up to now, not once per skipped period.
    """
    period = core.tick_period_ns
    horizon = core.quiet_horizon_ns
    next_tick = None
    last = None
    for now, bearing in items:
        now = int(now)
        if next_tick is None or (last is not None and now < last):
            next_tick = -(-now // period) * period
        while next_tick <= now:
            if last is not None and next_tick > last + horizon:
                next_tick += (now - next_tick) // period * period   # the quiet part skipped
            yield from core.tick(next_tick)
            next_tick += period
        last = now
        if bearing is not None:
            yield from core.add_bearing(bearing, now)
