"""Maximum likelihood of the horizontal solve: Zong & Cui 2015 eqs. (3)-(11) with the z prior.

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians. Parameters p = (x, y, z); the cost (the negative log-posterior of
:mod:`.horizontal_crlb`) is

    Σ_i e_θi²/σ_θi² + Σ_{i ∈ 2D} e_ψi²/σ_ψi² + (z − z₀)²/σ_z²,

e = measured − predicted angle (azimuth wrapped to (−π, π]); with σ_z = 0 z is held at z₀
(two parameters). With azimuths only the z terms decouple, so ẑ = z₀ exactly and the
covariance is blockdiag(J_h⁻¹, σ_z²). ``wmle`` grows σ with range (eqs. (9)-(11)).

The damping and stopping rules repeat those of core/estimators.py ``_levenberg_marquardt``
(three parameters with a prior block instead of three free ones).
"""

import numpy as np

from .horizontal_crlb import prior_covariance
from .estimators import (STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_MAX_ITERATIONS,
                         STATUS_OK)
from .horizontal_estimators import fix_result, parse_horizontal_options, solve2, start

_CHI2_STEP_TOL = 1e-10
_COST_RTOL = 1e-12


def ml_terms(p, X, factor=None, d_ref=None):
    """Measurement information A (M, 3, 3), gradient term b (M, 3), cost (M,) at X (M, 3).

    Zong & Cui 2015 eqs. (3)-(8): e = measured − predicted angles (azimuth wrapped to
    (−π, π]), cost Σ e²/σ², A = Σ ∇∇ᵀ/σ², b = Σ ∇ e/σ² (so the Gauss-Newton step of eq. (8)
    is X + A⁻¹b), ∇θ, ∇ψ as in core/crlb.py. With ``d_ref`` (``wmle``, eqs. (9)-(11)) every
    1/σ² is multiplied by ``factor`` (M, N) = d_ref²/d² of the iterate the weights belong to
    (that of X itself when ``factor`` is None). Also returns the rms station range (M,) and
    X's own factor (None without ``d_ref``). The z prior is not included.
    """
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        dx = X[:, 0:1] - p.px
        dy = X[:, 1:2] - p.py
        dz = X[:, 2:3] - p.pz
        rho2 = dx * dx + dy * dy
        r2 = rho2 + dz * dz
        rho = np.sqrt(rho2)
        e_az = p.az - np.arctan2(dy, dx)
        e_az -= 2.0 * np.pi * np.ceil((e_az - np.pi) / (2.0 * np.pi))
        e_el = np.where(p.use_el, p.el - np.arctan2(dz, rho), 0.0)
        wa = 1.0 / p.saz ** 2
        we = np.where(p.use_el, 1.0 / np.where(p.use_el, p.sel, 1.0) ** 2, 0.0)
        own = None
        if d_ref is not None:
            own = d_ref * d_ref / r2
            f = own if factor is None else factor
            wa, we = wa * f, we * f
        ga = np.stack([-dy / rho2, dx / rho2, np.zeros_like(dx)], axis=-1)
        ge = np.stack([-dx * dz / (rho * r2), -dy * dz / (rho * r2), rho / r2], axis=-1)
        ge = np.where(p.use_el[..., None], ge, 0.0)
        A = (np.einsum('mn,mni,mnj->mij', wa, ga, ga)
             + np.einsum('mn,mni,mnj->mij', we, ge, ge))
        b = (np.einsum('mn,mni,mn->mi', wa, ga, e_az)
             + np.einsum('mn,mni,mn->mi', we, ge, e_el))
        cost = np.sum(wa * e_az * e_az + we * e_el * e_el, axis=1)
        scale = np.sqrt(np.mean(r2, axis=1))
    return A, b, cost, scale, own


def prior_step(A, b, fixed):
    """Solve A Δ = b (M, 3, 3) by the Schur complement on z; Δz = 0 where ``fixed``.

    Where the altitude is fixed (σ_z = 0) the z row is dropped (a 2 × 2 system); otherwise
    Δ_h = (A_h − q qᵀ/s)⁻¹ (b_h − q b_z/s), Δz = (b_z − qᵀΔ_h)/s, which stays well
    conditioned for a tiny σ_z (huge s). NaN where the horizontal block is singular.
    """
    s = np.where(fixed, 1.0, A[:, 2, 2])
    q = np.where(fixed[:, None], 0.0, A[:, :2, 2])
    bz = np.where(fixed, 0.0, b[:, 2])
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        S = A[:, :2, :2] - q[:, :, None] * q[:, None, :] / s[:, None, None]
        d_h, _, _ = solve2(S, b[:, :2] - q * (bz / s)[:, None])
        dz = (bz - np.einsum('mi,mi->m', q, d_h)) / s
    return np.concatenate([d_h, dz[:, None]], axis=1)


def levenberg_marquardt(p, x0, max_iterations, tolerance, d_ref=None):
    """Gauss-Newton (Zong & Cui 2015 eq. (8)) with Levenberg-Marquardt damping, M problems.

    Parameters (x, y, z); the cost is the ML cost of :func:`ml_terms` plus the prior term
    (z − z₀)²/σ_z² (σ_z > 0) or z held at z₀ (σ_z = 0). The damping and stopping rules are
    those of core/estimators.py ``_levenberg_marquardt``: step (A + λ diag A) Δ = b, accepted
    when the cost does not increase (for ``wmle`` under the previous iterate's weights), λ
    from 0 (pure Gauss-Newton), ×10 (at least 1e-3) on rejection, ÷10 (0 below 1e-6) on
    acceptance; converged when the undamped step is shorter than ``tolerance`` × rms range or
    its predicted decrease bᵀΔ is below max(1e-10/dof, 1e-12) × cost; the sub-tolerance step is
    not taken; diverged when λ > 1e12 or the rms range grows 1e8-fold. Returns (X, information
    at X without the prior, iterations, converged, diverged).
    """
    M = p.M
    fixed = p.sz == 0.0
    wz = np.where(fixed, 0.0, 1.0 / np.where(fixed, 1.0, p.sz) ** 2)
    finite0 = np.all(np.isfinite(x0), axis=1)
    X = np.where(finite0[:, None], x0, 0.0)
    X[:, 2] = np.where(fixed | ~np.isfinite(x0[:, 2]), p.z0, X[:, 2])

    def terms(X, factor=None):
        A, b, cost, scale, own = ml_terms(p, X, factor, d_ref)
        dz = X[:, 2] - p.z0
        A = A.copy()
        A[:, 2, 2] += wz
        b = b.copy()
        b[:, 2] -= wz * dz
        return A, b, cost + wz * dz * dz, scale, own

    A, b, cost, scale, factor = terms(X)
    scale0 = scale.copy()
    n_meas = p.N + np.count_nonzero(p.use_el, axis=1)
    rel_tol = np.maximum(_CHI2_STEP_TOL / np.maximum(n_meas - 2, 1), _COST_RTOL)
    lam = np.zeros(M)
    it = np.zeros(M, dtype=int)
    conv = np.zeros(M, dtype=bool)
    div = ~finite0
    done = div.copy()
    diag = np.eye(3, dtype=bool)
    for _ in range(max_iterations):
        if done.all():
            break
        run = ~done
        g = prior_step(A, b, fixed)
        damped = lam > 0
        step = g
        if np.any(damped):
            Ad = A.copy()
            Ad[:, diag] *= (1.0 + lam)[:, None]
            step = np.where(damped[:, None], prior_step(Ad, b, fixed), g)
        gn = np.linalg.norm(g, axis=1)
        decrease = np.abs(np.einsum('mi,mi->m', b, g))
        small = run & ((gn <= tolerance * scale) | (decrease <= rel_tol * cost))
        step_ok = np.all(np.isfinite(step), axis=1)
        trying = run & ~small & step_ok
        it += run
        conv |= small
        if np.any(trying):
            Xt = np.where(trying[:, None], X + np.where(step_ok[:, None], step, 0.0), X)
            if d_ref is None:
                At, bt, ct, st, ft = terms(Xt)
                ok = trying & (ct <= cost)
            else:
                _, _, c_old, _, _ = terms(Xt, factor)
                ok = trying & (c_old <= cost)
                At, bt, ct, st, ft = terms(Xt)
            X = np.where(ok[:, None], Xt, X)
            A = np.where(ok[:, None, None], At, A)
            b = np.where(ok[:, None], bt, b)
            cost = np.where(ok, ct, cost)
            scale = np.where(ok, st, scale)
            if d_ref is not None:
                factor = np.where(ok[:, None], ft, factor)
            lam = np.where(ok, np.where(lam < 1e-6, 0.0, 0.1 * lam),
                           np.where(trying, np.maximum(10.0 * lam, 1e-3), lam))
        runaway = run & ~small & ((lam > 1e12) | ~step_ok | (scale > 1e8 * scale0))
        div |= runaway
        done |= small | runaway
    info, _, _, _, _ = ml_terms(p, X, None, d_ref)
    X[~finite0] = np.nan
    return X, info, it, conv & finite0, div


def iterative_result(p, method, X, info, iterations, converged, diverged):
    """FixResult of an ML iteration: covariance from the prior-combined information."""
    cov, ok = prior_covariance(info, p.sz)
    ok &= np.all(np.isfinite(X), axis=1)
    status = np.where(converged, STATUS_OK,
                      np.where(diverged, STATUS_DIVERGED, STATUS_MAX_ITERATIONS)).astype(object)
    status[~ok] = STATUS_DEGENERATE
    return fix_result(p, X[:, :2], cov, iterations, converged, status.astype(str), method,
                      z=X[:, 2])


def mle(p, **options):
    """Maximum likelihood (maximum a posteriori for σ_z > 0), Zong & Cui 2015 eqs. (3)-(8).

    X̂ = argmin Σ e_θ²/σ_θ² + Σ_{2D} e_ψ²/σ_ψ² + (z − z₀)²/σ_z² over (x, y, z) (z = z₀ fixed
    when σ_z = 0), by :func:`levenberg_marquardt` from ``ls``. With azimuths only the z
    terms decouple and ẑ = z₀ exactly. Covariance: the inverse of the prior-combined
    information at X̂ (:func:`.horizontal_crlb.prior_covariance`), m². Options:
    ``max_iterations``, ``tolerance``, ``initial``.
    """
    opts, initial = parse_horizontal_options('mle', options, p.M)
    X, info, it, conv, div = levenberg_marquardt(p, start(p, initial), opts['max_iterations'],
                                                 opts['tolerance'])
    return iterative_result(p, 'mle', X, info, it, conv, div)


def wmle(p, **options):
    """Range-weighted ML, Zong & Cui 2015 eqs. (9)-(11), with the z prior.

    σ_k = σ_ref,k · d_k / d_ref (eqs. (9)-(10)), d_k = |X_i − S_k| the slant range to the
    current iterate (z of the iterate: z₀ when σ_z = 0), held fixed within a step (eq. (11),
    iteratively reweighted, as in the 3D ``wmle``); the prior term is not range-scaled.
    Covariance: inverse prior-combined information with σ(d̂), m². Options:
    ``reference_range`` (d_ref, m), ``max_iterations``, ``tolerance``, ``initial``.
    """
    opts, initial = parse_horizontal_options('wmle', options, p.M)
    X, info, it, conv, div = levenberg_marquardt(p, start(p, initial), opts['max_iterations'],
                                                 opts['tolerance'], opts['reference_range'])
    return iterative_result(p, 'wmle', X, info, it, conv, div)
