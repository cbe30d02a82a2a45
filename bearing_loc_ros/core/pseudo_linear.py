"""Pseudo-linear bearing localization: the closed forms ``ls`` and ``tls`` and the shared start.

Wang, Zhang & Wu eqs. (2)-(5): every bearing gives equations linear in the target X once the
measured angles replace the true ones (H X = Y, eq. (3)). ``ls`` solves them by least squares
(eq. (4)) and ``tls`` by total least squares (eq. (5)). ``ls`` is also the starting point of
every iterative estimator (:func:`start`).

Conventions: ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal, radians;
an azimuth-only (1D) bearing has elevation NaN (its elevation row is zero).
"""

import numpy as np

from .crlb import safe_inverse
from .estimator_spec import BEARING_SIGMA, COMMON_OPTIONS, CONSISTENCY, declare, MULTISTATION
from .fix import FixResult, STATUS_DEGENERATE, STATUS_OK
from .pseudo_linear_single import solve_one


def start(spec, bearings, options, fast_start=None, validated=False):
    """Validate bearings and options of estimator ``spec``; return (options, X0 (M, 3)).

    X0 is option ``initial`` or else ``ls`` (Wang, Zhang & Wu eq. (4), the pseudo-linear
    start both papers use), computed by ``fast_start()`` when given (the same maths on an
    estimator's own arrays, faster for large batches).
    """
    if not validated:
        bearings.validate()
    opts = spec.parse(options, bearings.M)
    x0 = opts.get('initial')
    if x0 is None:
        x0 = ls_unchecked(bearings).position if fast_start is None else fast_start()
    return opts, x0


def pseudo_linear_system(bearings):
    """Rows of Wang, Zhang & Wu eq. (3), H X = Y, with measured angles in place of true ones.

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


@declare('ls', MULTISTATION, COMMON_OPTIONS + (CONSISTENCY,), BEARING_SIGMA)
def ls(bearings, **options):
    """Pseudo-linear least squares, Wang, Zhang & Wu eq. (4): X_LS = (HᵀH)⁻¹ HᵀY.

    H, Y from :func:`pseudo_linear_system` (Wang, Zhang & Wu eqs. (2)-(3)); HᵀH and HᵀY are summed
    station by station, so the cost is O(N) and no (2N × 3) matrix is formed per problem.
    Units: m. Biased at long range (noise in H); the initial guess of the iterative methods.
    Covariance: (HᵀH)⁻¹ HᵀΣH (HᵀH)⁻¹ with Σ = diag(ρ_i² σ_θi², r_i² σ_ψi²) evaluated at the
    estimate (first-order error propagation of eq. (4)). Status degenerate_geometry where
    HᵀH is singular (for example parallel bearings). Options: the common
    ``max_iterations``/``tolerance`` (ignored) and ``consistency`` (default true: an ``ok``
    fix that fails the residual χ², outlier or nonlinearity check at its estimate is
    ``low_confidence``; :func:`~bearing_loc_ros.core.robust.consistency_status`).
    """
    bearings.validate()
    opts = ls.spec.parse(options)
    res = solve_one('ls', bearings) if bearings.M == 1 else None
    return checked(ls_unchecked(bearings) if res is None else res, bearings,
                   opts['consistency'])


def checked(result, bearings, consistency):
    """``result``, with :func:`~bearing_loc_ros.core.robust.consistency_status` applied when
    option ``consistency`` (a validated bool) is on."""
    if not consistency:
        return result
    from .robust import consistency_status     # (core.robust imports the estimators)
    return consistency_status(result, bearings)


def ls_unchecked(bearings):
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


@declare('tls', MULTISTATION, COMMON_OPTIONS + (CONSISTENCY,), BEARING_SIGMA)
def tls(bearings, **options):
    """Total least squares, Wang, Zhang & Wu eq. (5).

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
    singular (the TLS solution does not exist, v₄(1) = 0). Option ``consistency`` as for
    :func:`ls`.
    """
    bearings.validate()
    opts = tls.spec.parse(options)
    res = solve_one('tls', bearings) if bearings.M == 1 else None
    if res is not None:
        return checked(res, bearings, opts['consistency'])
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
    return checked(_closed_form_result(bearings, x, ok, H, Ainv_ls, 'tls'), bearings,
                   opts['consistency'])
