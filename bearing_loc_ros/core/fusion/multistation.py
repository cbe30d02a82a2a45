"""Multi-station strategy: one fix per epoch from the time-aligned bearings of many stations.

Per epoch (epoch time t from :mod:`.triggers`):

1. Alignment (:func:`~bearing_loc_ros.core.alignment.align`): for each live station at most
   one bearing, the nearest within ``sync_tolerance`` or interpolated between two bracketing
   bearings. In nearest mode each bearing is used in at most one epoch (consecutive fixes
   stay independent); interpolation may reuse a bracketing pair for several epochs.
2. Estimation and outlier gating (:func:`.gating.solve_epoch`, the configured estimator,
   for example the pseudo-linear LS of Wang, Zhang & Wu eq. (4) for ``ls`` or the MLE of
   Zong & Cui 2015 eqs. (3)-(8) for ``mle``), robust where the estimator supports it
   (core.robust), with each station's σ as its trust allows
   (:class:`~bearing_loc_ros.core.station_trust.StationTrust`: leave-one-out residual
   history, σ floor). Fixes that fail their consistency checks are epochs of reason
   ``low_confidence`` (counted, never a fix).

The strategy reads the :class:`~.stations.StationRegistry` and returns :class:`Epoch` results;
the pipeline (:class:`~.pipeline.FusionCore`) counts them and advances the registry's
``last_epoch_ns``.
"""

from ..alignment import align, NEAREST
from .config import MODE_MULTISTATION, TRIGGER_EVENT
from ..station_trust import StationTrust
from .gating import LOW_CONFIDENCE, solve_epoch
from .results import LEVEL_ERROR, LEVEL_OK, LEVEL_WARN
from .triggers import event_epoch_time, timer_epoch_times


class MultiStationStrategy:
    """Epochs of the multi-station mode over a station registry (module docstring)."""

    mode = MODE_MULTISTATION

    def __init__(self, registry, trust=None):
        self.registry = registry
        self._used_until = {}     # nearest mode: station -> stamp of its last used bearing
        self.trust = trust if trust is not None else StationTrust()
        self.low_confidence = 0
        self.last_solve = 'none'     # '3d' or 'horizontal': the solve of the last estimate
        self.reconfigure(registry.config)

    # ----------------------------------------------------------------- pipeline hooks
    def reconfigure(self, config):
        """σ floors of the trust (``sigma_floor_deg``, ``station_sigma_floors``); alignment
        settings are read from the registry per epoch."""
        self.trust.sigma_floor, self.trust.floors = config.sigma_floors()

    def refusal(self, station):
        """Every station contributes: never refuses a bearing."""
        return None

    def station_removed(self, station):
        """Forget the alignment history of ``station``."""
        self._used_until.pop(station, None)
        self.trust.forget(station)

    def reset(self, now):
        """After a backward time jump: forget the alignment history."""
        self._used_until.clear()
        self.trust.reset()

    def on_bearing(self, bearing, now):
        """A bearing was buffered: the event trigger may complete an epoch."""
        if self.registry.config.trigger == TRIGGER_EVENT:
            return self._event_epochs(now)
        return []

    def on_tick(self, now):
        """Clock tick: due event or timer epochs."""
        reg = self.registry
        cfg = reg.config
        if cfg.trigger == TRIGGER_EVENT:
            return self._event_epochs(now)
        return [self.epoch(t, now) for t in timer_epoch_times(
            now, cfg.period_ns, reg.max_latency_ns, reg.last_epoch_ns, reg.align.buffer_age_ns)]

    def geometry(self):
        """Station -> (position, σ_θ, σ_ψ) of every live station (planning hook)."""
        return self.registry.geometry()

    def diagnostic_values(self):
        """low_confidence_fixes, suspect_stations (σ claim inconsistent with their
        leave-one-out residuals), solve (``3d`` or ``horizontal``, the last estimate's,
        core.horizontal) and trust_scale.<station> (s_k > 1 only)."""
        out = {'low_confidence_fixes': self.low_confidence,
               'suspect_stations': ','.join(self.trust.suspects()),
               'solve': self.last_solve}
        for s in self.registry.stations:
            k = self.trust.scale(s)
            if k > 1.0:
                out[f'trust_scale.{s}'] = f'{k:.3g}'
        return out

    def overall_status(self, live, stale, fixes, last_epoch):
        """(level, message) of the overall diagnostic entry."""
        need = self.registry.config.min_stations
        if len(live) < need:
            return LEVEL_ERROR, f'{len(live)} live station(s), need {need}'
        if last_epoch is not None and not last_epoch.ok:
            return LEVEL_WARN, f'no fix: {last_epoch.reason}'
        if stale:
            return LEVEL_WARN, f'stale: {", ".join(stale)}'
        return LEVEL_OK, 'fixing' if fixes else 'waiting for an epoch'

    # ----------------------------------------------------------------- epochs
    def _event_epochs(self, now):
        t = event_epoch_time(self.registry, now)
        if t is None:
            return []
        return [self.epoch(t, now)]

    def epoch(self, t, now):
        """Align the live stations' bearings to ``t`` (ns) and solve; an :class:`Epoch`."""
        reg = self.registry
        cfg = reg.config
        reg.prune_all()
        nearest_only = not reg.align.interpolation
        aligned, how, missing = [], {}, []
        used_until = self._used_until
        for s in reg.live_stations():
            b, kind = align(reg.buffer(s), t, reg.align,
                            after_ns=used_until.get(s) if nearest_only else None)
            if b is None:
                missing.append(s)
                continue
            aligned.append(b)
            how[s] = kind
            if kind == NEAREST and nearest_only:
                used_until[s] = int(b.stamp_ns)
        ep = solve_epoch(aligned, cfg.estimator, cfg.estimator_options, cfg.min_stations,
                         cfg.outlier_gate, validated=True, trust=self.trust)
        if ep.reason == LOW_CONFIDENCE:
            self.low_confidence += 1
        if ep.result is not None:
            solved = getattr(ep.result, 'solve', None)
            self.last_solve = str(solved[0]) if solved is not None else '3d'
        ep.stamp_ns, ep.produced_ns = int(t), int(now)
        ep.how, ep.missing, ep.stale = how, missing, reg.stale_stations()
        return ep
