"""The fusion pipeline of the fusion node as a pure, clock-free state machine (no ROS).

Parts, each readable on its own:

* :mod:`.config`: :class:`FusionConfig`, the settings and their validation;
* :mod:`.results`: :class:`Epoch`, the one result type of a fix (core to message), and the
  no-fix reasons;
* :mod:`.gating`: solving one epoch with χ² outlier gating (:func:`solve_epoch`);
* :mod:`.stations`: the station registry (buffers, arrival checks, states, clock);
* :mod:`.triggers`: when epochs happen (``event``, ``timer``);
* :mod:`.multistation`, :mod:`.single_station` and :mod:`.window`: the strategies (many
  fixed stations; one moving station, target motion analysis; a stationary emitter, every
  bearing of a sliding window in one fix), composed with the registry by
* :mod:`.pipeline`: :class:`FusionCore`, :func:`make_core` and :func:`replay`.

Display geometry (error ellipsoids, bearing rays, marker sizes) is in
:mod:`bearing_loc_ros.core.display`.
"""

from ..display import error_ellipsoid, quaternion_from_matrix, ray_endpoints
from .config import (FusionConfig, MODE_MULTISTATION, MODE_TMA, MODE_WINDOW, NS_PER_S,
                     TRIGGER_EVENT, TRIGGER_TIMER, TRIGGERS)
from .gating import gate_threshold, normalized_residuals, solve_epoch
from .pipeline import FusionCore, make_core, MODES, RATE_WINDOW_NS, replay
from .results import (BAD_COVARIANCE, DEGENERATE_GEOMETRY, DiagnosticEntry, Epoch,
                      ESTIMATOR_ERROR, INCONSISTENT_BEARINGS, LEVEL_ERROR, LEVEL_OK,
                      LEVEL_WARN, NO_ELEVATION, NO_FIX_REASONS, NOT_CONVERGED, OK,
                      TOO_FEW_STATIONS, UNOBSERVABLE)
from .single_station import NOT_TRACKED, TmaStrategy
from .window import WindowStrategy
from .stations import (ALIVE, GEOMETRY_MOVE_TOLERANCE_M, INVALID_BEARING, STALE,
                       StationRegistry, StationStats, WAITING, WRONG_FRAME)


def TmaFusionCore(config=None, stations=()):  # noqa: N802 - the former class name
    """The single moving station (TMA) pipeline: ``FusionCore(config, stations, 'tma')``.

    Kept for one release under its former class name; use :func:`make_core` (mode ``auto``
    follows the estimator) or ``FusionCore(..., mode='tma')``.
    """
    return FusionCore(config, stations=stations, mode=MODE_TMA)


__all__ = [
    'ALIVE', 'BAD_COVARIANCE', 'DEGENERATE_GEOMETRY', 'DiagnosticEntry', 'Epoch',
    'error_ellipsoid', 'ESTIMATOR_ERROR', 'FusionConfig', 'FusionCore', 'gate_threshold',
    'GEOMETRY_MOVE_TOLERANCE_M', 'INCONSISTENT_BEARINGS', 'INVALID_BEARING', 'LEVEL_ERROR',
    'LEVEL_OK', 'LEVEL_WARN', 'make_core', 'MODE_MULTISTATION', 'MODE_TMA', 'MODE_WINDOW', 'MODES',
    'NO_ELEVATION', 'NO_FIX_REASONS', 'normalized_residuals', 'NOT_CONVERGED', 'NOT_TRACKED',
    'NS_PER_S', 'OK', 'quaternion_from_matrix', 'RATE_WINDOW_NS', 'ray_endpoints', 'replay',
    'solve_epoch', 'STALE', 'StationRegistry', 'StationStats', 'TmaFusionCore', 'TmaStrategy',
    'TOO_FEW_STATIONS', 'TRIGGER_EVENT', 'TRIGGER_TIMER', 'TRIGGERS', 'UNOBSERVABLE',
    'WAITING', 'WindowStrategy', 'WRONG_FRAME',
]
