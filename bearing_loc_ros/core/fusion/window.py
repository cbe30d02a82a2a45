"""Window strategy: a stationary emitter, every bearing of a sliding time window in one fix.

For a transmitter that does not move, bearings taken at different times are all
measurements of the same point, so every accepted bearing of every station stamped within
the last ``window`` seconds (relative to the newest stamp) enters one fix, however many
stations there are: several fixed ones, or one moving station (a direction finder driven
around in a car, a "fox hunt"), whose position each bearing carries (the station node's
odometry input). The fix is the configured multi-station estimator over all N bearings of
the window, Zong & Cui 2015 eqs. (3)-(8) for ``mle``:

    X̂ = argmin_X Σ_j wrap(θ_j − θ_j(X))² / σ_θj² [+ Σ_{2D} (ψ_j − ψ_j(X))² / σ_ψj²],

with the dimension selection of :mod:`~bearing_loc_ros.core.horizontal` (azimuth-only
bearings need the stated ``target_altitude``: the horizontal solve, z = z₀). Bearings of
one station at different times are independent measurements (independent noise), so the
information adds up as the platform moves and the CRLB of the accumulated bearings
(core.horizontal_crlb / core.crlb) shrinks with the baseline the platform has driven.

Bounds: at most ``window_max_bearings`` bearings (the oldest arrivals leave first) and none
stamped before the newest stamp minus ``window`` (wherever it arrived: stamps of several
stations need not arrive in order); :class:`BearingWindow` keeps both in amortised
O(log N) per added bearing. One fix costs O(N) per iteration (the estimators are
vectorised over bearings), plus O(K² N) for the robust consensus (K ≤ 16).

Outliers (reflections, the car body, a wrong heading): estimators that declare ``robust``
(``mle``, ``wmle``) run with it unless ``outlier_gate`` is 1; the horizontal solve's
robust fix (:mod:`~bearing_loc_ros.core.horizontal_robust`: pairwise consensus and a refit
without the outlier bearings) bounds what one bad bearing can do, and for every other
estimator (or 3D) the bearings whose normalized residual d² exceeds the χ² gate of
``outlier_gate`` are dropped and the fix recomputed (:data:`GATE_ROUNDS` rounds at most).
Each rejected bearing is counted once, for its station (diagnostics ``outliers``).

Enough geometry: a fix is published only when the estimator converged with a finite
covariance and the range is resolved: the nonlinearity ν = max_j sqrt(u_jᵀ P u_j) / d_j
(range σ over range from each bearing's position, core.robust) is at most
:data:`~bearing_loc_ros.core.robust.MAX_NONLINEARITY`; otherwise the epoch is
``unobservable`` (for example the first seconds of a drive, bearings still nearly
parallel). Triggers as TMA: ``event`` one epoch per accepted bearing, ``timer`` at most one
per tick when bearings arrived. A backward time jump empties the window.
"""

from collections import deque, OrderedDict
import heapq

import numpy as np

from .. import registry as _registry
from ..bearings import BearingSet
from ..robust import MAX_NONLINEARITY, nonlinearity
from .config import MODE_WINDOW, NS_PER_S, TRIGGER_EVENT, TRIGGER_TIMER
from .gating import (_trusted_set as window_set, covariance_ok, gate_threshold,
                     horizontal_capable, ignores_elevations, normalized_residuals,
                     without_elevations)
from .results import (BAD_COVARIANCE, DEGENERATE_GEOMETRY, Epoch, ESTIMATOR_ERROR,
                      LEVEL_ERROR, LEVEL_OK, LEVEL_WARN, NO_ELEVATION, NOT_CONVERGED, OK,
                      TOO_FEW_STATIONS, UNOBSERVABLE)

#: Re-solves after dropping gated bearings (estimators without ``robust``).
GATE_ROUNDS = 3
#: Epoch reason of a robust fix that failed its consistency checks.
LOW_CONFIDENCE = 'low_confidence'


def _window_gate(est, bs, pos, kwargs, gate):
    """(d² (N,), dof (N,), threshold (N,)) of the window's gate at the fix ``pos`` (3,) m:
    each bearing's normalised residual with the σ of the estimator's noise model and its
    χ² threshold of level ``gate`` (1 or 2 dof)."""
    saz, sel = _registry.noise_sigmas(est, bs, pos[None], kwargs)
    d2, dof = normalized_residuals(
        BearingSet(bs.positions, bs.azimuth, bs.elevation, saz, sel), pos)
    d2, dof = d2[0], dof[0]
    return d2, dof, np.where(dof == 2, gate_threshold(gate, 2), gate_threshold(gate, 1))


class BearingWindow:
    """The window's bearings in arrival order, pruned by count and by stamp without scans.

    Holds bearings (any object with ``stamp_ns``, int ns) under arrival numbers. ``newest``
    is the largest stamp held, from a monotone deque of arrivals whose stamps no later
    arrival reaches (the sliding-window maximum: its first live entry is the maximum);
    ``prune_before`` removes every bearing stamped before a cutoff, wherever it arrived,
    from a min-heap of (stamp, arrival). Entries of bearings that left by another way stay
    in the deque and the heap until they surface, and both are rebuilt when they hold more
    than twice the window (so memory stays O(N)). Costs: ``append`` O(log N), ``popleft``
    O(1), ``prune_before`` O(log N) per removed bearing, ``newest`` amortised O(1).
    """

    def __init__(self, bearings=()):
        self._items = OrderedDict()    # arrival number -> bearing, arrival order
        self._next = 0
        self._heap = []                # (stamp_ns, arrival)
        self._max = deque()            # (arrival, stamp_ns), stamps strictly decreasing
        for b in bearings:
            self.append(b)

    def __len__(self):
        return len(self._items)

    def __iter__(self):
        return iter(self._items.values())

    def append(self, bearing):
        """Add ``bearing`` as the newest arrival."""
        k, stamp = self._next, int(bearing.stamp_ns)
        self._next += 1
        self._items[k] = bearing
        heapq.heappush(self._heap, (stamp, k))
        while self._max and self._max[-1][1] <= stamp:
            self._max.pop()
        self._max.append((k, stamp))
        if len(self._heap) > 2 * len(self._items) + 64 or \
                len(self._max) > 2 * len(self._items) + 64:
            self._rebuild()

    def popleft(self):
        """Remove and return the oldest arrival."""
        return self._items.popitem(last=False)[1]

    def newest(self):
        """The largest stamp held (ns), or None when empty."""
        while self._max and self._max[0][0] not in self._items:
            self._max.popleft()
        return self._max[0][1] if self._max else None

    def prune_before(self, cutoff_ns):
        """Remove every bearing stamped before ``cutoff_ns``; return them."""
        out = []
        heap, items = self._heap, self._items
        while heap and heap[0][0] < cutoff_ns:
            b = items.pop(heapq.heappop(heap)[1], None)
            if b is not None:
                out.append(b)
        return out

    def _rebuild(self):
        self._heap = [(int(b.stamp_ns), k) for k, b in self._items.items()]
        heapq.heapify(self._heap)
        self._max = deque()
        for k, b in self._items.items():
            stamp = int(b.stamp_ns)
            while self._max and self._max[-1][1] <= stamp:
                self._max.pop()
            self._max.append((k, stamp))


class WindowStrategy:
    """Epochs of the window mode over a station registry (module docstring)."""

    mode = MODE_WINDOW

    def __init__(self, registry):
        self.registry = registry
        self._window = BearingWindow()    # accepted Bearings, arrival order
        self._pending = False
        self._rejected_ids = set()    # id() of window bearings already counted as rejected
        self.low_confidence = 0
        self.last_solve = 'none'

    @property
    def window_bearings(self):
        """Number of bearings in the window."""
        return len(self._window)

    # ----------------------------------------------------------------- pipeline hooks
    def reconfigure(self, config):
        """A shorter window or a smaller bound takes effect at once."""
        self._prune()

    def refusal(self, station):
        """Every station contributes: never refuses a bearing."""
        return None

    def station_removed(self, station):
        """Drop the removed station's bearings from the window."""
        self._window = BearingWindow(b for b in self._window if b.station != station)
        self._rejected_ids &= {id(b) for b in self._window}

    def reset(self, now):
        """After a backward time jump: empty the window."""
        self._window = BearingWindow()
        self._rejected_ids.clear()
        self._pending = False

    def on_bearing(self, bearing, now):
        """An accepted bearing joins the window; the event trigger solves at once."""
        self._window.append(bearing)
        self._prune()
        self._pending = True
        if self.registry.config.trigger == TRIGGER_EVENT:
            return [self.epoch(now)]
        return []

    def on_tick(self, now):
        """Timer trigger: solve if bearings arrived since the last epoch."""
        if self.registry.config.trigger == TRIGGER_TIMER and self._pending and self._window:
            return [self.epoch(now)]
        return []

    def geometry(self):
        """Empty: a window of moving stations has no static coverage map."""
        return {}

    def diagnostic_values(self):
        """window_bearings, window_stations, window_span_s, low_confidence_fixes, solve."""
        w = self._window
        span = ((max(b.stamp_ns for b in w) - min(b.stamp_ns for b in w)) / NS_PER_S
                if w else 0.0)
        return {'window_bearings': len(w),
                'window_stations': ','.join(sorted({b.station for b in w})),
                'window_span_s': f'{span:.3f}',
                'low_confidence_fixes': self.low_confidence,
                'solve': self.last_solve}

    def overall_status(self, live, stale, fixes, last_epoch):
        """(level, message) of the overall diagnostic entry."""
        if not live and not self._window:
            return LEVEL_ERROR, 'no live station'
        if last_epoch is not None and not last_epoch.ok:
            return LEVEL_WARN, f'no fix: {last_epoch.reason}'
        return LEVEL_OK, 'fixing' if fixes else 'waiting for geometry'

    # ----------------------------------------------------------------- window
    def _prune(self):
        """At most ``window_max_bearings`` (oldest arrivals leave first), then none stamped
        before the newest stamp minus ``window``; a bearing that leaves is forgotten as
        rejected. Amortised O(log N) per bearing that leaves (:class:`BearingWindow`)."""
        cfg = self.registry.config
        w = self._window
        gone = []
        while len(w) > int(cfg.window_max_bearings):
            gone.append(w.popleft())
        newest = w.newest()
        if newest is not None:
            gone += w.prune_before(newest - int(round(float(cfg.window) * NS_PER_S)))
        if self._rejected_ids:
            for b in gone:
                self._rejected_ids.discard(id(b))

    # ----------------------------------------------------------------- epochs
    def epoch(self, now):
        """Solve the window's bearings; an :class:`Epoch` stamped with the newest stamp."""
        self._pending = False
        self._prune()
        cfg = self.registry.config
        used = list(self._window)
        stamp = max(b.stamp_ns for b in used)
        ep = self._solve(used, cfg)
        if ep.reason == LOW_CONFIDENCE:
            self.low_confidence += 1
        new = [b for b in ep.rejected if id(b) not in self._rejected_ids]
        self._rejected_ids.update(id(b) for b in ep.rejected)
        ep.detail = (ep.detail + '; ' if ep.detail else '') + \
            f'{len(ep.rejected)} of {len(used)} window bearings rejected'
        ep.rejected = new
        ep.stamp_ns, ep.produced_ns = int(stamp), int(now)
        ep.stale = self.registry.stale_stations()
        return ep

    def _solve(self, used, cfg):
        est = cfg.estimator
        kwargs = _registry.scoped_options(est, dict(cfg.estimator_options))
        spec = _registry.spec(est)
        gate = float(cfg.outlier_gate)
        robust = spec.accepts('robust') and kwargs.setdefault('robust', gate < 1.0)
        # Option consistency (gate 1: off) checks every fix; a first fix that fails it gets
        # one gate round and a re-solve, as in core.fusion.gating.solve_epoch.
        retry = spec.accepts('consistency') and bool(kwargs.setdefault('consistency',
                                                                       gate < 1.0)) \
            and gate < 1.0
        horizontal = horizontal_capable(kwargs)
        # use_elevations false: the solve and the gate see azimuth-only sets, while the
        # window keeps its own bearings (rejections are remembered by their identity).
        ignore_el = ignores_elevations(kwargs)
        n_el = 0 if ignore_el else sum(1 for b in used if b.has_elevation)
        if len(used) < 2 or (not horizontal and len(used) + n_el < 3):
            return Epoch(TOO_FEW_STATIONS, estimator=est, bearings=used,
                         detail=f'{len(used)} bearing(s) in the window')
        if not horizontal and n_el == 0:
            return Epoch(NO_ELEVATION, estimator=est, bearings=used,
                         detail='azimuth-only bearings: set target_altitude')
        rejected = []
        for _ in range(GATE_ROUNDS + 1):
            bs = without_elevations(window_set(used)) if ignore_el else window_set(used)
            try:
                res = _registry.solve(est, bs, **kwargs)
            except Exception as exc:  # noqa: B902 - any estimator failure is a counted no-fix
                return Epoch(ESTIMATOR_ERROR, estimator=est, bearings=used, rejected=rejected,
                             detail=f'{type(exc).__name__}: {exc}')
            status = str(res.status[0])
            self.last_solve = str(res.solve[0]) if res.solve is not None else '3d'
            pos = np.asarray(res.position[0], dtype=float)
            cov = np.asarray(res.covariance[0], dtype=float)
            excluded = getattr(res, 'excluded', None)
            if excluded is not None:
                out = excluded[0].any(axis=1)
                rejected = rejected + [b for b, x in zip(used, out) if x]
                used = [b for b, x in zip(used, out) if not x]
                bs = bs.subset(~out)
            common = dict(estimator=est, bearings=used, rejected=rejected, status=status,
                          iterations=int(res.iterations[0]), result=res)
            if status == 'degenerate_geometry' or not np.all(np.isfinite(pos)):
                return Epoch(DEGENERATE_GEOMETRY, **common)
            if status == LOW_CONFIDENCE:
                if retry and not robust:
                    retry = False
                    # (only the worst bearing: a fix dragged by an outlier can put honest
                    # bearings beyond the gate too)
                    d2, _, thr = _window_gate(est, bs, pos, kwargs, gate)
                    ratio = np.where(np.isfinite(d2), d2 / thr, 0.0)
                    k = int(np.argmax(ratio))
                    if ratio[k] > 1.0 and len(used) - 1 >= 3:
                        rejected = rejected + [used[k]]
                        used = used[:k] + used[k + 1:]
                        continue
                return Epoch(LOW_CONFIDENCE, position=pos, covariance=0.5 * (cov + cov.T),
                             detail='failed the consistency checks', **common)
            if status != 'ok' or not bool(res.converged[0]):
                return Epoch(NOT_CONVERGED, **common)
            if not covariance_ok(cov):
                return Epoch(BAD_COVARIANCE, **common)
            d2, dof, thr = _window_gate(est, bs, pos, kwargs, gate)
            bad = np.isfinite(d2) & (d2 > thr)
            if robust or not bad.any() or len(used) - int(bad.sum()) < 3:
                break
            rejected = rejected + [b for b, x in zip(used, bad) if x]
            used = [b for b, x in zip(used, bad) if not x]
        if bad.any() and not robust:
            return Epoch(NOT_CONVERGED, detail='residuals beyond the gate after '
                         f'{GATE_ROUNDS} rounds', **common)
        P = 0.5 * (cov + cov.T)
        d = pos[None] - bs.positions[0]
        rng = np.linalg.norm(d, axis=1)
        nu = float(nonlinearity(P, d / rng[:, None], rng, rng > 0))
        if not nu <= MAX_NONLINEARITY:
            return Epoch(UNOBSERVABLE, detail=f'range not resolved yet (range sigma / range '
                         f'{nu:.3g} > {MAX_NONLINEARITY:g})', **common)
        n_free = 2 if self.last_solve == 'horizontal' else 3
        residuals = {}
        for b, v in zip(used, d2):
            residuals[b.station] = residuals.get(b.station, 0.0) + float(v)
        return Epoch(OK, position=pos, covariance=P, residuals=residuals,
                     chi2=float(np.nansum(d2)), dof=int(np.sum(dof)) - n_free, **common)
