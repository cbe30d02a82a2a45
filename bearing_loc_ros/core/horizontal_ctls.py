"""Constrained TLS of the horizontal solve: Wang, Zhang & Wu eqs. (9)-(20) reduced to the plane.

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians. The target altitude z₀ is stated (see :mod:`.horizontal_estimators`); Δz_i = z₀ − z_i.

Derivation. The plane-reduced pseudo-linear system H X = Y, X = (x, y), has per station i the
rows (azimuth, elevation)

    h_i = [[sin θ, −cos θ], [cos θ sin ψ, sin θ sin ψ]],
    Y_i = [sin θ x_i − cos θ y_i,  cos θ sin ψ x_i + sin θ sin ψ y_i + cos ψ Δz_i].

With measured angles θ = θ* + n_i, ψ = ψ* + m_i and E = [n_1, m_1, ..., n_N, m_N]ᵀ, a first-order
expansion of the true rows gives the analogue of eq. (9), H* = H + [F_1E  F_2E],
Y* = Y + F_4E, with 2 × 2 blocks (rows: azimuth, elevation equation; columns: n_i, m_i)

    f_1i = [[−cos θ, 0], [sin θ sin ψ, −cos θ cos ψ]]
    f_2i = [[−sin θ, 0], [−cos θ sin ψ, −sin θ cos ψ]]
    f_4i = [[−(cos θ x_i + sin θ y_i), 0],
            [sin θ sin ψ x_i − cos θ sin ψ y_i, −(cos θ cos ψ x_i + sin θ cos ψ y_i − sin ψ Δz_i)]]

f_1i, f_2i are the 3D blocks of the paper; the 3D f_3i (the z column, [[0, 0], [0, −sin ψ]])
multiplies the now-known z₀ and joins f_4i: f_4i(2D) = f_4i(3D) − z₀ f_3i. Theorem 1
(eqs. (10)-(19)) then holds with two unknowns: C = [H Y] (2N × 3), perturbation
[F_1E F_2E F_4E], H_X = x F_1 + y F_2 − F_4 and G = F_1ᵀF_1 + F_2ᵀF_2 + F_4ᵀF_4 (per station
2 × 2: the Frobenius norm of the perturbation of the reduced C), so the CTLS problem
min EᵀGE s.t. C[X; −1] + H_X E = 0 becomes (eq. (11))

    f(X) = Σ_i r_iᵀ S_i⁻¹ r_i,  r_i = h_i X − Y_i,  S_i = h_Xi G_i⁻¹ h_Xiᵀ.

Its gradient T_n and Hessian H_n (appendix A) are those of the 3D code with the z column
dropped: U_i = S_i⁻¹ r_i; for j ∈ {1, 2}: B3 column j = F_jᵀU, B1 column j = H_X G⁻¹ F_jᵀU,
B2 column j = F_j G⁻¹ H_XᵀU;

    T_n = 2 Σ (h − B1)ᵀ U,   H_n = 2 Σ (h − B1 − B2)ᵀ S⁻¹ (h − B1 − B2) − 2 Σ B3ᵀ G⁻¹ B3,

and the Newton iteration X_{n+1} = X_n − μ_n H_n⁻¹ T_n of eq. (20). 1D stations: the
elevation row and the m_i column are zeroed and the [1, 1] entries of G and S set to 1 (the
1 × 1 reduced problem, as in the 3D code). ``ctls_am`` (Abatzoglou-Mendel) replaces G⁻¹ by
P_E = diag(σ_θi², σ_ψi²): origin- and unit-independent, efficient to first order.

Covariance. The bearing noise: eq. (30) reduced, everything at the estimate with predicted
angles, P₀ = A⁻¹ [Σ h*ᵀS⁻¹ (H_X P_E H_Xᵀ) S⁻¹h*] A⁻¹, A = Σ h*ᵀS⁻¹h*. The fit treats z₀ as
exact; σ_z is carried through the fit itself by refitting at the four nonzero nodes
z₀ + σ_z x_j of the five-point Gauss-Hermite rule
(:func:`.horizontal_estimators.altitude_covariance`): S_i depends on Δz_i and on X, so X̂
is not linear in z₀, and the first-order gain k = A⁻¹g, g = Σ h*ᵀS⁻¹c_i, c_i = (0, cos ψ_i)
(∂Y_i/∂z₀), understated the covariance up to a thousandfold (σ_z = 300 m, one elevation
station); k remains the fallback where a refit fails.
"""

import numpy as np

from .constrained_tls import block_hx, block_s, BlockProblem, ctls_blocks
from .horizontal_crlb import inverse2
from .estimators import (STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_MAX_ITERATIONS,
                         STATUS_OK)
from .horizontal_estimators import (altitude_covariance, fix_result, parse_horizontal_options,
                                    plane_system, sandwich, start)
from .solvers import CHI2_STEP_TOL, COST_RTOL, inv2, newton_backtracking

WEIGHTINGS = ('paper', 'am')


def blocks(theta, psi, use_el, px, py, dz):
    """F_1, F_2, F_4 of the module docstring as (M, N, 3, 2, 2); 1D rows/columns zeroed.

    The 3D blocks of :func:`~.constrained_tls.ctls_blocks` at the station position
    (p_x, p_y, −Δz), Δz = z₀ − p_z, without F_3 (z₀ is known).
    """
    return ctls_blocks(theta, psi, use_el, np.stack([px, py, -dz], axis=-1))[:, :, (0, 1, 3)]


class PlaneCTLS(BlockProblem):
    """Blocks of the plane-reduced eq. (11) for a batch (measured angles, fixed over X)."""

    def __init__(self, p, weighting):
        if weighting not in WEIGHTINGS:
            raise ValueError(f'weighting: must be one of {WEIGHTINGS}, got {weighting!r}')
        self.p = p
        self.weighting = weighting
        self.one_d = ~p.use_el
        self.dz = p.z0[:, None] - p.pz
        self.F = blocks(p.az, p.el, p.use_el, p.px, p.py, self.dz)
        self.H, self.Y, _ = plane_system(p)
        self.PE = np.zeros(p.az.shape + (2, 2))
        self.PE[..., 0, 0] = p.saz ** 2
        self.PE[..., 1, 1] = np.where(p.use_el, np.nan_to_num(p.sel), 0.0) ** 2
        self.Ginv = self._ginv(self.F)

    def take(self, idx):
        """The problems ``idx`` only."""
        out = object.__new__(PlaneCTLS)
        out.p = self.p.take(idx)
        out.weighting = self.weighting
        for name in ('one_d', 'dz', 'F', 'H', 'Y', 'PE', 'Ginv'):
            setattr(out, name, getattr(self, name)[idx])
        return out

    def covariance(self, X):
        """Reduced eq. (30) for the bearing noise (module docstring): (P₀ (M, 3, 3) m², zero
        z row and column, +inf where singular; k = A⁻¹g (M, 2), the first-order ∂X/∂z₀; ok)."""
        p = self.p
        dx, dy = X[:, 0:1] - p.px, X[:, 1:2] - p.py
        th = np.arctan2(dy, dx)
        ps = np.where(p.use_el, np.arctan2(self.dz, np.hypot(dx, dy)), 0.0)
        pred = p.take(slice(None))
        pred.az, pred.el = th, ps
        Hs, _, _ = plane_system(pred)
        F = blocks(th, ps, p.use_el, p.px, p.py, self.dz)
        Ginv = self._ginv(F)
        Hx = block_hx(X, F)
        Sinv = inv2(block_s(Hx, Ginv, self.one_d))
        Q = Hx @ self.PE @ np.swapaxes(Hx, -1, -2)
        A = np.einsum('mnki,mnkl,mnlj->mij', Hs, Sinv, Hs)
        B = np.einsum('mnki,mnkl,mnlp,mnpq,mnqj->mij', Hs, Sinv, Q, Sinv, Hs)
        c = np.zeros(p.az.shape + (2,))
        c[..., 1] = np.where(p.use_el, np.cos(ps), 0.0)
        g = np.einsum('mnki,mnkl,mnl->mi', Hs, Sinv, c)
        Ainv, ok = inverse2(A)
        ok &= np.all(np.isfinite(B), axis=(1, 2)) & np.all(np.isfinite(g), axis=1)
        P0, k = sandwich(Ainv, B, g, ok)
        return P0, k, ok


def _rms_horizontal_range(sub, X):
    """rms horizontal station range (M,), m, at X (M, 2): the scale of the step test."""
    return np.sqrt(np.mean((X[:, 0:1] - sub.p.px) ** 2 + (X[:, 1:2] - sub.p.py) ** 2, axis=1))


def constrained_tls(p, weighting='paper', **options):
    """Plane-reduced CTLS by the Newton iteration of Wang, Zhang & Wu eq. (20), M problems.

    ``p`` a :class:`.horizontal_estimators.HorizontalProblem`. X_{n+1} = X_n − μ^n H_n⁻¹T_n
    from the plane ``ls`` (or option ``initial``): the one safeguarded Newton iteration of
    the 3D code, core.solvers.newton_backtracking (Gauss-Newton part of H_n where H_n is
    not positive definite, step halving so f never increases, ``diverged`` where no descent
    step exists; converged when the full Newton step is shorter than ``tolerance`` × rms
    horizontal station range, or at a stop when its predicted decrease is below
    max(1e-10/dof, 1e-12) × f, dof = angles − 2).
    ``weighting``: ``'paper'`` (``ctls``) or ``'am'`` (``ctls_am``). Covariance: reduced eq.
    (30), σ_z by four refits at z₀ + σ_z x_j where an elevation is used (module
    docstring), m². Options: ``step_decay``, ``max_iterations``, ``tolerance``, ``initial``.
    """
    name = 'ctls' if weighting == 'paper' else 'ctls_am'
    opts, initial = parse_horizontal_options(name, options, p.M)
    problem = PlaneCTLS(p, weighting)
    X = start(p, initial)[:, :2].copy()
    dof = np.maximum(p.N + np.count_nonzero(p.use_el, axis=1) - 2, 1)
    rel_tol = np.maximum(CHI2_STEP_TOL / dof, COST_RTOL)
    finite0 = np.all(np.isfinite(X), axis=1)
    X, iterations, converged, diverged = newton_backtracking(
        problem, X, opts['step_decay'], opts['tolerance'], opts['max_iterations'], rel_tol,
        _rms_horizontal_range)
    P0, k, ok = problem.covariance(np.where(np.isfinite(X), X, 0.0))
    ok &= finite0

    def refit(q, idx):
        # The same iteration from the fit, at the shifted altitudes (σ_z = 0: no recursion).
        return constrained_tls(q, weighting, initial=X[idx], step_decay=opts['step_decay'],
                               max_iterations=opts['max_iterations'],
                               tolerance=opts['tolerance']).position[:, :2]

    P = altitude_covariance(p, np.where(ok[:, None], X, np.nan), P0, k, refit)
    status = np.where(converged, STATUS_OK,
                      np.where(diverged, STATUS_DIVERGED, STATUS_MAX_ITERATIONS)).astype(object)
    status[~ok] = STATUS_DEGENERATE
    return fix_result(p, X, P, iterations, converged, status.astype(str), name)
