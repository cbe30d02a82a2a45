"""Small dense solvers shared by the estimators: batched 3 × 3 and 2 × 2 systems in closed form,
and the one safeguarded Newton iteration of constrained TLS.

Pure numpy, no Python loop over problems. Used by the maximum likelihood iteration
(:mod:`~bearing_loc_ros.core.estimators`), the pseudo-linear closed forms
(:mod:`~bearing_loc_ros.core.pseudo_linear`) and constrained TLS in 3D
(:mod:`~bearing_loc_ros.core.constrained_tls`) and in the plane
(:mod:`~bearing_loc_ros.core.horizontal_ctls`).
"""

import numpy as np

from .crlb import safe_inverse

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


#: Largest tr(A) tr(A⁻¹) (a bound on the condition number κ = λ_max/λ_min) for which
#: :func:`spd_inverse3` (and its float twin single_floats.inverse3) use cofactors. Their error
#: grows as κ² ε (measured: up to 4e-10 relative at κ = 1e4, 3e-12 at κ ≤ 1e3), against κ ε
#: for LAPACK's inverse.
INVERSE3_MAX_CONDITION = 1e3


def spd_inverse3(A):
    """Inverse of M symmetric 3 × 3 matrices A (M, 3, 3) (information → covariance), any units.

    The result of crlb.safe_inverse (inf where A is not finite or its reciprocal condition
    number is below 1e-12) computed by cofactors, A⁻¹ = adj(A) / det(A), where A is positive
    definite (positive leading principal minors, Sylvester's criterion) and
    tr(A) tr(A⁻¹) ≤ :data:`INVERSE3_MAX_CONDITION` (then κ ≤ 1e3, the safe_inverse test
    passes and the cofactors agree with LAPACK to ≤ 1e-11 relative to the largest entry);
    the remaining matrices go to safe_inverse (LAPACK). The same operations in the same order
    as single_floats.inverse3.
    """
    a00, a01, a02 = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    a11, a12, a22 = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    with np.errstate(invalid='ignore', over='ignore', divide='ignore'):
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        c22 = a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        good = ((a00 > 0.0) & (c22 > 0.0) & (det > 0.0) & (det < np.inf)
                & ((a00 + a11 + a22) * (c00 + c11 + c22) <= INVERSE3_MAX_CONDITION * det))
        i = 1.0 / det
        out = np.empty(A.shape)
        for (r, c), v in (((0, 0), c00), ((0, 1), c01), ((0, 2), c02), ((1, 1), c11),
                          ((1, 2), c12), ((2, 2), c22)):
            out[:, r, c] = out[:, c, r] = v * i
    if not good.all():
        bad = np.flatnonzero(~good)
        out[bad] = safe_inverse(A[bad])
    return out


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


def solve2(A, b):
    """Solve M 2 × 2 systems A x = b (A (M, 2, 2), b (M, 2)) by cofactors; NaN where
    det(A) ≤ 0 (A is then not positive definite)."""
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = np.where(det > 0, 1.0 / det, np.nan)
        return np.stack([(A[:, 1, 1] * b[:, 0] - A[:, 0, 1] * b[:, 1]) * inv,
                         (A[:, 0, 0] * b[:, 1] - A[:, 1, 0] * b[:, 0]) * inv], axis=1)


def newton_backtracking(problem, X, mu, tolerance, max_iterations, rel_tol, scale_of):
    """Safeguarded Newton iteration of Wang, Zhang & Wu eq. (20) over M problems (in place).

    X_{n+1} = X_n − μ_n H_n⁻¹ T_n with μ_n = μ^n (``mu``, the paper's step decay).
    ``problem`` gives ``derivatives(X)`` -> (f, T, H_n, H_gn) (cost, gradient, Hessian and
    its positive semi-definite Gauss-Newton part), ``cost(X)`` and ``take(idx)``; X is
    (M, d), d = 3 (core.constrained_tls) or 2 (the plane, core.horizontal_ctls). Safeguards:
    H_gn where H_n is not positive definite (a Gauss-Newton direction); the step halved (up
    to 40 times) until f does not increase, so the cost never increases. Converged when the
    full step is shorter than ``tolerance`` × ``scale_of(sub, X)`` (the rms station range,
    m), or, for a problem that stops without meeting it (no trial step lowers f, or the
    iteration limit), when the predicted decrease ½|T_nᵀ H_n⁻¹ T_n| of its last Newton step
    is below ``rel_tol`` (M,) × f (the rounding stop of the maximum likelihood iteration:
    1e-10 f/dof or 1e-12 f). Otherwise no descent step is diverged. Non-finite starts are
    diverged. Returns (X, iterations, converged, diverged).
    """
    M, d = X.shape
    solve = solve3 if d == 3 else solve2
    iterations = np.zeros(M, dtype=int)
    converged = np.zeros(M, dtype=bool)
    finite0 = np.all(np.isfinite(X), axis=1)
    X[~finite0] = 0.0
    diverged = ~finite0
    active = np.flatnonzero(finite0)
    flat = np.zeros(M, dtype=bool)       # last predicted decrease below rel_tol × f
    for n in range(max_iterations):
        if active.size == 0:
            break
        sub = problem.take(active)
        Xa = X[active]
        f, T, Hn, Hgn = sub.derivatives(Xa)
        w = np.linalg.eigvalsh(np.where(np.isfinite(Hn), Hn, 0.0))
        pd = np.all(np.isfinite(Hn), axis=(1, 2)) & (w[:, 0] > 1e-12 * np.abs(w[:, -1]))
        step = -solve(np.where(pd[:, None, None], Hn, Hgn), T)      # −H_n⁻¹ T_n
        iterations[active] += 1
        small = np.linalg.norm(step, axis=1) <= tolerance * scale_of(sub, Xa)
        usable = np.all(np.isfinite(step), axis=1) & np.isfinite(f)
        with np.errstate(invalid='ignore'):
            flat[active] = usable & (0.5 * np.abs(np.einsum('mi,mi->m', T, step))
                                     <= rel_tol[active] * np.abs(f))
        # Backtracking on μ_n = μ^n (eq. (20)): never accept a cost increase.
        t = np.full(active.size, mu ** n)
        found = ~usable
        accepted = np.zeros(active.size, dtype=bool)
        for _ in range(41):
            todo = np.flatnonzero(~found)
            if todo.size == 0:
                break
            Xt = Xa[todo] + t[todo, None] * step[todo]
            ft = sub.take(todo).cost(Xt)
            ok = np.isfinite(ft) & (ft <= f[todo])
            Xa[todo[ok]] = Xt[ok]
            accepted[todo[ok]] = True
            found[todo[ok]] = True
            t[todo[~ok]] *= 0.5
        X[active] = Xa
        stalled = ~(small & usable) & ~accepted
        newly = (small & usable) | (stalled & flat[active])
        converged[active[newly]] = True
        diverged[active[stalled & ~newly]] = True
        active = active[~(newly | stalled)]
    converged[active[flat[active]]] = True       # iteration limit reached at the optimum
    X[~finite0] = np.nan
    return X, iterations, converged, diverged
