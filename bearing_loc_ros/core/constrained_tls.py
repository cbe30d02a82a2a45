"""Constrained total least squares (CTLS) bearing localization (Wang, Zhang & Wu).

Model (Wang, Zhang & Wu eqs. (6)-(9)): with measured angles θ_i = θ_i* + n_i, ψ_i = ψ_i* + m_i and
E = [n_1, m_1, ..., n_N, m_N]ᵀ, the pseudo-linear system H X = Y of eq. (3) is perturbed as

    H* = H + [F_1E  F_2E  F_3E],   Y* = Y + F_4E                                  (9)

with block-diagonal F_j = diag(f_j1, ..., f_jN), one 2 × 2 block per station (rows: azimuth
and elevation equation; columns: n_i and m_i):

    f_1i = [[−cos θ, 0], [sin θ sin ψ, −cos θ cos ψ]]
    f_2i = [[−sin θ, 0], [−cos θ sin ψ, −sin θ cos ψ]]
    f_3i = [[0, 0], [0, −sin ψ]]
    f_4i = [[−(cos θ x_i + sin θ y_i), 0],
            [sin θ sin ψ x_i − cos θ sin ψ y_i, −(cos θ cos ψ x_i + sin θ cos ψ y_i + sin ψ z_i)]]

Theorem 1 (eqs. (10)-(19)): with C = [H Y], H_X = Σ_j a_j F_j − F_4 (a_j = X_j),
G = Σ_{j=1..4} F_jᵀF_j, the CTLS problem min EᵀGE s.t. C[X; −1] + H_X E = 0 becomes

    f(X) = [X; −1]ᵀ Cᵀ (H_X G⁻¹ H_Xᵀ)⁻¹ C [X; −1] = Σ_i r_iᵀ S_i⁻¹ r_i,            (11)

r_i = H_i X − Y_i, S_i = h_i g_i⁻¹ h_iᵀ (2 × 2). Everything is block diagonal, so f, its
gradient T_n and Hessian H_n (appendix A) are sums of per-station 2 × 2 terms: O(N).

Two weightings share this code:

* ``'paper'`` (estimator ``ctls``): G as published. G contains F_4, i.e. the station
  coordinates, so the estimate depends on the coordinate origin and units.
* ``'am'`` (estimator ``ctls_am``): the Abatzoglou-Mendel form min EᵀP_E⁻¹E, i.e. G⁻¹ is
  replaced by P_E = diag(σ_θi², σ_ψi²). Invariant to origin and units; its eq. (30)
  covariance equals the CRLB (to first order it is the maximum likelihood estimator).

1D (azimuth-only) stations: the elevation equation and the m_i column do not exist. We keep
2 × 2 blocks but zero the elevation row and the m_i column of every f_ji (so f_ji reduces to
its [0, 0] entry), and set the otherwise-zero [1, 1] entry of g_i and S_i to 1. With the
elevation residual r_i[1] = 0 this is exactly the 1 × 1 reduced problem (the regularising 1 never
meets a non-zero entry). For ``'am'``, P_E[1, 1] = 0 for 1D stations.
"""

import numpy as np

from .bearings import BearingSet
from .conventions import azimuth_elevation
from .crlb import safe_inverse
from .estimator_spec import (BEARING_SIGMA, CONSISTENCY, declare, ITERATIVE_OPTIONS,
                             MULTISTATION, STEP_DECAY)
from .fix import iterative_result
from .pseudo_linear import checked, pseudo_linear_system, start
from .solvers import COST_RTOL, CHI2_STEP_TOL, inv2, newton_backtracking

WEIGHTINGS = ('paper', 'am')


def ctls_blocks(theta, psi, has_el, positions):
    """F_1..F_4 of Wang, Zhang & Wu eq. (9) as (M, N, 4, 2, 2) blocks (1D rows/columns zeroed).

    θ, ψ (M, N) rad, ``has_el`` (M, N) bool, ``positions`` (M, N, 3) m (F_4 is in m).
    """
    c, s = np.cos(theta), np.sin(theta)
    cp, sp = np.cos(psi), np.sin(psi)
    x, y, z = positions[..., 0], positions[..., 1], positions[..., 2]
    F = np.zeros(theta.shape + (4, 2, 2))
    F[..., 0, 0, 0] = -c                                  # f_1i
    F[..., 0, 1, 0] = s * sp
    F[..., 0, 1, 1] = -c * cp
    F[..., 1, 0, 0] = -s                                  # f_2i
    F[..., 1, 1, 0] = -c * sp
    F[..., 1, 1, 1] = -s * cp
    F[..., 2, 1, 1] = -sp                                 # f_3i
    F[..., 3, 0, 0] = -(c * x + s * y)                    # f_4i
    F[..., 3, 1, 0] = s * sp * x - c * sp * y
    F[..., 3, 1, 1] = -(c * cp * x + s * cp * y + sp * z)
    one_d = ~has_el
    F[one_d, :, 1, :] = 0.0
    F[one_d, :, :, 1] = 0.0
    return F


# The per-station 2 × 2 block algebra of eqs. (11), (20) and appendix A, shared with the
# plane-reduced problem of core.horizontal_ctls: F holds the n blocks F_1..F_n of the unknowns
# and the constant block F_{n+1} last (n = 3 here, 2 there), X is (M, n).

def block_ginv(F, PE, one_d, weighting):
    """G⁻¹ per station (M, N, 2, 2): P_E for ``am`` (Abatzoglou-Mendel), else
    (Σ_j F_jᵀ F_j)⁻¹ (Wang, Zhang & Wu Theorem 1); a 1D station's elevation entry is 1."""
    if weighting == 'am':
        return PE                                         # G⁻¹ = P_E (Abatzoglou-Mendel)
    G = np.einsum('mnjki,mnjkl->mnil', F, F)              # G = Σ_j F_jᵀ F_j (Theorem 1)
    G[one_d, 1, 1] = 1.0
    return inv2(G)


def block_hx(X, F):
    """H_X = Σ_j a_j F_j − F_{n+1} (Wang, Zhang & Wu Theorem 1), (M, N, 2, 2); X (M, n)."""
    n = X.shape[-1]
    return np.einsum('mj,mnjkl->mnkl', X, F[:, :, :n]) - F[:, :, n]


def block_s(Hx, Ginv, one_d):
    """S = H_X G⁻¹ H_Xᵀ per station (M, N, 2, 2); a 1D station's elevation entry is 1."""
    S = Hx @ Ginv @ np.swapaxes(Hx, -1, -2)
    S[one_d, 1, 1] = 1.0
    return S


def block_cost(X, F, Ginv, H, Y, one_d):
    """f(X) of Wang, Zhang & Wu eq. (11), (M,); NaN where S is singular. r = H X − Y."""
    Sinv = inv2(block_s(block_hx(X, F), Ginv, one_d))
    r = np.einsum('mnki,mi->mnk', H, X) - Y               # C [X; −1] = H X − Y
    return np.einsum('mnk,mnkl,mnl->m', r, Sinv, r)


def block_derivatives(X, F, Ginv, H, Y, one_d):
    """f, gradient T_n (M, n), Hessian H_n (M, n, n) and its first (PSD) part.

    Wang, Zhang & Wu (2006) eq. (20) and appendix A:
        U  = (H_X G⁻¹ H_Xᵀ)⁻¹ C [X; −1]
        B1 = [H_X G⁻¹ F_1ᵀU  H_X G⁻¹ F_2ᵀU  H_X G⁻¹ F_3ᵀU]
        B2 = [F_1 G⁻¹ H_XᵀU  F_2 G⁻¹ H_XᵀU  F_3 G⁻¹ H_XᵀU]
        B3 = [F_1ᵀU  F_2ᵀU  F_3ᵀU]
        T_n = 2 (UᵀH − UᵀB1)ᵀ
        H_n = 2 (H − B1 − B2)ᵀ (H_X G⁻¹ H_Xᵀ)⁻¹ (H − B1 − B2) − 2 B3ᵀ G⁻¹ B3
    (the appendix's last line drops the factor 2 of T_n, and its intermediate second
    derivative prints (F_jG⁻¹H_Xᵀ + H_XG⁻¹F_jᵀ)⁻¹ where no inverse belongs; the final H_n
    above is the correct derivative, checked by finite differences in the tests).
    """
    n = X.shape[-1]
    Hx = block_hx(X, F)
    Sinv = inv2(block_s(Hx, Ginv, one_d))
    r = np.einsum('mnki,mi->mnk', H, X) - Y
    U = np.einsum('mnkl,mnl->mnk', Sinv, r)
    f = np.einsum('mnk,mnk->m', r, U)
    HxG = Hx @ Ginv                                       # H_X G⁻¹ (M, N, 2, 2)
    B3 = np.einsum('mnjlk,mnl->mnkj', F[:, :, :n], U)     # column j: F_jᵀ U
    B1 = np.einsum('mnkl,mnlj->mnkj', HxG, B3)            # column j: H_X G⁻¹ F_jᵀ U
    K = np.einsum('mnlk,mnl->mnk', HxG, U)                # G⁻¹ H_Xᵀ U (G⁻¹ symmetric)
    B2 = np.einsum('mnjkl,mnl->mnkj', F[:, :, :n], K)     # column j: F_j G⁻¹ H_Xᵀ U
    D = H - B1 - B2
    T = 2.0 * np.einsum('mnk,mnkj->mj', U, H - B1)
    H_gn = 2.0 * np.einsum('mnki,mnkl,mnlj->mij', D, Sinv, D)
    H_n = H_gn - 2.0 * np.einsum('mnki,mnkl,mnlj->mij', B3, Ginv, B3)
    return f, T, H_n, H_gn


class BlockProblem:
    """A batch of CTLS problems as per-station blocks, fixed over X: ``F`` (M, N, n+1, 2, 2),
    ``Ginv``, ``H``, ``Y``, ``PE``, ``one_d`` and ``weighting`` (set by the subclass: the 3D
    problem here, the plane-reduced one in core.horizontal_ctls)."""

    def _ginv(self, F):
        return block_ginv(F, self.PE, self.one_d, self.weighting)

    def cost(self, X):
        """f(X) of Wang, Zhang & Wu eq. (11), (M,); NaN where some S_i is singular."""
        return block_cost(X, self.F, self.Ginv, self.H, self.Y, self.one_d)

    def derivatives(self, X):
        """f (M,), gradient T_n (M, n), Hessian H_n and its first part (M, n, n)
        (:func:`block_derivatives`)."""
        return block_derivatives(X, self.F, self.Ginv, self.H, self.Y, self.one_d)


class _CTLSProblem(BlockProblem):
    """Blocks of Wang, Zhang & Wu eq. (11) for a batch, with the measured angles (fixed over X)."""

    def __init__(self, bearings, weighting):
        if weighting not in WEIGHTINGS:
            raise ValueError(f'weighting: must be one of {WEIGHTINGS}, got {weighting!r}')
        self.weighting = weighting
        self.has_el = bearings.has_elevation
        self.one_d = ~self.has_el
        psi = np.where(self.has_el, bearings.elevation, 0.0)
        self.F = ctls_blocks(bearings.azimuth, psi, self.has_el, bearings.positions)
        self.H, self.Y, _ = pseudo_linear_system(bearings)
        self.PE = np.zeros(bearings.azimuth.shape + (2, 2))
        self.PE[..., 0, 0] = bearings.sigma_az ** 2
        self.PE[..., 1, 1] = np.where(self.has_el, bearings.sigma_el, 0.0) ** 2
        self.Ginv = self._ginv(self.F)
        self.positions = bearings.positions

    def take(self, idx):
        out = object.__new__(_CTLSProblem)
        out.weighting = self.weighting
        for name in ('has_el', 'one_d', 'F', 'H', 'Y', 'PE', 'Ginv', 'positions'):
            setattr(out, name, getattr(self, name)[idx])
        return out

    def covariance(self, X, sigma_az, sigma_el):
        """P_ΔX of Wang, Zhang & Wu eq. (30) at X (M, 3), m²; everything evaluated at X.

        P = A⁻¹ H*ᵀ S⁻¹ (H_X P_E H_Xᵀ) S⁻¹ H* A⁻¹, A = H*ᵀ S⁻¹ H*, S = H_X G⁻¹ H_Xᵀ, where
        H*, F_j, G and H_X use the angles predicted from X (the noise-free angles of eq. (3),
        which is how eq. (30) is evaluated for the true target in eq. (32)); P_E =
        diag(σ_θi², σ_ψi²) from the bearings (1D: the elevation variance is 0). Returned
        symmetrised, (P + Pᵀ)/2: with an ill-conditioned A the rounding of A⁻¹ (LAPACK) made
        P[0, 2] and P[2, 0] differ by 1e-4 relative (two stations nearly in line with the
        target); the one-problem path (core/ctls_single.py) symmetrises the same way.
        """
        th, ps = azimuth_elevation(X[:, None, :] - self.positions)
        ps = np.where(self.has_el, ps, 0.0)
        pred = BearingSet(self.positions, th, np.where(self.has_el, ps, np.nan), sigma_az,
                          sigma_el)
        Hs, _, _ = pseudo_linear_system(pred)
        F = ctls_blocks(th, ps, self.has_el, self.positions)
        Ginv = self._ginv(F)
        Hx = block_hx(X, F)
        Sinv = inv2(block_s(Hx, Ginv, self.one_d))
        Q = Hx @ self.PE @ np.swapaxes(Hx, -1, -2)       # H_X P_E H_Xᵀ (eq. (29))
        A = np.einsum('mnki,mnkl,mnlj->mij', Hs, Sinv, Hs)
        B = np.einsum('mnki,mnkl,mnlp,mnpq,mnqj->mij', Hs, Sinv, Q, Sinv, Hs)
        Ainv = safe_inverse(A)
        ok = np.all(np.isfinite(Ainv), axis=(1, 2)) & np.all(np.isfinite(B), axis=(1, 2))
        P = np.full(A.shape, np.inf)
        Po = Ainv[ok] @ B[ok] @ Ainv[ok]
        P[ok] = 0.5 * (Po + np.swapaxes(Po, 1, 2))       # symmetrised (rounding of A⁻¹BA⁻¹)
        return P


def ctls_cost(X, bearings, weighting='paper'):
    """f(X) of Wang, Zhang & Wu eq. (11) for X (M, 3) m and the measured bearings; (M,)."""
    return _CTLSProblem(bearings, weighting).cost(np.atleast_2d(np.asarray(X, dtype=float)))


def ctls_derivatives(X, bearings, weighting='paper'):
    """(f, T_n, H_n, GN part) of Wang, Zhang & Wu eq. (20)/appendix A at X (M, 3); for checks."""
    return _CTLSProblem(bearings, weighting).derivatives(
        np.atleast_2d(np.asarray(X, dtype=float)))


def ctls_covariance(X, bearings, weighting='paper'):
    """Predicted covariance P_ΔX (M, 3, 3), m², of Wang, Zhang & Wu eq. (30) at X (M, 3).

    With X the true target this is the paper's error model; sqrt(trace) is ε of eq. (32).
    ``weighting='am'`` gives the Abatzoglou-Mendel CTLS, whose P equals the CRLB.
    """
    p = _CTLSProblem(bearings, weighting)
    return p.covariance(np.atleast_2d(np.asarray(X, dtype=float)), bearings.sigma_az,
                        bearings.sigma_el)


def _rms_range(sub, X):
    """rms station range (M,), m, at X (M, 3): the scale of the step test."""
    return np.sqrt(np.mean(np.sum((X[:, None, :] - sub.positions) ** 2, axis=-1), axis=1))


def station_centroid(positions):
    """Mean station position (M, 3), m, of ``positions`` (M, N, 3): the origin ``ctls_am`` is
    solved in (:func:`constrained_tls`).

    Summed station by station in station order (Python floats for M = 1, one numpy addition
    per station otherwise): the same IEEE operations in the same order, so the one-problem
    and batch paths use the same centre to the bit.
    """
    M, N, _ = positions.shape
    if M == 1:
        sx = sy = sz = 0.0
        for x, y, z in positions[0].tolist():
            sx += x
            sy += y
            sz += z
        return np.array([[sx / N, sy / N, sz / N]])
    c = np.zeros((M, 3))
    for n in range(N):
        c += positions[:, n]
    return c / N


def constrained_tls(bearings, weighting='paper', **options):
    """CTLS by the Newton iteration of Wang, Zhang & Wu eq. (20), batch over M problems.

    X_{n+1} = X_n − μ_n H_n⁻¹ T_n (eq. (20)), started from X_LS (eq. (4), as the paper
    suggests) or option ``initial``. μ_n = μ^n with μ = option ``step_decay`` (default 1:
    the paper requires μ < 1 but leaves its value open, section 5). Safeguards (ours): when
    H_n is not positive definite the positive semi-definite first term of H_n is used instead
    (a Gauss-Newton direction), and the step is halved (up to 40 times) until f does not
    increase, so the cost never increases. Converged when the full Newton step H_n⁻¹T_n is
    shorter than ``tolerance`` × rms range. Near the optimum the step can stay just above
    that while every trial step changes f only by rounding: so a problem that stops without
    meeting the step test (no trial step lowers f, or the iteration limit is reached) has
    also converged when the predicted decrease of its last Newton step, ½ T_nᵀH_n⁻¹T_n, is
    below 1e-10 × f/dof (the step is then under 1e-5 of the standard deviation implied by
    the residual scatter; dof = measurements − 3) or below 1e-12 × f (the cost's rounding):
    the stop the maximum likelihood iteration uses (core/estimators.py). Otherwise no
    descent step is ``diverged`` and the limit is ``max_iterations``.
    Covariance: eq. (30) at the estimate (:meth:`_CTLSProblem.covariance`). One ``ctls_am``
    problem (M = 1) runs the same iteration on Python floats (core/ctls_single.py, same
    results to rounding). ``ctls`` keeps the batch path: its G holds the station coordinates,
    so with coordinates of tens of km a rounding difference grows to ~1e-9 of the covariance.

    Centring (``ctls_am`` only, both paths): the problem is solved in coordinates centred on
    the stations, p_i − c and X − c with c the station centroid (:func:`station_centroid`;
    option ``initial`` shifted alike), and c is added back to the estimate. With G⁻¹ = P_E
    everything depends on X and the stations only through X − p_i: the rows h_i hold angles
    only, r_i = h_i X − h_i p_i = h_i (X − p_i), H_X = Σ_j a_j F_j − F_4 has the entries
    −(cos θ (x − x_i) + sin θ (y − y_i)) etc. (F_4 is linear in p_i, F_1..F_3 hold angles
    only), X_LS (eq. (4)) moves with the origin, and the step test's rms range and eq. (30)
    (at the angles predicted from X − p_i) do not change; so f, T_n, H_n, the iterates and
    P are translation invariant in exact arithmetic, and centring changes results only by
    rounding (measured on ordinary problems, stations ±50 km from the origin: median 1e-13
    of the range; up to 1e-9 where the old or new fix stopped one Newton step of that size
    short of the optimum, the stopping point being decided by rounding of f). It matters in
    large absolute coordinates (UTM-like, stations near (8e6, 9e6) m): Y_i = h_i p_i ~ 1e7 m
    and r_i = h_i X − Y_i cancels to metres, so f carried rounding of 1e-11..1e-10 relative
    (1e-13 centred), above the 1e-12 f of the rounding stop; the backtracking's f_t ≤ f
    compared rounding noise, and the one-problem and batch paths (different summation
    order) stopped differently: ``ok`` against ``max_iterations`` or ``diverged``, fixes up
    to 3e-8 of the range apart (test/test_ctls_utm.py). ``ctls`` (the paper's G holds p_i
    through F_4) is not translation invariant (module doc, bench/ctls_origin.py) and is
    solved in the given coordinates.

    ``weighting``: ``'paper'`` (estimator ``ctls``) or ``'am'`` (``ctls_am``), see module doc.
    Options: ``step_decay``, ``max_iterations``, ``tolerance``, ``initial``.
    """
    if weighting not in WEIGHTINGS:
        raise ValueError(f'weighting: must be one of {WEIGHTINGS}, got {weighting!r}')
    spec = (ctls if weighting == 'paper' else ctls_am).spec
    bearings.validate()
    if weighting == 'paper':
        return _solve(spec, bearings, weighting, options)
    centre = station_centroid(bearings.positions)       # ctls_am: centred (see above)
    centred = BearingSet(bearings.positions - centre[:, None, :], bearings.azimuth,
                         bearings.elevation, bearings.sigma_az, bearings.sigma_el,
                         bearings.stations)
    res = _solve(spec, centred, weighting, options, centre)
    res.position = res.position + centre
    return res


def _solve(spec, bearings, weighting, options, centre=None):
    """:func:`constrained_tls` for validated ``bearings``; option ``initial`` minus
    ``centre`` (M, 3) when given (the bearings are then centred on it)."""
    name = spec.name
    if bearings.M == 1 and weighting == 'am':
        opts = spec.parse(options, 1)
        if opts.get('initial') is not None:
            opts['initial'] = opts['initial'] - centre
        # (imported here: the compiled one-problem path loads numba, which a process that
        # never solves one problem need not pay for)
        from .ctls_single import solve_one
        res = solve_one(name, bearings, opts)
        if res is not None:
            return res
    opts, x0 = start(spec, bearings, options, validated=True)
    if centre is not None and opts.get('initial') is not None:
        x0 = x0 - centre
    problem = _CTLSProblem(bearings, weighting)
    mu, tol = opts['step_decay'], opts['tolerance']
    dof = np.maximum(bearings.N + np.count_nonzero(bearings.has_elevation, axis=1) - 3, 1)
    rel_tol = np.maximum(CHI2_STEP_TOL / dof, COST_RTOL)
    X, iterations, converged, diverged = newton_backtracking(
        problem, x0.copy(), mu, tol, opts['max_iterations'], rel_tol, _rms_range)
    P = problem.covariance(np.where(np.isfinite(X), X, 0.0), bearings.sigma_az,
                           bearings.sigma_el)
    return iterative_result(name, X, P, iterations, converged, diverged)


CTLS_OPTIONS = ITERATIVE_OPTIONS + (STEP_DECAY, CONSISTENCY)


@declare('ctls', MULTISTATION, CTLS_OPTIONS, BEARING_SIGMA)
def ctls(bearings, **options):
    """Constrained TLS exactly as Wang, Zhang & Wu publish it (eqs. (9)-(20), appendix A, (30)).

    See :func:`constrained_tls` (weighting ``'paper'``). Options: ``step_decay`` (μ of
    eq. (20)), ``max_iterations``, ``tolerance``, ``initial``, ``consistency`` (default true:
    an ``ok`` fix that fails the residual χ², outlier or nonlinearity check at its estimate,
    for example one stopped at a spurious minimum, is ``low_confidence``;
    :func:`~bearing_loc_ros.core.robust.consistency_status`).
    """
    return checked(constrained_tls(bearings, weighting='paper', **options), bearings,
                   options.get('consistency', CONSISTENCY.default))


@declare('ctls_am', MULTISTATION, CTLS_OPTIONS, BEARING_SIGMA)
def ctls_am(bearings, **options):
    """Abatzoglou-Mendel constrained TLS: Wang, Zhang & Wu eq. (11) with G replaced by P_E⁻¹.

    f(X) = [X; −1]ᵀCᵀ(H_X P_E H_Xᵀ)⁻¹C[X; −1]; invariant to origin and units and efficient
    (its eq. (30) covariance is the CRLB). See :func:`constrained_tls` (weighting ``'am'``).
    Same options as :func:`ctls`.
    """
    # (option consistency validated by constrained_tls)
    return checked(constrained_tls(bearings, weighting='am', **options), bearings,
                   options.get('consistency', CONSISTENCY.default))
