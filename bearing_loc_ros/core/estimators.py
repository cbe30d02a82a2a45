"""Bearing-only localization estimators, batch-first, and the registry that names them.

Every estimator takes a :class:`~bearing_loc_ros.core.bearings.BearingSet` (M problems of N
bearings, any mix of 1D/2D) and keyword options, and returns a :class:`FixResult`.

* ``ls``: seed 000 eq. (4), pseudo-linear least squares (closed form).
* ``tls``: seed 000 eq. (5), total least squares (closed form).
* ``ctls``: seed 000 eqs. (9)-(20), appendix A, (30): constrained TLS with the paper's G,
  Newton iteration (core/ctls.py).
* ``ctls_am``: seed 000 eq. (11) with G = P_E⁻¹ (Abatzoglou-Mendel CTLS), same Newton code.
* ``mle``: seed 003 eqs. (3)-(8), Gauss-Newton maximum likelihood with Levenberg-Marquardt
  damping (the default, :data:`DEFAULT_ESTIMATOR`).
* ``wmle``: seed 003 eqs. (9)-(11), maximum likelihood with σ growing with range.

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians; an azimuth-only (1D) bearing has elevation NaN. Every estimator is O(N) per problem
and per iteration (sums of per-station terms; no dense 2N × 2N matrix is ever formed) and is
vectorised over the M problems (no Python loop over problems or stations).

Options (keyword arguments; an unknown one raises ``ValueError('options.<name>: ...')``):

* ``max_iterations`` (int ≥ 1, default 50) and ``tolerance`` (float > 0, default 1e-9):
  accepted by every estimator, ignored by the closed-form ``ls`` and ``tls``. An iterative
  estimator has converged when its full (undamped) Newton/Gauss-Newton step is shorter than
  ``tolerance`` × the rms station-to-estimate range (a relative, unit-free test).
* ``initial`` ((3,) or (M, 3), m): starting point of the iterative estimators (default: ``ls``).
* ``reference_range`` (m, > 0, default 1000): ``wmle`` only, d_ref of seed 003 eqs. (9)-(10).
* ``step_decay`` (0 < μ ≤ 1, default 1): ``ctls``/``ctls_am`` only, μ of seed 000 eq. (20).

Status values: ``ok`` (converged), ``max_iterations``, ``diverged`` (no descent possible or the
estimate ran away), ``degenerate_geometry`` (the information matrix is singular at the
estimate, e.g. all bearings on one line; position is NaN then). ``converged`` is True only for
``ok``, and a converged result always has a finite position.
"""

from dataclasses import dataclass
import numbers

import numpy as np

from .crlb import crlb, safe_inverse

STATUS_OK = 'ok'
STATUS_MAX_ITERATIONS = 'max_iterations'
STATUS_DIVERGED = 'diverged'
STATUS_DEGENERATE = 'degenerate_geometry'
STATUSES = (STATUS_OK, STATUS_MAX_ITERATIONS, STATUS_DIVERGED, STATUS_DEGENERATE)

#: Estimator used when none is named (CLI, fusion node): best measured RMSE/CRLB among the
#: estimators that converge reliably (docs/readme/estimation.md).
DEFAULT_ESTIMATOR = 'mle'

#: Default reference range d_ref (m) of ``wmle`` (seed 003 eqs. (9)-(10)).
DEFAULT_REFERENCE_RANGE = 1000.0

_CHI2_STEP_TOL = 1e-10   # converged when the Gauss-Newton step is < 1e-5 standard deviations
_COST_RTOL = 1e-12       # ... or its predicted cost decrease is below the cost's rounding
_COMMON_OPTIONS = {'max_iterations': 50, 'tolerance': 1e-9}
_ITERATIVE_OPTIONS = dict(_COMMON_OPTIONS, initial=None)


@dataclass
class FixResult:
    """Result of an estimator over M problems.

    Attributes:
        position: (M, 3) estimates, m (NaN only where status is degenerate_geometry).
        covariance: (M, 3, 3) estimator covariance, m² (inf where unknown).
        iterations: (M,) int, iterations used (0 for closed-form estimators).
        converged: (M,) bool.
        status: (M,) array of str, one of ``STATUSES``.
        method: estimator name.
    """

    position: np.ndarray
    covariance: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    status: np.ndarray
    method: str

    @property
    def M(self):
        """Number of problems."""
        return self.position.shape[0]

    def single(self, m=0):
        """Problem ``m`` as a dict of plain Python values (position list, covariance lists...)."""
        return {
            'method': self.method,
            'position': self.position[m].tolist(),
            'covariance': self.covariance[m].tolist(),
            'converged': bool(self.converged[m]),
            'iterations': int(self.iterations[m]),
            'status': str(self.status[m]),
        }


# ----------------------------------------------------------------------------------------------
# Options


def parse_options(method, options, defaults, M=None):
    """Merge ``options`` over ``defaults`` for estimator ``method``, validating every value.

    Raises ``ValueError('options.<name>: ...')`` for an unknown option or a bad value, so the
    CLI can report the field. ``M`` (number of problems) checks the shape of ``initial``.
    """
    for name in options:
        if name not in defaults:
            raise ValueError(f'options.{name}: unknown option for estimator {method!r} '
                             f'(accepted: {", ".join(sorted(defaults))})')
    out = dict(defaults)
    out.update(options)
    if 'max_iterations' in out:
        v = out['max_iterations']
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
            raise ValueError('options.max_iterations: must be an integer >= 1')
        out['max_iterations'] = int(v)
    for name, upper in (('tolerance', None), ('reference_range', None), ('step_decay', 1.0)):
        if name in out:
            v = out[name]
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not np.isfinite(v) \
                    or v <= 0 or (upper is not None and v > upper):
                rng = '> 0' if upper is None else f'in (0, {upper:g}]'
                raise ValueError(f'options.{name}: must be a finite number {rng}')
            out[name] = float(v)
    if out.get('initial') is not None:
        x0 = np.asarray(out['initial'], dtype=float)
        if x0.ndim == 1:
            x0 = x0[None]
        if x0.ndim != 2 or x0.shape[1] != 3 or (M is not None and x0.shape[0] not in (1, M)):
            raise ValueError(f'options.initial: expected shape (3,) or ({M}, 3), got '
                             f'{np.shape(out["initial"])}')
        if not np.all(np.isfinite(x0)):
            raise ValueError('options.initial: non-finite coordinate')
        out['initial'] = np.broadcast_to(x0, (M if M is not None else x0.shape[0], 3)).copy()
    return out


def _start(method, bearings, options, defaults):
    """Validate bearings and options; return (options, initial positions (M, 3))."""
    bearings.validate()
    opts = parse_options(method, options, defaults, bearings.M)
    x0 = opts.get('initial')
    if x0 is None:
        x0 = _ls(bearings).position
    return opts, x0


# ----------------------------------------------------------------------------------------------
# Pseudo-linear estimators (seed 000 eqs. (2)-(5))


def pseudo_linear_system(bearings):
    """Rows of seed 000 eq. (3), H X = Y, with measured angles in place of true ones.

    Per station i (eq. (2)):
        azimuth row:   [sin θ_i, −cos θ_i, 0]                 · X = sin θ_i x_i − cos θ_i y_i
        elevation row: [cos θ_i sin ψ_i, sin θ_i sin ψ_i, −cos ψ_i] · X
                       = cos θ_i sin ψ_i x_i + sin θ_i sin ψ_i y_i − cos ψ_i z_i
    The elevation row of a 1D station is zero (weight 0), so any mix of 1D/2D works.

    Returns:
        H (M, N, 2, 3), Y (M, N, 2), mask (M, N, 2) bool (False for absent elevation rows).
    """
    th = bearings.azimuth
    has_el = bearings.has_elevation
    ps = np.where(has_el, bearings.elevation, 0.0)
    st, ct = np.sin(th), np.cos(th)
    sp, cp = np.sin(ps), np.cos(ps)
    zero = np.zeros_like(th)
    row1 = np.stack([st, -ct, zero], axis=-1)
    row2 = np.stack([ct * sp, st * sp, -cp], axis=-1)
    H = np.stack([row1, row2], axis=-2)
    H[..., 1, :] *= has_el[..., None]
    Y = np.einsum('mnkj,mnj->mnk', H, bearings.positions)
    mask = np.stack([np.ones_like(has_el), has_el], axis=-1)
    return H, Y, mask


def _pseudo_linear_covariance(bearings, x, ok, H, Ainv):
    """First-order covariance of a pseudo-linear solution X = A⁻¹ HᵀY (ls, tls).

    An angle error δθ_i moves the azimuth equation residual by ρ_i δθ_i and δψ_i the elevation
    residual by r_i δψ_i (ρ, r horizontal and slant range at the estimate), so with
    Σ = diag(ρ_i² σ_θi², r_i² σ_ψi²): P = A⁻¹ HᵀΣH A⁻¹, m².
    """
    d = np.where(ok[:, None, None], x[:, None, :], 0.0) - bearings.positions
    rho2 = d[..., 0] ** 2 + d[..., 1] ** 2
    r2 = rho2 + d[..., 2] ** 2
    var = np.stack([rho2 * bearings.sigma_az ** 2,
                    np.where(bearings.has_elevation, r2 * np.nan_to_num(bearings.sigma_el) ** 2,
                             0.0)], axis=-1)
    B = np.einsum('mnki,mnk,mnkj->mij', H, var, H)
    cov = np.full((bearings.M, 3, 3), np.inf)
    if np.any(ok):
        cov[ok] = Ainv[ok] @ B[ok] @ Ainv[ok]
    return cov


def _closed_form_result(bearings, x, ok, H, Ainv, method):
    cov = _pseudo_linear_covariance(bearings, x, ok, H, Ainv)
    x = np.where(ok[:, None], x, np.nan)
    status = np.where(ok, STATUS_OK, STATUS_DEGENERATE)
    return FixResult(x, cov, np.zeros(bearings.M, dtype=int), ok.copy(), status, method)


def ls(bearings, **options):
    """Pseudo-linear least squares, seed 000 eq. (4): X_LS = (HᵀH)⁻¹ HᵀY.

    H, Y from :func:`pseudo_linear_system` (seed 000 eqs. (2)-(3)); HᵀH and HᵀY are summed
    station by station, so the cost is O(N) and no (2N × 3) matrix is formed per problem.
    Units: m. Biased at long range (noise in H); the initial guess of the iterative methods.
    Covariance: (HᵀH)⁻¹ HᵀΣH (HᵀH)⁻¹ with Σ = diag(ρ_i² σ_θi², r_i² σ_ψi²) evaluated at the
    estimate (first-order error propagation of eq. (4)). Status degenerate_geometry where
    HᵀH is singular (for example parallel bearings). Options: only the common
    ``max_iterations``/``tolerance`` (ignored).
    """
    bearings.validate()
    parse_options('ls', options, _COMMON_OPTIONS)
    return _ls(bearings)


def _ls(bearings):
    """:func:`ls` without validation (the initial guess of the iterative estimators)."""
    H, Y, _ = pseudo_linear_system(bearings)
    A = np.einsum('mnki,mnkj->mij', H, H)
    b = np.einsum('mnki,mnk->mi', H, Y)
    Ainv = safe_inverse(A)
    ok = np.all(np.isfinite(Ainv), axis=(-2, -1))
    x = np.full((bearings.M, 3), np.nan)
    if np.any(ok):
        x[ok] = np.einsum('mij,mj->mi', Ainv[ok], b[ok])
    return _closed_form_result(bearings, x, ok, H, Ainv, 'ls')


def tls(bearings, **options):
    """Total least squares, seed 000 eq. (5).

    Maths: v₄ is the right singular vector of C' = [−Y H] (2N × 4; the absent elevation rows
    of 1D stations are zero rows, which is the same as dropping them) for the smallest
    singular value σ₄, and X_TLS = [v₄(2), v₄(3), v₄(4)] / v₄(1). Equivalently (the classical
    TLS normal equations) X = (HᵀH − σ₄² I)⁻¹ HᵀY with σ₄² = min ‖HX − Y‖² / (1 + ‖X‖²).

    Implementation, O(N): σ₄² is taken from the eigenvalues of the 4 × 4 normal matrix
    C'ᵀC' (summed per station), then refined by three fixed-point (Rayleigh quotient) steps
    X ← (HᵀH − λI)⁻¹HᵀY, λ ← ‖HX − Y‖² / (1 + ‖X‖²) with residuals computed directly (the
    squared 4 × 4 normal matrix alone loses accuracy when station coordinates are large).
    The test suite checks this against np.linalg.svd of [−Y H].

    TLS depends on the origin and units (it is not invariant to translations). Covariance:
    σ₄² is second order in the angle errors, so TLS and LS share the first-order covariance
    (HᵀH)⁻¹HᵀΣH(HᵀH)⁻¹ (see :func:`ls`), m². Status degenerate_geometry where HᵀH − σ₄²I is
    singular (the TLS solution does not exist, v₄(1) = 0).
    """
    bearings.validate()
    parse_options('tls', options, _COMMON_OPTIONS)
    H, Y, _ = pseudo_linear_system(bearings)
    A = np.einsum('mnki,mnkj->mij', H, H)
    b = np.einsum('mnki,mnk->mi', H, Y)
    yy = np.einsum('mnk,mnk->m', Y, Y)
    C4 = np.empty((bearings.M, 4, 4))
    C4[:, 0, 0] = yy
    C4[:, 0, 1:] = -b
    C4[:, 1:, 0] = -b
    C4[:, 1:, 1:] = A
    C4[~np.all(np.isfinite(C4), axis=(1, 2))] = 0.0
    lam = np.linalg.eigvalsh(C4)[:, 0]
    eye = np.eye(3)
    for _ in range(3):
        Ainv = safe_inverse(A - lam[:, None, None] * eye)
        x = np.einsum('mij,mj->mi', Ainv, b)
        r = np.einsum('mnki,mi->mnk', H, x) - Y
        lam_new = np.einsum('mnk,mnk->m', r, r) / (1.0 + np.einsum('mi,mi->m', x, x))
        lam = np.where(np.isfinite(lam_new), lam_new, lam)
    Ainv = safe_inverse(A - lam[:, None, None] * eye)
    ok = np.all(np.isfinite(Ainv), axis=(-2, -1))
    x = np.full((bearings.M, 3), np.nan)
    if np.any(ok):
        x[ok] = np.einsum('mij,mj->mi', Ainv[ok], b[ok])
    ok &= np.all(np.isfinite(x), axis=1)
    # First-order covariance: the LS sandwich (the TLS correction is second order).
    Ainv_ls = safe_inverse(A)
    ok &= np.all(np.isfinite(Ainv_ls), axis=(-2, -1))
    return _closed_form_result(bearings, x, ok, H, Ainv_ls, 'tls')


# ----------------------------------------------------------------------------------------------
# Maximum likelihood (seed 003)


def range_scaled_sigmas(bearings, position, reference_range):
    """σ of every bearing grown with range, seed 003 eqs. (9)-(10): σ(d) = σ_ref · d / d_ref.

    ``position`` (M, 3) is the target (estimate), d = |X − S_k| the slant range from station
    k, ``reference_range`` d_ref (m); σ_ref is the σ stored in the BearingSet (rad).
    Returns (sigma_az, sigma_el), each (M, N), rad (sigma_el NaN for 1D bearings).
    """
    d = np.linalg.norm(np.asarray(position, dtype=float)[:, None, :] - bearings.positions,
                       axis=-1)
    f = d / float(reference_range)
    return bearings.sigma_az * f, bearings.sigma_el * f


def _solve3(A, b):
    """Solve M symmetric 3 × 3 systems A x = b in closed form (cofactors); NaN where singular."""
    a00, a01, a02 = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    a11, a12, a22 = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_det = np.where(det > 0, 1.0 / det, np.nan)
        x = np.stack([c00 * b0 + c01 * b1 + c02 * b2,
                      c01 * b0 + c11 * b1 + c12 * b2,
                      c02 * b0 + c12 * b1 + c22 * b2], axis=1) * inv_det[:, None]
    return x


class _MLProblem:
    """Per-problem arrays of the ML cost of seed 003 eqs. (3)-(5) for a subset of problems.

    The cost is J(X) = Σ_k w_θk e_θk² + w_ψk e_ψk² with e = measured − predicted angle
    (azimuth wrapped to (−π, π]) and w = 1/σ², seed 003 eq. (3) with W of eq. (4) (or of
    eq. (11) when ``d_ref`` is set: σ_k = σ_ref,k · d_k / d_ref, d_k = |X − S_k| evaluated at
    the current iterate).
    """

    def __init__(self, bearings, d_ref=None):
        pos = bearings.positions
        self.px, self.py, self.pz = pos[..., 0], pos[..., 1], pos[..., 2]
        has_el = bearings.has_elevation
        self.az = bearings.azimuth
        self.el = np.where(has_el, bearings.elevation, 0.0)
        self.w_az = 1.0 / bearings.sigma_az ** 2
        self.w_el = np.where(has_el, 1.0 / np.where(has_el, bearings.sigma_el, 1.0) ** 2, 0.0)
        self.d_ref2 = None if d_ref is None else float(d_ref) ** 2

    def take(self, idx):
        """The same problem restricted to the problems ``idx``."""
        out = object.__new__(_MLProblem)
        for name in ('px', 'py', 'pz', 'az', 'el', 'w_az', 'w_el'):
            setattr(out, name, getattr(self, name)[idx])
        out.d_ref2 = self.d_ref2
        return out

    def evaluate(self, X, old_weight_scale=None):
        """Cost, normal matrix A = JᵀW⁻¹J (3 × 3), b = JᵀW⁻¹e, rms range, at X (M, 3).

        Seed 003 eq. (7): J holds the angle gradients (crlb.angle_jacobians; the paper's J_i
        is −J because its e is measured − predicted), so the Gauss-Newton step of eq. (8) is
        X_{i+1} = X_i + A⁻¹ b. For range weighting, ``old_weight_scale`` (M, N) (the weight
        factor d_ref²/d² of the current iterate) gives the cost of X under the current
        iterate's W_i (used to accept or reject a step); the returned weight factor is that of
        X itself. Returns (cost, A, b, scale, cost_under_old_weights, weight_factor).
        """
        with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
            return self._evaluate(X, old_weight_scale)

    def _evaluate(self, X, old_weight_scale):
        dx = X[:, 0:1] - self.px
        dy = X[:, 1:2] - self.py
        dz = X[:, 2:3] - self.pz
        rho2 = dx * dx + dy * dy
        rho = np.sqrt(rho2)
        r2 = rho2 + dz * dz
        # Residuals e = measured − predicted (seed 003 eq. (5)); azimuth wrapped to (−π, π].
        e_az = self.az - np.arctan2(dy, dx)
        e_az -= 2.0 * np.pi * np.ceil((e_az - np.pi) / (2.0 * np.pi))
        e_el = self.el - np.arctan2(dz, rho)
        ea2 = e_az * e_az
        ee2 = e_el * e_el
        w_az, w_el = self.w_az, self.w_el
        wf = None
        old_cost = None
        if self.d_ref2 is not None:
            # Seed 003 eqs. (9)-(11): σ_k = σ_ref (d_k / d_ref) → weight factor d_ref² / d_k².
            wf = self.d_ref2 / r2
            if old_weight_scale is not None:
                old_cost = np.sum(old_weight_scale * (w_az * ea2 + w_el * ee2), axis=1)
            w_az = w_az * wf
            w_el = w_el * wf
        # Angle gradients, crlb.angle_jacobians: ∇θ = (−dy, dx, 0)/ρ²,
        # ∇ψ = (−dx dz, −dy dz, ρ²)/(ρ r²).
        inv_rho2 = 1.0 / rho2
        t = dz / (rho * r2)
        gax = -dy * inv_rho2
        gay = dx * inv_rho2
        gex = -dx * t
        gey = -dy * t
        gez = rho / r2
        wax, way = w_az * gax, w_az * gay
        wex, wey, wez = w_el * gex, w_el * gey, w_el * gez
        M = X.shape[0]
        A = np.empty((M, 3, 3))
        A[:, 0, 0] = np.sum(wax * gax + wex * gex, axis=1)
        A[:, 0, 1] = A[:, 1, 0] = np.sum(wax * gay + wex * gey, axis=1)
        A[:, 0, 2] = A[:, 2, 0] = np.sum(wex * gez, axis=1)
        A[:, 1, 1] = np.sum(way * gay + wey * gey, axis=1)
        A[:, 1, 2] = A[:, 2, 1] = np.sum(wey * gez, axis=1)
        A[:, 2, 2] = np.sum(wez * gez, axis=1)
        b = np.stack([np.sum(wax * e_az + wex * e_el, axis=1),
                      np.sum(way * e_az + wey * e_el, axis=1),
                      np.sum(wez * e_el, axis=1)], axis=1)
        cost = np.sum(w_az * ea2 + w_el * ee2, axis=1)
        scale = np.sqrt(np.mean(r2, axis=1))
        if old_cost is None:
            old_cost = cost
        return cost, A, b, scale, old_cost, wf


def _levenberg_marquardt(problem, x0, max_iterations, tolerance):
    """Gauss-Newton (seed 003 eq. (8)) with Levenberg-Marquardt damping, over M problems.

    Step: (A + λ diag(A)) Δ = b, X ← X + Δ if the cost does not increase (else the step is
    rejected and λ ← max(10λ, 10⁻³)); λ starts at 0 (pure Gauss-Newton, eq. (8)) and is
    divided by 10 after an accepted step. Converged when the undamped Gauss-Newton step
    Δ = A⁻¹b is shorter than ``tolerance`` × rms range, or when its predicted cost decrease
    bᵀΔ = ΔᵀAΔ (the squared step length in standard deviations) is below 1e-10 or below
    1e-12 × cost (smaller decreases cannot be resolved in floating point). Problems are
    iterated together; converged ones are frozen, and the working set is compacted when it
    halves (no Python loop over problems). Returns (X, A at X, iterations, converged,
    diverged); A is the Fisher information at X (seed 003 eqs. (6)-(8)), in 1/m².
    """
    M = x0.shape[0]
    X = x0.copy()
    iterations = np.zeros(M, dtype=int)
    converged = np.zeros(M, dtype=bool)
    diverged = np.zeros(M, dtype=bool)
    finite0 = np.all(np.isfinite(X), axis=1)
    X[~finite0] = 0.0
    cost, A, b, scale, _, wf = problem.evaluate(X)
    scale0 = scale.copy()
    lam = np.zeros(M)
    active = np.flatnonzero(finite0)
    sub = problem if active.size == M else problem.take(active)
    s_X, s_cost, s_A, s_b, s_scale = X[active], cost[active], A[active], b[active], scale[active]
    s_wf = None if wf is None else wf[active]
    s_lam = lam[active]
    s_scale0 = scale0[active]
    s_iter = np.zeros(active.size, dtype=int)
    s_done = np.zeros(active.size, dtype=bool)
    s_conv = np.zeros(active.size, dtype=bool)
    s_div = np.zeros(active.size, dtype=bool)

    def flush():
        X[active] = s_X
        A[active] = s_A
        iterations[active] = s_iter
        converged[active] = s_conv
        diverged[active] = s_div

    for _ in range(max_iterations):
        if s_done.all():
            break
        if 2 * np.count_nonzero(~s_done) <= s_done.size and s_done.size > 64:
            flush()
            keep = np.flatnonzero(~s_done)
            active = active[keep]
            sub = sub.take(keep)
            s_X, s_cost, s_A, s_b, s_scale = (s_X[keep], s_cost[keep], s_A[keep], s_b[keep],
                                              s_scale[keep])
            s_wf = None if s_wf is None else s_wf[keep]
            s_lam, s_scale0, s_iter = s_lam[keep], s_scale0[keep], s_iter[keep]
            s_done, s_conv, s_div = s_done[keep], s_conv[keep], s_div[keep]
        run = ~s_done
        step_gn = _solve3(s_A, s_b)
        diag = np.einsum('mii->mi', s_A)
        A_damped = s_A + (s_lam[:, None] * diag)[:, :, None] * np.eye(3)
        step = np.where((s_lam > 0)[:, None], _solve3(A_damped, s_b), step_gn)
        Xt = s_X + np.where(run[:, None], np.nan_to_num(step), 0.0)
        c_t, A_t, b_t, sc_t, c_old, wf_t = sub.evaluate(Xt, s_wf)
        # Converged: the undamped step is short relative to the range, or its predicted cost
        # decrease bᵀA⁻¹b (χ² units: the squared step length in standard deviations) is below
        # 1e-10 or below the rounding level of the cost itself.
        decrease = np.einsum('mi,mi->m', s_b, step_gn)
        small = ((np.linalg.norm(step_gn, axis=1) <= tolerance * s_scale)
                 | (np.abs(decrease) <= np.maximum(_CHI2_STEP_TOL, _COST_RTOL * s_cost)))
        accept = run & np.isfinite(c_t) & (c_old <= s_cost) & np.all(np.isfinite(step), axis=1)
        s_X = np.where(accept[:, None], Xt, s_X)
        s_cost = np.where(accept, c_t, s_cost)
        s_A = np.where(accept[:, None, None], A_t, s_A)
        s_b = np.where(accept[:, None], b_t, s_b)
        s_scale = np.where(accept, sc_t, s_scale)
        if s_wf is not None:
            s_wf = np.where(accept[:, None], wf_t, s_wf)
        s_lam = np.where(accept, np.where(s_lam < 1e-6, 0.0, 0.1 * s_lam),
                         np.maximum(10.0 * s_lam, 1e-3))
        s_iter += run
        newly = run & small
        s_conv |= newly
        runaway = run & ~newly & ((s_lam > 1e12) | (s_scale > 1e8 * s_scale0))
        s_div |= runaway
        s_done |= newly | runaway
    flush()
    X[~finite0] = np.nan
    return X, A, iterations, converged & finite0, diverged | ~finite0


def _iterative_result(method, x, cov, iterations, converged, diverged):
    """Assemble a FixResult from an iteration's outcome: statuses and the NaN policy.

    A problem whose covariance is not finite (singular information) or whose position is not
    finite is ``degenerate_geometry`` with NaN position and inf covariance; otherwise
    converged → ``ok``, diverged → ``diverged``, else ``max_iterations``.
    """
    cov = np.array(cov, dtype=float)
    finite_cov = np.all(np.isfinite(cov), axis=(-2, -1))
    finite_x = np.all(np.isfinite(x), axis=1)
    degenerate = ~finite_cov | ~finite_x
    status = np.where(converged, STATUS_OK,
                      np.where(diverged, STATUS_DIVERGED, STATUS_MAX_ITERATIONS)).astype(object)
    status[degenerate] = STATUS_DEGENERATE
    converged = converged & ~degenerate
    x = np.where(degenerate[:, None], np.nan, x)
    cov[degenerate] = np.inf
    return FixResult(x, cov, iterations, converged, status.astype(str), method)


def mle(bearings, **options):
    """Gauss-Newton maximum likelihood, seed 003 eqs. (3)-(8), per-bearing σ.

    Maths: X̂ = argmin J(X) = eᵀW⁻¹e (eq. (3), (6)) with W = diag(σ_θk², σ_ψk²) (eq. (4)) and
    e = measured − predicted angles (eq. (5); azimuth residuals wrapped to (−π, π]; 1D
    bearings contribute only their azimuth term). Iteration eq. (8),
    X_{i+1} = X_i − (J_iᵀW⁻¹J_i)⁻¹J_iᵀW⁻¹e(X_i), started from ``ls`` (the paper's pseudo-linear
    initial value), with Levenberg-Marquardt damping so the cost never increases (see
    :func:`_levenberg_marquardt`). Covariance: the inverse Fisher information J_iᵀW⁻¹J_i at the
    estimate — the CRLB of crlb.py evaluated at X̂ (m²). Options: ``max_iterations``,
    ``tolerance``, ``initial``. Cost O(N) per iteration and problem.
    """
    opts, x0 = _start('mle', bearings, options, _ITERATIVE_OPTIONS)
    x, info, it, conv, div = _levenberg_marquardt(_MLProblem(bearings), x0,
                                                  opts['max_iterations'], opts['tolerance'])
    return _iterative_result('mle', x, safe_inverse(info), it, conv, div)


def wmle(bearings, **options):
    """Range-weighted maximum likelihood, seed 003 eqs. (9)-(11).

    The σ stored in the bearings is σ_ref, the error at the reference range d_ref (option
    ``reference_range``, m, default 1000). At every Gauss-Newton iterate X_i the paper sets
    σ_ki = (d_ki / d_ref) σ_ref (eqs. (9)-(10)), d_ki the range from station k to the
    current estimate X_i (we use the slant range |X_i − S_k|; the paper calls it 目标距离,
    "target distance"), builds W_i (eq. (11)) and takes the step of eq. (8) with W_i. W_i is
    held fixed within a step (iteratively reweighted least squares; the log σ(d) term of the
    exact likelihood is not included, exactly as in the paper). A step is accepted when it
    does not increase the cost under W_i. Covariance: inverse Fisher information with
    σ(d̂) at the estimate (m²). Options: ``reference_range``, ``max_iterations``,
    ``tolerance``, ``initial``.
    """
    defaults = dict(_ITERATIVE_OPTIONS, reference_range=DEFAULT_REFERENCE_RANGE)
    opts, x0 = _start('wmle', bearings, options, defaults)
    problem = _MLProblem(bearings, d_ref=opts['reference_range'])
    x, info, it, conv, div = _levenberg_marquardt(problem, x0, opts['max_iterations'],
                                                  opts['tolerance'])
    return _iterative_result('wmle', x, safe_inverse(info), it, conv, div)


# ----------------------------------------------------------------------------------------------
# Constrained TLS (seed 000): implemented in core/ctls.py, imported lazily (it builds on the
# helpers above, so a module-level import would be circular).


def ctls(bearings, **options):
    """Constrained TLS exactly as seed 000 publishes it (eqs. (9)-(20), appendix A, (30)).

    See :func:`bearing_loc_ros.core.ctls.constrained_tls`. Options: ``step_decay`` (μ of
    eq. (20)), ``max_iterations``, ``tolerance``, ``initial``.
    """
    from .ctls import constrained_tls
    return constrained_tls(bearings, weighting='paper', **options)


def ctls_am(bearings, **options):
    """Abatzoglou-Mendel constrained TLS: seed 000 eq. (11) with G replaced by P_E⁻¹.

    f(X) = [X; −1]ᵀCᵀ(H_X P_E H_Xᵀ)⁻¹C[X; −1]; invariant to origin and units and efficient
    (its eq. (30) covariance is the CRLB). See :func:`bearing_loc_ros.core.ctls.constrained_tls`.
    """
    from .ctls import constrained_tls
    return constrained_tls(bearings, weighting='am', **options)


ESTIMATORS = {
    'ls': ls,
    'tls': tls,
    'ctls': ctls,
    'ctls_am': ctls_am,
    'mle': mle,
    'wmle': wmle,
}


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
    bearings.validate()
    return fn(bearings, **options)


def noise_model_crlb(method, position, bearings, **options):
    """CRLB (M, 3, 3), m², at ``position`` under the noise model estimator ``method`` assumes.

    For ``wmle`` the σ grow with range (seed 003 eqs. (9)-(10), option ``reference_range``);
    for every other estimator the bearings' σ are used as given. inf where singular or where
    ``position`` is NaN.
    """
    position = np.asarray(position, dtype=float)
    pos = np.where(np.isfinite(position), position, 0.0)
    if method == 'wmle':
        d_ref = options.get('reference_range', DEFAULT_REFERENCE_RANGE)
        saz, sel = range_scaled_sigmas(bearings, pos, d_ref)
    else:
        saz, sel = bearings.sigma_az, bearings.sigma_el
    out = crlb(pos, bearings.positions, saz, sel, bearings.has_elevation)
    out[~np.all(np.isfinite(position), axis=1)] = np.inf
    return out
