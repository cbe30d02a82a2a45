"""The fusion pipeline of the fusion node as a pure, clock-free state machine.

:class:`FusionCore` takes bearings (:class:`~bearing_loc_ros.core.bearings.Bearing`) and
"now" times (integer nanoseconds on the node clock) and returns :class:`Epoch` results; it
never reads a clock, never sleeps and uses no randomness, so the same sequence of
:meth:`FusionCore.add_bearing` / :meth:`FusionCore.tick` calls gives the same fixes live (the
fusion node), offline over a bag (``bearing_loc bag process``, via :func:`replay`) and in
benchmarks.

Per epoch (DESIGN.md "Time alignment" and "Estimators"):

1. Alignment (:mod:`.alignment`): for each live station at most one bearing, the nearest
   within ``sync_tolerance`` or interpolated between two bracketing bearings.
2. Estimation: ``locate(estimator, BearingSet, **options)`` (seed 000 eq. (4) for ``ls``,
   seed 003 eqs. (3)-(8) for ``mle``...).
3. Outlier gating (:func:`solve_epoch`): with the fix X̂, station i's normalized residual
   d_i² = (wrap(θ_i − θ_i(X̂)) / σ_θi)² + ((ψ_i − ψ_i(X̂)) / σ_ψi)² (seed 003 eq. (3): the
   Gaussian measurement model) is compared with the χ² quantile of probability
   ``outlier_gate`` with k_i = 1 (azimuth only) or 2 (azimuth + elevation) degrees of freedom;
   the worst offender is dropped and the fix recomputed while enough stations remain.
4. A fix is returned only if the estimator converged, reported status ``ok`` and gave a finite
   position and a finite, symmetric positive semi-definite covariance; otherwise the epoch
   carries a no-fix reason from :data:`NO_FIX_REASONS`.

Epoch triggers: ``event`` (an epoch as soon as every live station has a bearing newer than
the previous epoch; epoch time = the oldest of the stations' newest stamps; a station that
has not reported yet is waited for during ``station_timeout`` after it was added) or
``timer`` (at each tick, every grid time t_k = k / rate with t_k <= now − max_latency not
yet processed).
"""

from collections import Counter, deque
from dataclasses import dataclass, field, replace
from functools import lru_cache
import math
import numbers

import numpy as np

from . import estimators as _estimators
from . import registry as _registry
from .alignment import (AlignmentConfig, DROP_REASONS, FROM_FUTURE, INTERPOLATED, NEAREST,
                        StationBuffer, TOO_LATE, align, seconds_to_ns)
from .bearings import BearingSet
from .conventions import azimuth_elevation, los_vector, wrap_angle
from .crlb import angle_jacobians
from .tma import SPEED_REFERENCES, STATUS_UNOBSERVABLE, TmaAccumulator

NS_PER_S = 1_000_000_000

#: Epoch triggers.
TRIGGER_EVENT = 'event'
TRIGGER_TIMER = 'timer'
TRIGGERS = (TRIGGER_EVENT, TRIGGER_TIMER)

#: No-fix reasons (each counted in diagnostics under ``no_fix.<reason>``).
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
OK = 'ok'

#: Rejection reasons of bearings given to the core that break the contract.
INVALID_BEARING = 'invalid_bearing'
WRONG_FRAME = 'wrong_frame'
#: TMA mode: a bearing of a station other than the tracked one.
NOT_TRACKED = 'not_tracked'

#: Fusion modes (the node's ``mode`` parameter; ``auto`` follows the estimator).
MODE_MULTISTATION = 'multistation'
MODE_TMA = 'tma'
TMA_ESTIMATORS = _registry.TMA_ESTIMATORS
mode_for_estimator = _registry.mode_of


#: Station states.
WAITING = 'waiting'
ALIVE = 'alive'
STALE = 'stale'

#: Diagnostic levels (mapped to diagnostic_msgs/DiagnosticStatus by the node).
LEVEL_OK = 'ok'
LEVEL_WARN = 'warn'
LEVEL_ERROR = 'error'

#: A station moving more than this (m) counts as a geometry change (planning hook).
GEOMETRY_MOVE_TOLERANCE_M = 1.0
#: Window (ns) over which the fix rate is measured.
RATE_WINDOW_NS = 5 * NS_PER_S


default_estimator = _registry.default_estimator


@lru_cache(maxsize=64)
def gate_threshold(probability, dof):
    """χ² gate: the ``probability`` quantile of χ² with ``dof`` degrees of freedom.

    Closed forms (no scipy needed): k = 1: (Φ⁻¹((1 + p) / 2))², k = 2: −2 ln(1 − p).
    p = 0.999 gives 10.83 (k = 1) and 13.82 (k = 2). p >= 1 disables the gate (inf).
    """
    p = float(probability)
    if p >= 1.0:
        return math.inf
    if dof == 2:
        return -2.0 * math.log1p(-p)
    if dof == 1:
        from statistics import NormalDist
        return NormalDist().inv_cdf(0.5 * (1.0 + p)) ** 2
    raise ValueError(f'dof: expected 1 or 2, got {dof}')


def normalized_residuals(bearings, position, position_covariance=None):
    """Squared normalized angle residuals of a BearingSet at estimate(s) ``position``.

    Args:
        bearings: BearingSet (M problems, N stations).
        position: (M, 3) or (3,) estimate X̂, m.
        position_covariance: optional (M, N, 3, 3) or (N, 3, 3) station position
            covariance P_i, m²; it inflates each angle variance by gᵀ P_i g, g the angle's
            gradient (first-order propagation, seed 003 eq. (6) gradients).

    Returns:
        d2 (M, N): (wrap(θ_i − θ_i(X̂)) / σ_θ)² + ((ψ_i − ψ_i(X̂)) / σ_ψ)² (second term only
        for 2D stations); NaN where the estimate lies on the station's vertical axis.
        dof (M, N) int: 1 (azimuth only) or 2.
    Units: dimensionless; angles in rad, ENU convention (seed 000 eq. (1)).
    """
    x = np.atleast_2d(np.asarray(position, dtype=float))
    az_hat, el_hat = azimuth_elevation(x[:, None, :] - bearings.positions)
    var_az = bearings.sigma_az ** 2
    has_el = bearings.has_elevation
    var_el = np.where(has_el, np.nan_to_num(bearings.sigma_el, nan=1.0) ** 2, 1.0)
    if position_covariance is not None:
        P = np.asarray(position_covariance, dtype=float)
        P = np.broadcast_to(P if P.ndim == 4 else P[None], bearings.positions.shape + (3,))
        g_az, g_el = angle_jacobians(x, bearings.positions)
        with np.errstate(invalid='ignore'):
            var_az = var_az + np.einsum('mni,mnij,mnj->mn', g_az, P, g_az)
            var_el = var_el + np.where(has_el, np.einsum('mni,mnij,mnj->mn', g_el, P, g_el),
                                       0.0)
    with np.errstate(invalid='ignore'):
        d2 = wrap_angle(bearings.azimuth - az_hat) ** 2 / var_az
        d2 = d2 + np.where(has_el, (np.nan_to_num(bearings.elevation) - el_hat) ** 2 / var_el,
                           0.0)
    rho = np.hypot(x[:, None, 0] - bearings.positions[..., 0],
                   x[:, None, 1] - bearings.positions[..., 1])
    d2 = np.where(rho > 0.0, d2, np.nan)
    dof = np.where(has_el, 2, 1)
    return d2, dof


def quaternion_from_matrix(R):
    """Unit quaternion(s) (x, y, z, w), w >= 0, of rotation matrices R (..., 3, 3).

    Shepperd's method: of 4w², 4x², 4y², 4z² (1 + tr R, 1 + R00 − R11 − R22, ...) the largest
    is square-rooted and the other components follow from the off-diagonal sums/differences,
    which is accurate for every rotation including half turns. Same convention as
    conventions.quaternion_from_azel (R maps body axes onto world axes).
    """
    R = np.asarray(R, dtype=float)
    m = [[R[..., i, j] for j in range(3)] for i in range(3)]
    diag = np.stack([1.0 + m[0][0] + m[1][1] + m[2][2], 1.0 + m[0][0] - m[1][1] - m[2][2],
                     1.0 - m[0][0] + m[1][1] - m[2][2], 1.0 - m[0][0] - m[1][1] + m[2][2]],
                    axis=-1)
    k = np.argmax(diag, axis=-1)
    s = 0.5 * np.sqrt(np.maximum(np.take_along_axis(diag, k[..., None], -1)[..., 0], 1e-300))
    f = 0.25 / s
    cand = np.stack([
        np.stack([(m[2][1] - m[1][2]) * f, (m[0][2] - m[2][0]) * f, (m[1][0] - m[0][1]) * f,
                  s], -1),
        np.stack([s, (m[0][1] + m[1][0]) * f, (m[0][2] + m[2][0]) * f,
                  (m[2][1] - m[1][2]) * f], -1),
        np.stack([(m[0][1] + m[1][0]) * f, s, (m[1][2] + m[2][1]) * f,
                  (m[0][2] - m[2][0]) * f], -1),
        np.stack([(m[0][2] + m[2][0]) * f, (m[1][2] + m[2][1]) * f, s,
                  (m[1][0] - m[0][1]) * f], -1)], axis=-2)
    q = np.take_along_axis(cand, k[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def error_ellipsoid(covariance, n_sigma=1.0):
    """Axes and orientation of the n-σ error ellipsoid of position covariance(s) (..., 3, 3).

    With the eigen-decomposition P = V diag(λ) Vᵀ (V made a proper rotation, det V = +1), the
    ellipsoid {x : xᵀ P⁻¹ x <= n²} has semi-axes n √λ_k along the columns of V. Returns
    (diameters (..., 3) = 2 n √λ, m, ready for an RViz SPHERE marker's scale, and the
    quaternion (..., 4) (x, y, z, w) rotating the marker's x, y, z axes onto V's columns).
    Negative eigenvalues from round-off are clipped to 0. Raises ``ValueError`` for a
    non-finite covariance.
    """
    P = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(P)):
        raise ValueError('covariance: non-finite entries')
    lam, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, -1, -2)))
    det = np.linalg.det(V)
    V = V.copy()
    V[..., :, 2] *= np.where(det < 0.0, -1.0, 1.0)[..., None]
    return 2.0 * float(n_sigma) * np.sqrt(np.clip(lam, 0.0, None)), quaternion_from_matrix(V)


def ray_endpoints(positions, azimuth, elevation, length):
    """Line segments (N, 2, 3) from each station along its bearing, for LINE_LIST markers.

    End = p_i + L_i u(θ_i, ψ_i), u the line-of-sight unit vector (DESIGN.md); an azimuth-only
    bearing (ψ NaN) is drawn horizontal. ``length`` L (m) is a scalar or (N,) array.
    """
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    u = los_vector(np.asarray(azimuth, dtype=float).reshape(-1),
                   np.asarray(elevation, dtype=float).reshape(-1))
    L = np.broadcast_to(np.asarray(length, dtype=float), (p.shape[0],))
    return np.stack([p, p + L[:, None] * u], axis=1)


def _seconds(name, value, positive=False):
    v = float(value)
    if not math.isfinite(v) or v < 0.0 or (positive and v == 0.0):
        raise ValueError(f'{name}: must be {"> 0" if positive else ">= 0"} seconds, got {value}')
    return v


@dataclass(frozen=True)
class FusionConfig:
    """Settings of :class:`FusionCore` (the fusion node's parameters; seconds, Hz, metres).

    Attributes:
        frame_id: world frame; bearings in another frame are rejected (``wrong_frame``).
        trigger: ``event`` or ``timer`` (module docstring).
        rate: timer epoch rate, Hz (also the node's housekeeping tick rate in event mode).
        max_latency: timer mode: epoch t_k is processed once now >= t_k + max_latency, s.
        sync_tolerance: nearest alignment window |stamp − t|, s.
        interpolation: interpolate between bracketing bearings.
        max_interpolation_gap: longest bracketing gap t1 − t0, s.
        station_timeout: a station is stale when now − (its newest stamp) > this, s.
        buffer_size: bearings kept per station. buffer_age: their maximum age, s.
        min_stations: fewest stations in a fix (>= 2).
        estimator: a name in core.estimators.ESTIMATORS.
        estimator_options: keyword options for it (only those its signature accepts are passed).
        outlier_gate: χ² gate probability in [0.5, 1]; 1 disables gating.
        time_jump_tolerance: "now" going back by more than this (s) clears the buffers.
        target_speed: TMA speed prior v_c, m/s (seed 001; required > 0 for tma_* estimators,
            0 = unset).
        window: TMA window, s: bearings older than the newest minus this leave the sums.
        speed_reference: TMA prior on 'relative' (|v_t − v_o|, seed 001) or 'ground' (|v_t|)
            speed.
    """

    frame_id: str = 'map'
    trigger: str = TRIGGER_EVENT
    rate: float = 10.0
    max_latency: float = 0.2
    sync_tolerance: float = 0.05
    interpolation: bool = False
    max_interpolation_gap: float = 1.0
    station_timeout: float = 5.0
    buffer_size: int = 50
    buffer_age: float = 10.0
    min_stations: int = 2
    estimator: str = field(default_factory=default_estimator)
    estimator_options: dict = field(default_factory=dict)
    outlier_gate: float = 0.999
    time_jump_tolerance: float = 0.1
    target_speed: float = 0.0
    window: float = 120.0
    speed_reference: str = 'relative'

    def validate(self):
        """Raise ``ValueError`` naming the first invalid field; return self."""
        if not isinstance(self.frame_id, str) or not self.frame_id:
            raise ValueError('frame_id: must be a non-empty string')
        if self.trigger not in TRIGGERS:
            raise ValueError(f'trigger: {self.trigger!r} is not one of {list(TRIGGERS)}')
        if not (math.isfinite(float(self.rate)) and 0.0 < float(self.rate) <= 1000.0):
            raise ValueError(f'rate: must be in (0, 1000] Hz, got {self.rate}')
        _seconds('max_latency', self.max_latency)
        _seconds('sync_tolerance', self.sync_tolerance)
        _seconds('max_interpolation_gap', self.max_interpolation_gap, positive=True)
        _seconds('station_timeout', self.station_timeout, positive=True)
        _seconds('buffer_age', self.buffer_age, positive=True)
        _seconds('time_jump_tolerance', self.time_jump_tolerance)
        if int(self.buffer_size) < 2:
            raise ValueError(f'buffer_size: must be >= 2, got {self.buffer_size}')
        if float(self.buffer_age) <= float(self.max_latency) + float(self.sync_tolerance):
            raise ValueError('buffer_age: must exceed max_latency + sync_tolerance, or the '
                             'bearings of an epoch are pruned before it is processed')
        if int(self.min_stations) < 2:
            raise ValueError(f'min_stations: must be >= 2, got {self.min_stations}')
        if not isinstance(self.estimator_options, dict):
            raise ValueError('estimator_options: must be a dict')
        _seconds('window', self.window, positive=True)
        if self.speed_reference not in SPEED_REFERENCES:
            raise ValueError(f'speed_reference: {self.speed_reference!r} is not one of '
                             f'{list(SPEED_REFERENCES)}')
        v = float(self.target_speed)
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f'target_speed: must be finite and >= 0 m/s, got {v}')
        if self.estimator in TMA_ESTIMATORS:
            if v <= 0.0:
                raise ValueError(f'target_speed: must be > 0 m/s for the TMA estimator '
                                 f'{self.estimator} (the speed prior of seed 001)')
            it = self.estimator_options.get('max_iterations', 1)
            if int(it) != it or it < 1:
                raise ValueError(f'max_iterations: must be an integer >= 1, got {it}')
        else:
            check_estimator(self.estimator, self.estimator_options)
        g = float(self.outlier_gate)
        if not 0.5 <= g <= 1.0:
            raise ValueError(f'outlier_gate: probability must be in [0.5, 1], got {g}')
        return self

    def replace(self, **changes):
        """A copy with ``changes`` applied (validate it before use)."""
        return replace(self, **changes)

    def alignment(self):
        """The :class:`AlignmentConfig` (integer ns) of these settings."""
        return AlignmentConfig(
            sync_tolerance_ns=seconds_to_ns(self.sync_tolerance),
            interpolation=bool(self.interpolation),
            max_interpolation_gap_ns=seconds_to_ns(self.max_interpolation_gap),
            buffer_size=int(self.buffer_size), buffer_age_ns=seconds_to_ns(self.buffer_age))

    @property
    def period_ns(self):
        """Timer period 1 / rate, integer ns."""
        return max(1, int(round(NS_PER_S / float(self.rate))))


ESTIMATOR_OPTION_SCOPE = _registry.OPTION_SCOPE
estimator_kwargs = _registry.scoped_options
noise_sigmas = _registry.noise_sigmas


def check_estimator(name, options):
    """Validate an estimator name and its options without side effects (ValueError)."""
    _registry.check(name, options)


@dataclass
class Solution:
    """Result of :func:`solve_epoch` for one set of aligned bearings.

    ``reason`` is ``'ok'`` with a fix, else one of :data:`NO_FIX_REASONS` (position and
    covariance then None). ``used``/``rejected`` are lists of Bearing (rejected = dropped by
    the outlier gate); ``residuals`` maps station -> d² at the final fix; ``chi2`` is their
    sum and ``dof`` = (number of angles) − 3.
    """

    reason: str
    position: np.ndarray = None
    covariance: np.ndarray = None
    used: list = field(default_factory=list)
    rejected: list = field(default_factory=list)
    status: str = ''
    iterations: int = 0
    residuals: dict = field(default_factory=dict)
    chi2: float = float('nan')
    dof: int = 0
    detail: str = ''

    @property
    def ok(self):
        """True when a fix was produced."""
        return self.reason == OK


def _count_reason(bearings):
    """No-fix reason of BearingSet.validate's counting rules (at least two stations, one
    elevation, three angles), or None; checked without building arrays."""
    n = len(bearings)
    n_el = sum(1 for b in bearings if not math.isnan(b.elevation))
    if n < 2 or n + n_el < 3:
        return TOO_FEW_STATIONS
    if n_el == 0:
        return NO_ELEVATION
    return None


def _covariance_ok(cov):
    if not np.all(np.isfinite(cov)):
        return False
    lam = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    return bool(lam[-1] > 0.0 and lam[0] >= -1e-9 * lam[-1])


def _trusted_set(bearings):
    """One-problem BearingSet (M = 1) of validated Bearings with exactly 3-coordinate
    positions: the same arrays as ``BearingSet.from_bearings(..., validate=False)`` without
    its reshaping and copies (~9 µs instead of ~23 µs at N = 10)."""
    el = np.array([[b.elevation for b in bearings]], dtype=float)
    sel = np.array([[b.sigma_elevation for b in bearings]], dtype=float)
    return BearingSet(np.array([[b.position for b in bearings]], dtype=float),
                      np.array([[b.azimuth for b in bearings]], dtype=float), el,
                      np.array([[b.sigma_azimuth for b in bearings]], dtype=float),
                      np.where(np.isfinite(el), sel, np.nan), [b.station for b in bearings])


def solve_epoch(bearings, estimator, options=None, min_stations=2, outlier_gate=0.999,
                validated=False):
    """Fix from aligned bearings (one per station) with χ² outlier gating.

    Loop: check the counts (at least ``min_stations`` stations, one elevation, three angles:
    BearingSet.validate's rules), run ``locate(estimator, ...)``, accept only a converged
    ``ok`` result with finite position and a finite positive semi-definite covariance;
    compute each station's d² (:func:`normalized_residuals` with the σ the estimator
    assumes, :func:`noise_sigmas`, and the station position covariance) and, if the worst
    ratio d_i² / gate_threshold(outlier_gate, k_i) exceeds 1, drop that station and repeat,
    as long as the remaining set is still solvable; if it is not, the epoch has no fix
    (``inconsistent_bearings``). Returns a :class:`Solution`. Never raises for bad geometry
    or estimator failures (they become reasons); the estimator's own exceptions become
    ``estimator_error`` with the message in ``detail``. The bearings' fields are expected to
    be valid; invalid ones end as ``estimator_error``, since ``locate`` validates the set.
    ``validated=True`` (FusionCore, whose bearings passed Bearing.validate on arrival) skips
    that second check of the same fields, builds the BearingSet directly (:func:`_trusted_set`)
    and calls the estimator directly: same result, ~60 µs less per estimation at N = 10.
    """
    options = dict(options or {})
    used = list(bearings)
    rejected = []
    kwargs = estimator_kwargs(estimator, options)
    if validated:
        make_set = _trusted_set

        def run(bs):
            return _estimators.ESTIMATORS[estimator](bs, **kwargs)
    else:
        def make_set(b):
            return BearingSet.from_bearings(b, validate=False)

        def run(bs):
            return _estimators.locate(estimator, bs, **kwargs)
    while True:
        if len(used) < int(min_stations):
            return Solution(TOO_FEW_STATIONS, used=used, rejected=rejected,
                            detail=f'{len(used)} < min_stations {min_stations}')
        reason = _count_reason(used)
        if reason is not None:
            return Solution(reason, used=used, rejected=rejected,
                            detail=f'{len(used)} station(s)')
        bs = make_set(used)
        try:
            res = run(bs)
        except Exception as exc:  # noqa: B902 - any estimator failure is a counted no-fix
            return Solution(ESTIMATOR_ERROR, used=used, rejected=rejected,
                            detail=f'{type(exc).__name__}: {exc}')
        status = str(res.status[0])
        pos = np.asarray(res.position[0], dtype=float)
        cov = np.asarray(res.covariance[0], dtype=float)
        common = dict(used=used, rejected=rejected, status=status,
                      iterations=int(res.iterations[0]))
        if status == _estimators.STATUS_DEGENERATE:
            return Solution(DEGENERATE_GEOMETRY, **common)
        if status != _estimators.STATUS_OK or not bool(res.converged[0]):
            return Solution(NOT_CONVERGED, **common)
        if not np.all(np.isfinite(pos)):
            return Solution(DEGENERATE_GEOMETRY, detail='non-finite position', **common)
        if not _covariance_ok(cov):
            return Solution(BAD_COVARIANCE, **common)
        pcov = np.array([np.asarray(b.position_covariance, dtype=float) for b in used])
        saz, sel = noise_sigmas(estimator, bs, pos[None], kwargs)
        gated = BearingSet(bs.positions, bs.azimuth, bs.elevation, saz, sel, bs.stations)
        # Zero station covariances (fixed stations, the usual case) inflate nothing: skip the
        # Jacobians (same d², ~40 µs less at N = 10).
        d2, dof = normalized_residuals(gated, pos, pcov[None] if pcov.any() else None)
        d2, dof = d2[0], dof[0]
        thr = np.array([gate_threshold(outlier_gate, int(k)) for k in dof])
        with np.errstate(invalid='ignore'):
            excess = np.where(np.isfinite(d2), d2 / thr, 0.0)
        worst = int(np.argmax(excess))
        if excess[worst] > 1.0:
            remaining = used[:worst] + used[worst + 1:]
            if len(remaining) >= int(min_stations) and _count_reason(remaining) is None:
                rejected = rejected + [used[worst]]
                used = remaining
                continue
            return Solution(INCONSISTENT_BEARINGS,
                            detail=f'{used[worst].station} d2={d2[worst]:.3g} but too few '
                                   f'stations left to drop it', **common)
        residuals = {b.station: float(v) for b, v in zip(used, d2)}
        return Solution(OK, position=pos, covariance=0.5 * (cov + cov.T),
                        residuals=residuals, chi2=float(np.nansum(d2)),
                        dof=int(np.sum(dof)) - 3, **common)


def _bearing_problem(b):
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


def _position_covariance_problem(pcov):
    """None for a finite (3, 3) station position covariance with a non-negative diagonal
    (m², the rule of ros_conversions.bearing_from_msg), else the problem text."""
    try:
        c = (pcov if type(pcov) is np.ndarray else np.asarray(pcov, dtype=float))
        v = c.ravel().tolist() if c.shape == (3, 3) else None
    except (TypeError, ValueError):
        v = None
    if v is None or not all(isinstance(x, (float, int)) for x in v):
        return 'position_covariance: expected a (3, 3) array of numbers, m²'
    if not all(map(math.isfinite, v)) or v[0] < 0.0 or v[4] < 0.0 or v[8] < 0.0:
        return 'position_covariance: non-finite or negative variance'
    return None


@dataclass
class Epoch:
    """One output epoch of :class:`FusionCore`.

    Attributes:
        stamp_ns: epoch time t the bearings were aligned to (the fix stamp), ns.
        produced_ns: node-clock "now" when it was computed, ns.
        reason: ``'ok'`` (a fix) or a no-fix reason (:data:`NO_FIX_REASONS`).
        position (3,), covariance (3, 3): the fix, m / m² (None without a fix).
        estimator, status, iterations: what produced it.
        bearings: aligned Bearings in the fix; rejected: Bearings dropped by the gate.
        how: station -> 'nearest' | 'interpolated'.
        missing: live stations with no bearing within the alignment window.
        stale: stations left out because they are stale.
        residuals: station -> d² at the fix; chi2, dof: their sum and degrees of freedom.
        detail: human-readable detail of a no-fix reason.
        velocity (3,), state_covariance (6, 6): TMA mode only (else None): target velocity,
            m/s, and the covariance of (position, velocity), m², m²/s, m²/s².
    """

    stamp_ns: int
    produced_ns: int
    reason: str
    position: np.ndarray = None
    covariance: np.ndarray = None
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


class FusionCore:
    """Multi-station fusion pipeline: buffers, alignment, epochs, estimation, gating, counters.

    Usage (the node and ``bag process`` do exactly this)::

        core = FusionCore(FusionConfig(...), stations=['station_1', 'station_2'])
        epochs = core.add_bearing(bearing, now_ns)   # on every accepted message
        epochs += core.tick(now_ns)                 # every core.tick_period_ns
        core.count_bad_message(station, reason, now_ns)   # messages that failed conversion
        core.drain_events()                         # [(level, text)] to log
        core.diagnostics(now_ns)                    # [DiagnosticEntry] to publish

    All inputs are integer ns on one clock; no wall clock is read. A bearing's arrival is
    classified as the first that applies: ``duplicate`` (same stamp as a buffered bearing of
    its station), ``out_of_order`` (older than the station's newest), ``too_late`` (stamp
    < last epoch − sync_tolerance, so no future epoch could use it, or older than
    now − buffer_age), ``from_future`` (stamp > now + buffer_age: buffered, it would make
    every later bearing of its station out of order); such bearings are dropped and counted.
    "now" moving back by more than ``time_jump_tolerance`` (a bag looping, a simulation
    reset) clears every buffer and the epoch history and is reported as an event. In nearest
    mode each bearing is used in at most one epoch (consecutive fixes stay independent);
    interpolation may reuse a bracketing pair for several epochs when epochs are denser than
    the bearings.
    """

    mode = MODE_MULTISTATION

    def __init__(self, config=None, stations=()):
        self._apply_config(self._check_mode(
            (config if config is not None else FusionConfig()).validate()))
        self._buffers = {}
        self._stats = {}
        self._used_until = {}
        self._last_epoch_ns = None
        self._last_now_ns = None
        self._first_now_ns = None
        self._events = []
        self._fix_times = deque()
        self.epochs = 0
        self.fixes = 0
        self.no_fix = Counter()
        self.outliers = 0
        self.bad_messages = 0
        self.dropped = Counter()
        self.time_jumps = 0
        self.iterations = 0
        self.last_fix_stamp_ns = None
        self.last_epoch = None
        self.geometry_version = 0
        self._next_check_ns = None    # earliest now at which a station state may change
        self._scan_now_ns = None      # now of the last full state scan
        self._expected = None         # cached event-trigger station list (None: recompute)
        for s in stations:
            self.add_station(s)

    # ----------------------------------------------------------------- configuration
    @property
    def tick_period_ns(self):
        """How often the owner should call :meth:`tick` (1 / rate), ns."""
        return self.config.period_ns

    def check_config(self, **changes):
        """Validate ``changes`` to the configuration without applying them (ValueError)."""
        return self._check_mode(self.config.replace(**changes).validate())

    def _check_mode(self, config):
        """The estimator must belong to this mode (mode_for_estimator); switching between a
        TMA and a multi-station estimator needs a restart with the other mode."""
        mode = mode_for_estimator(config.estimator)
        if mode != self.mode:
            raise ValueError(f'estimator: {config.estimator} is a {mode} estimator but the '
                             f'fusion runs in mode {self.mode}; switching between tma_* and '
                             'multi-station estimators needs a restart')
        return config

    def reconfigure(self, **changes):
        """Apply validated ``changes`` (buffer bounds take effect at once; buffers are kept)."""
        new = self.check_config(**changes)
        old_align = self._align
        self._apply_config(new)
        if self._align != old_align:
            for buf in self._buffers.values():
                buf.size, buf.age_ns = self._align.buffer_size, self._align.buffer_age_ns
        self._next_check_ns = None
        return new

    def _apply_config(self, config):
        self.config = config
        self._align = config.alignment()
        self._timeout_ns = seconds_to_ns(config.station_timeout)
        self._jump_tolerance_ns = seconds_to_ns(config.time_jump_tolerance)
        self._max_latency_ns = seconds_to_ns(config.max_latency)
        self._next_check_ns = None
        self._expected = None

    # ----------------------------------------------------------------- stations
    @property
    def stations(self):
        """Known station ids, in the order they were added."""
        return list(self._stats)

    def add_station(self, station):
        """Register ``station`` (idempotent); it is 'waiting' until its first bearing."""
        if station not in self._stats:
            self._stats[station] = StationStats(station, since_ns=self._last_now_ns)
            self._buffers[station] = StationBuffer(station, self._align.buffer_size,
                                                   self._align.buffer_age_ns)
            self._events.append(('info', f'station {station} added'))
            self._expected = None
            self._next_check_ns = None     # its waiting period must be scheduled
        return self._stats[station]

    def remove_station(self, station):
        """Forget ``station`` (its buffer and counters)."""
        if self._stats.pop(station, None) is not None:
            self._buffers.pop(station, None)
            self._used_until.pop(station, None)
            self._expected = None
            self.geometry_version += 1
            self._events.append(('info', f'station {station} removed'))

    def station_stats(self, station):
        """The :class:`StationStats` of ``station``."""
        return self._stats[station]

    def station_state(self, station):
        """'waiting', 'alive' or 'stale' (as of the last call that passed a now)."""
        return self._stats[station].state

    def live_stations(self):
        """Stations currently alive."""
        return [s for s, st in self._stats.items() if st.state == ALIVE]

    def geometry(self):
        """Planning hook: station -> (position (3,), σ_θ, σ_ψ or NaN) of every live station.

        ``geometry_version`` increments whenever this changes (a station joins, goes stale,
        comes back, is removed or moves more than GEOMETRY_MOVE_TOLERANCE_M), so a consumer
        (for example an accuracy map of core.planning) recomputes only then.
        """
        out = {}
        for s in self.live_stations():
            b = self._buffers[s].newest
            if b is not None:
                out[s] = (np.asarray(b.position, dtype=float).copy(), float(b.sigma_azimuth),
                          float(b.sigma_elevation))
        return out

    # ----------------------------------------------------------------- inputs
    def count_bad_message(self, station, reason, now_ns=None):
        """Count a message of ``station`` rejected before reaching the core (conversion)."""
        st = self.add_station(station)
        st.received += 1
        st.bad[reason] += 1
        self.bad_messages += 1
        if now_ns is not None:
            self._advance(int(now_ns))

    def add_bearing(self, bearing, now_ns):
        """Ingest one bearing received at node-clock time ``now_ns``; return new Epochs.

        Returns [] unless the trigger is ``event`` and this bearing completes an epoch.
        Invalid bearings (``Bearing.validate``) and bearings in another frame are counted as
        bad messages (``invalid_bearing`` / ``wrong_frame``), never raised.
        """
        now = int(now_ns)
        if self._bad_station_id(bearing, now):
            return []
        st = self.add_station(bearing.station)
        self._advance(now, bearing.station)
        st.received += 1
        detail = _bearing_problem(bearing)
        if detail is not None:
            st.bad[INVALID_BEARING] += 1
            self.bad_messages += 1
            self._events.append(('warn', f'{bearing.station}: invalid bearing ({detail})'))
            return []
        if bearing.frame_id != self.config.frame_id:
            st.bad[WRONG_FRAME] += 1
            self.bad_messages += 1
            return []
        stamp = int(bearing.stamp_ns)
        buf = self._buffers[bearing.station]
        reason = buf.classify(stamp)
        if reason is None and self._is_too_late(stamp, now):
            reason = TOO_LATE
        if reason is None and stamp > now + self._align.buffer_age_ns:
            reason = FROM_FUTURE
        if reason is not None:
            st.dropped[reason] += 1
            self.dropped[reason] += 1
            return []
        st.evicted += buf.push(bearing)
        st.accepted += 1
        st.last_stamp_ns = stamp
        # Python floats: ~1 µs instead of ~5 µs of numpy on 3-vectors, per bearing.
        pos = bearing.position
        pos = tuple(pos.tolist() if type(pos) is np.ndarray else (float(v) for v in pos))
        if st.position is None or math.dist(pos, st.position) > GEOMETRY_MOVE_TOLERANCE_M:
            st.position = pos
            self.geometry_version += 1
        self._set_state(st, self._state_at(st, now))
        if st.state == ALIVE:
            due = stamp + self._timeout_ns
            if self._next_check_ns is not None and due < self._next_check_ns:
                self._next_check_ns = due
        if self.config.trigger == TRIGGER_EVENT:
            return self._event_epochs(now)
        return []

    def _bad_station_id(self, bearing, now):
        """Count (as a bad message of no station) a bearing whose station id is not a
        non-empty string; True when it was dropped."""
        if isinstance(bearing.station, str) and bearing.station:
            return False
        self.bad_messages += 1
        self._events.append(('warn', f'bearing with station id {bearing.station!r} dropped '
                                     '(must be a non-empty string)'))
        self._advance(now)
        return True

    def tick(self, now_ns):
        """Clock tick at node-clock time ``now_ns``: prune, update states, run due epochs."""
        now = int(now_ns)
        self._advance(now)
        if self.config.trigger == TRIGGER_EVENT:
            return self._event_epochs(now)
        period = self.config.period_ns
        target = now - self._max_latency_ns
        if target < 0:
            return []
        k_last = target // period
        if self._last_epoch_ns is None:
            k_first = k_last
        else:
            k_first = self._last_epoch_ns // period + 1
            backfill = max(1, self._align.buffer_age_ns // period)
            k_first = max(k_first, k_last - backfill + 1)
        return [self._epoch(k * period, now) for k in range(k_first, k_last + 1)]

    @property
    def has_events(self):
        """True when log events are pending (a cheap test before :meth:`drain_events`)."""
        return bool(self._events)

    def drain_events(self):
        """Return and forget the pending log events: list of (level 'info'|'warn', text)."""
        ev, self._events = self._events, []
        return ev

    # ----------------------------------------------------------------- internals
    def _is_too_late(self, stamp, now):
        if stamp < now - self._align.buffer_age_ns:
            return True
        return (self._last_epoch_ns is not None
                and stamp < self._last_epoch_ns - self._align.sync_tolerance_ns)

    def _advance(self, now, station=None):
        """Time-jump detection, pruning and station states at ``now``.

        Cost O(1) amortised per call: only ``station``'s buffer is pruned here (every buffer
        is pruned before an epoch, :meth:`_prune_all`, and on ticks), and the station states
        are rescanned only when one may have timed out (``_next_check_ns``). Buffers are
        always pruned at the newest now seen, so the result is the same as pruning every
        buffer on every call.
        """
        if self._first_now_ns is None:
            self._first_now_ns = now
            for st in self._stats.values():
                st.since_ns = now if st.since_ns is None else st.since_ns
        last = self._last_now_ns
        if last is not None and now < last - self._jump_tolerance_ns:
            self._reset_time(now, last)
        elif last is None or now > last:
            # A small backward step (within the tolerance) keeps the newest now.
            self._last_now_ns = now
        if station is None:
            self._prune_all()
        else:
            self._buffers[station].prune(self._last_now_ns)
        if (self._next_check_ns is None or now > self._next_check_ns
                or now < self._scan_now_ns):
            self._update_states(now)

    def _prune_all(self):
        for buf in self._buffers.values():
            buf.prune(self._last_now_ns)

    def _reset_time(self, now, last):
        self.time_jumps += 1
        for buf in self._buffers.values():
            buf.clear()
        for st in self._stats.values():
            st.last_stamp_ns = None
            st.state = WAITING
            st.since_ns = now
        self._used_until.clear()
        self._last_epoch_ns = None
        self._fix_times.clear()
        self._first_now_ns = now
        self._last_now_ns = now
        self._next_check_ns = None
        self._expected = None
        self.geometry_version += 1
        self._events.append(('warn', f'time jumped back from {last / NS_PER_S:.3f} s to '
                                     f'{now / NS_PER_S:.3f} s: buffers cleared'))

    def _state_at(self, st, now):
        if st.last_stamp_ns is None:
            return WAITING
        if now - st.last_stamp_ns > self._timeout_ns:
            return STALE
        return ALIVE

    def _set_state(self, st, new):
        if new != st.state:
            if new == STALE:
                self._events.append(('warn', f'station {st.station} stale: no bearing for '
                                             f'more than {self.config.station_timeout} s'))
            elif new == ALIVE:
                self._events.append(('info', f'station {st.station} alive'
                                     + (' again' if st.state == STALE else '')))
            st.state = new
            self._expected = None
            self.geometry_version += 1

    def _update_states(self, now):
        """Full scan: every station's state at ``now``, and the next time one may change
        (an alive station timing out, or a waiting one no longer waited for)."""
        nxt = None
        for st in self._stats.values():
            self._set_state(st, self._state_at(st, now))
            if st.state == ALIVE:
                due = st.last_stamp_ns + self._timeout_ns
            elif st.state == WAITING and st.since_ns is not None and st.since_ns >= now - \
                    self._timeout_ns:
                due = st.since_ns + self._timeout_ns
            else:
                continue
            nxt = due if nxt is None or due < nxt else nxt
        self._next_check_ns = nxt if nxt is not None else now + 1000 * NS_PER_S
        self._scan_now_ns = now
        self._expected = None

    def _expected_stations(self, now):
        """Event trigger: live stations, plus stations that have not reported yet but were
        added (or the clock reset) less than station_timeout ago."""
        if self._expected is None:
            self._expected = [
                s for s, st in self._stats.items()
                if st.state == ALIVE or (st.state == WAITING and st.since_ns is not None
                                         and now - st.since_ns <= self._timeout_ns)]
        return self._expected

    def _event_epochs(self, now):
        expected = self._expected_stations(now)
        if not expected:
            return []
        newest = [self._buffers[s].newest_stamp_ns for s in expected]
        if any(n is None for n in newest):
            return []
        t = min(newest)
        if self._last_epoch_ns is not None and t <= self._last_epoch_ns:
            return []
        return [self._epoch(t, now)]

    def _epoch(self, t, now):
        cfg = self.config
        self._last_epoch_ns = t
        self._prune_all()
        nearest_only = not self._align.interpolation
        aligned, how, missing = [], {}, []
        live = self.live_stations()
        stale = [s for s, st in self._stats.items() if st.state == STALE]
        for s in live:
            b, kind = align(self._buffers[s], t, self._align,
                            after_ns=self._used_until.get(s) if nearest_only else None)
            if b is None:
                missing.append(s)
                continue
            aligned.append(b)
            how[s] = kind
            if kind == NEAREST and nearest_only:
                self._used_until[s] = int(b.stamp_ns)
        sol = solve_epoch(aligned, cfg.estimator, cfg.estimator_options, cfg.min_stations,
                          cfg.outlier_gate, validated=True)
        self.epochs += 1
        for b in sol.rejected:
            self._stats[b.station].outliers += 1
            self.outliers += 1
        ep = Epoch(stamp_ns=int(t), produced_ns=int(now), reason=sol.reason,
                   estimator=cfg.estimator, status=sol.status, iterations=sol.iterations,
                   bearings=list(sol.used), rejected=list(sol.rejected),
                   how={b.station: how[b.station] for b in aligned}, missing=missing,
                   stale=stale, residuals=sol.residuals, chi2=sol.chi2, dof=sol.dof,
                   detail=sol.detail)
        if sol.ok:
            ep.position, ep.covariance = sol.position, sol.covariance
            self.fixes += 1
            self.iterations += sol.iterations
            self.last_fix_stamp_ns = int(t)
            self._fix_times.append(int(now))
            while self._fix_times and self._fix_times[0] <= now - RATE_WINDOW_NS:
                self._fix_times.popleft()
            for b in sol.used:
                self._stats[b.station].used += 1
        else:
            self.no_fix[sol.reason] += 1
        self.last_epoch = ep
        return ep

    # ----------------------------------------------------------------- diagnostics
    def fix_rate(self, now_ns):
        """Fixes per second over the last RATE_WINDOW_NS (or since start), node clock."""
        now = int(now_ns)
        first = self._first_now_ns if self._first_now_ns is not None else now
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
        last_fix_stamp. Station keys: state, received, accepted, used, outliers, evicted,
        bad.<reason>, dropped.<reason>, last_stamp, age_s.
        """
        now = int(now_ns)
        states = {s: self._state_at(st, now) for s, st in self._stats.items()}
        live = [s for s, v in states.items() if v == ALIVE]
        stale = [s for s, v in states.items() if v == STALE]
        non_conv = self.no_fix[NOT_CONVERGED] + self.no_fix[ESTIMATOR_ERROR]
        attempts = self.fixes + non_conv
        values = {
            'estimator': self.config.estimator,
            'trigger': self.config.trigger,
            'alignment': INTERPOLATED if self._align.interpolation else NEAREST,
            'epochs': self.epochs,
            'fixes': self.fixes,
            'fix_rate_hz': f'{self.fix_rate(now):.3f}',
            'converged_fraction': (f'{self.fixes / attempts:.4f}' if attempts else 'n/a'),
            'mean_iterations': (f'{self.iterations / self.fixes:.2f}' if self.fixes else 'n/a'),
            'rejected_bearings': self.outliers,
            'bad_messages': self.bad_messages,
            'time_jumps': self.time_jumps,
            'live_stations': ','.join(live),
            'stale_stations': ','.join(stale),
            'last_fix_stamp': (f'{self.last_fix_stamp_ns / NS_PER_S:.9f}'
                               if self.last_fix_stamp_ns is not None else 'none'),
        }
        for r in DROP_REASONS:
            values[f'dropped.{r}'] = self.dropped[r]
        for r in NO_FIX_REASONS:
            values[f'no_fix.{r}'] = self.no_fix[r]
        if len(live) < self.config.min_stations:
            level = LEVEL_ERROR
            msg = f'{len(live)} live station(s), need {self.config.min_stations}'
        elif self.last_epoch is not None and not self.last_epoch.ok:
            level, msg = LEVEL_WARN, f'no fix: {self.last_epoch.reason}'
        elif stale:
            level, msg = LEVEL_WARN, f'stale: {", ".join(stale)}'
        else:
            level, msg = LEVEL_OK, 'fixing' if self.fixes else 'waiting for an epoch'
        out = [DiagnosticEntry('fusion', level, msg, values)]
        for s, st in self._stats.items():
            sv = {'state': states[s], 'received': st.received, 'accepted': st.accepted,
                  'used': st.used, 'outliers': st.outliers, 'evicted': st.evicted,
                  'last_stamp': (f'{st.last_stamp_ns / NS_PER_S:.9f}'
                                 if st.last_stamp_ns is not None else 'none'),
                  'age_s': (f'{(now - st.last_stamp_ns) / NS_PER_S:.3f}'
                            if st.last_stamp_ns is not None else 'n/a')}
            for r, n in sorted(st.bad.items()):
                sv[f'bad.{r}'] = n
            for r in DROP_REASONS:
                sv[f'dropped.{r}'] = st.dropped[r]
            lvl = LEVEL_OK if states[s] == ALIVE else LEVEL_WARN
            msg = (states[s] if not st.bad
                   else f'{states[s]}, {sum(st.bad.values())} bad message(s)')
            out.append(DiagnosticEntry(f'station {s}', lvl, msg, sv, hardware_id=s))
        return out


@dataclass
class DiagnosticEntry:
    """One diagnostic status, ROS-free (the node turns it into DiagnosticStatus)."""

    name: str
    level: str
    message: str
    values: dict
    hardware_id: str = ''


# ---------------------------------------------------------------------------------------------
# Single-station TMA mode (issue 5): one moving station, constant-velocity target, speed prior.

class TmaFusionCore(FusionCore):
    """Single moving station TMA (seed 001) with FusionCore's interface (mode ``tma``).

    The bearings of one station (the first one that delivers an accepted bearing, the "tracked"
    station; bearings of any other station are counted as ``bad.not_tracked``) go through the same
    arrival checks as in the multi-station pipeline (invalid, wrong frame, duplicate, out of order,
    too late: counted, never raised) and then, in O(1), into a
    :class:`~bearing_loc_ros.core.tma.TmaAccumulator` (recursive P, Ω of seed 001 Table 1, README
    "Target motion analysis" (T13)) bounded to the last ``window`` seconds. Each epoch solves the
    configured TMA estimator (``tma_ple`` (T6)-(T8), ``tma_ctls`` (T9)-(T12), ``tma_ctls6`` (T12b),
    ``tma_mle``) with the speed prior |v| = ``target_speed`` (T5, ``speed_reference`` 'relative' or
    'ground') and returns an :class:`Epoch` whose position (3,) m and velocity (3,) m/s are the
    target state at the newest bearing's stamp, ``covariance`` the (3, 3) position block and
    ``state_covariance`` the (6, 6) (position, velocity) constrained CRLB at the estimate
    (T15)-(T16), m², m²/s, m²/s².

    Triggers: ``event``: one epoch per accepted bearing; ``timer``: at most one epoch per
    tick, when bearings arrived since the last one (bounds the CPU of ``tma_mle``). No fix
    (a counted reason, :data:`NO_FIX_REASONS`): ``unobservable`` (too few bearings, no
    significant bearing change or a range the CRLB cannot resolve, (T18)),
    ``no_elevation`` (3-D TMA needs the elevation of every bearing), ``degenerate_geometry``,
    ``not_converged`` (tma_mle), ``bad_covariance``, ``estimator_error``. Time going back by
    more than ``time_jump_tolerance`` clears the buffers and the accumulator.
    """

    mode = MODE_TMA

    def __init__(self, config=None, stations=()):
        self._acc = None
        self._tracked = None
        self._pending = None      # newest accepted bearing not yet estimated
        self._newest = None       # newest bearing in the accumulator
        super().__init__(config, stations)

    def _apply_config(self, config):
        super()._apply_config(config)
        old = self._acc
        if (old is None or old.window != float(config.window)
                or old.speed_reference != config.speed_reference):
            self._acc = TmaAccumulator(float(config.target_speed) or 1.0,
                                       window=float(config.window),
                                       speed_reference=config.speed_reference)
            if old is not None:
                for e in old._entries:       # keep the window across a reconfiguration
                    self._acc.add(*e[:6])

    @property
    def tracked_station(self):
        """The station whose bearings feed the TMA (None until the first bearing)."""
        return self._tracked

    @property
    def window_bearings(self):
        """Number of bearings in the TMA window."""
        return len(self._acc)

    def remove_station(self, station):
        """Forget ``station``; removing the tracked station clears the TMA window."""
        super().remove_station(station)
        if station == self._tracked:
            self._tracked = None
            self._clear_tma()

    def _clear_tma(self):
        self._acc.reset()
        self._pending = None
        self._newest = None

    def _reset_time(self, now, last):
        super()._reset_time(now, last)
        self._clear_tma()

    def _event_epochs(self, now):
        return []           # TMA epochs come from add_bearing / tick

    def add_bearing(self, bearing, now_ns):
        """Ingest one bearing (see the class docstring); return new Epochs."""
        now = int(now_ns)
        station = bearing.station
        if self._bad_station_id(bearing, now):
            return []
        if self._tracked is not None and station != self._tracked:
            st = self.add_station(station)
            st.received += 1
            if not st.bad[NOT_TRACKED]:
                self._events.append(('warn', f'tma mode tracks station {self._tracked}: '
                                             f'bearings of {station} are ignored'))
            st.bad[NOT_TRACKED] += 1
            self.bad_messages += 1
            self._advance(now, station)
            return []
        before = self._stats[station].accepted if station in self._stats else 0
        super().add_bearing(bearing, now)
        st = self._stats[station]
        if st.accepted == before:
            return []
        if self._tracked is None:
            self._tracked = station
            self._events.append(('info', f'tma: tracking station {station}'))
        if math.isnan(bearing.elevation):
            return [self._record(Epoch(stamp_ns=int(bearing.stamp_ns), produced_ns=now,
                                       reason=NO_ELEVATION, estimator=self.config.estimator,
                                       bearings=[bearing],
                                       detail='3-D TMA needs azimuth and elevation'), now)]
        try:
            self._acc.add(bearing.stamp_ns / NS_PER_S, bearing.position, bearing.azimuth,
                          bearing.elevation, bearing.sigma_azimuth, bearing.sigma_elevation)
        except ValueError as exc:      # the arrival checks make this unreachable
            return [self._record(Epoch(stamp_ns=int(bearing.stamp_ns), produced_ns=now,
                                       reason=ESTIMATOR_ERROR, estimator=self.config.estimator,
                                       bearings=[bearing], detail=str(exc)), now)]
        self._newest = bearing
        self._pending = bearing
        if self.config.trigger == TRIGGER_EVENT:
            return [self._tma_epoch(now)]
        return []

    def tick(self, now_ns):
        """Clock tick: prune, update states; timer trigger: estimate if bearings arrived."""
        now = int(now_ns)
        self._advance(now)
        if self.config.trigger == TRIGGER_TIMER and self._pending is not None:
            return [self._tma_epoch(now)]
        return []

    def _tma_epoch(self, now):
        cfg = self.config
        b = self._newest
        self._pending = None
        method = TMA_ESTIMATORS[cfg.estimator]
        opts = {}
        if method == 'mle' and 'max_iterations' in cfg.estimator_options:
            opts['max_iterations'] = int(cfg.estimator_options['max_iterations'])
        ep = Epoch(stamp_ns=int(b.stamp_ns), produced_ns=int(now), reason=ESTIMATOR_ERROR,
                   estimator=cfg.estimator, bearings=[b], how={b.station: NEAREST})
        try:
            res = self._acc.estimate(method, speed=float(cfg.target_speed), **opts)
        except Exception as exc:  # noqa: B902 - any estimator failure is a counted no-fix
            ep.detail = f'{type(exc).__name__}: {exc}'
            return self._record(ep, now)
        status = str(res.status[0])
        ep.status, ep.iterations = status, int(res.iterations[0])
        ep.detail = str(res.reason[0])
        pos = np.asarray(res.position[0], dtype=float)
        vel = np.asarray(res.velocity[0], dtype=float)
        C = np.asarray(res.covariance[0], dtype=float)
        if status == STATUS_UNOBSERVABLE:
            ep.reason = UNOBSERVABLE
        elif status == _estimators.STATUS_DEGENERATE:
            ep.reason = DEGENERATE_GEOMETRY
        elif status != _estimators.STATUS_OK or not bool(res.converged[0]):
            ep.reason = NOT_CONVERGED
        elif not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))):
            ep.reason, ep.detail = DEGENERATE_GEOMETRY, 'non-finite state'
        elif not (np.all(np.isfinite(C)) and _covariance_ok(C)):
            ep.reason = BAD_COVARIANCE
        else:
            C = 0.5 * (C + C.T)
            ep.reason = OK
            ep.position, ep.covariance = pos, C[:3, :3].copy()
            ep.velocity, ep.state_covariance = vel, C
        return self._record(ep, now)

    def _record(self, ep, now):
        """Counters of an epoch (the same bookkeeping as FusionCore's epochs)."""
        self._last_epoch_ns = ep.stamp_ns
        self.epochs += 1
        if ep.ok:
            self.fixes += 1
            self.iterations += ep.iterations
            self.last_fix_stamp_ns = ep.stamp_ns
            self._fix_times.append(int(now))
            while self._fix_times and self._fix_times[0] <= now - RATE_WINDOW_NS:
                self._fix_times.popleft()
            self._stats[ep.bearings[0].station].used += 1
        else:
            self.no_fix[ep.reason] += 1
        self.last_epoch = ep
        return ep

    def geometry(self):
        """Planning hook: empty in TMA mode (one station has no static coverage map)."""
        return {}

    def diagnostics(self, now_ns):
        """FusionCore's diagnostics plus ``tracked_station``, ``window_bearings``,
        ``target_speed``, ``speed_reference``; the level follows the tracked station."""
        out = super().diagnostics(now_ns)
        d = out[0]
        d.values.update(tracked_station=self._tracked or 'none',
                        window_bearings=len(self._acc),
                        target_speed=f'{float(self.config.target_speed):.3f}',
                        speed_reference=self.config.speed_reference)
        if not d.values['live_stations']:
            d.level, d.message = LEVEL_ERROR, 'no live station'
        elif self.last_epoch is not None and not self.last_epoch.ok:
            d.level, d.message = LEVEL_WARN, f'no fix: {self.last_epoch.reason}'
        else:
            d.level = LEVEL_OK
            d.message = 'tracking' if self.fixes else 'waiting for an epoch'
        return out


#: Fusion modes of the node: name -> class with FusionCore's interface; the node's ``mode``
#: parameter picks one (``auto``: :func:`mode_for_estimator`).
MODES = {FusionCore.mode: FusionCore, TmaFusionCore.mode: TmaFusionCore}


def make_core(config, stations=(), mode='auto'):
    """The fusion core of ``mode`` (``auto``: the estimator's mode) for ``config``.

    The one place that maps configuration to a core class, for the node, ``bag process`` and
    the benchmarks. ValueError naming the field for an unknown mode or an estimator of
    another mode.
    """
    config = config if config is not None else FusionConfig()
    if mode == 'auto':
        mode = mode_for_estimator(config.estimator)
    if mode not in MODES:
        raise ValueError(f'mode: {mode!r} is not one of {["auto"] + sorted(MODES)}')
    return MODES[mode](config, stations=stations)


def replay(core, items):
    """Run ``core`` over time-ordered arrivals exactly as the node would; yield Epochs.

    ``items`` is an iterable of (now_ns, bearing) in arrival order (bearing may be None for
    a pure clock update, for example a /clock message). Before each arrival, :meth:`tick` is
    called at every multiple of ``core.tick_period_ns`` up to now (the node's timer). A
    backward jump of now restarts the tick grid. Live and replayed fixes are identical when
    every bearing arrived before its epoch was due (now >= t + max_latency in timer mode).
    """
    period = core.tick_period_ns
    next_tick = None
    last = None
    for now, bearing in items:
        now = int(now)
        if next_tick is None or (last is not None and now < last):
            next_tick = -(-now // period) * period
        while next_tick <= now:
            yield from core.tick(next_tick)
            next_tick += period
        last = now
        if bearing is not None:
            yield from core.add_bearing(bearing, now)
