"""The result of every estimator: one :class:`FixResult` type for multi-station fixes and TMA.

Multi-station estimators (``ls`` ... ``wmle``) fill the common fields: ``position`` (M, 3),
``covariance`` (M, 3, 3), ``iterations``, ``converged``, ``status`` and ``method``. The
single-station TMA estimators (``tma_ple`` ... ``tma_mle``, Lin et al.) estimate the state
(position, velocity) at the time of the last bearing; they fill the same fields, with
``covariance`` the (M, 6, 6) covariance of that state, plus the optional TMA fields
(``velocity``, ``t``, ``reason``...). A consumer that needs only the position reads
``position`` and :attr:`FixResult.position_covariance` (always (M, 3, 3)), and
:attr:`FixResult.velocity` / :attr:`FixResult.state_covariance` (None for a multi-station
fix): one conversion path serves both kinds.

Status values: ``ok`` (converged), ``max_iterations``, ``diverged`` (no descent possible or the
estimate ran away), ``degenerate_geometry`` (singular information at the estimate; position NaN
then) and, for TMA only, ``unobservable`` (too few bearings, constant line of sight or a range
the CRLB cannot resolve). ``converged`` is True only for ``ok``, and a converged result always
has a finite position. Units: m, m/s, s; ENU.
"""

from dataclasses import dataclass
import typing

import numpy as np

# Named string constants: alike core.fusion.results' no-fix reasons in shape only.
STATUS_OK = 'ok'
STATUS_MAX_ITERATIONS = 'max_iterations'
STATUS_DIVERGED = 'diverged'
STATUS_DEGENERATE = 'degenerate_geometry'
STATUS_UNOBSERVABLE = 'unobservable'
#: A fix that failed its consistency checks (residual chi-square, nonlinearity, too many
#: excluded bearings; core.robust): position and covariance are given, but it is not
#: trusted (the fusion node never publishes it on ``fix``).
STATUS_LOW_CONFIDENCE = 'low_confidence'
#: Statuses of the multi-station estimators.
STATUSES = (STATUS_OK, STATUS_MAX_ITERATIONS, STATUS_DIVERGED, STATUS_DEGENERATE,
            STATUS_LOW_CONFIDENCE)
#: Statuses of the TMA estimators.
TMA_STATUSES = (STATUS_OK, STATUS_UNOBSERVABLE, STATUS_DEGENERATE, STATUS_MAX_ITERATIONS,
                STATUS_LOW_CONFIDENCE)

_TMA_FIELDS = ('velocity', 't', 't0', 'position0', 'relative_position0', 'relative_velocity',
               'observer_velocity', 'range', 'reason')


@dataclass
class FixResult:
    """Estimates for M problems.

    Attributes:
        position: (M, 3) estimates, m (NaN where no usable estimate exists). For TMA the
            target position at time ``t``.
        covariance: covariance of the estimated state, inf where unknown: (M, 3, 3) m² for a
            multi-station fix; (M, 6, 6) of (position, velocity) for TMA (m², m²/s, m²/s²).
        iterations: (M,) int, iterations used (0 for closed forms).
        converged: (M,) bool.
        status: (M,) array of str (:data:`STATUSES` or, for TMA, :data:`TMA_STATUSES`).
        method: estimator name.

    TMA only (None for a multi-station fix):
        velocity: (M, 3) target velocity, m/s. t: (M,) time of the last bearing, s (the epoch
        of ``position``). t0: (M,) time of the first bearing, s. position0: (M, 3) target
        position at ``t0``, m. relative_position0: (M, 3) p0 and relative_velocity: (M, 3) v,
        the state relative to the observer's fitted track (m, m/s). observer_velocity: (M, 3)
        v_o, m/s. range: (M,) target-observer distance at ``t``, m. reason: (M,) str, ''
        when ok, else why not.

    Robust multi-station fixes only (``mle``, ``wmle``; core.robust), else None:
        excluded: (M, N, 2) bool, the (azimuth, elevation) of each bearing left out of the
        fix as an outlier. nonlinearity: (M,) range σ / range seen from the worst station.

    Multi-station fixes through the dimension selection (core.horizontal.locate, the
    registry's ``solve``), else None:
        solve: (M,) str, ``'3d'`` or ``'horizontal'``, the solve that produced each fix.
        target_altitude, target_altitude_sigma: (M,) m, the stated altitude z₀ and its σ_z
        (NaN where the problem was solved in 3D).
    """

    position: np.ndarray
    covariance: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    status: np.ndarray
    method: str
    velocity: typing.Optional[np.ndarray] = None
    t: typing.Optional[np.ndarray] = None
    t0: typing.Optional[np.ndarray] = None
    position0: typing.Optional[np.ndarray] = None
    relative_position0: typing.Optional[np.ndarray] = None
    relative_velocity: typing.Optional[np.ndarray] = None
    observer_velocity: typing.Optional[np.ndarray] = None
    range: typing.Optional[np.ndarray] = None
    reason: typing.Optional[np.ndarray] = None
    excluded: typing.Optional[np.ndarray] = None
    nonlinearity: typing.Optional[np.ndarray] = None
    solve: typing.Optional[np.ndarray] = None
    target_altitude: typing.Optional[np.ndarray] = None
    target_altitude_sigma: typing.Optional[np.ndarray] = None

    @property
    def M(self):
        """Number of problems."""
        return self.position.shape[0]

    @property
    def has_velocity(self):
        """True for a TMA result (the state includes the target velocity)."""
        return self.velocity is not None

    @property
    def position_covariance(self):
        """(M, 3, 3) covariance of ``position``, m², for every kind of result."""
        return self.covariance[..., :3, :3]

    @property
    def state_covariance(self):
        """(M, 6, 6) covariance of (position, velocity) for TMA, None for a multi-station fix."""
        return self.covariance if self.has_velocity else None

    @property
    def ok(self):
        """(M,) bool: a usable estimate (status ok or max_iterations, finite position)."""
        return (np.isin(self.status, (STATUS_OK, STATUS_MAX_ITERATIONS))
                & np.all(np.isfinite(self.position), axis=-1))

    def single(self, m=0):
        """Problem ``m`` as a dict of plain Python values (NaN/inf left as floats).

        Keys: method, position, covariance, converged, iterations, status; for TMA also t,
        velocity, t0, position0, range and reason; with a dimension selection also solve
        (and target_altitude, target_altitude_sigma for a horizontal solve).
        """
        out = {
            'method': self.method,
            'position': self.position[m].tolist(),
            'covariance': self.covariance[m].tolist(),
            'converged': bool(self.converged[m]),
            'iterations': int(self.iterations[m]),
            'status': str(self.status[m]),
        }
        if self.has_velocity:
            out.update({
                't': float(self.t[m]),
                'velocity': self.velocity[m].tolist(),
                't0': float(self.t0[m]),
                'position0': self.position0[m].tolist(),
                'range': float(self.range[m]),
                'reason': str(self.reason[m]),
            })
        if self.solve is not None:
            out['solve'] = str(self.solve[m])
            if out['solve'] == 'horizontal':
                out['target_altitude'] = float(self.target_altitude[m])
                out['target_altitude_sigma'] = float(self.target_altitude_sigma[m])
        return out


def iterative_result(method, x, cov, iterations, converged, diverged):
    """Assemble a FixResult from an iteration's outcome: statuses and the NaN policy.

    A problem whose covariance is not finite (singular information) or whose position is not
    finite is ``degenerate_geometry`` with NaN position and inf covariance; otherwise
    converged → ``ok``, diverged → ``diverged``, else ``max_iterations``.
    """
    cov = np.array(cov, dtype=float)
    finite_cov = np.all(np.isfinite(cov), axis=(-2, -1))
    finite_x = np.all(np.isfinite(x), axis=1)
    degenerate = ~finite_cov | ~finite_x
    status = np.where(converged, STATUS_OK,
                      np.where(diverged, STATUS_DIVERGED, STATUS_MAX_ITERATIONS)).astype(object)
    status[degenerate] = STATUS_DEGENERATE
    converged = converged & ~degenerate
    x = np.where(degenerate[:, None], np.nan, x)
    cov[degenerate] = np.inf
    return FixResult(x, cov, iterations, converged, status.astype(str), method)
