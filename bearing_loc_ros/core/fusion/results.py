"""What one fusion epoch produces: the :class:`Epoch` (the one result type of a fix, from the
estimator to the message) and the ROS-free diagnostic entry.

An epoch either carries a fix (``reason == 'ok'``: position (3,) m and covariance (3, 3) m²
in the world ENU frame, REP-103) or one of the no-fix reasons of :data:`NO_FIX_REASONS`,
each counted in diagnostics under ``no_fix.<reason>``.
"""

from dataclasses import dataclass, field

import numpy as np

OK = 'ok'

#: No-fix reasons (each counted in diagnostics under ``no_fix.<reason>``). Named string
#: constants, alike core.fix's statuses in shape only.
TOO_FEW_STATIONS = 'too_few_stations'
NO_ELEVATION = 'no_elevation'
DEGENERATE_GEOMETRY = 'degenerate_geometry'
NOT_CONVERGED = 'not_converged'
BAD_COVARIANCE = 'bad_covariance'
INCONSISTENT_BEARINGS = 'inconsistent_bearings'
ESTIMATOR_ERROR = 'estimator_error'
UNOBSERVABLE = 'unobservable'
NO_FIX_REASONS = (TOO_FEW_STATIONS, NO_ELEVATION, DEGENERATE_GEOMETRY, NOT_CONVERGED,
                  BAD_COVARIANCE, INCONSISTENT_BEARINGS, ESTIMATOR_ERROR, UNOBSERVABLE)

#: Diagnostic levels (mapped to diagnostic_msgs/DiagnosticStatus by the node).
LEVEL_OK = 'ok'
LEVEL_WARN = 'warn'
LEVEL_ERROR = 'error'


@dataclass
class Epoch:
    """One output epoch of the fusion pipeline, and the result of :func:`solve_epoch`.

    Attributes:
        reason: ``'ok'`` (a fix) or a no-fix reason (:data:`NO_FIX_REASONS`).
        stamp_ns: epoch time t the bearings were aligned to (the fix stamp), ns (None for a
            bare :func:`~bearing_loc_ros.core.fusion.gating.solve_epoch` result).
        produced_ns: node-clock "now" when it was computed, ns (None likewise).
        position (3,), covariance (3, 3): the fix, m / m² (None without a fix).
        result: the estimator's own result object of the last solve (``FixResult`` of
            core.estimators, or the TMA result, M = 1), None when no estimator ran.
        estimator, status, iterations: what produced it.
        bearings: Bearings in the fix (the aligned ones minus those the gate dropped);
            rejected: Bearings dropped by the outlier gate.
        how: station -> 'nearest' | 'interpolated'.
        missing: live stations with no bearing within the alignment window.
        stale: stations left out because they are stale.
        residuals: station -> d² at the fix; chi2, dof: their sum and its degrees of freedom
            (number of angles − 3).
        detail: human-readable detail of a no-fix reason.
        velocity (3,), state_covariance (6, 6): TMA mode only (else None): target velocity,
            m/s, and the covariance of (position, velocity), m², m²/s, m²/s².
    """

    reason: str
    stamp_ns: int = None
    produced_ns: int = None
    position: np.ndarray = None
    covariance: np.ndarray = None
    result: object = None
    estimator: str = ''
    status: str = ''
    iterations: int = 0
    bearings: list = field(default_factory=list)
    rejected: list = field(default_factory=list)
    how: dict = field(default_factory=dict)
    missing: list = field(default_factory=list)
    stale: list = field(default_factory=list)
    residuals: dict = field(default_factory=dict)
    chi2: float = float('nan')
    dof: int = 0
    detail: str = ''
    velocity: np.ndarray = None
    state_covariance: np.ndarray = None

    @property
    def ok(self):
        """True when the epoch produced a fix."""
        return self.reason == OK

    @property
    def stations(self):
        """Stations whose bearings are in the fix."""
        return [b.station for b in self.bearings]

    @property
    def used(self):
        """The bearings in the fix (alias of ``bearings``, the gate's vocabulary)."""
        return self.bearings


@dataclass
class DiagnosticEntry:
    """One diagnostic status, ROS-free (the node turns it into DiagnosticStatus)."""

    name: str
    level: str
    message: str
    values: dict
    hardware_id: str = ''
