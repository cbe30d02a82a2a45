"""TMA model, options and input preparation (Lin et al. sec. 2; (T1)-(T5) of docs/tma.md).

The constant-velocity target model, the speed prior and the observer track of
:mod:`bearing_loc_ros.core.tma` (see its docstring for the equations and conventions): the
options every TMA estimator shares, the validation of one batch of problems into (M, K)
arrays, the observer's fitted velocity (T2) and the simulation of noisy bearings (T1)-(T4).
"""

from dataclasses import dataclass

import numpy as np

from ..bearings import _check_bearing_fields, BearingSet, MAX_ELEVATION
from ..conventions import azimuth_elevation, wrap_angle
from ..estimator_spec import MAX_ITERATIONS, Option
from .confidence import MAX_ML_DISTANCE, MAX_NONLINEARITY


SPEED_REFERENCES = ('relative', 'ground')

#: Options of every TMA estimator (one option set serves them all: the iteration options are
#: accepted and ignored by the closed forms).
TMA_OPTIONS = (
    Option('speed_reference', 'relative', 'choice',
           "speed prior on the relative ('relative') or the target's own ('ground') velocity",
           choices=SPEED_REFERENCES),
    Option('min_bearings', 3, 'count', 'fewer bearings (at least 3) give unobservable'),
    Option('alpha', 1e-3, 'probability', 'level of the constant line-of-sight test (T18)'),
    Option('max_range_ratio', 1.0, 'positive',
           'unobservable when the CRLB range std exceeds this fraction of the range (inf: '
           'never)', allow_inf=True),
    Option('covariance', True, 'flag', 'compute the constrained CRLB (T15)-(T16) and the '
           'confidence tests (T19)-(T22)'),
    Option('max_nonlinearity', MAX_NONLINEARITY, 'positive',
           'low_confidence when the range nonlinearity kappa over the confidence region '
           'exceeds this (T21; inf: never)', allow_inf=True),
    Option('max_ml_distance', MAX_ML_DISTANCE, 'positive',
           'low_confidence when the fix lies more than this many standard deviations from '
           'the maximum likelihood estimate (T20; inf: never)', allow_inf=True),
    Option('start', None, 'object', 'tma_mle: initial (p0, v), m and m/s'),
    MAX_ITERATIONS,
    Option('xtol', 1e-10, 'positive', 'tma_mle: relative step tolerance'),
    Option('dtol', 1e-3, 'positive', 'tma_mle: step tolerance in standard deviations'),
)

#: Default options shared by every TMA estimator (see :data:`TMA_OPTIONS`).
DEFAULTS = {o.name: o.default for o in TMA_OPTIONS[:7]}


# --------------------------------------------------------------------------------------------
# Input preparation
# --------------------------------------------------------------------------------------------

@dataclass
class _Data:
    """Validated (M, K) arrays of one batch of TMA problems."""

    tau: np.ndarray        # (M, K) s, t − t_0
    t0: np.ndarray         # (M,)
    obs: np.ndarray        # (M, K, 3) observer positions
    az: np.ndarray
    el: np.ndarray
    s_az: np.ndarray
    s_el: np.ndarray
    speed: np.ndarray      # (M,)
    v_o: np.ndarray        # (M, 3) (T2)
    delta: np.ndarray      # (M, K, 3) (T2)

    @property
    def M(self):
        return self.az.shape[0]

    def take(self, idx):
        """The problems ``idx`` (an index array or mask) as a new _Data."""
        return _Data(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))


#: Largest |observation time|, s (about 317 years: Unix seconds fit, and the squares of the
#: time spans stay far inside the float range; 1e155 s overflowed them).
MAX_ABS_TIME = 1e10
#: Largest speed prior, m/s (the fusion node's ``target_speed`` bound).
MAX_SPEED = 1e6


def prepare(bearings, times, speed, speed_reference):
    """Validate one batch; raise ValueError naming the bad field."""
    if not isinstance(bearings, BearingSet):
        raise ValueError('bearings: expected a BearingSet')
    if speed_reference not in SPEED_REFERENCES:
        raise ValueError(f'speed_reference: expected one of {SPEED_REFERENCES}, '
                         f'got {speed_reference!r}')
    M, K = bearings.M, bearings.N
    _check_bearing_fields(bearings.positions, bearings.azimuth, bearings.elevation,
                          bearings.sigma_az, bearings.sigma_el)
    if K < 1:
        raise ValueError('observations: empty')
    if not np.all(bearings.has_elevation):
        raise ValueError('elevation: 3-D TMA needs azimuth and elevation on every bearing')
    try:
        t = np.broadcast_to(np.asarray(times, dtype=float), (M, K))
    except ValueError:
        raise ValueError(f't: expected shape ({K},) or ({M}, {K}), '
                         f'got {np.shape(times)}') from None
    if not np.all(np.isfinite(t)):
        raise ValueError('t: non-finite observation time')
    if np.any(np.abs(t) > MAX_ABS_TIME):
        raise ValueError(f't: |t| must be <= {MAX_ABS_TIME:g} s')
    if np.any(np.diff(t, axis=1) < 0):
        raise ValueError('t: observation times must be non-decreasing')
    try:
        vc = np.broadcast_to(np.asarray(speed, dtype=float), (M,)).copy()
    except ValueError:
        raise ValueError(f'speed: expected a scalar or ({M},) array') from None
    if not np.all(np.isfinite(vc)) or np.any(vc <= 0) or np.any(vc > MAX_SPEED):
        raise ValueError(f'speed: must be > 0 and <= {MAX_SPEED:g} m/s')
    tau = t - t[:, :1]
    obs = bearings.positions
    v_o, delta = observer_track(tau, obs)
    return _Data(tau, t[:, 0].copy(), obs, bearings.azimuth, bearings.elevation,
                 bearings.sigma_az, bearings.sigma_el, vc, v_o, delta)


def observer_track(tau, observer):
    """Observer velocity v_o (T2), the least-squares slope of o_k on τ_k, and δ_k.

    v_o = (K Σ τ o − Σ τ Σ o) / (K Σ τ² − (Σ τ)²) (m/s); δ_k = o_k − o_0 − v_o τ_k (m).
    v_o = 0 when all bearings share one time. Shapes: tau (M, K), observer (M, K, 3) ->
    (M, 3), (M, K, 3).
    """
    tau = np.asarray(tau, dtype=float)
    o = np.asarray(observer, dtype=float) - np.asarray(observer, dtype=float)[:, :1]
    tc = tau - tau.mean(axis=1, keepdims=True)
    den = np.sum(tc * tc, axis=1)
    num = np.einsum('mk,mki->mi', tc, o)
    v_o = np.where(den[:, None] > 0, num / np.where(den > 0, den, 1.0)[:, None], 0.0)
    delta = o - v_o[:, None, :] * tau[..., None]
    return v_o, delta


# --------------------------------------------------------------------------------------------
# Simulation (Lin et al. sec. 4.2)
# --------------------------------------------------------------------------------------------

def simulate_tma(times, target_position, target_velocity, observer_positions, sigma_az,
                 sigma_el=None, rng=None, M=None):
    """Bearings of a constant-velocity target from a moving observer, (T1)-(T4).

    Args:
        times: (K,) s. target_position: (3,) or (M, 3) m at times[0]; target_velocity: (3,)
        or (M, 3) m/s. observer_positions: (K, 3) or (M, K, 3) m. sigma_az/sigma_el: rad
        (σ_el defaults to σ_az). rng: numpy Generator or None (noise-free). M: number of
        problems (default from the shapes).
    Noisy elevations are clipped to |ψ| ≤ π/2 − 1e-9 (``bearings.MAX_ELEVATION``, as
    :func:`bearing_loc_ros.core.bearings.simulate_bearings`), so that any σ gives valid
    bearings.
    Returns (BearingSet (M, K) of ENU angles, times (M, K)).
    """
    t = np.asarray(times, dtype=float)
    p = np.atleast_2d(np.asarray(target_position, dtype=float))
    vt = np.atleast_2d(np.asarray(target_velocity, dtype=float))
    o = np.asarray(observer_positions, dtype=float)
    o = o[None] if o.ndim == 2 else o
    M = max(p.shape[0], vt.shape[0], o.shape[0]) if M is None else int(M)
    K = t.shape[-1]
    tau = t - t[..., :1]
    tgt = p[:, None, :] + vt[:, None, :] * np.broadcast_to(tau, (M, K))[..., None]
    az, el = azimuth_elevation(tgt - o)
    saz = np.broadcast_to(np.asarray(sigma_az, dtype=float), (M, K))
    sel = np.broadcast_to(np.asarray(sigma_az if sigma_el is None else sigma_el, float),
                          (M, K))
    if rng is not None:
        az = az + saz * rng.standard_normal((M, K))
        el = np.clip(el + sel * rng.standard_normal((M, K)), -MAX_ELEVATION, MAX_ELEVATION)
    bs = BearingSet.from_arrays(np.broadcast_to(o, (M, K, 3)), wrap_angle(az), el, saz, sel,
                                validate=False)
    return bs, np.broadcast_to(t, (M, K)).copy()
