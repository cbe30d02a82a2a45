"""Bearing-only localization estimators, batch-first, and the registry that names them.

Every estimator takes a :class:`~bearing_loc_ros.core.bearings.BearingSet` (M problems of N
bearings, any mix of 1D/2D) and keyword options, and returns a :class:`FixResult`.
Names (DESIGN.md): ``ls`` (seed 000 eq. (4)), ``tls`` (seed 000 eq. (5)), ``ctls``
(seed 000 eqs. (9)-(20)), ``mle`` (seed 003 eqs. (3)-(8)), ``wmle`` (seed 003 eqs. (9)-(11)).
"""

from dataclasses import dataclass

import numpy as np

from .crlb import safe_inverse

STATUS_OK = 'ok'
STATUS_MAX_ITERATIONS = 'max_iterations'
STATUS_DIVERGED = 'diverged'
STATUS_DEGENERATE = 'degenerate_geometry'
STATUSES = (STATUS_OK, STATUS_MAX_ITERATIONS, STATUS_DIVERGED, STATUS_DEGENERATE)


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


def ls(bearings, **_options):
    """Pseudo-linear least squares, seed 000 eq. (4): X_LS = (HᵀH)⁻¹ HᵀY.

    H, Y from :func:`pseudo_linear_system` (seed 000 eq. (2)-(3)); HᵀH and HᵀY are summed
    station by station, so the cost is O(N) and no (2N × 3) matrix is formed per problem.
    Units: m. Biased at long range (noise in H); the initial guess of the iterative methods.
    Covariance: (HᵀH)⁻¹ HᵀΣH (HᵀH)⁻¹ with Σ = diag(ρ_i² σ_θi², r_i² σ_ψi²) evaluated at the
    estimate (first-order error propagation of eq. (4)). Status degenerate_geometry where
    HᵀH is singular (for example parallel bearings).
    """
    H, Y, _ = pseudo_linear_system(bearings)
    A = np.einsum('mnki,mnkj->mij', H, H)
    b = np.einsum('mnki,mnk->mi', H, Y)
    Ainv = safe_inverse(A)
    ok = np.all(np.isfinite(Ainv), axis=(-2, -1))
    x = np.full((bearings.M, 3), np.nan)
    if np.any(ok):
        x[ok] = np.einsum('mij,mj->mi', Ainv[ok], b[ok])
    # First-order covariance of the equation errors: an angle error δθ moves the azimuth
    # equation residual by ρ δθ, an elevation error by r δψ (distances at the estimate).
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
    status = np.where(ok, STATUS_OK, STATUS_DEGENERATE)
    return FixResult(x, cov, np.zeros(bearings.M, dtype=int), ok, status, 'ls')


ESTIMATORS = {
    'ls': ls,
}


def locate(method, bearings, **options):
    """Run estimator ``method`` (a name in :data:`ESTIMATORS`) on a BearingSet.

    Raises ``ValueError`` for an unknown name or invalid bearings (see BearingSet.validate).
    """
    try:
        fn = ESTIMATORS[method]
    except KeyError:
        raise ValueError(f'method: unknown estimator {method!r}; choose one of '
                         f'{sorted(ESTIMATORS)}') from None
    bearings.validate()
    return fn(bearings, **options)
