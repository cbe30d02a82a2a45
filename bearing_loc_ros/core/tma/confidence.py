"""Confidence of a TMA fix (T19)-(T22): is its covariance, the constrained CRLB, honest?

Every TMA estimator reports the constrained CRLB (T15)-(T16) at its estimate as the
covariance. That is the error covariance of the fix only when (a) the bearings fit the
model, (b) the fix is the maximum likelihood (ML) estimate, whose covariance the CRLB is,
to well within one standard deviation, and (c) the model is close to linear over the
confidence region, so that a Gaussian ellipsoid describes it. A fix that fails one of
them keeps its state and covariance but gets the status ``low_confidence`` (never ``ok``),
with the failed test in ``reason``. Conventions as :mod:`bearing_loc_ros.core.tma`: m, m/s,
s, rad, ENU; x = (p0, v) the relative state (T1)-(T3).

(T19) Residual χ². With the whitened residuals e_k = (wrap(θ̂_k − θ_k)/σ_θ,
      (ψ̂_k − ψ_k)/σ_ψ) of the K bearings at the fix, χ² = Σ e² ~ χ²_{2K−5} at the ML
      estimate of a correct model (5 free parameters on the speed constraint). The fix fails
      when χ² exceeds the χ²_{2K−5} quantile :data:`CONSISTENCY_PROBABILITY` (0.999, the
      level of the multi-station test, docs/estimators.md): the bearings do not fit a
      constant-velocity target with these σ, so no covariance from them is honest.

(T20) Distance to the ML estimate. J (2K × 5) is the whitened Jacobian of the angles in
      the five coordinates of the constraint manifold that ``tma_mle`` uses (p0, and the
      tangent plane of the velocity direction s, v = v_c s (− v_o for ``ground``)).
      One Gauss-Newton step from the fix, h = −(JᵀJ)⁻¹Jᵀe, is to first order the way to
      the ML estimate, and D = sqrt(hᵀJᵀJh) = sqrt(eᵀJ(JᵀJ)⁻¹Jᵀe) its length in standard
      deviations of the fix's own covariance (JᵀJ is the Fisher information on the
      manifold, whose inverse is the CRLB). The fix's error is (ML − truth) − h, so its
      mean squared Mahalanobis error is about dof + D²: a fix with D > ``max_ml_distance``
      (1) fails. This is what separates the biased ``tma_ple`` and ``tma_ctls`` (D of 2 to
      50, median 13, in the paper's scenario at 100 s, errors 4-10 times the CRLB) from
      ``tma_ctls6`` (D ≤ 0.7) and ``tma_mle`` (D ≈ 0).

(T21) Range nonlinearity κ (the parameter-effects curvature of Bates & Watts 1980, applied
      to the range). The bearings see the target only through e0 = p0/r0 and b = v/r0
      (1/s, T6) with r0 = |p0|, to which they are close to linear; the range comes from the
      speed prior alone, r0(b) = v_c/|b| ('relative', T8) or the root of
      |r0 b + v_o| = v_c ('ground'). With Σ_b = B C Bᵀ the covariance of b (C the
      constrained CRLB of x, B = ∂b/∂x = [−b e0ᵀ/r0, I/r0]), g = ∂r0/∂b and
      H = ∂²r0/∂b² (implicit differentiation of F = |r0 b + v_o|² − v_c² = 0, v_o = 0 for
      'relative': g = −r0 b/|b|², H = (r0/|b|²)(3 b bᵀ/|b|² − I)), and b = b̂ + Σ_b^½ u on the
      boundary |u| = z of the confidence region of level z:

          first-order term of r0:   max |gᵀΣ_b^½ u|     = z sqrt(gᵀΣ_b g) = z σ_r0,
          second-order term:        max |½ uᵀ S u|      = ½ z² ‖S‖₂,  S = Σ_b^½ H Σ_b^½,
          κ = (second order) / (first order) = ½ z ‖S‖₂ / σ_r0   (dimensionless).

      z = :data:`REGION_Z` = sqrt(χ²₃ quantile 0.9999) = 4.59, the Mahalanobis radius of a
      confidently wrong fix. The fix fails when κ > ``max_nonlinearity`` (0.2). When Σ_b is
      elongated along b (a range resolved by the bearing rate), κ = z ν_r with
      ν_r = σ_r0/r0 (the range std over the range, the ν of docs/estimators.md seen along
      the line of sight), and the confidence interval of the range is exactly
      [r̂0/(1 + κ), r̂0/(1 − κ)] against the reported r̂0(1 ± κ): unbounded at κ ≥ 1.
      ν alone misses the worst case: a fix whose velocity is almost across the line of
      sight sits at the maximum of r0 over b's component along the line of sight, where
      the first-order term, hence ν, vanishes while the range is anything below that
      maximum; there κ → ∞ (20 s of the paper's scenario: ν = 0.06 with a Mahalanobis²
      error of 150 at 410 km instead of 135 km).

(T22) Relative speed prior and a manoeuvring observer. With ``speed_reference``
      'relative' the prior v_c = |v| is the target's speed relative to the observer's
      fitted straight-line track (T2), v_o the least-squares slope of the window's observer
      positions, not to the observer itself; a manoeuvre changes v_o with the window, and no
      one can state the speed relative to it (a 90° turn: fixes 3.5 km off with Mahalanobis²
      errors of 700, bench/tma_manoeuvre.py). The observer's velocity departs from v_o by
      about u = 4 max_k |δ̄_k| / T (T the window's span, δ̄_k the δ_k of (T2) averaged over
      runs of K/10 bearings against position noise; u = aT/2 for a constant acceleration a
      across the track); the fix fails when u exceeds
      :data:`MANOEUVRE_FRACTION` (1 %) of v_c. 'ground' has no such test: its prior is the
      target's own speed.

Calibration of the bounds (docs/tma.md, "Confidence of a fix"; ``bench/tma_seed001.py
--confidence``): ``max_ml_distance`` = 1 keeps 98-100 % of the ``tma_ctls6`` fixes that pass (T21)
and bounds their mean Mahalanobis² error near dof + 1. ``max_nonlinearity`` = 0.2: over
63 configurations (windows 20-100 s × σ 0.1°-0.3° × start 0.5-2 × the paper's), the
``ok`` fixes of ``tma_ctls6`` and ``tma_mle`` have Mahalanobis² errors above
χ²₃(0.9999) = 21.1 at a rate of 0.035-0.042 % (three seed sets, 14 000-24 000 ``ok``
fixes each), the multi-station figure (0.02-0.06 %) and 3-4 times the Gaussian 0.01 % of
κ ≤ 0.1; 0.25 gives 0.05-0.10 %, 0.3 gives 0.08 %, 0.5 gives 0.2 %.
"""

import numpy as np

from .. import chisq
from ..conventions import azimuth_elevation, wrap_angle
from ..crlb import angle_jacobians

#: Level of the residual χ² test (T19): upper quantile of χ²_{2K−5}.
CONSISTENCY_PROBABILITY = 0.999
#: Radius z of the confidence region over which κ (T21) is measured: the square root of the
#: χ²₃ quantile 0.9999 (21.1), the Mahalanobis radius of a confidently wrong fix.
REGION_Z = float(np.sqrt(chisq.ppf(0.9999, 3)))
#: Default largest κ of an ``ok`` fix (option ``max_nonlinearity``).
MAX_NONLINEARITY = 0.2
#: Default largest distance D to the ML estimate, in standard deviations (``max_ml_distance``).
MAX_ML_DISTANCE = 1.0
#: Largest departure u of the observer's velocity from its fitted track, as a fraction of
#: the prior speed, of an ``ok`` fix with a 'relative' speed prior (T22).
MANOEUVRE_FRACTION = 0.01


def residuals(data, p0, v):
    """Whitened residuals (M, K, 2) = [wrap(θ̂ − θ)/σ_θ, (ψ̂ − ψ)/σ_ψ] and d = p_k (T3)-(T4)."""
    d = p0[:, None, :] + v[:, None, :] * data.tau[..., None] - data.delta
    az, el = azimuth_elevation(d)
    e = np.stack([wrap_angle(az - data.az) / data.s_az, (el - data.el) / data.s_el], -1)
    return e, d


def tangent_basis(s):
    """Orthonormal basis E (M, 3, 2) of the plane normal to unit vectors s (M, 3)."""
    a = np.where((np.abs(s[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = a - np.sum(a * s, -1, keepdims=True) * s
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(s, e1)
    return np.stack([e1, e2], axis=-1)


def whitened_jacobian(d, s_az, s_el, E, vc, tau):
    """Jacobian (M, 2K, 5) of the whitened angles in (p0, tangent step of s) (T17, T20).

    d (M, K, 3) relative positions p_k, s_az/s_el (M, K) rad, E (M, 3, 2) the tangent basis
    of the velocity direction s, vc (M,) m/s, tau (M, K) s: ∂/∂p0 = G_k, ∂/∂δ = G_k v_c E τ_k,
    G_k = [∇θ/σ_θ; ∇ψ/σ_ψ] at p_k (rad/m over rad).
    """
    M = d.shape[0]
    g_t, g_p = angle_jacobians(np.zeros((M, 3)), -d)
    G = np.stack([g_t / s_az[..., None], g_p / s_el[..., None]], -2)
    Jv = (G @ (vc[:, None, None] * E)[:, None]) * tau[..., None, None]
    return np.concatenate([G, Jv], axis=-1).reshape(M, -1, 5)


def ml_distance(data, p0, v, speed_reference='relative'):
    """Distance D (M,) of the fixes to the ML estimate, std (T20), and their residual χ² (T19).

    D² = eᵀJ(JᵀJ)⁺Jᵀe, the Gauss-Newton decrease of the cost, with JᵀJ equilibrated by its
    diagonal and directions of eigenvalue below 1e-12 of the largest left out.
    """
    M = p0.shape[0]
    off = data.v_o if speed_reference == 'ground' else np.zeros((M, 3))
    s = v + off
    s = s / np.linalg.norm(s, axis=-1, keepdims=True)
    e, d = residuals(data, p0, v)
    J = whitened_jacobian(d, data.s_az, data.s_el, tangent_basis(s), data.speed, data.tau)
    Jte = np.einsum('mki,mk->mi', J, e.reshape(M, -1))
    JtJ = np.swapaxes(J, -1, -2) @ J
    dg = np.sqrt(np.abs(np.diagonal(JtJ, axis1=-2, axis2=-1)))
    dg = np.where(dg > 0, dg, 1.0)
    A = JtJ / dg[:, :, None] / dg[:, None, :]
    w, V = np.linalg.eigh(A)
    proj = np.einsum('mji,mj->mi', V, Jte / dg)
    keep = w > 1e-12 * w[:, -1:]
    D2 = np.sum(np.where(keep, proj * proj / np.where(keep, w, 1.0), 0.0), axis=-1)
    return np.sqrt(np.maximum(D2, 0.0)), np.sum(e * e, axis=(1, 2))


def range_nonlinearity(p0, v, C, v_o, speed_reference='relative', z=REGION_Z):
    """κ (M,) of (T21): the second-order over the first-order term of the range r0(b) on the
    boundary of the level-z confidence region; inf where the first-order term vanishes.

    p0 (M, 3) m, v (M, 3) m/s, C (M, 6, 6) the constrained CRLB of (p0, v) (T15), v_o (M, 3)
    m/s (used for ``ground``).
    """
    r0 = np.linalg.norm(p0, axis=-1)
    e0 = p0 / r0[:, None]
    b = v / r0[:, None]
    M = len(r0)
    B = np.zeros((M, 3, 6))
    B[:, :, :3] = -b[:, :, None] * e0[:, None, :] / r0[:, None, None]
    B[:, :, 3:] = np.eye(3) / r0[:, None, None]
    with np.errstate(invalid='ignore', over='ignore'):
        Sb = B @ C @ np.swapaxes(B, -1, -2)
    fin = np.all(np.isfinite(Sb), axis=(-2, -1))
    Sb = np.where(fin[:, None, None], 0.5 * (Sb + np.swapaxes(Sb, -1, -2)), np.eye(3))
    # r0(b) from F(r0, b) = |r0 b + v_o|² − v_c² = 0 (v_o = 0 for 'relative'): implicit
    # derivatives g = −F_b/F_r, H = −(F_bb + F_rb gᵀ + g F_rbᵀ + F_rr g gᵀ)/F_r.
    w = r0[:, None] * b + (np.asarray(v_o, dtype=float) if speed_reference == 'ground'
                           else 0.0)
    Fr = 2.0 * np.sum(w * b, axis=-1)
    with np.errstate(divide='ignore', invalid='ignore'):
        g = -2.0 * r0[:, None] * w / Fr[:, None]
        Frb = 2.0 * (w + r0[:, None] * b)
        H = -(2.0 * r0[:, None, None] ** 2 * np.eye(3)
              + Frb[:, :, None] * g[:, None, :] + g[:, :, None] * Frb[:, None, :]
              + 2.0 * np.sum(b * b, -1)[:, None, None] * g[:, :, None] * g[:, None, :]) \
            / Fr[:, None, None]
    fin &= np.isfinite(Fr) & (Fr != 0) & np.all(np.isfinite(H), axis=(-2, -1))
    H = np.where(fin[:, None, None], H, 0.0)
    g = np.where(fin[:, None], g, 0.0)
    lam, V = np.linalg.eigh(Sb)
    L = V * np.sqrt(np.maximum(lam, 0.0))[:, None, :]              # Σ_b = L Lᵀ
    S = np.swapaxes(L, -1, -2) @ H @ L
    first = np.linalg.norm(np.einsum('mji,mj->mi', L, g), axis=-1)   # σ_r0, m
    second = np.max(np.abs(np.linalg.eigvalsh(S)), axis=-1)          # m
    with np.errstate(divide='ignore', invalid='ignore'):
        kappa = 0.5 * z * second / first
    return np.where(fin & (first > 0), kappa, np.inf)


def manoeuvre_speed(data):
    """u (M,) of (T22), m/s: 4 max_k |δ̄_k| / T, the departure of the observer's velocity
    from its fitted straight-line track (0 for a window of no duration). δ̄ is δ averaged
    over runs of max(1, K // 10) consecutive bearings, so that noise on the observer
    positions (GPS) averages out instead of reading as a manoeuvre."""
    K = data.delta.shape[1]
    w = max(1, K // 10)
    c = np.cumsum(np.concatenate([np.zeros_like(data.delta[:, :1]), data.delta], axis=1),
                  axis=1)
    smooth = (c[:, w:] - c[:, :-w]) / w
    span = data.tau.max(axis=1) - data.tau.min(axis=1)
    dev = np.linalg.norm(smooth, axis=-1).max(axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(span > 0, 4.0 * dev / span, 0.0)


def assess(data, p0, v, C, opts):
    """Tests (T19)-(T22) of fixes (M,): (ok (M,) bool, reason (M,) str, '' where ok).

    ``opts``: the estimator options (``speed_reference``, ``max_nonlinearity``,
    ``max_ml_distance``); C (M, 6, 6) the constrained CRLB of (p0, v).
    """
    ref = opts['speed_reference']
    D, chi2 = ml_distance(data, p0, v, ref)
    kappa = range_nonlinearity(p0, v, C, data.v_o, ref)
    dof = 2 * data.az.shape[1] - 5
    limit = chisq.isf(1.0 - CONSISTENCY_PROBABILITY, max(dof, 1))
    u = manoeuvre_speed(data) if ref == 'relative' else np.zeros(len(D))
    reasons = []
    for m in range(len(D)):
        why = []
        if not chi2[m] <= limit:
            why.append(f'bearings do not fit the model: residual chi2={chi2[m]:.4g} above '
                       f'{limit:.4g} ({dof} dof)')
        if not D[m] <= opts['max_ml_distance']:
            why.append(f'not the maximum likelihood fix: {D[m]:.3g} std from it (limit '
                       f'{opts["max_ml_distance"]:.3g}), so the CRLB is not its covariance')
        if not kappa[m] <= opts['max_nonlinearity']:
            why.append(f'range nonlinear over the confidence region: kappa={kappa[m]:.3g} '
                       f'(limit {opts["max_nonlinearity"]:.3g}), the covariance understates '
                       'the range error')
        if not u[m] <= MANOEUVRE_FRACTION * data.speed[m]:
            why.append(f'relative speed prior with a manoeuvring observer: its velocity '
                       f'departs from its fitted straight track by about {u[m]:.3g} m/s, so '
                       'the relative speed is not defined; state the ground speed '
                       '(speed_reference ground)')
        reasons.append('; '.join(why))
    return np.array([r == '' for r in reasons], dtype=bool), np.array(reasons, dtype=object)
