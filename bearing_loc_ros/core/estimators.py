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
#: estimators that converge reliably (README "Estimation").
DEFAULT_ESTIMATOR = 'mle'

#: Default reference range d_ref (m) of ``wmle`` (seed 003 eqs. (9)-(10)).
DEFAULT_REFERENCE_RANGE = 1000.0

_CHI2_STEP_TOL = 1e-10   # converged when the Gauss-Newton step is < 1e-5 standard deviations
_COST_RTOL = 1e-12       # ... or its predicted cost decrease is below the cost's rounding
#                          (both relative to the cost, see _levenberg_marquardt)
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


def _start(method, bearings, options, defaults, ml_problem=None, validated=False):
    """Validate bearings and options; return (options, initial positions (M, 3)).

    The initial positions are option ``initial`` or else ``ls`` (seed 000 eq. (4), the
    pseudo-linear start both seeds use), computed from ``ml_problem``'s station-major arrays
    when given (faster for large batches).
    """
    if not validated:
        bearings.validate()
    opts = parse_options(method, options, defaults, bearings.M)
    x0 = opts.get('initial')
    if x0 is None:
        x0 = _ls(bearings).position if ml_problem is None else ml_problem.pseudo_linear_start()
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
    """FixResult of a pseudo-linear solution; degenerate where it lies on a station.

    A solution within 1e-9 × (1 m + largest |station coordinate| + largest station range) of
    a station is the pseudo-linear system's answer for co-located stations (every ray starts
    at one point, so the point itself zeroes every residual): the bearing model is undefined
    there and the first-order covariance collapses to ~0, so it is reported as
    degenerate_geometry instead of a confident fix.
    """
    with np.errstate(invalid='ignore'):
        dist = np.linalg.norm(x[:, None, :] - bearings.positions, axis=-1)
        scale = (1.0 + np.max(np.abs(bearings.positions), axis=(1, 2))
                 + np.max(dist, axis=1))
        ok = ok & ~np.any(dist <= 1e-9 * scale[:, None], axis=1)
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


# Rows of the packed per-problem state of the ML iteration (see _MLProblem.pack).
_A00, _A01, _A02, _A11, _A12, _A22, _B0, _B1, _B2, _COST, _SCALE, _OLD = range(12)


def _solve3_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """Solve symmetric 3 × 3 systems from their 6 unique entries (cofactors); NaN if det ≤ 0."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_det = np.where(det > 0, 1.0 / det, np.nan)
    return ((c00 * b0 + c01 * b1 + c02 * b2) * inv_det,
            (c01 * b0 + (a00 * a22 - a02 * a02) * b1 + (a01 * a02 - a00 * a12) * b2) * inv_det,
            (c02 * b0 + (a01 * a02 - a00 * a12) * b1 + (a00 * a11 - a01 * a01) * b2) * inv_det)


def _solve3(A, b):
    """Solve M symmetric 3 × 3 systems A x = b (A (M, 3, 3), b (M, 3)); NaN where singular."""
    return np.stack(_solve3_packed(A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 1, 1], A[:, 1, 2],
                                   A[:, 2, 2], b[:, 0], b[:, 1], b[:, 2]), axis=1)


class _MLProblem:
    """Per-bearing arrays of the ML cost of seed 003 eqs. (3)-(5), station-major (N, M).

    The cost is J(X) = Σ_k (e_θk/σ_θk)² + (e_ψk/σ_ψk)² with e = measured − predicted angle
    (azimuth wrapped to (−π, π]), seed 003 eq. (3) with W of eq. (4); with ``d_ref`` set,
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

    def pseudo_linear_start(self):
        """X_LS of seed 000 eq. (4) (M, 3) from the station-major arrays; NaN if degenerate.

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
        x = np.stack(_solve3_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2), axis=1)
        x[~ok] = np.nan
        return x

    def take(self, idx):
        """The same problem restricted to the problems ``idx``."""
        out = object.__new__(_MLProblem)
        for name in ('px', 'py', 'pz', 'az', 'el', 'sa', 'se'):
            setattr(out, name, getattr(self, name)[:, idx])
        out.d_ref = self.d_ref
        out.n_measurements = self.n_measurements[idx]
        return out

    def pack(self, x, y, z, old_factor=None):
        """Packed state at X = (x, y, z), each (M,): rows _A00.._OLD of a (12, M) array.

        A = JᵀW⁻¹J (6 unique entries, 1/m²) and b = JᵀW⁻¹e (1/m) of seed 003 eqs. (7)-(8),
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
            # Residuals e = measured − predicted (seed 003 eq. (5)); azimuth wrapped (−π, π].
            e_az = self.az - np.arctan2(dy, dx)
            e_az -= 2.0 * np.pi * np.ceil((e_az - np.pi) / (2.0 * np.pi))
            e_el = self.el - np.arctan2(dz, rho)
            sa, se = self.sa, self.se
            ra = sa * e_az                                     # whitened residuals
            re = se * e_el
            q = np.empty((12, x.shape[0]))
            factor = None
            if self.d_ref is not None:
                # Seed 003 eqs. (9)-(11): σ_k(d) = σ_ref (d_k / d_ref).
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
            q[_COST] = (ra * ra + re * re).sum(axis=0)
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


def _levenberg_marquardt(problem, x0, max_iterations, tolerance):
    """Gauss-Newton (seed 003 eq. (8)) with Levenberg-Marquardt damping, over M problems.

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
    information at X (seed 003 eqs. (6)-(8)), in 1/m².
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
    rel_tol = np.maximum(_CHI2_STEP_TOL / dof, _COST_RTOL)
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
        g = _solve3_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2)   # A⁻¹ b, eq. (8)
        if np.any(lam > 0):
            k = 1.0 + lam
            d = _solve3_packed(a00 * k, a01, a02, a11 * k, a12, a22 * k, b0, b1, b2)
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
    return X, _unpack_matrix(Q), iterations, converged & finite0, diverged


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
    bearings.validate()
    problem = _MLProblem(bearings)
    opts, x0 = _start('mle', bearings, options, _ITERATIVE_OPTIONS, problem, validated=True)
    x, info, it, conv, div = _levenberg_marquardt(problem, x0, opts['max_iterations'],
                                                  opts['tolerance'])
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
    bearings.validate()
    opts = parse_options('wmle', options, defaults, bearings.M)
    problem = _MLProblem(bearings, d_ref=opts['reference_range'])
    opts, x0 = _start('wmle', bearings, options, defaults, problem, validated=True)
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


#: Accepted options and their defaults, per estimator (validated by :func:`parse_options`).
OPTION_DEFAULTS = {
    'ls': _COMMON_OPTIONS,
    'tls': _COMMON_OPTIONS,
    'ctls': dict(_ITERATIVE_OPTIONS, step_decay=1.0),
    'ctls_am': dict(_ITERATIVE_OPTIONS, step_decay=1.0),
    'mle': _ITERATIVE_OPTIONS,
    'wmle': dict(_ITERATIVE_OPTIONS, reference_range=DEFAULT_REFERENCE_RANGE),
}


def option_defaults(method):
    """The options estimator ``method`` accepts, with their defaults ({} for a TMA name)."""
    return dict(OPTION_DEFAULTS.get(method, {}))


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
