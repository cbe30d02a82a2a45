"""Single moving station strategy: target motion analysis (TMA) with a speed prior.

The bearings of one station (the first one that delivers an accepted bearing, the "tracked"
station; bearings of any other station are refused and counted as ``bad.not_tracked``) go
through the registry's arrival checks and then, in O(1), into a
:class:`~bearing_loc_ros.core.tma.TmaAccumulator` (the recursive P, Ω of Lin et al.,
Table 1) bounded to the last ``window`` seconds. Each epoch solves the configured TMA
estimator (``tma_ple``, ``tma_ctls``, ``tma_ctls6``, ``tma_mle``: the registry names, passed
to the accumulator as they are) with the speed prior |v| = ``target_speed``
(``speed_reference`` 'relative' or 'ground') and returns an :class:`Epoch` whose position
(3,) m and velocity (3,) m/s are the target state at the newest bearing's stamp,
``covariance`` the (3, 3) position block and ``state_covariance`` the (6, 6) (position,
velocity) constrained CRLB at the estimate, m², m²/s, m²/s².

Triggers: ``event``: one epoch per accepted bearing; ``timer``: at most one epoch per tick,
when bearings arrived since the last one (bounds the CPU of ``tma_mle``). No fix (a counted
reason): ``unobservable`` (too few bearings, no significant bearing change or a range the
CRLB cannot resolve), ``no_elevation`` (3-D TMA needs the elevation of every bearing),
``degenerate_geometry``, ``not_converged`` (tma_mle), ``low_confidence`` (the fix failed
its confidence checks, core.tma.confidence: it carries position and covariance, is counted
in ``low_confidence_fixes`` and goes to ``fix/low_confidence`` only), ``bad_covariance``,
``estimator_error``. A backward time jump clears the accumulator.
"""

import math

import numpy as np

from .. import estimators as _estimators
from ..alignment import NEAREST
from ..fix import STATUS_LOW_CONFIDENCE
from ..tma import STATUS_UNOBSERVABLE, TmaAccumulator
from .config import MODE_TMA, NS_PER_S, TRIGGER_EVENT, TRIGGER_TIMER
from .gating import covariance_ok, LOW_CONFIDENCE
from .results import (BAD_COVARIANCE, DEGENERATE_GEOMETRY, Epoch, ESTIMATOR_ERROR,
                      LEVEL_ERROR, LEVEL_OK, LEVEL_WARN, NO_ELEVATION, NOT_CONVERGED, OK,
                      UNOBSERVABLE)

#: A bearing of a station other than the tracked one.
NOT_TRACKED = 'not_tracked'


def _accumulator(config):
    return TmaAccumulator(float(config.target_speed) or 1.0, window=float(config.window),
                          speed_reference=config.speed_reference)


class TmaStrategy:
    """Epochs of the TMA mode over a station registry (module docstring)."""

    mode = MODE_TMA

    def __init__(self, registry):
        self.registry = registry
        self.accumulator = _accumulator(registry.config)
        self.tracked_station = None
        self._pending = None      # newest accepted bearing not yet estimated
        self._newest = None       # newest bearing in the accumulator
        self.low_confidence = 0   # fixes that failed their confidence checks

    @property
    def window_bearings(self):
        """Number of bearings in the TMA window."""
        return len(self.accumulator)

    # ----------------------------------------------------------------- pipeline hooks
    def reconfigure(self, config):
        """A new window or speed reference rebuilds the accumulator from its bearings."""
        old = self.accumulator
        if old.window == float(config.window) and old.speed_reference == config.speed_reference:
            return
        self.accumulator = _accumulator(config)
        if len(old):
            bs, times = old.bearings()
            for k in range(times.shape[1]):
                self.accumulator.add(times[0, k], bs.positions[0, k], bs.azimuth[0, k],
                                     bs.elevation[0, k], bs.sigma_az[0, k], bs.sigma_el[0, k])

    def refusal(self, station):
        """(reason, first warning) when ``station`` is not the tracked one, else None."""
        if self.tracked_station is None or station == self.tracked_station:
            return None
        return NOT_TRACKED, (f'tma mode tracks station {self.tracked_station}: bearings of '
                             f'{station} are ignored')

    def station_removed(self, station):
        """Removing the tracked station clears the TMA window."""
        if station == self.tracked_station:
            self.tracked_station = None
            self.reset(None)

    def reset(self, now):
        """Forget every bearing (a backward time jump, or the tracked station removed)."""
        self.accumulator.reset()
        self._pending = None
        self._newest = None

    def on_bearing(self, bearing, now):
        """A bearing of the tracked station was buffered: add it to the window."""
        if self.tracked_station is None:
            self.tracked_station = bearing.station
            self.registry.events.append(('info', f'tma: tracking station {bearing.station}'))
        est = self.registry.config.estimator
        if math.isnan(bearing.elevation):
            return [Epoch(NO_ELEVATION, stamp_ns=int(bearing.stamp_ns), produced_ns=now,
                          estimator=est, bearings=[bearing],
                          detail='3-D TMA needs azimuth and elevation')]
        try:
            self.accumulator.add(bearing.stamp_ns / NS_PER_S, bearing.position,
                                 bearing.azimuth, bearing.elevation, bearing.sigma_azimuth,
                                 bearing.sigma_elevation)
        except ValueError as exc:      # the arrival checks make this unreachable
            return [Epoch(ESTIMATOR_ERROR, stamp_ns=int(bearing.stamp_ns), produced_ns=now,
                          estimator=est, bearings=[bearing], detail=str(exc))]
        self._newest = bearing
        self._pending = bearing
        if self.registry.config.trigger == TRIGGER_EVENT:
            return [self.epoch(now)]
        return []

    def on_tick(self, now):
        """Timer trigger: estimate if bearings arrived since the last epoch."""
        if self.registry.config.trigger == TRIGGER_TIMER and self._pending is not None:
            return [self.epoch(now)]
        return []

    def geometry(self):
        """Empty: one moving station has no static coverage map."""
        return {}

    def diagnostic_values(self):
        """tracked_station, window_bearings, low_confidence_fixes, target_speed (m/s),
        speed_reference."""
        cfg = self.registry.config
        return dict(tracked_station=self.tracked_station or 'none',
                    window_bearings=len(self.accumulator),
                    low_confidence_fixes=self.low_confidence,
                    target_speed=f'{float(cfg.target_speed):.3f}',
                    speed_reference=cfg.speed_reference)

    def overall_status(self, live, stale, fixes, last_epoch):
        """(level, message) of the overall diagnostic entry: follows the tracked station."""
        if not live:
            return LEVEL_ERROR, 'no live station'
        if last_epoch is not None and not last_epoch.ok:
            return LEVEL_WARN, f'no fix: {last_epoch.reason}'
        return LEVEL_OK, 'tracking' if fixes else 'waiting for an epoch'

    # ----------------------------------------------------------------- epochs
    def epoch(self, now):
        """Solve the configured TMA estimator over the window; an :class:`Epoch` stamped
        with the newest bearing's time."""
        cfg = self.registry.config
        b = self._newest
        self._pending = None
        # The TMA accumulator takes max_iterations (tma_mle iterates; the closed forms
        # ignore it); the other shared options do not apply to TMA.
        opts = {}
        if 'max_iterations' in cfg.estimator_options:
            opts['max_iterations'] = int(cfg.estimator_options['max_iterations'])
        ep = Epoch(ESTIMATOR_ERROR, stamp_ns=int(b.stamp_ns), produced_ns=int(now),
                   estimator=cfg.estimator, bearings=[b], how={b.station: NEAREST})
        try:
            res = self.accumulator.estimate(cfg.estimator, speed=float(cfg.target_speed),
                                            **opts)
        except Exception as exc:  # noqa: B902 - any estimator failure is a counted no-fix
            ep.detail = f'{type(exc).__name__}: {exc}'
            return ep
        status = str(res.status[0])
        ep.result = res
        ep.status, ep.iterations = status, int(res.iterations[0])
        ep.detail = str(res.reason[0])
        pos = np.asarray(res.position[0], dtype=float)
        vel = np.asarray(res.velocity[0], dtype=float)
        C = np.asarray(res.covariance[0], dtype=float)
        if status == STATUS_UNOBSERVABLE:
            ep.reason = UNOBSERVABLE
        elif status == _estimators.STATUS_DEGENERATE:
            ep.reason = DEGENERATE_GEOMETRY
        elif (status == STATUS_LOW_CONFIDENCE and np.all(np.isfinite(pos))
              and np.all(np.isfinite(C[:3, :3]))):
            self.low_confidence += 1
            ep.reason = LOW_CONFIDENCE
            ep.position, ep.covariance = pos, 0.5 * (C[:3, :3] + C[:3, :3].T)
        elif status != _estimators.STATUS_OK or not bool(res.converged[0]):
            ep.reason = NOT_CONVERGED
        elif not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))):
            ep.reason, ep.detail = DEGENERATE_GEOMETRY, 'non-finite state'
        elif not (np.all(np.isfinite(C)) and covariance_ok(C)):
            ep.reason = BAD_COVARIANCE
        else:
            C = 0.5 * (C + C.T)
            ep.reason = OK
            ep.position, ep.covariance = pos, C[:3, :3].copy()
            ep.velocity, ep.state_covariance = vel, C
        return ep
