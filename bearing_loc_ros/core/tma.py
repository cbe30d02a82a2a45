"""Target motion analysis (TMA) from one moving station with a speed prior (Lin et al.).

One station (the observer) measures azimuth and elevation of a target over time. The target
moves at constant velocity; the prior speed v_c fixes the scale that bearings alone leave
free. Equation numbers (T1)...(T18) refer to docs/tma.md, which derives
them from the text of Lin et al. (its formulas did not survive in our copy).

Conventions (docs/conventions.md). ENU world frame, metres, seconds, radians. Azimuth θ is ENU
(counter-clockwise from East), elevation ψ above the horizontal plane. Lin et al. measure their
azimuth θ' clockwise from North (the y axis): θ' = π/2 − θ, converted at the boundary
(``conventions.compass_to_enu``; the CLI flag ``--compass``). Only one sign changes: the
paper's azimuth row p_x cos θ' − p_y sin θ' = 0 is −h_θ·p = 0 below, the elevation row and the
line-of-sight vector e = (cos φ sin θ', cos φ cos θ', sin φ) = u(θ, ψ) are the same.

Model (Lin et al. sec. 2, eq. (1)-(3)). Bearing k is taken at time t_k from observer position
o_k; τ_k = t_k − t_0 counts from the first bearing of the window.

(T1)  target:            p_T(t) = o_0 + p0 + (v + v_o) (t − t_0)
(T2)  observer velocity: v_o = least-squares slope of o_k against τ_k;
      manoeuvre:         δ_k = o_k − o_0 − v_o τ_k   (≡ 0 for a constant-velocity observer)
(T3)  relative position: p_k = p_T(t_k) − o_k = p0 + v τ_k − δ_k
(T4)  θ_k = atan2(p_k,y, p_k,x) + n_k,  ψ_k = atan2(p_k,z, ρ_k) + m_k,  n ~ N(0, σ_θ²),
      m ~ N(0, σ_ψ²) independent.
(T5)  speed prior: |v| = v_c ('relative', Lin et al.: the prior relative speed) or
      |v + v_o| = v_c ('ground': the target's own speed, what type recognition gives).

So (p0, v) is the target state relative to the observer's fitted constant-velocity track,
exactly the relative motion p = p_t − p_o, v = v_t − v_o of Lin et al. when the observer does
not manoeuvre. ``ple`` and ``ctls`` use the paper's model (δ ≡ 0); ``mle`` and the CRLB use
the given observer positions exactly (any δ).
"""

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri

from .bearings import _check_bearing_fields, BearingSet
from .conventions import azimuth_elevation, los_vector, wrap_angle
from .crlb import angle_jacobians, safe_inverse
from .estimator_spec import (BEARING_SIGMA, declare, MAX_ITERATIONS, Option, TMA)
from .fix import (FixResult, STATUS_DEGENERATE, STATUS_MAX_ITERATIONS, STATUS_OK,
                  STATUS_UNOBSERVABLE, TMA_STATUSES)

__all__ = ['SPEED_REFERENCES', 'STATUS_UNOBSERVABLE', 'TMA_OPTIONS', 'TMA_STATUSES',
           'TmaAccumulator', 'TmaSums', 'batch_sums', 'bearing_terms', 'constrained_crlb',
           'constraint_gradient', 'estimate_from_sums', 'fisher_terms', 'observer_track',
           'prefix_sums', 'simulate_tma', 'state_transform', 'tma', 'tma_crlb', 'tma_ctls',
           'tma_ctls6', 'tma_mle', 'tma_ple']

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
    Option('covariance', True, 'flag', 'compute the constrained CRLB (T15)-(T16)'),
    Option('start', None, 'object', 'tma_mle: initial (p0, v), m and m/s'),
    MAX_ITERATIONS,
    Option('xtol', 1e-10, 'positive', 'tma_mle: relative step tolerance'),
    Option('dtol', 1e-3, 'positive', 'tma_mle: step tolerance in standard deviations'),
)

#: Default options shared by every TMA estimator (see :data:`TMA_OPTIONS`).
DEFAULTS = {o.name: o.default for o in TMA_OPTIONS[:5]}

#: Deprecated name of :class:`~bearing_loc_ros.core.fix.FixResult` (TMA results are
#: FixResults with the velocity fields set).
TmaResult = FixResult


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


def _prepare(bearings, times, speed, speed_reference):
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
    if np.any(np.diff(t, axis=1) < 0):
        raise ValueError('t: observation times must be non-decreasing')
    try:
        vc = np.broadcast_to(np.asarray(speed, dtype=float), (M,)).copy()
    except ValueError:
        raise ValueError(f'speed: expected a scalar or ({M},) array') from None
    if not np.all(np.isfinite(vc)) or np.any(vc <= 0):
        raise ValueError('speed: must be finite and > 0 (m/s)')
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
# Pseudo-linear moments (T6)-(T12) and their recursive / prefix accumulation
# --------------------------------------------------------------------------------------------

def bearing_terms(azimuth, elevation, sigma_az, sigma_el):
    """Per-bearing 3x3 terms of the pseudo-linear normal matrices (T6), (T10)-(T11), (T18).

    With h_θ = (−sin θ, cos θ, 0), h_ψ = (−sin ψ cos θ, −sin ψ sin θ, cos ψ) (the unit vectors
    normal to the line of sight u(θ, ψ) along increasing θ and ψ) and their derivatives
    h_θ' = ∂h_θ/∂θ = (−cos θ, −sin θ, 0), h_ψθ' = ∂h_ψ/∂θ = (sin ψ sin θ, −sin ψ cos θ, 0),
    h_ψψ' = ∂h_ψ/∂ψ = (−cos ψ cos θ, −cos ψ sin θ, −sin ψ):

        Ph = h_θ h_θᵀ/σ_θ² + h_ψ h_ψᵀ/σ_ψ²                       (row weights 1/σ², T7)
        Oh = h_θ' h_θ'ᵀ + (σ_θ²/σ_ψ²) h_ψθ' h_ψθ'ᵀ + h_ψψ' h_ψψ'ᵀ  (first-order E[ΔhᵀWΔh], T11)
        Qh = h_θ h_θᵀ/(σ_θ cos ψ)² + h_ψ h_ψᵀ/σ_ψ²                (constant-LOS test, T18)

    Angles in rad (ENU), σ in rad; arrays of any shape (...,) -> (..., 3, 3) each.
    """
    az = np.asarray(azimuth, dtype=float)
    el = np.asarray(elevation, dtype=float)
    st, ct, sp, cp = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    z = np.zeros_like(st)
    h_t = np.stack([-st, ct, z], axis=-1)
    h_p = np.stack([-sp * ct, -sp * st, cp], axis=-1)
    d_t = np.stack([-ct, -st, z], axis=-1)
    d_pt = np.stack([sp * st, -sp * ct, z], axis=-1)
    d_pp = np.stack([-cp * ct, -cp * st, -sp], axis=-1)
    w_t = 1.0 / np.asarray(sigma_az, dtype=float) ** 2
    w_p = 1.0 / np.asarray(sigma_el, dtype=float) ** 2

    def outer(a, b):
        return a[..., :, None] * b[..., None, :]

    Ph = w_t[..., None, None] * outer(h_t, h_t) + w_p[..., None, None] * outer(h_p, h_p)
    Oh = (outer(d_t, d_t) + (w_p / w_t)[..., None, None] * outer(d_pt, d_pt)
          + outer(d_pp, d_pp))
    Qh = ((w_t / cp ** 2)[..., None, None] * outer(h_t, h_t)
          + w_p[..., None, None] * outer(h_p, h_p))
    return Ph, Oh, Qh


@dataclass
class TmaSums:
    """Sufficient statistics of the pseudo-linear estimators, for any leading shape S.

    Moments with τ_r = t_k − t_ref (s): A_j = Σ τ_r^j Ph_k, B_j = Σ τ_r^j Oh_k (j = 0, 1, 2),
    Q = Σ Qh_k (see :func:`bearing_terms`); observer sums T1 = Σ τ_r, T2 = Σ τ_r²,
    O1 = Σ (o_k − o_ref), TO = Σ τ_r (o_k − o_ref); the first bearing of the window
    (t0, e0 = u(θ_0, ψ_0), o0, its Oh as ``B_first``) and the last (t_last, o_last).
    Adding a bearing adds its terms (Lin et al. sec. 3.2.1: P(k+1) = P(k) + ..., (T13)); the
    paper's P, Ω follow in O(1) from :meth:`paper_matrices`.
    """

    n: np.ndarray
    t_ref: np.ndarray
    o_ref: np.ndarray
    t0: np.ndarray
    e0: np.ndarray
    o0: np.ndarray
    B_first: np.ndarray
    t_last: np.ndarray
    o_last: np.ndarray
    A0: np.ndarray
    A1: np.ndarray
    A2: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    Q: np.ndarray
    T1: np.ndarray
    T2: np.ndarray
    O1: np.ndarray
    TO: np.ndarray

    def moments_at_t0(self):
        """(A0, A1, A2, B0, B1, B2) re-referenced to τ = t − t0 (shift c = t_ref − t0).

        Σ (τ + c)² X = A2 + 2c A1 + c² A0 and Σ (τ + c) X = A1 + c A0.
        """
        c = (self.t_ref - self.t0)[..., None, None]
        A1 = self.A1 + c * self.A0
        A2 = self.A2 + 2 * c * self.A1 + c * c * self.A0
        B1 = self.B1 + c * self.B0
        B2 = self.B2 + 2 * c * self.B1 + c * c * self.B0
        return self.A0, A1, A2, self.B0, B1, B2

    def paper_matrices(self):
        """The paper's P = AᵀWA and Ω (Lin et al. sec. 3.2.1; (T10)-(T11)), shape (S, 4, 4).

        Rows of A: a_k = [τ_k h_kᵀ, h_k·e0] (T9), k ≥ 1 (bearing 0 defines e0 and is taken as
        exact, as in the paper), i.e. P = L P6 Lᵀ with L = [[I3, 0], [0, e0ᵀ]] and
        P6 = [[A2, A1], [A1, A0]]; Ω likewise from the B moments without bearing 0.
        """
        A0, A1, A2, B0, B1, B2 = self.moments_at_t0()
        B0 = B0 - self.B_first
        e0 = self.e0
        return _lift(A0, A1, A2, e0), _lift(B0, B1, B2, e0)

    def observer_velocity(self):
        """v_o (T2) from the observer sums (shift invariant), m/s; 0 if one time only."""
        den = self.n * self.T2 - self.T1 ** 2
        num = self.n[..., None] * self.TO - self.T1[..., None] * self.O1
        good = den > 1e-12 * np.maximum(self.n * self.T2, 1e-300)
        return np.where(good[..., None], num / np.where(good, den, 1.0)[..., None], 0.0)


def _lift(X0, X1, X2, e0):
    """[[X2, X1 e0], [e0ᵀ X1, e0ᵀ X0 e0]] (S, 4, 4): the paper's 4x4 from the 6x6 moments."""
    S = X0.shape[:-2]
    out = np.empty(S + (4, 4))
    out[..., :3, :3] = X2
    c = np.einsum('...ij,...j->...i', X1, e0)
    out[..., :3, 3] = c
    out[..., 3, :3] = c
    out[..., 3, 3] = np.einsum('...i,...ij,...j->...', e0, X0, e0)
    return out


def prefix_sums(bearings, times):
    """:class:`TmaSums` of every prefix of every problem: leading shape (M, K).

    Entry [m, k] summarises bearings 0..k of problem m (t_ref = t0 = times[m, 0]), so the
    running ple/ctls estimate after every bearing costs one cumulative sum (used by the
    benchmark; (T13) in batch form).
    """
    t = np.broadcast_to(np.asarray(times, dtype=float), bearings.azimuth.shape)
    M, K = t.shape
    tau = t - t[:, :1]
    Ph, Oh, Qh = bearing_terms(bearings.azimuth, bearings.elevation, bearings.sigma_az,
                               bearings.sigma_el)
    w1 = tau[..., None, None]
    w2 = w1 * w1
    cs = np.cumsum
    o = bearings.positions - bearings.positions[:, :1]
    e0 = los_vector(bearings.azimuth[:, 0], bearings.elevation[:, 0])
    return TmaSums(
        n=np.broadcast_to(np.arange(1, K + 1, dtype=float), (M, K)).copy(),
        t_ref=np.repeat(t[:, :1], K, axis=1), o_ref=np.repeat(bearings.positions[:, :1], K, 1),
        t0=np.repeat(t[:, :1], K, axis=1), e0=np.repeat(e0[:, None], K, axis=1),
        o0=np.repeat(bearings.positions[:, :1], K, axis=1),
        B_first=np.repeat(Oh[:, :1], K, axis=1),
        t_last=t.copy(), o_last=bearings.positions.copy(),
        A0=cs(Ph, axis=1), A1=cs(w1 * Ph, axis=1), A2=cs(w2 * Ph, axis=1),
        B0=cs(Oh, axis=1), B1=cs(w1 * Oh, axis=1), B2=cs(w2 * Oh, axis=1),
        Q=cs(Qh, axis=1), T1=cs(tau, axis=1), T2=cs(tau * tau, axis=1),
        O1=cs(o, axis=1), TO=cs(tau[..., None] * o, axis=1))


def batch_sums(bearings, times):
    """:class:`TmaSums` of each whole problem (leading shape (M,)): the batch recomputation."""
    t = np.broadcast_to(np.asarray(times, dtype=float), bearings.azimuth.shape)
    tau = t - t[:, :1]
    Ph, Oh, Qh = bearing_terms(bearings.azimuth, bearings.elevation, bearings.sigma_az,
                               bearings.sigma_el)
    w1 = tau[..., None, None]
    o = bearings.positions - bearings.positions[:, :1]
    return TmaSums(
        n=np.full(t.shape[0], float(t.shape[1])), t_ref=t[:, 0].copy(),
        o_ref=bearings.positions[:, 0].copy(), t0=t[:, 0].copy(),
        e0=los_vector(bearings.azimuth[:, 0], bearings.elevation[:, 0]),
        o0=bearings.positions[:, 0].copy(), B_first=Oh[:, 0].copy(), t_last=t[:, -1].copy(),
        o_last=bearings.positions[:, -1].copy(),
        A0=Ph.sum(1), A1=(w1 * Ph).sum(1), A2=(w1 * w1 * Ph).sum(1),
        B0=Oh.sum(1), B1=(w1 * Oh).sum(1), B2=(w1 * w1 * Oh).sum(1), Q=Qh.sum(1),
        T1=tau.sum(1), T2=(tau * tau).sum(1), O1=o.sum(1),
        TO=np.einsum('mk,mki->mi', tau, o))


# --------------------------------------------------------------------------------------------
# Closed forms: ple (Lin et al. sec. 3.1) and ctls (sec. 3.2) from the sums
# --------------------------------------------------------------------------------------------

def _smallest_generalized_eigvec(P, Om, rcond=1e-13):
    """Eigenvector z of P z = λ Ω z for the smallest λ (batched, P, Ω symmetric, Ω > 0).

    Diagonal equilibration D = sqrt(diag Ω), then Ω̃^{-1/2} P̃ Ω̃^{-1/2} y = λ y and
    z = D⁻¹ Ω̃^{-1/2} y. Returns z (..., n), λ (...), ok (...) (False where Ω is singular).
    """
    d = np.sqrt(np.abs(np.diagonal(Om, axis1=-2, axis2=-1)))
    okd = np.all(d > 0, axis=-1) & np.all(np.isfinite(P), axis=(-2, -1)) \
        & np.all(np.isfinite(Om), axis=(-2, -1))
    d = np.where(okd[..., None], d, 1.0)
    Dinv = 1.0 / d
    Ot = Om * Dinv[..., :, None] * Dinv[..., None, :]
    Pt = P * Dinv[..., :, None] * Dinv[..., None, :]
    Ot = np.where(okd[..., None, None], Ot, np.eye(P.shape[-1]))
    Pt = np.where(okd[..., None, None], Pt, np.eye(P.shape[-1]))
    w, V = np.linalg.eigh(Ot)
    ok = okd & (w[..., 0] > rcond * w[..., -1])
    w = np.where(ok[..., None], w, 1.0)
    R = (V / np.sqrt(w)[..., None, :]) @ np.swapaxes(V, -1, -2)
    lam, Y = np.linalg.eigh(R @ Pt @ R)
    z = np.einsum('...ij,...j->...i', R, Y[..., :, 0]) * Dinv
    return z, lam[..., 0], ok


def _scale_from_speed(b, speed, v_o, speed_reference):
    """Initial range r0 from the speed prior (T8): |r0 b| = v_c or |r0 b + v_o| = v_c.

    'relative': r0 = v_c / |b| (Lin et al. sec. 3.1). 'ground': the positive root of
    |b|² r0² + 2 (b·v_o) r0 + |v_o|² − v_c² = 0. NaN where no positive root exists.
    """
    bb = np.sum(b * b, axis=-1)
    with np.errstate(divide='ignore', invalid='ignore'):
        if speed_reference == 'relative':
            r0 = speed / np.sqrt(bb)
        else:
            bv = np.sum(b * v_o, axis=-1)
            disc = bv * bv - bb * (np.sum(v_o * v_o, axis=-1) - speed ** 2)
            r0 = (-bv + np.sqrt(np.where(disc >= 0, disc, np.nan))) / bb
    return np.where(np.isfinite(r0) & (r0 > 0), r0, np.nan)


def estimate_from_sums(sums, method, speed, speed_reference='relative', min_bearings=3,
                       alpha=1e-3):
    """Closed-form ple/ctls/ctls6 relative state (p0, v) from :class:`TmaSums` of shape S.

    ple (T7): b = −(HᵀWH)⁻¹ HᵀW y = −A2⁻¹ A1 e0 (Lin et al. sec. 3.1).
    ctls (T12): z = [b; ζ] the generalized eigenvector of (P, Ω) for the smallest generalized
    eigenvalue, b ← b/ζ (Lin et al. sec. 3.2.1). ctls6 (T12b): z = (v, p0)/r0 from (P6, Ω6),
    e0 ← the direction of z's p0 part. Then r0 from the speed prior (T8), p0 = r0 e0,
    v = r0 b. Gates (T18): n < ``min_bearings`` or a constant line of sight (λ_min(Q) below
    the chi-square (2n − 2) quantile 1 − ``alpha``) -> 'unobservable'. ``speed`` (m/s)
    broadcasts against S. The CRLB range gate needs the bearings: see :func:`tma_ple`.

    Returns (p0 (S, 3) m, v (S, 3) m/s, status (S,) str, reason (S,) str); NaN unless ok.
    """
    S = sums.n.shape
    status = np.full(S, STATUS_OK, dtype=object)
    reason = np.full(S, '', dtype=object)
    n = sums.n
    few = (n < max(min_bearings, 3)) | ~(sums.t_last > sums.t0)
    status[few] = STATUS_UNOBSERVABLE
    reason[few] = (f'too few bearings: 3-D TMA needs at least {max(min_bearings, 3)} '
                   'at two or more times')
    lam_q = np.linalg.eigvalsh(sums.Q)[..., 0]
    dof = np.maximum(2 * n - 2, 1)
    flat = ~few & (lam_q <= chdtri(dof, alpha))     # chi-square quantile 1 − alpha
    status[flat] = STATUS_UNOBSERVABLE
    for idx in zip(*np.nonzero(flat)):
        reason[idx] = ('no significant bearing change over the window '
                       f'(chi2={max(lam_q[idx], 0.0):.3g} for {int(dof[idx])} dof): constant '
                       'line of sight, e.g. a collision course, gives no range')
    A0, A1, A2, B0, B1, B2 = sums.moments_at_t0()
    e0 = sums.e0
    if method == 'ple':
        w = np.linalg.eigvalsh(A2)
        good = (w[..., 0] > 1e-12 * w[..., -1]) & (w[..., -1] > 0)
        A2s = np.where(good[..., None, None], A2, np.eye(3))
        b = -np.linalg.solve(A2s, np.einsum('...ij,...j->...i', A1, e0)[..., None])[..., 0]
    elif method == 'ctls':
        P, Om = sums.paper_matrices()
        z, _, good = _smallest_generalized_eigvec(P, Om)
        with np.errstate(divide='ignore', invalid='ignore'):
            b = z[..., :3] / z[..., 3:]
    elif method == 'ctls6':
        P6 = np.concatenate([np.concatenate([A2, A1], -1), np.concatenate([A1, A0], -1)], -2)
        O6 = np.concatenate([np.concatenate([B2, B1], -1), np.concatenate([B1, B0], -1)], -2)
        z, _, good = _smallest_generalized_eigvec(P6, O6)
        # z = (v, p0)/r0 up to sign: the target is in front of the first bearing.
        sgn = np.where(np.einsum('...i,...i->...', z[..., 3:], e0) < 0, -1.0, 1.0)
        z = z * sgn[..., None]
        nz = np.linalg.norm(z[..., 3:], axis=-1)
        with np.errstate(divide='ignore', invalid='ignore'):
            b = z[..., :3] / nz[..., None]
            e0 = z[..., 3:] / nz[..., None]
    else:
        raise ValueError(f'method: unknown closed-form TMA estimator {method!r}')
    v_o = sums.observer_velocity()
    r0 = _scale_from_speed(b, np.asarray(speed, dtype=float), v_o, speed_reference)
    bad = (status == STATUS_OK) & ~(good & np.isfinite(r0))
    status[bad] = STATUS_DEGENERATE
    reason[bad] = (f'{method}: singular pseudo-linear system or no positive range '
                   'matching the speed prior')
    p0 = r0[..., None] * e0
    v = r0[..., None] * b
    nok = status != STATUS_OK
    p0[nok] = np.nan
    v[nok] = np.nan
    return p0, v, status, reason


# --------------------------------------------------------------------------------------------
# Fisher information and constrained CRLB (T14)-(T15)
# --------------------------------------------------------------------------------------------

def fisher_terms(p0, v, tau, delta, sigma_az, sigma_el):
    """Per-bearing Fisher information (M, K, 6, 6) of x = (p0, v) (T14).

    F_k = G_kᵀ diag(σ_θ⁻², σ_ψ⁻²) G_k with G_k = [∇θ; ∇ψ](p_k) · [I3, τ_k I3], p_k from (T3),
    ∇θ, ∇ψ from :func:`bearing_loc_ros.core.crlb.angle_jacobians` (Zong & Cui 2015 eqs. (6)-(8),
    Lin et al. sec. 3.3). Units: x in m and m/s.
    """
    p0 = np.asarray(p0, dtype=float)
    v = np.asarray(v, dtype=float)
    tau = np.asarray(tau, dtype=float)
    d = p0[:, None, :] + v[:, None, :] * tau[..., None] - delta
    # angle_jacobians differentiates the angles of (target − station): target 0, station −p_k.
    g_t, g_p = angle_jacobians(np.zeros((d.shape[0], 3)), -d)
    G = np.stack([g_t, g_p], axis=-2)                          # (M, K, 2, 3)
    G6 = np.concatenate([G, G * tau[..., None, None]], axis=-1)  # (M, K, 2, 6)
    w = np.stack([1.0 / np.asarray(sigma_az) ** 2, 1.0 / np.asarray(sigma_el) ** 2], axis=-1)
    return np.einsum('mkai,mka,mkaj->mkij', G6, w, G6)


def constraint_gradient(v, v_o, speed_reference='relative'):
    """Gradient (…, 6) of the speed constraint (T5) c(x) = |v (+ v_o)|² − v_c² in x = (p0, v)."""
    g = np.zeros(np.shape(v)[:-1] + (6,))
    g[..., 3:] = 2.0 * (np.asarray(v) + (np.asarray(v_o) if speed_reference == 'ground'
                                         else 0.0))
    return g


def constrained_crlb(J, grad):
    """Constrained CRLB (Stoica & Ng 1998) C = U (Uᵀ J U)⁻¹ Uᵀ (T15), shape (…, 6, 6).

    U (…, 6, 5) is an orthonormal basis of the null space of the constraint gradient ``grad``
    (…, 6) (broadcast to J's leading shape); J the Fisher information (…, 6, 6). inf where
    UᵀJU is singular (unobservable).
    """
    J = np.asarray(J, dtype=float)
    g = np.broadcast_to(np.asarray(grad, dtype=float), J.shape[:-1])
    Qm, _ = np.linalg.qr(g[..., :, None], mode='complete')
    U = Qm[..., :, 1:]
    red = np.swapaxes(U, -1, -2) @ J @ U
    inv = safe_inverse(red)
    out = np.full(J.shape, np.inf)
    fin = np.all(np.isfinite(inv), axis=(-2, -1))
    out[fin] = U[fin] @ inv[fin] @ np.swapaxes(U[fin], -1, -2)
    return out


def state_transform(tau_last):
    """T (…, 6, 6) mapping x = (p0, v) to the target state (position, velocity) at τ (T1)."""
    tau_last = np.asarray(tau_last, dtype=float)
    T = np.broadcast_to(np.eye(6), tau_last.shape + (6, 6)).copy()
    T[..., 0, 3] = T[..., 1, 4] = T[..., 2, 5] = tau_last
    return T


def tma_crlb(bearings, times, p0, v, speed_reference='relative'):
    """Constrained CRLB of the relative state x = (p0, v), (M, 6, 6), at a given state.

    Geometry (observer positions, times, σ) from ``bearings``/``times``; the measured angles
    are not used. For the target state at time τ use T C Tᵀ with :func:`state_transform`
    (v_o is known, so the target velocity has the covariance of v). (T14)-(T15).
    """
    t = np.broadcast_to(np.asarray(times, dtype=float), bearings.azimuth.shape)
    tau = t - t[:, :1]
    v_o, delta = observer_track(tau, bearings.positions)
    p0 = np.broadcast_to(np.asarray(p0, dtype=float), (bearings.M, 3))
    v = np.broadcast_to(np.asarray(v, dtype=float), (bearings.M, 3))
    J = fisher_terms(p0, v, tau, delta, bearings.sigma_az, bearings.sigma_el).sum(1)
    return constrained_crlb(J, constraint_gradient(v, v_o, speed_reference))


# --------------------------------------------------------------------------------------------
# Estimators
# --------------------------------------------------------------------------------------------

def _finish(method, data, p0, v, status, reason, iterations, converged, opts):
    """Target state (T1), covariance (T15)-(T16), range gate (T18); NaN if unusable."""
    M = data.M
    tau_l = data.tau[:, -1]
    status = np.asarray(status, dtype=object).copy()
    reason = np.asarray(reason, dtype=object).copy()
    good = np.isin(status, (STATUS_OK, STATUS_MAX_ITERATIONS)) \
        & np.all(np.isfinite(p0), -1) & np.all(np.isfinite(v), -1)
    cov = np.full((M, 6, 6), np.inf)
    d_last = p0 + v * tau_l[:, None] - data.delta[:, -1]
    rng = np.linalg.norm(d_last, axis=-1)
    if opts['covariance'] and np.any(good):
        g = np.nonzero(good)[0]
        J = fisher_terms(p0[g], v[g], data.tau[g], data.delta[g], data.s_az[g],
                         data.s_el[g]).sum(1)
        C = constrained_crlb(J, constraint_gradient(v[g], data.v_o[g],
                                                    opts['speed_reference']))
        T = state_transform(tau_l[g])
        with np.errstate(invalid='ignore'):
            Cx = T @ C @ np.swapaxes(T, -1, -2)
        fin = np.all(np.isfinite(Cx), axis=(-2, -1))
        u = d_last[g] / rng[g, None]
        var_r = np.einsum('mi,mij,mj->m', u, np.where(fin[:, None, None], Cx[:, :3, :3], 0),
                          u)
        ratio = np.where(fin, np.sqrt(np.maximum(var_r, 0)) / rng[g], np.inf)
        gate = ratio > opts['max_range_ratio']
        cov[g] = Cx
        for i in np.nonzero(gate)[0]:
            m = g[i]
            status[m] = STATUS_UNOBSERVABLE
            reason[m] = (f'range not resolved: CRLB range std is {100 * ratio[i]:.3g}% of the '
                         f'range (limit {100 * opts["max_range_ratio"]:.3g}%)')
            good[m] = False
    pos0 = data.obs[:, 0] + p0
    vel = v + data.v_o
    pos = pos0 + vel * tau_l[:, None]
    for arr in (pos0, vel, pos, p0, v):
        arr[~good] = np.nan
    rng = np.where(good, rng, np.nan)
    cov[~good] = np.inf
    converged = np.asarray(converged, dtype=bool) & good
    return FixResult(pos, cov, np.asarray(iterations, dtype=int), converged,
                     status.astype(str), 'tma_' + method, velocity=vel, t=data.t0 + tau_l,
                     t0=data.t0.copy(), position0=pos0, relative_position0=p0,
                     relative_velocity=v, observer_velocity=data.v_o.copy(), range=rng,
                     reason=reason.astype(str))


def _options(options, fn=None):
    """Options merged over the defaults of :data:`TMA_OPTIONS`, each value validated."""
    return (fn or tma_mle).spec.parse(options)


def _closed_form(method, bearings, times, speed, options, fn):
    opts = _options(options, fn)
    data = _prepare(bearings, times, speed, opts['speed_reference'])
    sums = batch_sums(bearings, times)
    p0, v, status, reason = estimate_from_sums(sums, method, data.speed,
                                               opts['speed_reference'], opts['min_bearings'],
                                               opts['alpha'])
    M = data.M
    return data, p0, v, status, reason, _finish(
        method, data, p0.copy(), v.copy(), status, reason, np.zeros(M, int),
        status == STATUS_OK, opts)


@declare('tma_ple', TMA, TMA_OPTIONS, BEARING_SIGMA, inputs=('times', 'speed'))
def tma_ple(bearings, times, speed, **options):
    """Pseudo-linear least squares TMA (Lin et al. sec. 3.1), (T6)-(T8).

    With p0 = r0 e0 (e0 the line of sight of the first bearing, taken as exact) and
    b = v / r0 (1/s), every later bearing gives two equations τ_k h·b = −h·e0 (h = h_θ, h_ψ
    at the measured angles, T6), H b = −y; b = −(HᵀWH)⁻¹HᵀWy with W = diag(σ⁻²) (T7; the
    paper's unweighted form for equal σ); r0 = v_c/|b|, p0 = r0 e0, v = r0 b (T8).
    Biased: H holds the noisy angles (E{b̂ − b} ≠ 0, Lin et al. sec. 3.1).

    Args: ``bearings`` BearingSet (M, K) of observer positions and ENU angles (every bearing
    with elevation), ``times`` (K,) or (M, K) s, non-decreasing, ``speed`` v_c m/s (scalar or
    (M,)). Options: ``speed_reference`` ('relative' | 'ground', T5), ``min_bearings``,
    ``alpha`` (constant-LOS test level), ``max_range_ratio`` (CRLB range gate),
    ``covariance`` (compute the CRLB). Returns a FixResult with the velocity fields (core/fix.py).
    """
    return _closed_form('ple', bearings, times, speed, options, tma_ple)[-1]


@declare('tma_ctls', TMA, TMA_OPTIONS, BEARING_SIGMA, inputs=('times', 'speed'))
def tma_ctls(bearings, times, speed, **options):
    """Constrained total least squares TMA (Lin et al. sec. 3.2), (T9)-(T13).

    Augmented matrix A = [H, y] (rows a_k = [τ_k hᵀ, h·e0], T9), P = AᵀWA (T10),
    Ω = E[ΔAᵀWΔA] to first order in the angle noise (T11; bearing 0 exact, as in the paper).
    min zᵀPz subject to zᵀΩz = 1 gives P z = λ Ω z: z is the generalized eigenvector for the
    smallest λ (T12), b = z[:3]/z[3]; then (T8). Asymptotically unbiased (sec. 3.2.2).
    P and Ω are sums over bearings: :class:`TmaAccumulator` updates them in O(1) (T13).
    Same arguments and options as :func:`tma_ple`.
    """
    return _closed_form('ctls', bearings, times, speed, options, tma_ctls)[-1]


@declare('tma_ctls6', TMA, TMA_OPTIONS, BEARING_SIGMA, inputs=('times', 'speed'))
def tma_ctls6(bearings, times, speed, **options):
    """CTLS on the full homogeneous system, without the initial-bearing anchor (T12b).

    Not in Lin et al.: every bearing (the first one included) gives h·(p0 + v τ_k) = 0, rows
    g_k = [τ_k hᵀ, hᵀ] in z = (v, p0)/r0. P6 = Σ w g gᵀ = [[A2, A1], [A1, A0]] and
    Ω6 = [[B2, B1], [B1, B0]] (first-order noise of the rows, T11); z is the generalized
    eigenvector of (P6, Ω6) for the smallest eigenvalue, signed so that p0·e0 > 0 and scaled
    by the speed prior (T8). The paper's CTLS fixes p0 ∥ e0 from one noisy bearing, an error
    that no later bearing averages out; here every bearing counts alike (see the benchmark in
    docs/tma.md). Same recursive sums, arguments and options as :func:`tma_ctls`.
    """
    return _closed_form('ctls6', bearings, times, speed, options, tma_ctls6)[-1]


def _tangent_basis(s):
    """Orthonormal basis E (M, 3, 2) of the plane normal to unit vectors s (M, 3)."""
    a = np.where((np.abs(s[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = a - np.sum(a * s, -1, keepdims=True) * s
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(s, e1)
    return np.stack([e1, e2], axis=-1)


def _residuals(data, p0, v):
    """Whitened residuals (M, K, 2) = [wrap(θ̂ − θ)/σ_θ, (ψ̂ − ψ)/σ_ψ] and d = p_k (T3)-(T4)."""
    d = p0[:, None, :] + v[:, None, :] * data.tau[..., None] - data.delta
    az, el = azimuth_elevation(d)
    e = np.stack([wrap_angle(az - data.az) / data.s_az, (el - data.el) / data.s_el], -1)
    return e, d


def _mle_start(data, sums, opts, methods=('ctls', 'ctls6', 'ple')):
    """Start of :func:`tma_mle`: of the closed forms, the one with the lowest ML cost (T17).

    Returns (p0, v, status, reason); status/reason of the first method where none is ok.
    """
    best = None
    best_cost = np.full(data.M, np.inf)
    for m in methods:
        p0, v, st, rs = estimate_from_sums(sums, m, data.speed, opts['speed_reference'],
                                           opts['min_bearings'], opts['alpha'])
        if best is None:
            best = [p0.copy(), v.copy(), st.copy(), rs.copy()]
        ok = st == STATUS_OK
        if np.any(ok):
            e, _ = _residuals(data, np.where(ok[:, None], p0, 0.0),
                              np.where(ok[:, None], v, 0.0))
            c = np.where(ok, np.sum(e * e, axis=(1, 2)), np.inf)
            c = np.where(np.isfinite(c), c, np.inf)
            use = c < best_cost
            best_cost[use] = c[use]
            for arr, new in zip(best, (p0, v, st, rs)):
                arr[use] = new[use]
    return tuple(best)


@declare('tma_mle', TMA, TMA_OPTIONS, BEARING_SIGMA, inputs=('times', 'speed'))
def tma_mle(bearings, times, speed, **options):
    """Maximum likelihood TMA with the speed constraint, Gauss-Newton/Levenberg-Marquardt (T17).

    Minimises Σ_k wrap(θ̂_k − θ_k)²/σ_θk² + (ψ̂_k − ψ_k)²/σ_ψk² over x = (p0, v) with the angles
    θ̂, ψ̂ of p_k = p0 + v τ_k − δ_k (T3, the observer positions are used exactly) subject to
    (T5). The constraint is kept exactly by the parametrisation v = v_c s (− v_o for
    'ground') with s a unit vector updated on its tangent plane, s ← normalise(s + E δ):
    5 unknowns (p0, δ). Marquardt damping with Nielsen's gain-ratio update: a step is
    accepted only if it lowers the cost, so the result is never worse than the start and
    never NaN. Converged when the step is shorter than ``dtol`` (1e-3) standard deviations
    (hᵀJᵀJh < dtol²: far below the statistical error) or ``xtol`` (1e-10) relative.
    Start: ``start`` = (p0, v) arrays,
    else the closed form (:func:`tma_ctls`, :func:`tma_ctls6`, :func:`tma_ple`) with the lowest
    cost.
    Efficient (reaches the CRLB (T15)) at small noise: the reference of the benchmark.
    Options as :func:`tma_ple` plus ``start``, ``max_iterations`` (50), ``dtol``, ``xtol``.
    Status max_iterations: not converged, estimate kept (cost reduced).
    """
    opts = _options(options, tma_mle)
    start = opts.pop('start', None)
    max_it = int(opts.pop('max_iterations', 50))
    xtol = float(opts.pop('xtol', 1e-10))
    dtol = float(opts.pop('dtol', 1e-3))
    data = _prepare(bearings, times, speed, opts['speed_reference'])
    if start is None:
        sums = batch_sums(bearings, times)
        p0, v, status, reason = _mle_start(data, sums, opts)
    else:
        p0 = np.array(np.broadcast_to(np.asarray(start[0], float), (data.M, 3)))
        v = np.array(np.broadcast_to(np.asarray(start[1], float), (data.M, 3)))
        status = np.full(data.M, STATUS_OK, dtype=object)
        reason = np.full(data.M, '', dtype=object)
        bad = ~(np.all(np.isfinite(p0), -1) & np.all(np.isfinite(v), -1))
        status[bad], reason[bad] = STATUS_DEGENERATE, 'start: non-finite initial state'
    M = data.M
    vc = data.speed
    off = data.v_o if opts['speed_reference'] == 'ground' else np.zeros((M, 3))
    active = status == STATUS_OK
    # Project the start onto the constraint manifold (T5).
    s = np.where(active[:, None], v + off, [1.0, 0.0, 0.0])
    s = s / np.where(np.linalg.norm(s, axis=-1) > 0, np.linalg.norm(s, axis=-1), 1.0)[:, None]
    p0 = np.where(active[:, None], p0, 0.0)
    v = vc[:, None] * s - off
    e, d = _residuals(data, p0, v)
    cost = np.sum(e * e, axis=(1, 2))
    mu = np.full(M, 1e-9)
    nu = np.full(M, 2.0)
    iters = np.zeros(M, dtype=int)
    converged = np.zeros(M, dtype=bool)
    running = active & np.isfinite(cost)
    for _ in range(max_it):
        if not np.any(running):
            break
        r = np.nonzero(running)[0]
        iters[r] += 1
        E = _tangent_basis(s[r])
        g_t, g_p = angle_jacobians(np.zeros((len(r), 3)), -d[r])
        G = np.stack([g_t / data.s_az[r][..., None], g_p / data.s_el[r][..., None]], -2)
        Jv = (G @ (vc[r, None, None] * E)[:, None]) * data.tau[r][..., None, None]
        J = np.concatenate([G, Jv], axis=-1).reshape(len(r), -1, 5)     # (m, 2K, 5)
        Jt = np.swapaxes(J, -1, -2)
        JtJ = Jt @ J
        Jte = (Jt @ e[r].reshape(len(r), -1, 1))[..., 0]
        dg = np.diagonal(JtJ, axis1=1, axis2=2)
        dg = np.where(dg > 0, dg, 1.0)
        A = JtJ + (mu[r, None] * dg)[:, :, None] * np.eye(5)
        try:
            step = -np.linalg.solve(A, Jte[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.stack([-np.linalg.lstsq(a, b_, rcond=None)[0]
                             for a, b_ in zip(A, Jte)])
        p_new = p0[r] + step[:, :3]
        s_new = s[r] + np.einsum('mij,mj->mi', E, step[:, 3:])
        s_new /= np.linalg.norm(s_new, axis=-1, keepdims=True)
        v_new = vc[r, None] * s_new - off[r]
        sub = _Data(data.tau[r], data.t0[r], data.obs[r], data.az[r], data.el[r],
                    data.s_az[r], data.s_el[r], vc[r], data.v_o[r], data.delta[r])
        e_new, d_new = _residuals(sub, p_new, v_new)
        c_new = np.sum(e_new * e_new, axis=(1, 2))
        # Gain ratio ρ = actual / predicted decrease of the cost |e + J h|² (Nielsen 1999).
        dec = np.einsum('mi,mij,mj->m', step, JtJ, step)
        pred = -2.0 * np.sum(step * Jte, -1) - dec
        acc = np.isfinite(c_new) & (c_new < cost[r])
        with np.errstate(divide='ignore', invalid='ignore'):
            rho = np.where(pred > 0, (cost[r] - c_new) / pred, 0.0)
        ra = r[acc]
        p0[ra], s[ra], v[ra] = p_new[acc], s_new[acc], v_new[acc]
        e[ra], d[ra], cost[ra] = e_new[acc], d_new[acc], c_new[acc]
        mu[ra] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * np.clip(rho[acc], 0, 1) - 1.0) ** 3)
        mu[ra] = np.maximum(mu[ra], 1e-15)
        nu[ra] = 2.0
        rj = r[~acc]
        mu[rj] *= nu[rj]
        nu[rj] *= 2.0
        rel = np.maximum(np.linalg.norm(step[:, :3], axis=-1)
                         / np.maximum(np.linalg.norm(p_new, axis=-1), 1e-300),
                         np.linalg.norm(step[:, 3:], axis=-1))
        # Converged when the step is below dtol standard deviations (its Mahalanobis length
        # in the Fisher information JᵀJ) or below xtol relative; a rejected step that small
        # also ends the iteration (rounding), the current estimate is kept.
        done = (dec < dtol ** 2) | (rel < xtol) | (mu[r] > 1e12)
        converged[r[done]] = True
        running[r[done]] = False
    status = status.copy()
    reason = reason.copy()
    nc = active & ~converged
    status[nc] = STATUS_MAX_ITERATIONS
    reason[nc] = f'mle: not converged in {max_it} iterations (estimate kept, cost reduced)'
    p0 = np.where(active[:, None], p0, np.nan)
    v = np.where(active[:, None], v, np.nan)
    return _finish('mle', data, p0, v, status, reason, iters, converged, opts)


#: The TMA estimators by their registry names (core.registry, the fusion node and the CLI).
TMA_FUNCTIONS = {
    'tma_ple': tma_ple,
    'tma_ctls': tma_ctls,
    'tma_ctls6': tma_ctls6,
    'tma_mle': tma_mle,
}

_CLOSED_FORMS = {tma_ple: 'ple', tma_ctls: 'ctls', tma_ctls6: 'ctls6'}

#: Deprecated: the same functions by their former short names (accepted for one release).
TMA_ESTIMATORS = {
    'ple': tma_ple,
    'ctls': tma_ctls,
    'ctls6': tma_ctls6,
    'mle': tma_mle,
}


def tma_function(method):
    """The TMA estimator function called ``method`` (``tma_ple`` ..., or a former short name
    ``ple`` ...); ValueError naming the choices if unknown."""
    fn = TMA_FUNCTIONS.get(method) if isinstance(method, str) else None
    if fn is None and isinstance(method, str):
        fn = TMA_ESTIMATORS.get(method)
    if fn is None:
        raise ValueError(f'method: unknown TMA estimator {method!r}; choose one of '
                         f'{sorted(TMA_FUNCTIONS)}')
    return fn


def tma(method, bearings, times, speed, **options):
    """Run TMA estimator ``method`` (see :func:`tma_function`) -> FixResult with velocity."""
    return tma_function(method)(bearings, times, speed, **options)


# --------------------------------------------------------------------------------------------
# Recursive accumulator for the fusion node (T13)
# --------------------------------------------------------------------------------------------

class TmaAccumulator:
    """Recursive P, Ω (Lin et al. sec. 3.2.1, Table 1; (T13)) over a sliding time window.

    ``add`` costs O(1): it adds the bearing's terms (:func:`bearing_terms`) to the moments of
    :class:`TmaSums` and, when ``window`` (s) is set, subtracts the terms of bearings older
    than t − window. The moments are re-summed from the stored bearings whenever as many
    bearings have been evicted as remain (amortised O(1)), which bounds rounding drift and
    re-references τ to the window start. ``estimate`` solves ple/ctls from the sums in O(1)
    (plus an O(K) vectorised CRLB for the covariance) and runs mle on the stored window.

    Args:
        speed: prior speed v_c, m/s (T5). window: None (grow forever) or seconds (> 0).
        speed_reference: 'relative' (Lin et al.) or 'ground'. Further keyword options are
        passed to the estimators (see :func:`tma_ple`).
    """

    def __init__(self, speed, window=None, speed_reference='relative', **options):
        if not (np.isfinite(speed) and speed > 0):
            raise ValueError('speed: must be finite and > 0 (m/s)')
        if window is not None and not (np.isfinite(window) and window > 0):
            raise ValueError('window: must be None or finite and > 0 (s)')
        if speed_reference not in SPEED_REFERENCES:
            raise ValueError(f'speed_reference: expected one of {SPEED_REFERENCES}')
        _options(options)
        self.speed = float(speed)
        self.window = None if window is None else float(window)
        self.speed_reference = speed_reference
        self.options = options
        self.reset()

    def reset(self):
        """Forget every bearing."""
        self._entries = deque()
        self._evicted = 0
        self._sums = None

    def __len__(self):
        return len(self._entries)

    @property
    def t_last(self):
        """Time of the newest bearing (s) or None."""
        return self._entries[-1][0] if self._entries else None

    def add(self, t, observer, azimuth, elevation, sigma_azimuth, sigma_elevation):
        """Add one bearing (t s, observer (3,) m, ENU angles rad, σ rad); O(1).

        Raises ValueError naming the field for invalid values or a time older than the
        newest bearing (out of order: the caller decides whether to reset).
        """
        t = float(t)
        o = np.asarray(observer, dtype=float).reshape(-1)
        if not np.isfinite(t):
            raise ValueError('t: non-finite observation time')
        if o.shape != (3,):
            raise ValueError('observer: expected 3 coordinates')
        if elevation is None or not np.isfinite(elevation):
            raise ValueError('elevation: 3-D TMA needs azimuth and elevation on every bearing')
        _check_bearing_fields(o[None, None], np.array([[azimuth]], float),
                              np.array([[elevation]], float),
                              np.array([[sigma_azimuth]], float),
                              np.array([[sigma_elevation]], float))
        if self._entries and t < self._entries[-1][0]:
            raise ValueError(f't: bearing at {t!r} s is older than the newest one '
                             f'({self._entries[-1][0]!r} s)')
        Ph, Oh, Qh = bearing_terms(azimuth, elevation, sigma_azimuth, sigma_elevation)
        entry = (t, o, float(azimuth), float(elevation), float(sigma_azimuth),
                 float(sigma_elevation), Ph, Oh, Qh)
        self._entries.append(entry)
        if self._sums is None:
            self._rebuild()
        else:
            self._apply(entry, +1.0)
            self._sums.t_last = np.array(t)
            self._sums.o_last = o
        if self.window is not None:
            while self._entries[0][0] < t - self.window:
                self._apply(self._entries.popleft(), -1.0)
                self._evicted += 1
            if self._evicted:
                self._set_first()
            if self._evicted >= len(self._entries):
                self._rebuild()

    def _apply(self, entry, sign):
        s = self._sums
        t, o, Ph, Oh, Qh = entry[0], entry[1], entry[6], entry[7], entry[8]
        tau = t - float(s.t_ref)
        do = o - s.o_ref
        s.n = s.n + sign
        s.A0 = s.A0 + sign * Ph
        s.A1 = s.A1 + sign * tau * Ph
        s.A2 = s.A2 + sign * tau * tau * Ph
        s.B0 = s.B0 + sign * Oh
        s.B1 = s.B1 + sign * tau * Oh
        s.B2 = s.B2 + sign * tau * tau * Oh
        s.Q = s.Q + sign * Qh
        s.T1 = s.T1 + sign * tau
        s.T2 = s.T2 + sign * tau * tau
        s.O1 = s.O1 + sign * do
        s.TO = s.TO + sign * tau * do

    def _set_first(self):
        f = self._entries[0]
        s = self._sums
        s.t0 = np.array(f[0])
        s.e0 = los_vector(f[2], f[3])
        s.o0 = f[1]
        s.B_first = f[7]

    def _rebuild(self):
        f = self._entries[0]
        z3 = np.zeros((3, 3))
        self._sums = TmaSums(
            n=np.array(0.0), t_ref=np.array(f[0]), o_ref=f[1].copy(), t0=np.array(f[0]),
            e0=los_vector(f[2], f[3]), o0=f[1], B_first=f[7],
            t_last=np.array(self._entries[-1][0]), o_last=self._entries[-1][1],
            A0=z3, A1=z3, A2=z3, B0=z3, B1=z3, B2=z3, Q=z3, T1=np.array(0.0),
            T2=np.array(0.0), O1=np.zeros(3), TO=np.zeros(3))
        for entry in self._entries:
            self._apply(entry, +1.0)
        self._evicted = 0

    def sums(self):
        """The current :class:`TmaSums` with leading shape (1,) (a copy)."""
        s = self._sums
        return TmaSums(**{k: np.asarray(getattr(s, k))[None].copy()
                          for k in TmaSums.__dataclass_fields__})

    def paper_matrices(self):
        """The paper's P(k), Ω(k) (4, 4) for the current window (Lin et al. sec. 3.2.1)."""
        P, Om = self.sums().paper_matrices()
        return P[0], Om[0]

    def bearings(self):
        """The stored window as (BearingSet with M = 1, times (1, K))."""
        e = self._entries
        bs = BearingSet.from_arrays(np.array([x[1] for x in e]), np.array([x[2] for x in e]),
                                    np.array([x[3] for x in e]), np.array([x[4] for x in e]),
                                    np.array([x[5] for x in e]), validate=False)
        return bs, np.array([[x[0] for x in e]])

    def estimate(self, method='tma_ctls', speed=None, **options):
        """Estimate for the current window with TMA estimator ``method`` -> FixResult (M = 1).

        ``method``: ``tma_ple``, ``tma_ctls``, ``tma_ctls6`` or ``tma_mle`` (the former short
        names ``ple`` ... are accepted too).

        ple/ctls come from the recursive sums in O(1) (the covariance, if requested, is an
        O(K) vectorised CRLB); mle starts from the recursive ctls (or ple) solution and
        iterates over the stored bearings. Raises ValueError when no bearing was added.
        """
        if not self._entries:
            raise ValueError('observations: no bearing added yet')
        opts = dict(self.options)
        opts.update(options)
        opts['speed_reference'] = self.speed_reference
        vc = self.speed if speed is None else float(speed)
        bs, times = self.bearings()
        fn = tma_function(method)
        fo = _options(opts, fn)
        data = _prepare(bs, times, vc, self.speed_reference)
        sums = self.sums()
        if fn is tma_mle:
            p0, v, status, reason = _mle_start(data, sums, fo)
            if status[0] != STATUS_OK:
                return _finish('mle', data, p0, v, status, reason, np.zeros(1, int),
                               np.zeros(1, bool), fo)
            return tma_mle(bs, times, vc, start=(p0, v), **opts)
        method = _CLOSED_FORMS[fn]
        p0, v, status, reason = estimate_from_sums(sums, method, np.array([vc]),
                                                   self.speed_reference, fo['min_bearings'],
                                                   fo['alpha'])
        return _finish(method, data, p0, v, status, reason, np.zeros(1, int),
                       status == STATUS_OK, fo)


# --------------------------------------------------------------------------------------------
# Simulation helper (Lin et al. sec. 4.2)
# --------------------------------------------------------------------------------------------

def simulate_tma(times, target_position, target_velocity, observer_positions, sigma_az,
                 sigma_el=None, rng=None, M=None):
    """Bearings of a constant-velocity target from a moving observer, (T1)-(T4).

    Args:
        times: (K,) s. target_position: (3,) or (M, 3) m at times[0]; target_velocity: (3,)
        or (M, 3) m/s. observer_positions: (K, 3) or (M, K, 3) m. sigma_az/sigma_el: rad
        (σ_el defaults to σ_az). rng: numpy Generator or None (noise-free). M: number of
        problems (default from the shapes).
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
        el = el + sel * rng.standard_normal((M, K))
    bs = BearingSet.from_arrays(np.broadcast_to(o, (M, K, 3)), wrap_angle(az), el, saz, sel,
                                validate=False)
    return bs, np.broadcast_to(t, (M, K)).copy()
