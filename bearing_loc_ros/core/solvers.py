"""Small dense solvers shared by the estimators: batched 3 × 3 and 2 × 2 systems in closed form.

Pure numpy, no Python loop over problems. Used by the maximum likelihood iteration
(:mod:`~bearing_loc_ros.core.estimators`), the pseudo-linear closed forms
(:mod:`~bearing_loc_ros.core.pseudo_linear`) and constrained TLS
(:mod:`~bearing_loc_ros.core.constrained_tls`).
"""

import numpy as np

#: Stopping thresholds of the iterative estimators, relative to the cost (a sum of squared
#: whitened residuals): converged when the predicted decrease of the full step is below
#: CHI2_STEP_TOL × cost/dof (the step is then shorter than 1e-5 of the standard deviation
#: implied by the residual scatter) or below COST_RTOL × cost (the cost's rounding level).
CHI2_STEP_TOL = 1e-10
COST_RTOL = 1e-12


def solve3_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """Solve symmetric 3 × 3 systems A x = b from their 6 unique entries by cofactors.

    Arguments are arrays of one shape (one entry per problem); returns (x0, x1, x2), NaN
    where det(A) ≤ 0 (A is then not positive definite).
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_det = np.where(det > 0, 1.0 / det, np.nan)
    return ((c00 * b0 + c01 * b1 + c02 * b2) * inv_det,
            (c01 * b0 + (a00 * a22 - a02 * a02) * b1 + (a01 * a02 - a00 * a12) * b2) * inv_det,
            (c02 * b0 + (a01 * a02 - a00 * a12) * b1 + (a00 * a11 - a01 * a01) * b2) * inv_det)


def solve3(A, b):
    """Solve M symmetric 3 × 3 systems A x = b (A (M, 3, 3), b (M, 3)); NaN where singular."""
    return np.stack(solve3_packed(A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 1, 1], A[:, 1, 2],
                                  A[:, 2, 2], b[:, 0], b[:, 1], b[:, 2]), axis=1)


def inv2(A):
    """Inverse of stacked 2 × 2 matrices (..., 2, 2) in closed form; NaN where singular."""
    a, b, c, d = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
    det = a * d - b * c
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_det = np.where(det != 0, 1.0 / det, np.nan)
    out = np.empty_like(A)
    out[..., 0, 0] = d * inv_det
    out[..., 0, 1] = -b * inv_det
    out[..., 1, 0] = -c * inv_det
    out[..., 1, 1] = a * inv_det
    return out
