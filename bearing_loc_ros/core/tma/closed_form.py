"""Closed-form TMA estimators of Lin et al.: ple (sec. 3.1), ctls (sec. 3.2) and ctls6.

Each solves the pseudo-linear system of the sums (:mod:`.sums`) in closed form (T7), (T12),
(T12b) and scales it by the speed prior (T8); the constant line-of-sight test (T18) marks a
window without range information as unobservable. Conventions as
:mod:`bearing_loc_ros.core.tma`.
"""

import numpy as np

from ..estimator_spec import BEARING_SIGMA, declare, TMA
from ..fix import STATUS_DEGENERATE, STATUS_OK, STATUS_UNOBSERVABLE
from .model import prepare, TMA_OPTIONS
from .observability import finish
from .roots import resolve
from .sums import batch_sums


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

    'relative': r0 = v_c / |b| (Lin et al. sec. 3.1). 'ground': the larger positive root of
    |b|² r0² + 2 (b·v_o) r0 + |v_o|² − v_c² = 0 (the smaller one, when positive too, is the
    mirror of (T23), which the estimators weigh against it). NaN where no positive root
    exists.
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


def _prior_inconsistent(b, v_o, speed, speed_reference):
    """Reason of a speed prior that no positive range fits (T8), for one problem.

    'ground': the target's ground speed |r0 b + v_o| over r0 > 0 is at least
    |v_o − (v_o·b̂) b̂| when b·v_o < 0 (the closest approach of the line r0 b + v_o to the
    origin) and more than |v_o| otherwise; a smaller v_c has no positive root.
    """
    if speed_reference != 'ground':
        return ('speed prior inconsistent with the bearings: they show no line-of-sight '
                'motion, so no finite range gives the stated relative speed')
    nb = float(np.linalg.norm(b))
    bv = float(np.dot(b, v_o)) / nb if nb > 0 and np.isfinite(nb) else 0.0
    floor = (float(np.sqrt(max(float(np.dot(v_o, v_o)) - bv * bv, 0.0))) if bv < 0
             else float(np.linalg.norm(v_o)))
    return (f'speed prior inconsistent with the bearings: no positive range gives the target '
            f'a ground speed of {speed:.4g} m/s (the bearings need at least {floor:.4g} m/s '
            "from the observer's fitted straight track (T2)); check target_speed")


def estimate_from_sums(sums, method, speed, speed_reference='relative', min_bearings=3,
                       alpha=1e-3, closest=False):
    """Closed-form ple/ctls/ctls6 relative state (p0, v) from :class:`TmaSums` of shape S.

    ple (T7): b = −(HᵀWH)⁻¹ HᵀW y = −A2⁻¹ A1 e0 (Lin et al. sec. 3.1).
    ctls (T12): z = [b; ζ] the generalized eigenvector of (P, Ω) for the smallest generalized
    eigenvalue, b ← b/ζ (Lin et al. sec. 3.2.1). ctls6 (T12b): z = (v, p0)/r0 from (P6, Ω6),
    e0 ← the direction of z's p0 part. Then r0 from the speed prior (T8), p0 = r0 e0,
    v = r0 b. Gates (T18): n < ``min_bearings`` or a constant line of sight (λ_min(Q) below
    the chi-square (2n − 2) quantile 1 − ``alpha``) -> 'unobservable'. ``speed`` (m/s)
    broadcasts against S. The CRLB range gate needs the bearings: see :func:`tma_ple`.
    ``closest`` (a start of :func:`tma_mle` only): where a 'ground' prior has no positive
    root but b·v_o < 0, r0 = −b·v_o/|b|², the range whose ground speed is closest to v_c
    (the pseudo-linear b assumes a straight observer; a manoeuvre can move it off the prior).

    Returns (p0 (S, 3) m, v (S, 3) m/s, status (S,) str, reason (S,) str); NaN unless ok.
    """
    from scipy.special import chdtri    # here: importing scipy.special costs ~0.2 s
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
    vc = np.broadcast_to(np.asarray(speed, dtype=float), S)
    r0 = _scale_from_speed(b, vc, v_o, speed_reference)
    if closest and speed_reference == 'ground':
        with np.errstate(divide='ignore', invalid='ignore'):
            near = -np.sum(b * v_o, axis=-1) / np.sum(b * b, axis=-1)
        r0 = np.where(np.isfinite(r0), r0, np.where(np.isfinite(near) & (near > 0), near,
                                                    np.nan))
    singular = (status == STATUS_OK) & ~good
    status[singular] = STATUS_DEGENERATE
    reason[singular] = f'{method}: singular pseudo-linear system'
    noroot = (status == STATUS_OK) & ~np.isfinite(r0)
    status[noroot] = STATUS_DEGENERATE
    for idx in zip(*np.nonzero(noroot)):
        reason[idx] = _prior_inconsistent(b[idx], v_o[idx], float(vc[idx]), speed_reference)
    p0 = r0[..., None] * e0
    v = r0[..., None] * b
    nok = status != STATUS_OK
    p0[nok] = np.nan
    v[nok] = np.nan
    return p0, v, status, reason


def _closed_form(method, bearings, times, speed, options, fn):
    opts = fn.spec.parse(options)
    data = prepare(bearings, times, speed, opts['speed_reference'])
    sums = batch_sums(bearings, times)
    p0, v, status, reason = estimate_from_sums(sums, method, data.speed,
                                               opts['speed_reference'], opts['min_bearings'],
                                               opts['alpha'])
    p0, v, status, reason, _ = resolve(data, p0, v, status, reason, status == STATUS_OK,
                                       opts['speed_reference'])
    M = data.M
    return data, p0, v, status, reason, finish(
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
    With 'ground' and two positive roots of (T8) both fixes are evaluated on the bearings
    and the better one taken, or the fix is 'unobservable' when they fit alike (T23,
    :mod:`.roots`).
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
