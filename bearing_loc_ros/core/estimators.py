"""Bearing-only localization estimators, batch-first, and the table that names them.

Every estimator takes a :class:`~bearing_loc_ros.core.bearings.BearingSet` (M problems of N
bearings, any mix of 1D/2D) and keyword options, and returns a
:class:`~bearing_loc_ros.core.fix.FixResult`. Each is declared with its options, noise model
and mode next to its definition (:mod:`~bearing_loc_ros.core.estimator_spec`);
:mod:`~bearing_loc_ros.core.registry` answers questions about them by name.

* ``ls``: Wang, Zhang & Wu eq. (4), pseudo-linear least squares (closed form,
  core/pseudo_linear.py).
* ``tls``: Wang, Zhang & Wu eq. (5), total least squares (closed form, core/pseudo_linear.py).
* ``ctls``: Wang, Zhang & Wu eqs. (9)-(20), appendix A, (30): constrained TLS with the paper's
  G, Newton iteration (core/constrained_tls.py).
* ``ctls_am``: Wang, Zhang & Wu eq. (11) with G = P_E⁻¹ (Abatzoglou-Mendel CTLS), same code.
* ``mle``: Zong & Cui 2015 eqs. (3)-(8), Gauss-Newton maximum likelihood with
  Levenberg-Marquardt damping (the default, :data:`DEFAULT_ESTIMATOR`).
* ``wmle``: Zong & Cui 2015 eqs. (9)-(11), maximum likelihood with σ growing with range.

Conventions (docs/design.md): ENU metres, azimuth θ CCW from East, elevation ψ above the
horizontal, radians; an azimuth-only (1D) bearing has elevation NaN. Every estimator is O(N)
per problem and per iteration (sums of per-station terms; no dense 2N × 2N matrix is ever
formed) and is vectorised over the M problems (no Python loop over problems or stations).

Options (keyword arguments; an unknown one raises ``ValueError('options.<name>: ...')``):

* ``max_iterations`` (int ≥ 1, default 50) and ``tolerance`` (float > 0, default 1e-9):
  accepted by every estimator, ignored by the closed-form ``ls`` and ``tls``. An iterative
  estimator has converged when its full (undamped) Newton/Gauss-Newton step is shorter than
  ``tolerance`` × the rms station-to-estimate range (a relative, unit-free test).
* ``initial`` ((3,) or (M, 3), m): starting point of the iterative estimators (default: ``ls``).
* ``reference_range`` (m, > 0, default 1000): ``wmle`` only, d_ref of Zong & Cui 2015
  eqs. (9)-(10).
* ``step_decay`` (0 < μ ≤ 1, default 1): ``ctls``/``ctls_am`` only, μ of Wang, Zhang & Wu
  eq. (20).

Status values (:mod:`~bearing_loc_ros.core.fix`): ``ok`` (converged), ``max_iterations``,
``diverged`` (no descent possible or the estimate ran away), ``degenerate_geometry`` (the
information matrix is singular at the estimate, e.g. all bearings on one line; position is NaN
then). ``converged`` is True only for ``ok``, and a converged result always has a finite
position.
"""

import numpy as np

from .constrained_tls import ctls, ctls_am
from .crlb import crlb
from .estimator_spec import (BEARING_SIGMA, DEFAULT_REFERENCE_RANGE, declare, ITERATIVE_OPTIONS,
                             MULTISTATION, RANGE_GROWN_SIGMA, range_scaled_sigmas,
                             REFERENCE_RANGE, ROBUST, ROBUST_ON)
from .ml_single import solve_one
from .fix import (FixResult, iterative_result, STATUS_DEGENERATE, STATUS_DIVERGED,
                  STATUS_MAX_ITERATIONS, STATUS_OK, STATUSES)
from .pseudo_linear import ls, pseudo_linear_system, start, tls
from .robust import confident_result
from .solvers import CHI2_STEP_TOL, COST_RTOL, solve3_packed, spd_inverse3

__all__ = ['DEFAULT_ESTIMATOR', 'DEFAULT_REFERENCE_RANGE', 'ESTIMATORS', 'FixResult', 'STATUSES',
           'STATUS_DEGENERATE', 'STATUS_DIVERGED', 'STATUS_MAX_ITERATIONS', 'STATUS_OK', 'ctls',
           'ctls_am', 'locate', 'ls', 'mle', 'noise_model_crlb', 'option_defaults',
           'pseudo_linear_system', 'range_scaled_sigmas', 'tls', 'wmle']

#: Estimator used when none is named (CLI, fusion node): best measured RMSE/CRLB among the
#: estimators that converge reliably (docs/estimators.md).
DEFAULT_ESTIMATOR = 'mle'


# ----------------------------------------------------------------------------------------------
# Maximum likelihood (Zong & Cui 2015)

# Rows of the packed per-problem state of the ML iteration (see _MLProblem.pack).
_A00, _A01, _A02, _A11, _A12, _A22, _B0, _B1, _B2, _COST, _SCALE, _OLD = range(12)
# Two more rows with ``screen_rows``: the largest whitened r² of any angle and the smallest
# squared station range, m², at X (the robust screen's statistics, core.robust).
_WORST, _RHO2MIN = 12, 13


class _MLProblem:
    """Per-bearing arrays of the ML cost of Zong & Cui 2015 eqs. (3)-(5), station-major (N, M).

    The cost is J(X) = Σ_k (e_θk/σ_θk)² + (e_ψk/σ_ψk)² with e = measured − predicted angle
    (azimuth wrapped to (−π, π]), Zong & Cui 2015 eq. (3) with W of eq. (4); with ``d_ref`` set,
    σ_k = σ_ref,k · d_k / d_ref (eqs. (9)-(11)), d_k = |X − S_k| at the current iterate.
    Arrays are stored (N, M) so the sums over stations are fast row additions for small N
    and large M; 1D bearings have 1/σ_ψ = 0 (no elevation term).
    """

    def __init__(self, bearings, d_ref=None):
        pos = bearings.positions
        self.px = np.ascontiguousarray(pos[..., 0].T)
        self.py = np.ascontiguousarray(pos[..., 1].T)
        self.pz = np.ascontiguousarray(pos[..., 2].T)
        has_el = bearings.has_elevation.T
        self.az = np.ascontiguousarray(bearings.azimuth.T)
        self.el = np.where(has_el, bearings.elevation.T, 0.0)
        self.sa = 1.0 / bearings.sigma_az.T                       # sqrt of W⁻¹, eq. (4)
        self.se = np.where(has_el, 1.0 / np.where(has_el, bearings.sigma_el.T, 1.0), 0.0)
        self.d_ref = None if d_ref is None else float(d_ref)
        self.n_measurements = bearings.N + np.count_nonzero(has_el, axis=0)
        self.screen_rows = False

    def pseudo_linear_start(self):
        """X_LS (M, 3) of Wang, Zhang & Wu eq. (4) from the station-major arrays; NaN if singular.

        Same maths as :func:`ls`: HᵀH and HᵀY summed over the rows of eq. (2), solved by
        cofactors. H's rows are unit vectors, so HᵀH is dimensionless with trace N + n_2D;
        it is treated as singular when det(HᵀH) ≤ 1e-12 (trace/3)³ (≈ reciprocal condition
        number 1e-12, the threshold of crlb.safe_inverse used by ``ls``).
        """
        s, c = np.sin(self.az), np.cos(self.az)
        m = (self.se > 0).astype(float)
        sp, cp = np.sin(self.el), np.cos(self.el)
        y1 = s * self.px - c * self.py                          # azimuth row of eq. (2)
        h20, h21, h22 = m * c * sp, m * s * sp, -m * cp          # elevation row (0 for 1D)
        y2 = h20 * self.px + h21 * self.py + h22 * self.pz
        a00 = (s * s + h20 * h20).sum(axis=0)
        a01 = (-s * c + h20 * h21).sum(axis=0)
        a02 = (h20 * h22).sum(axis=0)
        a11 = (c * c + h21 * h21).sum(axis=0)
        a12 = (h21 * h22).sum(axis=0)
        a22 = (h22 * h22).sum(axis=0)
        b0 = (s * y1 + h20 * y2).sum(axis=0)
        b1 = (-c * y1 + h21 * y2).sum(axis=0)
        b2 = (h22 * y2).sum(axis=0)
        det = (a00 * (a11 * a22 - a12 * a12) + a01 * (a02 * a12 - a01 * a22)
               + a02 * (a01 * a12 - a02 * a11))
        ok = det > 1e-12 * ((a00 + a11 + a22) / 3.0) ** 3
        x = np.stack(solve3_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2), axis=1)
        x[~ok] = np.nan
        return x

    def take(self, idx):
        """The same problem restricted to the problems ``idx``."""
        out = object.__new__(_MLProblem)
        for name in ('px', 'py', 'pz', 'az', 'el', 'sa', 'se'):
            setattr(out, name, getattr(self, name)[:, idx])
        out.d_ref = self.d_ref
        out.screen_rows = self.screen_rows
        out.n_measurements = self.n_measurements[idx]
        return out

    def pack(self, x, y, z, old_factor=None):
        """Packed state at X = (x, y, z), each (M,): rows _A00.._OLD of a (12, M) array.

        A = JᵀW⁻¹J (6 unique entries, 1/m²) and b = JᵀW⁻¹e (1/m) of Zong & Cui 2015 eqs. (7)-(8),
        where J holds the angle gradients of crlb.angle_jacobians (the paper's J_i is −J,
        because its e is measured − predicted, so the Gauss-Newton step X_{i+1} = X_i −
        (J_iᵀW⁻¹J_i)⁻¹J_iᵀW⁻¹e of eq. (8) is X + A⁻¹b here); the cost J(X); the rms range
        (m); and, for range weighting, the cost of X under the weights W_i of the previous
        iterate (``old_factor`` = its d_ref²/d², (N, M)). Also returns this X's weight factor
        (None without range weighting).
        """
        with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
            dx = x - self.px
            dy = y - self.py
            dz = z - self.pz
            rho2 = dx * dx + dy * dy
            r2 = rho2 + dz * dz
            rho = np.sqrt(rho2)
            # Residuals e = measured − predicted (Zong & Cui 2015 eq. (5)), azimuth wrapped to
            # (−π, π].
            e_az = self.az - np.arctan2(dy, dx)
            e_az -= 2.0 * np.pi * np.ceil((e_az - np.pi) / (2.0 * np.pi))
            e_el = self.el - np.arctan2(dz, rho)
            sa, se = self.sa, self.se
            ra = sa * e_az                                     # whitened residuals
            re = se * e_el
            q = np.empty((14 if self.screen_rows else 12, x.shape[0]))
            factor = None
            if self.d_ref is not None:
                # Zong & Cui (2015) eqs. (9)-(11): σ_k(d) = σ_ref (d_k / d_ref).
                factor = self.d_ref * self.d_ref / r2
                rr = ra * ra + re * re
                q[_OLD] = (rr * (factor if old_factor is None else old_factor)).sum(axis=0)
                f = np.sqrt(factor)
                sa, se, ra, re = sa * f, se * f, ra * f, re * f
            # Whitened angle gradients (crlb.angle_jacobians): ∇θ = (−dy, dx, 0)/ρ²,
            # ∇ψ = (−dx dz, −dy dz, ρ²)/(ρ r²).
            qa = sa / rho2
            ax = -dy * qa
            ay = dx * qa
            t = se * dz / (rho * r2)
            ex = -dx * t
            ey = -dy * t
            ez = se * rho / r2
            q[_A00] = (ax * ax + ex * ex).sum(axis=0)
            q[_A01] = (ax * ay + ex * ey).sum(axis=0)
            q[_A02] = (ex * ez).sum(axis=0)
            q[_A11] = (ay * ay + ey * ey).sum(axis=0)
            q[_A12] = (ey * ez).sum(axis=0)
            q[_A22] = (ez * ez).sum(axis=0)
            q[_B0] = (ax * ra + ex * re).sum(axis=0)
            q[_B1] = (ay * ra + ey * re).sum(axis=0)
            q[_B2] = (ez * re).sum(axis=0)
            rra, rre = ra * ra, re * re
            q[_COST] = (rra + rre).sum(axis=0)
            if self.screen_rows:
                q[_WORST] = np.maximum(rra, rre).max(axis=0)
                q[_RHO2MIN] = rho2.min(axis=0)
            q[_SCALE] = np.sqrt(r2.mean(axis=0))
        if self.d_ref is None:
            q[_OLD] = q[_COST]
        return q, factor

    def evaluate(self, X):
        """Cost (M,), A (M, 3, 3), b (M, 3) and rms range (M,) at X (M, 3) (for checks)."""
        q, _ = self.pack(X[:, 0], X[:, 1], X[:, 2])
        return q[_COST], _unpack_matrix(q), q[[_B0, _B1, _B2]].T, q[_SCALE]


def _unpack_matrix(q):
    """(M, 3, 3) symmetric matrices from the packed rows _A00.._A22."""
    A = np.empty((q.shape[1], 3, 3))
    for (i, j), row in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
                           (_A00, _A01, _A02, _A11, _A12, _A22)):
        A[:, i, j] = A[:, j, i] = q[row]
    return A


def _levenberg_marquardt(problem, x0, max_iterations, tolerance, state=None):
    """Gauss-Newton (Zong & Cui 2015 eq. (8)) with Levenberg-Marquardt damping, over M problems.

    Step: (A + λ diag(A)) Δ = b, X ← X + Δ if the cost does not increase (else the step is
    rejected and λ ← max(10λ, 10⁻³)); λ starts at 0 (pure Gauss-Newton, eq. (8)) and is
    divided by 10 after an accepted step (0 below 10⁻⁶). Converged when the undamped step
    Δ = A⁻¹b is shorter than ``tolerance`` × rms range, or when its predicted cost decrease
    bᵀΔ = ΔᵀAΔ is below 1e-10 × cost/dof (dof = measurements − 3; i.e. the step is shorter
    than 1e-5 of the standard deviation implied by the residual scatter, which makes the test
    independent of the scale of σ and d_ref) or below 1e-12 × cost (smaller decreases cannot
    be resolved in floating point). The last, sub-tolerance step is not taken. Diverged when λ
    exceeds 10¹² (no descent step exists) or the estimate runs 10⁸ × its initial range away.
    Problems are iterated together (all state packed in one (12, M) array); converged ones
    are frozen and the working set is compacted when it halves: no Python loop over problems
    or stations. Returns (X, A at X, iterations, converged, diverged); A is the Fisher
    information at X (Zong & Cui 2015 eqs. (6)-(8)), in 1/m². ``state``: a list that
    receives the final packed state (rows, M) at X.
    """
    M = x0.shape[0]
    finite0 = np.all(np.isfinite(x0), axis=1)
    X = np.where(finite0[:, None], x0, 0.0).T.copy()           # (3, M)
    Q, factor = problem.pack(X[0], X[1], X[2])
    iterations = np.zeros(M, dtype=int)
    converged = np.zeros(M, dtype=bool)
    diverged = ~finite0
    active = np.flatnonzero(finite0)
    full = active.size == M
    sub = problem if full else problem.take(active)
    sX = X if full else X[:, active]
    sQ = Q if full else Q[:, active]
    sF = None if factor is None else (factor if full else factor[:, active])
    lam = np.zeros(active.size)
    scale0 = sQ[_SCALE].copy()
    # Decrease threshold relative to the cost: 1e-10 × cost/dof (the squared step in units
    # of the scatter-implied standard deviation), at least the cost's rounding level.
    dof = np.maximum(sub.n_measurements - 3, 1)
    rel_tol = np.maximum(CHI2_STEP_TOL / dof, COST_RTOL)
    it = np.zeros(active.size, dtype=int)
    done = np.zeros(active.size, dtype=bool)
    conv = np.zeros(active.size, dtype=bool)
    div = np.zeros(active.size, dtype=bool)

    def flush():
        X[:, active] = sX
        Q[:, active] = sQ
        iterations[active] = it
        converged[active] = conv
        diverged[active] = div

    for _ in range(max_iterations):
        if done.all():
            break
        n_run = done.size - np.count_nonzero(done)
        if done.size > 64 and 2 * n_run <= done.size:
            flush()
            keep = np.flatnonzero(~done)
            active, sub = active[keep], sub.take(keep)
            sX, sQ, lam, scale0 = sX[:, keep], sQ[:, keep], lam[keep], scale0[keep]
            rel_tol = rel_tol[keep]
            sF = None if sF is None else sF[:, keep]
            it, done, conv, div = it[keep], done[keep], conv[keep], div[keep]
        run = ~done
        a00, a01, a02, a11, a12, a22, b0, b1, b2 = sQ[:_COST]
        g = solve3_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2)   # A⁻¹ b, eq. (8)
        if np.any(lam > 0):
            k = 1.0 + lam
            d = solve3_packed(a00 * k, a01, a02, a11 * k, a12, a22 * k, b0, b1, b2)
            damped = lam > 0
            step = np.where(damped, np.stack(d), np.stack(g))
        else:
            step = np.stack(g)
        # Convergence (see docstring) on the undamped step g.
        gn = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        decrease = np.abs(b0 * g[0] + b1 * g[1] + b2 * g[2])
        small = (gn <= tolerance * sQ[_SCALE]) | (decrease <= rel_tol * sQ[_COST])
        if np.all(small | done):
            # Every remaining problem has converged. A converged problem's last step is below
            # the tolerance and is never taken (so a batch gives exactly the per-problem
            # results); when all have converged the trial evaluation is skipped.
            it += run
            conv |= run
            break
        step_ok = np.isfinite(step).all(axis=0)
        Xt = sX + np.where(run & step_ok, step, 0.0)
        Qt, Ft = sub.pack(Xt[0], Xt[1], Xt[2], sF)
        accept = run & ~small & step_ok & (Qt[_OLD] <= sQ[_COST])
        sX = np.where(accept, Xt, sX)
        sQ = np.where(accept, Qt, sQ)
        if sF is not None:
            sF = np.where(accept, Ft, sF)
        lam = np.where(accept, np.where(lam < 1e-6, 0.0, 0.1 * lam),
                       np.maximum(10.0 * lam, 1e-3))
        it += run
        newly = run & small
        conv |= newly
        runaway = run & ~newly & ((lam > 1e12) | (sQ[_SCALE] > 1e8 * scale0))
        div |= runaway
        done |= newly | runaway
    flush()
    X = X.T.copy()
    X[~finite0] = np.nan
    if state is not None:
        state.append(Q)
    return X, _unpack_matrix(Q), iterations, converged & finite0, diverged


@declare('mle', MULTISTATION, ITERATIVE_OPTIONS + (ROBUST_ON,), BEARING_SIGMA)
def mle(bearings, **options):
    """Gauss-Newton maximum likelihood, Zong & Cui 2015 eqs. (3)-(8), per-bearing σ.

    Maths: X̂ = argmin J(X) = eᵀW⁻¹e (eq. (3), (6)) with W = diag(σ_θk², σ_ψk²) (eq. (4)) and
    e = measured − predicted angles (eq. (5); azimuth residuals wrapped to (−π, π]; 1D
    bearings contribute only their azimuth term). Iteration eq. (8),
    X_{i+1} = X_i − (J_iᵀW⁻¹J_i)⁻¹J_iᵀW⁻¹e(X_i), started from ``ls`` (the paper's pseudo-linear
    initial value), with Levenberg-Marquardt damping so the cost never increases (see
    :func:`_levenberg_marquardt`). Covariance: the inverse Fisher information J_iᵀW⁻¹J_i at the
    estimate — the CRLB of crlb.py evaluated at X̂ (m²). Options: ``max_iterations``,
    ``tolerance``, ``initial``. Cost O(N) per iteration and problem. One problem (M = 1)
    runs the same iteration on Python floats (core/ml_single.py, same results to rounding).
    Option ``robust`` (default true: ``mle`` is the default estimator and must never
    report a confidently wrong fix): the fix is screened and, when in doubt (residual χ²
    outside its band, an angle beyond 3.9σ, a large confidence region, or no convergence),
    replaced by a consensus over station subsets and a refit without outlier bearings, and
    assessed (status ``ok`` or ``low_confidence``, fields ``excluded`` and
    ``nonlinearity``; :mod:`~bearing_loc_ros.core.robust`). At high SNR the screen keeps
    the paper's fix unchanged. ``robust=False`` gives the paper's estimator alone.
    """
    bearings.validate()
    res = stats = None
    if bearings.M == 1:
        opts = mle.spec.parse(options, 1)
        res = solve_one('mle', bearings, None, opts)
    if res is None:
        problem = _MLProblem(bearings)
        opts, x0 = start(mle.spec, bearings, options, problem.pseudo_linear_start,
                         validated=True)
        # The robust screen's residual statistics come from the iteration's last evaluation.
        problem.screen_rows = bool(opts['robust'])
        state = []
        x, info, it, conv, div = _levenberg_marquardt(problem, x0, opts['max_iterations'],
                                                      opts['tolerance'], state)
        res = iterative_result('mle', x, spd_inverse3(info), it, conv, div)
        if problem.screen_rows:
            Q = state[0]
            stats = (Q[_COST], Q[_WORST], Q[_RHO2MIN], problem.n_measurements)
    return confident_result(res, bearings, screen_stats=stats) if opts['robust'] else res


@declare('wmle', MULTISTATION, ITERATIVE_OPTIONS + (REFERENCE_RANGE, ROBUST),
         RANGE_GROWN_SIGMA)
def wmle(bearings, **options):
    """Range-weighted maximum likelihood, Zong & Cui 2015 eqs. (9)-(11).

    The σ stored in the bearings is σ_ref, the error at the reference range d_ref (option
    ``reference_range``, m, default 1000). At every Gauss-Newton iterate X_i the paper sets
    σ_ki = (d_ki / d_ref) σ_ref (eqs. (9)-(10)), d_ki the range from station k to the
    current estimate X_i (we use the slant range |X_i − S_k|; the paper calls it 目标距离,
    "target distance"), builds W_i (eq. (11)) and takes the step of eq. (8) with W_i. W_i is
    held fixed within a step (iteratively reweighted least squares; the log σ(d) term of the
    exact likelihood is not included, exactly as in the paper). A step is accepted when it
    does not increase the cost under W_i. Covariance: inverse Fisher information with
    σ(d̂) at the estimate (m²). Options: ``reference_range``, ``max_iterations``,
    ``tolerance``, ``initial``, ``robust`` (default false, opt-in because it replaces every
    paper fix; as for :func:`mle`, and every fix
    is refitted on the full likelihood, with the Σ log σ(d)² term the paper's cost
    omits: without it the cost falls toward 0 as the range grows; core.robust).
    """
    bearings.validate()
    opts = wmle.spec.parse(options, bearings.M)
    d_ref = opts['reference_range']
    res = None
    if bearings.M == 1:
        res = solve_one('wmle', bearings, d_ref, opts)
    if res is None:
        problem = _MLProblem(bearings, d_ref=d_ref)
        opts, x0 = start(wmle.spec, bearings, options, problem.pseudo_linear_start,
                         validated=True)
        x, info, it, conv, div = _levenberg_marquardt(problem, x0, opts['max_iterations'],
                                                      opts['tolerance'])
        res = iterative_result('wmle', x, spd_inverse3(info), it, conv, div)
    return confident_result(res, bearings, d_ref) if opts['robust'] else res


ESTIMATORS = {
    'ls': ls,
    'tls': tls,
    'ctls': ctls,
    'ctls_am': ctls_am,
    'mle': mle,
    'wmle': wmle,
}


def option_defaults(method):
    """The options estimator ``method`` accepts, with their defaults ({} for another name)."""
    fn = ESTIMATORS.get(method)
    spec = getattr(fn, 'spec', None)
    return {} if spec is None else spec.defaults()


def locate(method, bearings, **options):
    """Run estimator ``method`` (a name in :data:`ESTIMATORS`, None = DEFAULT_ESTIMATOR).

    Raises ``ValueError`` for an unknown name, invalid bearings (see BearingSet.validate) or
    an unknown/invalid option (message ``options.<name>: ...``).
    """
    if method is None:
        method = DEFAULT_ESTIMATOR
    try:
        fn = ESTIMATORS[method]
    except (KeyError, TypeError):
        raise ValueError(f'method: unknown estimator {method!r}; choose one of '
                         f'{sorted(ESTIMATORS)}') from None
    if getattr(fn, 'spec', None) is None:
        bearings.validate()            # a declared estimator validates its input itself
    return fn(bearings, **options)


def noise_model_crlb(method, position, bearings, **options):
    """CRLB (M, 3, 3), m², at ``position`` under the noise model estimator ``method`` assumes.

    The σ are those of the estimator's declared noise model (``spec.noise``): as given by the
    bearings, or grown with range for ``wmle`` (Zong & Cui 2015 eqs. (9)-(10), option
    ``reference_range``). inf where singular or where ``position`` is NaN.
    """
    position = np.asarray(position, dtype=float)
    pos = np.where(np.isfinite(position), position, 0.0)
    spec = getattr(ESTIMATORS.get(method), 'spec', None)
    noise = BEARING_SIGMA if spec is None else spec.noise
    saz, sel = noise.sigmas(bearings, pos, options)
    out = crlb(pos, bearings.positions, saz, sel, bearings.has_elevation)
    out[~np.all(np.isfinite(position), axis=1)] = np.inf
    return out
