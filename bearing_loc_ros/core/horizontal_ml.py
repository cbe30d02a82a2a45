"""Maximum likelihood of the horizontal solve: Zong & Cui 2015 eqs. (3)-(11) with the z prior.

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians. Parameters p = (x, y, z); the cost (the negative log-posterior of
:mod:`.horizontal_crlb`) is

    Σ_i e_θi²/σ_θi² + Σ_{i ∈ 2D} e_ψi²/σ_ψi² + (z − z₀)²/σ_z²,

e = measured − predicted angle (azimuth wrapped to (−π, π]); with σ_z = 0 z is held at z₀
(two parameters). With azimuths only the z terms decouple, so ẑ = z₀ exactly and the
covariance is blockdiag(J_h⁻¹, σ_z²). ``wmle`` grows σ with range (eqs. (9)-(11)).

The iteration is core/estimators.py ``_levenberg_marquardt`` itself, on the packed horizontal
cost of :class:`PlaneMLProblem` (the prior block in the z row and column).
"""

import numpy as np

from .horizontal_crlb import prior_covariance
from .estimators import (STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_MAX_ITERATIONS,
                         STATUS_OK)
from .horizontal_estimators import fix_result, parse_horizontal_options, start
from .horizontal_single import solve_one


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


class PlaneMLProblem:
    """The horizontal ML cost in the packed form of core/estimators.py ``_MLProblem``.

    So that one Levenberg-Marquardt implementation (core/estimators.py
    ``_levenberg_marquardt``: damping, acceptance, convergence and divergence rules) serves
    the 3D and the horizontal solve. :meth:`pack` returns the rows of A, b, the cost, the rms
    range and the cost under the previous weights (``wmle``) of :func:`ml_terms` plus the
    prior: A_zz += 1/σ_z², b_z −= (z − z₀)/σ_z², cost += (z − z₀)²/σ_z²; where σ_z = 0 the z
    row and column of A are those of the identity and b_z = 0, so the step never moves z
    off z₀. The prior (or the fixed z) counts as one measurement: dof = angles − 2.
    """

    def __init__(self, p, d_ref=None):
        self.p = p
        self.d_ref = d_ref
        self.fixed = p.sz == 0.0
        self.wz = np.where(self.fixed, 0.0, 1.0 / np.where(self.fixed, 1.0, p.sz) ** 2)
        self.n_measurements = p.N + np.count_nonzero(p.use_el, axis=1) + 1

    def take(self, idx):
        """The same problem restricted to the problems ``idx``."""
        return PlaneMLProblem(self.p.take(idx), self.d_ref)

    def pack(self, x, y, z, old_factor=None):
        """(12, M) packed state at X = (x, y, z) and X's weight factor (``wmle``; else None).

        Rows as core/estimators.py ``_MLProblem.pack``; ``old_factor`` (N, M), station-major
        as there, the weight factor d_ref²/d² of the previous iterate (``wmle``).
        """
        from .estimators import _A00, _A01, _A02, _A11, _A12, _A22, _B0, _B1, _B2, _COST, \
            _OLD, _SCALE
        p = self.p
        X = np.stack([x, y, z], axis=1)
        A, b, cost, scale, own = ml_terms(p, X, None, self.d_ref)
        old = cost
        if self.d_ref is not None and old_factor is not None:
            old = ml_terms(p, X, old_factor.T, self.d_ref)[2]
        dz = z - p.z0
        wz, fixed = self.wz, self.fixed
        q = np.empty((12, x.shape[0]))
        q[_A00], q[_A01], q[_A11] = A[:, 0, 0], A[:, 0, 1], A[:, 1, 1]
        q[_A02] = np.where(fixed, 0.0, A[:, 0, 2])
        q[_A12] = np.where(fixed, 0.0, A[:, 1, 2])
        q[_A22] = np.where(fixed, 1.0, A[:, 2, 2] + wz)
        q[_B0], q[_B1] = b[:, 0], b[:, 1]
        q[_B2] = np.where(fixed, 0.0, b[:, 2] - wz * dz)
        q[_COST] = cost + wz * dz * dz
        q[_OLD] = old + wz * dz * dz
        q[_SCALE] = scale
        return q, (None if own is None else own.T)


def levenberg_marquardt(p, x0, max_iterations, tolerance, d_ref=None):
    """Gauss-Newton (Zong & Cui 2015 eq. (8)) with Levenberg-Marquardt damping, M problems.

    Parameters (x, y, z); the cost is the ML cost of :func:`ml_terms` plus the prior term
    (z − z₀)²/σ_z² (σ_z > 0) or z held at z₀ (σ_z = 0). The iteration is the one of
    core/estimators.py ``_levenberg_marquardt`` on :class:`PlaneMLProblem` (its damping and
    stopping rules: step (A + λ diag A) Δ = b accepted when the cost does not increase, for
    ``wmle`` under the previous iterate's weights; converged when the undamped step is
    shorter than ``tolerance`` × rms range or its predicted decrease is below
    max(1e-10/dof, 1e-12) × cost; diverged when λ > 1e12 or the rms range grows 1e8-fold).
    Returns (X, information at X without the prior, iterations, converged, diverged).
    """
    from .estimators import _levenberg_marquardt
    x0 = np.array(x0, dtype=float)
    fixed = p.sz == 0.0
    x0[:, 2] = np.where(fixed | ~np.isfinite(x0[:, 2]), p.z0, x0[:, 2])
    X, _, it, conv, div = _levenberg_marquardt(PlaneMLProblem(p, d_ref), x0, max_iterations,
                                               tolerance)
    info, _, _, _, _ = ml_terms(p, np.where(np.isfinite(X), X, 0.0), None, d_ref)
    return X, info, it, conv, div


def iterative_result(p, method, X, info, iterations, converged, diverged):
    """FixResult of an ML iteration: covariance from the prior-combined information."""
    cov, ok = prior_covariance(info, p.sz)
    ok &= np.all(np.isfinite(X), axis=1)
    status = np.where(converged, STATUS_OK,
                      np.where(diverged, STATUS_DIVERGED, STATUS_MAX_ITERATIONS)).astype(object)
    status[~ok] = STATUS_DEGENERATE
    return fix_result(p, X[:, :2], cov, iterations, converged, status.astype(str), method,
                      z=X[:, 2])


def _one(p, method, d_ref, opts, initial):
    """The one-problem float path (core/horizontal_single.py), or None for the batch path."""
    return solve_one(p, method, d_ref, dict(opts, initial=initial))


def mle(p, **options):
    """Maximum likelihood (maximum a posteriori for σ_z > 0), Zong & Cui 2015 eqs. (3)-(8).

    X̂ = argmin Σ e_θ²/σ_θ² + Σ_{2D} e_ψ²/σ_ψ² + (z − z₀)²/σ_z² over (x, y, z) (z = z₀ fixed
    when σ_z = 0), by :func:`levenberg_marquardt` from ``ls``. With azimuths only the z
    terms decouple and ẑ = z₀ exactly. Covariance: the inverse of the prior-combined
    information at X̂ (:func:`.horizontal_crlb.prior_covariance`), m². Options:
    ``max_iterations``, ``tolerance``, ``initial``. One problem (M = 1) runs the same
    iteration on Python floats (core/horizontal_single.py, same results to rounding).
    """
    opts, initial = parse_horizontal_options('mle', options, p.M)
    if p.M == 1:
        res = _one(p, 'mle', None, opts, initial)
        if res is not None:
            return res
    X, info, it, conv, div = levenberg_marquardt(p, start(p, initial), opts['max_iterations'],
                                                 opts['tolerance'])
    return iterative_result(p, 'mle', X, info, it, conv, div)


def wmle(p, **options):
    """Range-weighted ML, Zong & Cui 2015 eqs. (9)-(11), with the z prior.

    σ_k = σ_ref,k · d_k / d_ref (eqs. (9)-(10)), d_k = |X_i − S_k| the slant range to the
    current iterate (z of the iterate: z₀ when σ_z = 0), held fixed within a step (eq. (11),
    iteratively reweighted, as in the 3D ``wmle``); the prior term is not range-scaled.
    Covariance: inverse prior-combined information with σ(d̂), m². Options:
    ``reference_range`` (d_ref, m), ``max_iterations``, ``tolerance``, ``initial``. One
    problem (M = 1) runs on Python floats as :func:`mle` does.
    """
    opts, initial = parse_horizontal_options('wmle', options, p.M)
    if p.M == 1:
        res = _one(p, 'wmle', opts['reference_range'], opts, initial)
        if res is not None:
            return res
    X, info, it, conv, div = levenberg_marquardt(p, start(p, initial), opts['max_iterations'],
                                                 opts['tolerance'], opts['reference_range'])
    return iterative_result(p, 'wmle', X, info, it, conv, div)
