"""Steps 2-4 of the :mod:`.robust` docstring for one problem, on floats, compiled.

The one-fix path of :func:`.robust.confident_result` (the fusion node and ``bearing_loc
locate`` solve one problem per call; every range-grown ``wmle`` fix goes through these
steps). The vectorised path (:mod:`.robust_consensus`, :func:`.robust.assess`) spends its
time in numpy call overhead on arrays of a few numbers; this module performs the same
computations, in the same order where the batch path fixes one: consensus candidates
(pseudo-linear ``ls`` of station subsets, Wang, Zhang & Wu eq. (4)), the MSAC score with
the log σ² term, Levenberg-Marquardt on the full negative log-likelihood of the inliers
(Zong & Cui 2015 eqs. (3)-(11) with the log σ(d) term), the all-bearing preference, and
the assessment (Fisher covariance, decisive exclusions, test-inversion widening for
range-grown σ, nonlinearity ν, second optimum).

The code is scalar float arithmetic, compiled by numba (:mod:`.jit`: the IEEE operations of
the source, no fast-math). Each Levenberg-Marquardt iterate is evaluated in one pass over
the stations (cost, Fisher information and gradient together). Each consensus candidate
(up to N(N + 1)/2 + 2 of them) sums its stations' packed normal equations in station order
and is solved by cofactors. 3 × 3 inverses and solves are cofactor formulas where
tr(A) tr(adj A) ≤ 1e5 det(A) (then κ(A) ≤ 1e5: crlb.safe_inverse's rank test certainly
passes and the result agrees with LAPACK's to about κ ε); other matrices are decided as
crlb.safe_inverse decides them, by eigenvalues of the characteristic cubic (Smith 1961)
where clear, else by LAPACK. Statuses,
exclusions and convergence flags are the batch path's; both refits accept a step within
the rounding of the cost (robust_consensus.ACCEPT_TOL) and so iterate to the same optimum
(measured against the batch path on the same input, 13,720 random problems of 3-10
stations, bench/one_fix_agreement.py --random: ≤ 1e-15 of the range for ``ok`` fixes,
≤ 8.5e-9 for ``low_confidence`` ones, whose refit can end at its iteration cap on a region
far from an ellipse; on the seed scenarios ≤ 5e-16 and ≤ 1.5e-9,
bench/one_fix_agreement.py; tested at 1e-9), covariances within 3e-8 of their largest
entry.

What the closed forms cannot decide or invert (an unclear rank test, an ill-conditioned
candidate system, information with a condition number up to :data:`MAX_CONDITION`) is done
by numpy's LAPACK, called from the compiled code as the batch path calls it. Where the floats
cannot follow the batch path to rounding (a division by zero, a major axis too close to
call, information worse conditioned than that, a non-finite Fisher information or angle
residual), :class:`Fallback` is raised and the caller runs the batch path. Units: m, rad; ENU,
azimuth θ CCW from East, elevation ψ above the horizontal.
"""

from functools import lru_cache
from math import acos, atan2, ceil, cos, inf, isfinite, log, nan, pi, sin, sqrt

from numba import objmode
import numpy as np

from .jit import jit, plain_array
from .robust_consensus import _station_masks, ACCEPT_TOL, STEP_TOL
from .robust_model import (_upper_cached, chi2_band, CONSISTENCY_PROBABILITY, DECISIVE_PROBABILITY,
                           MAX_REGION_NONLINEARITY, max_nonlinearity, MULTIMODE_PROBABILITY,
                           outlier_c2, REFIT_ITERATIONS, REFIT_ROUNDS, STATUS_REGION_Z,
                           TEST_INVERSION_Z)

_TWO_PI = 2.0 * pi
_RCOND = 1e-12
_CLEAR = 1e-5
#: tr(A) tr(adj A) / det(A) bound below which a cofactor inverse is used (κ(A) ≤ this).
_TRACE_CLEAR = 1e5
_INF6 = (inf,) * 6
_NAN3 = (nan, nan, nan)


class Fallback(Exception):
    """The float path cannot reproduce the batch path here: use the batch path."""


def _upper(dof, probability=CONSISTENCY_PROBABILITY):
    """robust_model.chi2_upper of one integer dof, as a float (cached)."""
    return _upper_cached(int(dof), probability)


@lru_cache(maxsize=64)
def _tables(n):
    """(consensus subset masks (K, n) of 0/1, χ² quantiles of CONSISTENCY_PROBABILITY by
    dof 0 … 2n (+inf below 1), the lower quantiles of its two-sided band by dof (0 below 1))
    of n stations, built once per n."""
    masks = np.ascontiguousarray(_station_masks(n), dtype=float)
    upper = np.array([_upper(k) for k in range(2 * n + 1)], dtype=float)
    lower = np.asarray(chi2_band(np.arange(2 * n + 1))[0], dtype=float)
    for table in (masks, upper, lower):
        table.flags.writeable = False
    return masks, upper, lower


@jit
def _upper_of(upper, dof):
    """upper[dof], +inf for dof < 1 (robust_model.chi2_upper)."""
    return upper[dof] if dof >= 1 else inf


@jit
def _max0(x):
    """Python's max(x, 0.0) (NaN stays NaN)."""
    return 0.0 if 0.0 > x else x


@jit
def _wrapped(e):
    """e wrapped to (−π, π]; a non-finite e (Python's ceil raises) is a :class:`Fallback`."""
    if not isfinite(e):
        raise Fallback('non-finite angle residual')
    return e - _TWO_PI * ceil((e - pi) / _TWO_PI)


# --- 3 × 3 symmetric matrices (packed a00, a01, a02, a11, a12, a22) -------------------------

@jit
def _eig_extremes(a00, a01, a02, a11, a12, a22):
    """(λ_min, λ_mid, λ_max) of a finite symmetric 3 × 3 matrix, packed (Smith 1961)."""
    a, b, c = a00, a11, a22
    d, e, f = a01, a12, a02
    q = (a + b + c) / 3.0
    aa, bb, cc = a - q, b - q, c - q
    r = sqrt((aa * aa + bb * bb + cc * cc + 2.0 * (d * d + e * e + f * f)) / 6.0)
    if not r > 0.0:
        return q, q, q
    det = (aa * (bb * cc - e * e) - d * (d * cc - e * f) + f * (d * e - bb * f)) / r ** 3.0
    phi = acos(min(1.0, max(-1.0, 0.5 * det))) / 3.0
    hi = q + 2.0 * r * cos(phi)
    lo = q + 2.0 * r * cos(phi + _TWO_PI / 3.0)
    return lo, 3.0 * q - hi - lo, hi


@jit
def _finite6(a00, a01, a02, a11, a12, a22):
    return (isfinite(a00) and isfinite(a01) and isfinite(a02) and isfinite(a11)
            and isfinite(a12) and isfinite(a22))


@jit
def _clear(a00, a01, a02, a11, a12, a22):
    """True when A (finite) is certainly well conditioned: λ_min > 1e-5 λ_max > 0.

    The closed-form λ_min is off by at most about sqrt(ε) λ_max (robust_consensus._psd_inverse),
    so then κ < 1e5: crlb.safe_inverse's rank test passes, and Gaussian elimination agrees
    with LAPACK's inverse to about κ ε.
    """
    lo, _, hi = _eig_extremes(a00, a01, a02, a11, a12, a22)
    return lo > _CLEAR * abs(hi) and hi > 0.0


@jit
def _full(a00, a01, a02, a11, a12, a22):
    A = np.empty((3, 3))
    A[0, 0], A[0, 1], A[0, 2] = a00, a01, a02
    A[1, 0], A[1, 1], A[1, 2] = a01, a11, a12
    A[2, 0], A[2, 1], A[2, 2] = a02, a12, a22
    return A


@jit
def _rank_ok(a00, a01, a02, a11, a12, a22):
    """crlb.safe_inverse's test: λ_min > 1e-12 |λ_max| and λ_max > 0 (False if not finite).

    In closed form where the answer is clear, else by LAPACK as safe_inverse decides it.
    """
    if not _finite6(a00, a01, a02, a11, a12, a22):
        return False
    if _clear(a00, a01, a02, a11, a12, a22):
        return True
    A = _full(a00, a01, a02, a11, a12, a22)
    with objmode(ok='boolean'):
        ok = _numpy_rank_ok(A)
    return ok


#: Condition number up to which an information matrix that is not certainly well conditioned
#: (:func:`_clear`) is inverted here, by numpy's LAPACK as on the batch path: its inverse then
#: differs from the batch path's by about κ ε ≤ 2e-9 relative (the information is summed in
#: another order). Above it, :class:`Fallback`: a difference of κ ε can move a decision (a
#: decisive exclusion, and with it the fix). Measured with bench/one_fix_agreement.py
#: --random: at 1e7 the same statuses and positions within 6.4e-10 as with no such inverse
#: here; at 1e8 one low_confidence fix of 14,136 (ν = 21, 700 km out) ended elsewhere.
MAX_CONDITION = 1e7


def _numpy_safe_inverse(A):
    """(crlb.safe_inverse's rank test passes, κ(A) ≤ :data:`MAX_CONDITION`, numpy's LAPACK
    inverse (zeros where not computed)) of a finite symmetric 3 × 3 ``A``."""
    w = np.linalg.eigvalsh(A)
    rank = bool(w[0] > _RCOND * abs(w[-1]) and w[-1] > 0)
    moderate = rank and bool(w[0] * MAX_CONDITION >= w[-1])
    return rank, moderate, (np.linalg.inv(A) if moderate else np.zeros((3, 3)))


def _numpy_rank_ok(A):
    """:func:`_rank_ok` by numpy's LAPACK, as the batch path (run as Python from compiled
    code: the LAPACK numba links orders its operations otherwise)."""
    w = np.linalg.eigvalsh(A)
    return bool(w[0] > _RCOND * abs(w[-1]) and w[-1] > 0)


@jit
def _lu_solve(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """Solve A x = b (A symmetric, packed): Gaussian elimination with partial pivoting (the
    first largest pivot), unrolled, as LAPACK's getrf orders it. (singular, x0, x1, x2):
    ``singular`` True (x zero) where a pivot is exactly zero."""
    a10, a20, a21 = a01, a02, a12
    p0, p1, p2 = 0, 1, 2
    if abs(a10) > abs(a00) and abs(a10) >= abs(a20):
        a00, a01, a02, a10, a11, a12 = a10, a11, a12, a00, a01, a02
        p0, p1 = 1, 0
    elif abs(a20) > abs(a00) and abs(a20) > abs(a10):
        a00, a01, a02, a20, a21, a22 = a20, a21, a22, a00, a01, a02
        p0, p2 = 2, 0
    if a00 == 0.0:
        return True, 0.0, 0.0, 0.0
    l10, l20 = a10 / a00, a20 / a00
    a11, a12 = a11 - l10 * a01, a12 - l10 * a02
    a21, a22 = a21 - l20 * a01, a22 - l20 * a02
    if abs(a21) > abs(a11):
        a11, a12, a21, a22 = a21, a22, a11, a12
        l10, l20 = l20, l10
        p1, p2 = p2, p1
    if a11 == 0.0:
        return True, 0.0, 0.0, 0.0
    l21 = a21 / a11
    a22 = a22 - l21 * a12
    if a22 == 0.0:
        return True, 0.0, 0.0, 0.0
    b = (b0, b1, b2)
    y0 = b[p0]
    y1 = b[p1] - l10 * y0
    y2 = b[p2] - l20 * y0 - l21 * y1
    x2 = y2 / a22
    x1 = (y1 - a12 * x2) / a11
    return False, (y0 - a01 * x1 - a02 * x2) / a00, x1, x2


@jit
def _cofactors(a00, a01, a02, a11, a12, a22):
    """(adj A packed, det A, clear) of a symmetric A.

    clear: A positive definite with tr(A) tr(adj A) ≤ 1e5 det(A). That product bounds κ(A),
    so crlb.safe_inverse's rank test passes and the cofactors agree with LAPACK's inverse to
    about κ ε.
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    clear = (a00 > 0.0 and c22 > 0.0 and det > 0.0 and det < inf
             and (a00 + a11 + a22) * (c00 + c11 + c22) <= _TRACE_CLEAR * det)
    return (c00, c01, c02, c11, c12, c22), det, clear


@jit
def _safe_inverse_packed(a00, a01, a02, a11, a12, a22):
    """crlb.safe_inverse of one symmetric matrix: (invertible, packed inverse); not
    invertible (+inf: it fails) with the inverse +inf. Cofactors or Gaussian elimination
    where the matrix is certainly well conditioned (:func:`_cofactors`, :func:`_clear`),
    else numpy's LAPACK as crlb.safe_inverse up to κ = :data:`MAX_CONDITION`, above it
    :class:`Fallback`.
    """
    c, det, clear = _cofactors(a00, a01, a02, a11, a12, a22)
    if clear:
        i = 1.0 / det
        return True, (c[0] * i, c[1] * i, c[2] * i, c[3] * i, c[4] * i, c[5] * i)
    if not _finite6(a00, a01, a02, a11, a12, a22):
        return False, _INF6
    if not _clear(a00, a01, a02, a11, a12, a22):
        A = _full(a00, a01, a02, a11, a12, a22)
        with objmode(rank='boolean', moderate='boolean', L='float64[:, :]'):
            rank, moderate, L = _numpy_safe_inverse(A)
        if not rank:
            return False, _INF6
        if not moderate:
            raise Fallback('ill-conditioned information')
        return True, (L[0, 0], L[1, 0], L[2, 0], L[1, 1], L[2, 1], L[2, 2])
    # Columns of the inverse; its lower triangle is kept (LU's inverse is symmetric only to
    # rounding, and the batch path reads the lower triangle as LAPACK returns it).
    s0, c00, c10, c20 = _lu_solve(a00, a01, a02, a11, a12, a22, 1.0, 0.0, 0.0)
    s1, _, c11, c21 = _lu_solve(a00, a01, a02, a11, a12, a22, 0.0, 1.0, 0.0)
    s2, _, _, c22 = _lu_solve(a00, a01, a02, a11, a12, a22, 0.0, 0.0, 1.0)
    if s0 or s1 or s2:
        raise Fallback('singular information')
    return True, (c00, c10, c20, c11, c21, c22)


@jit
def _quad_packed(v0, v1, v2, P):
    p00, p01, p02, p11, p12, p22 = P
    return (v0 * (p00 * v0 + p01 * v1 + p02 * v2) + v1 * (p01 * v0 + p11 * v1 + p12 * v2)
            + v2 * (p02 * v0 + p12 * v1 + p22 * v2))


@jit
def _solve_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """A x = b for symmetric A: cofactors where clear (:func:`_cofactors`), else Gaussian
    elimination with partial pivoting. (singular, x0, x1, x2)."""
    c, det, clear = _cofactors(a00, a01, a02, a11, a12, a22)
    if clear:
        c00, c01, c02, c11, c12, c22 = c
        return (False, (c00 * b0 + c01 * b1 + c02 * b2) / det,
                (c01 * b0 + c11 * b1 + c12 * b2) / det, (c02 * b0 + c12 * b1 + c22 * b2) / det)
    return _lu_solve(a00, a01, a02, a11, a12, a22, b0, b1, b2)


# --- the likelihood ---------------------------------------------------------------------------

@jit
def _terms(rows, grown, d_ref, x0, x1, x2):
    """Per station at X (N, 11): ra, re, a0, a1, h0, h1, h2, dx, dy, dz, d.

    ra, re the whitened residuals, (a0, a1, 0) and (h0, h1, h2) the whitened gradients
    ga, ge, 1/m, (dx, dy, dz) = X − station and d its range, m: robust_model.Data.evaluate's
    quantities (σ grown with range when ``grown``), one station at a time. ``rows`` per
    station (px, py, pz, θ, ψ, 1/σ_θ, 1/σ_ψ), ψ and 1/σ_ψ 0 without elevation.
    """
    n = rows.shape[0]
    T = np.empty((n, 11))
    for k in range(n):
        px, py, pz, az, el, ia, ie = (rows[k, 0], rows[k, 1], rows[k, 2], rows[k, 3],
                                      rows[k, 4], rows[k, 5], rows[k, 6])
        dx = x0 - px
        dy = x1 - py
        dz = x2 - pz
        rho2 = dx * dx + dy * dy
        r2 = rho2 + dz * dz
        rho = sqrt(rho2)
        d = sqrt(r2)
        e_az = _wrapped(az - atan2(dy, dx))
        e_el = el - atan2(dz, rho)
        if grown:
            f = d_ref / d
            ia *= f
            ie *= f
        s = ia / rho2
        t = dz / (rho * r2)
        T[k, 0] = ia * e_az
        T[k, 1] = ie * e_el
        T[k, 2] = -(dy * s)
        T[k, 3] = dx * s
        T[k, 4] = -(dx * t) * ie
        T[k, 5] = -(dy * t) * ie
        T[k, 6] = (rho / r2) * ie
        T[k, 7] = dx
        T[k, 8] = dy
        T[k, 9] = dz
        T[k, 10] = d
    return T


@jit
def _state(rows, grown, d_ref, x0, x1, x2, wa, we):
    """(L, F packed, ½∇L, Σ d²) at X: robust_consensus._refit's cost, information and gradient.

    L = Σ w (r² + log σ²); F = Σ w g gᵀ (+ Σ 2 (wa + we) u uᵀ / d² with range growth);
    ½∇L = −Σ w r g (+ Σ (wa (1 − ra²) + we (1 − re²)) u / d with range growth). One pass over
    the stations (:func:`_terms`).
    """
    T = _terms(rows, grown, d_ref, x0, x1, x2)
    cost = f00 = f01 = f02 = f11 = f12 = f22 = g0 = g1 = g2 = sd2 = 0.0
    for k in range(T.shape[0]):
        ra, re, a0, a1, h0, h1, h2 = T[k, 0], T[k, 1], T[k, 2], T[k, 3], T[k, 4], T[k, 5], T[k, 6]
        dx, dy, dz, d = T[k, 7], T[k, 8], T[k, 9], T[k, 10]
        w1, w2 = wa[k], we[k]
        sd2 += d * d
        wra = w1 * ra
        wre = w2 * re
        g0 -= wra * a0 + wre * h0
        g1 -= wra * a1 + wre * h1
        g2 -= wre * h2
        f00 += w1 * a0 * a0 + w2 * h0 * h0
        f01 += w1 * a0 * a1 + w2 * h0 * h1
        f02 += w2 * h0 * h2
        f11 += w1 * a1 * a1 + w2 * h1 * h1
        f12 += w2 * h1 * h2
        f22 += w2 * h2 * h2
        if grown:
            log_s2 = 2.0 * log(d / d_ref)
            cost += w1 * (ra * ra + log_s2) + w2 * (re * re + log_s2)
            k_ = (w1 * (1.0 - ra * ra) + w2 * (1.0 - re * re)) / d
            v = 2.0 * (w1 + w2) / (d * d)
            u0, u1, u2 = dx / d, dy / d, dz / d
            g0 += k_ * u0
            g1 += k_ * u1
            g2 += k_ * u2
            f00 += v * u0 * u0
            f01 += v * u0 * u1
            f02 += v * u0 * u2
            f11 += v * u1 * u1
            f12 += v * u1 * u2
            f22 += v * u2 * u2
        else:
            cost += w1 * (ra * ra) + w2 * (re * re)
    if not isfinite(cost):
        cost = inf
    return cost, (f00, f01, f02, f11, f12, f22), (g0, g1, g2), sd2


@jit
def _residuals(rows, grown, d_ref, x0, x1, x2):
    """Per station (N, 3): ra, re, log σ² at X (robust_model.Data.evaluate without gradients)."""
    n = rows.shape[0]
    out = np.empty((n, 3))
    for k in range(n):
        px, py, pz, az, el, ia, ie = (rows[k, 0], rows[k, 1], rows[k, 2], rows[k, 3],
                                      rows[k, 4], rows[k, 5], rows[k, 6])
        dx = x0 - px
        dy = x1 - py
        dz = x2 - pz
        rho2 = dx * dx + dy * dy
        e_az = _wrapped(az - atan2(dy, dx))
        e_el = el - atan2(dz, sqrt(rho2))
        if grown:
            d = sqrt(rho2 + dz * dz)
            f = d_ref / d
            out[k, 0] = (ia * f) * e_az
            out[k, 1] = (ie * f) * e_el
            out[k, 2] = 2.0 * log(d / d_ref)
        else:
            out[k, 0] = ia * e_az
            out[k, 1] = ie * e_el
            out[k, 2] = 0.0
    return out


@jit
def _cost(rows, grown, d_ref, X, wa, we):
    """robust_consensus._cost of one problem: L(X) = Σ w (r² + log σ²), +inf if not finite."""
    R = _residuals(rows, grown, d_ref, X[0], X[1], X[2])
    c = 0.0
    for k in range(R.shape[0]):
        ra, re, log_s2 = R[k, 0], R[k, 1], R[k, 2]
        c += wa[k] * (ra * ra + log_s2) + we[k] * (re * re + log_s2)
    return c if isfinite(c) else inf


@jit
def _inliers(rows, has, grown, d_ref, X, c2):
    R = _residuals(rows, grown, d_ref, X[0], X[1], X[2])
    n = R.shape[0]
    wa = np.empty(n)
    we = np.empty(n)
    for k in range(n):
        ra, re = R[k, 0], R[k, 1]
        wa[k] = 1.0 if ra * ra <= c2 else 0.0
        we[k] = 1.0 if has[k] and re * re <= c2 else 0.0
    return wa, we


@jit
def _solvable(wa, we):
    st = 0
    sa = se = 0.0
    for k in range(wa.shape[0]):
        if wa[k] + we[k] > 0:
            st += 1
        sa += wa[k]
        se += we[k]
    return st >= 2 and se >= 1 and sa + se >= 3


@jit
def _finite3(X):
    return isfinite(X[0]) and isfinite(X[1]) and isfinite(X[2])


@jit
def _refit(rows, grown, d_ref, X0, wa, we):
    """robust_consensus._refit for one problem (Levenberg-Marquardt on the full likelihood,
    at most REFIT_ITERATIONS steps)."""
    X = X0
    lam = 0.0
    cost, F, g, sd2 = _state(rows, grown, d_ref, X[0], X[1], X[2], wa, we)
    n = rows.shape[0]
    for _ in range(REFIT_ITERATIONS):
        f00, f01, f02, f11, f12, f22 = F
        if not _finite6(f00, f01, f02, f11, f12, f22):
            raise Fallback('non-finite information')
        singular, s0, s1, s2 = _solve_packed(f00 + lam * f00, f01, f02, f11 + lam * f11, f12,
                                             f22 + lam * f22, -g[0], -g[1], -g[2])
        s0 = s0 if isfinite(s0) and not singular else 0.0
        s1 = s1 if isfinite(s1) and not singular else 0.0
        s2 = s2 if isfinite(s2) and not singular else 0.0
        Xt = (X[0] + s0, X[1] + s1, X[2] + s2)
        ct, Ft, gt, sd2t = _state(rows, grown, d_ref, Xt[0], Xt[1], Xt[2], wa, we)
        if ct < inf and ct <= cost + ACCEPT_TOL * (1.0 + abs(cost)):   # (ct +inf: not finite)
            X = Xt
            cost, F, g, sd2 = ct, Ft, gt, sd2t
            lam = 0.1 * lam if lam > 1e-6 else 0.0
        else:
            lam = max(10.0 * lam, 1e-3)
        if sqrt(s0 * s0 + s1 * s1 + s2 * s2) <= STEP_TOL * sqrt(sd2 / n) or lam > 1e10:
            break
    return X


# --- step 2: consensus candidates ----------------------------------------------------------

@jit
def _station_equations(rows, hasf):
    """Per station the packed pseudo-linear normal equations (N, 9): a00 … a22, b0, b1, b2
    (Wang, Zhang & Wu eq. (4); robust_consensus._ls_candidates)."""
    n = rows.shape[0]
    E = np.empty((n, 9))
    for k in range(n):
        px, py, pz, az, el = rows[k, 0], rows[k, 1], rows[k, 2], rows[k, 3], rows[k, 4]
        h = hasf[k]
        s, c = sin(az), cos(az)
        sp, cp = sin(el), cos(el)
        q0, q1, q2 = h * c * sp, h * s * sp, -h * cp
        y1 = s * px + (-c) * py + 0.0 * pz
        y2 = q0 * px + q1 * py + q2 * pz
        E[k, 0] = s * s + q0 * q0
        E[k, 1] = s * (-c) + q0 * q1
        E[k, 2] = s * 0.0 + q0 * q2
        E[k, 3] = c * c + q1 * q1
        E[k, 4] = (-c) * 0.0 + q1 * q2
        E[k, 5] = 0.0 + q2 * q2
        E[k, 6] = s * y1 + q0 * y2
        E[k, 7] = (-c) * y1 + q1 * y2
        E[k, 8] = 0.0 * y1 + q2 * y2
    return E


@jit
def _solve_candidate(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """The ls fix of one station subset: safe_inverse(A) b as the batch path decides it."""
    c, det, clear = _cofactors(a00, a01, a02, a11, a12, a22)
    if clear:
        i = 1.0 / det
        p00, p01, p02, p11, p12, p22 = c[0] * i, c[1] * i, c[2] * i, c[3] * i, c[4] * i, c[5] * i
        return (p00 * b0 + p01 * b1 + p02 * b2, p01 * b0 + p11 * b1 + p12 * b2,
                p02 * b0 + p12 * b1 + p22 * b2)
    if not _finite6(a00, a01, a02, a11, a12, a22):
        return _NAN3
    if _clear(a00, a01, a02, a11, a12, a22):
        singular, x0, x1, x2 = _lu_solve(a00, a01, a02, a11, a12, a22, b0, b1, b2)
        if singular:
            raise Fallback('singular candidate equations')
        return x0, x1, x2
    if _rank_ok(a00, a01, a02, a11, a12, a22):
        # Ill-conditioned but invertible: numpy's LAPACK inverse, as the batch path (an
        # ill-conditioned system amplifies any other order of operations).
        A = _full(a00, a01, a02, a11, a12, a22)
        with objmode(x0='float64', x1='float64', x2='float64'):
            x0, x1, x2 = (np.linalg.inv(A) @ np.array([b0, b1, b2])).tolist()
        return x0, x1, x2
    return _NAN3


@jit
def _score(rows, has, grown, d_ref, X, c2):
    """robust_consensus._score of one candidate: the truncated cost with the log σ² of the
    inliers (+inf if not finite)."""
    x0, x1, x2 = X
    s = 0.0
    for k in range(rows.shape[0]):
        px, py, pz, az, el, ia, ie = (rows[k, 0], rows[k, 1], rows[k, 2], rows[k, 3],
                                      rows[k, 4], rows[k, 5], rows[k, 6])
        dx = x0 - px
        dy = x1 - py
        dz = x2 - pz
        rho2 = dx * dx + dy * dy
        e_az = _wrapped(az - atan2(dy, dx))
        if grown:
            d = sqrt(rho2 + dz * dz)
            f = d_ref / d
            ia *= f
            ie *= f
            log_s2 = 2.0 * log(d / d_ref)
        else:
            log_s2 = 0.0
        qa = ia * e_az
        qa *= qa
        s += qa + log_s2 if qa <= c2 else c2
        if has[k]:
            qe = ie * (el - atan2(dz, sqrt(rho2)))
            qe *= qe
            s += qe + log_s2 if qe <= c2 else c2
    return s if isfinite(s) else inf


@jit
def _best_candidate(rows, has, hasf, grown, d_ref, X_ml, c2, masks):
    """Step 2: (the best-scoring candidate, the all-station ls fix).

    Candidates: the estimator's fix, the ls fix of all stations and of the subsets of
    robust_consensus._station_masks (leaving out one station and, for N ≥ 5, every pair; pairs
    of spread stations for large N), each subset's normal equations summed in station order;
    the first lowest MSAC score wins, as the batch path's argmin.
    """
    E = _station_equations(rows, hasf)
    K, n = masks.shape
    cand = np.empty((K + 1, 3))
    if _finite3(X_ml):
        cand[0, 0], cand[0, 1], cand[0, 2] = X_ml
    else:
        cand[0, 0] = cand[0, 1] = cand[0, 2] = nan
    a = np.empty(9)
    for k in range(K):
        a[:] = 0.0
        for j in range(n):
            if masks[k, j] != 0.0:
                for i in range(9):
                    a[i] = a[i] + E[j, i]
        cand[k + 1, 0], cand[k + 1, 1], cand[k + 1, 2] = _solve_candidate(
            a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8])
    best, best_s = 0, inf
    for k in range(K + 1):
        C = (cand[k, 0], cand[k, 1], cand[k, 2])
        if _finite3(C):
            s = _score(rows, has, grown, d_ref, C, c2)
            if s < best_s:
                best, best_s = k, s
    return (cand[best, 0], cand[best, 1], cand[best, 2]), (cand[1, 0], cand[1, 1], cand[1, 2])


# --- step 3: refit -------------------------------------------------------------------------

@jit
def _consensus_fit(rows, has, hasf, grown, d_ref, X_ml, c2, masks, upper, lower):
    """robust_consensus.consensus_fit for one problem: (X, wa, we, the all-station ls fix,
    whether a rejected fit of all the angles exists, that fit)."""
    n = rows.shape[0]
    X, X_ls = _best_candidate(rows, has, hasf, grown, d_ref, X_ml, c2, masks)
    X = (X[0] if isfinite(X[0]) else 0.0, X[1] if isfinite(X[1]) else 0.0,
         X[2] if isfinite(X[2]) else 0.0)
    wa, we = _inliers(rows, has, grown, d_ref, X, c2)
    for _ in range(REFIT_ROUNDS):
        if _solvable(wa, we):
            a, e = wa, we
        else:
            a, e = np.ones(n), hasf.copy()
        Xa = _refit(rows, grown, d_ref, X, a, e)
        na, ne = _inliers(rows, has, grown, d_ref, Xa, c2)
        if not _solvable(na, ne):
            na, ne = a, e
        same = np.array_equal(na, a) and np.array_equal(ne, e)
        X, wa, we = Xa, na, ne
        if same:
            break
    return _prefer_all_bearings(rows, has, hasf, grown, d_ref, X, wa, we, X_ml, X_ls, upper,
                                lower)


@jit
def _chi2_all(rows, grown, d_ref, X, she):
    """Residual χ² of every angle at X (robust_consensus._prefer_all_bearings)."""
    R = _residuals(rows, grown, d_ref, X[0], X[1], X[2])
    chi2 = 0.0
    for k in range(rows.shape[0]):
        chi2 += R[k, 0] * R[k, 0] + she[k] * R[k, 1] * R[k, 1]
    return chi2


@jit
def _prefer_all_bearings(rows, has, hasf, grown, d_ref, X, wa, we, X_ml, X_ls, upper,
                         lower):
    n = rows.shape[0]
    all_kept = True
    n_has = 0
    for k in range(n):
        if not (wa[k] == 1.0 and (we[k] == 1.0 or not has[k])):
            all_kept = False
        n_has += 1 if has[k] else 0
    if all_kept:
        return X, wa, we, X_ls, False, X
    ones, she = np.ones(n), hasf.copy()
    dof = n + n_has - 3
    best, cost = X, inf
    first = True
    for start in (X_ml, X_ls):
        if _finite3(start):
            Xs = _refit(rows, grown, d_ref, start, ones, she)
            cs = _cost(rows, grown, d_ref, Xs, ones, she)
            if grown and dof >= 1 and _chi2_all(rows, grown, d_ref, Xs, she) < lower[dof]:
                cs = inf                    # ran out in range
        else:
            Xs, cs = _refit(rows, grown, d_ref, X, ones, she), inf
        if first or cs < cost:
            best, cost = Xs, cs
            first = False
    if isfinite(cost) and _chi2_all(rows, grown, d_ref, best, she) <= _upper_of(upper, dof):
        return best, ones, she, X_ls, False, X
    return X, wa, we, X_ls, isfinite(cost), best


# --- step 4: assessment --------------------------------------------------------------------

@jit
def _fisher_at(rows, grown, d_ref, X, wa, we):
    """Σ w g gᵀ packed at X, 1/m² (robust_model.fisher of Data.evaluate's gradients)."""
    T = _terms(rows, grown, d_ref, X[0], X[1], X[2])
    f00 = f01 = f02 = f11 = f12 = f22 = 0.0
    for k in range(T.shape[0]):
        a0, a1, h0, h1, h2 = T[k, 2], T[k, 3], T[k, 4], T[k, 5], T[k, 6]
        w1, w2 = wa[k], we[k]
        f00 += w1 * a0 * a0 + w2 * h0 * h0
        f01 += w1 * a0 * a1 + w2 * h0 * h1
        f02 += w2 * h0 * h2
        f11 += w1 * a1 * a1 + w2 * h1 * h1
        f12 += w2 * h1 * h2
        f22 += w2 * h2 * h2
    return f00, f01, f02, f11, f12, f22


@jit
def _test_inversion(rows, grown, d_ref, X, wa, we, P, u_out, t_max, z):
    """robust_model.test_inversion_covariance for one problem (P finite, packed):
    (finite, the widened P packed).

    ``u_out`` Σ of the unit lines of sight of the stations with a kept angle (orients the
    major axis away from them), ``t_max`` 10 × the largest finite station range, m; four
    fixed-point steps.
    """
    p00, p01, p02, p11, p12, p22 = P
    lo, mid, hi = _eig_extremes(p00, p01, p02, p11, p12, p22)
    if not hi - mid > 1e-4 * abs(hi):
        raise Fallback('major axis too close to call')
    # Eigenvector of λ_max: the largest cross product of two rows of P − λ_max I.
    R = _full(p00 - hi, p01, p02, p11 - hi, p12, p22 - hi)
    nc, c0, c1, c2 = -1.0, 0.0, 0.0, 0.0
    for i, j in ((0, 1), (0, 2), (1, 2)):
        d0 = R[i, 1] * R[j, 2] - R[i, 2] * R[j, 1]
        d1 = R[i, 2] * R[j, 0] - R[i, 0] * R[j, 2]
        d2 = R[i, 0] * R[j, 1] - R[i, 1] * R[j, 0]
        nd = d0 * d0 + d1 * d1 + d2 * d2
        if nc < 0.0 or nd > nc:
            nc, c0, c1, c2 = nd, d0, d1, d2
    if not nc > 0.0:
        raise Fallback('no major axis')
    nc = sqrt(nc)
    v0, v1, v2 = c0 / nc, c1 / nc, c2 / nc
    dot = v0 * u_out[0] + v1 * u_out[1] + v2 * u_out[2]
    if dot == 0.0:
        raise Fallback('major axis orientation')
    if dot < 0.0:
        v0, v1, v2 = -v0, -v1, -v2
    s0 = sqrt(_max0(_quad_packed(v0, v1, v2, P)))
    t = z * s0
    for _ in range(4):
        f00, f01, f02, f11, f12, f22 = _fisher_at(
            rows, grown, d_ref, (X[0] + t * v0, X[1] + t * v1, X[2] + t * v2), wa, we)
        inv, Pt = _safe_inverse_packed(f00, f01, f02, f11, f12, f22)
        st = sqrt(_max0(_quad_packed(v0, v1, v2, Pt))) if inv else inf
        if isfinite(st):
            zs = z * st
            t = t_max if t_max < zs else zs
        else:
            t = t_max
    add = _max0((t / z) ** 2.0 - s0 * s0)
    if not isfinite(add):
        return False, _INF6
    return True, (p00 + add * v0 * v0, p01 + add * v0 * v1, p02 + add * v0 * v2,
                  p11 + add * v1 * v1, p12 + add * v1 * v2, p22 + add * v2 * v2)


@jit
def _assess(rows, has, grown, d_ref, X, wa, we, X_ls, upper, max_nu, cd, q):
    """robust.assess for one problem: (finite, P packed, ok, ν, every exclusion decisive)."""
    n = rows.shape[0]
    T = _terms(rows, grown, d_ref, X[0], X[1], X[2])
    chi2 = o0 = o1 = o2 = 0.0
    rho_min, dmax = inf, 0.0
    excluded = np.empty((2 * n, 4))         # (r, gradient) of the excluded angles
    n_ex = 0
    n_has = 0
    for k in range(n):
        ra, re, a0, a1, h0, h1, h2 = T[k, 0], T[k, 1], T[k, 2], T[k, 3], T[k, 4], T[k, 5], T[k, 6]
        dx, dy, dz, d = T[k, 7], T[k, 8], T[k, 9], T[k, 10]
        w1, w2, h = wa[k], we[k], has[k]
        n_has += 1 if h else 0
        chi2 += w1 * ra * ra + w2 * re * re
        if w1 + w2 > 0:
            o0 += dx / d
            o1 += dy / d
            o2 += dz / d
            rk = sqrt(dx * dx + dy * dy)
            rho_min = rk if rk < rho_min else rho_min
        if isfinite(d):
            dmax = d if d > dmax else dmax
        if w1 == 0:
            excluded[n_ex, 0], excluded[n_ex, 1], excluded[n_ex, 2] = ra, a0, a1
            excluded[n_ex, 3] = 0.0
            n_ex += 1
        if w2 == 0 and h:
            excluded[n_ex, 0], excluded[n_ex, 1], excluded[n_ex, 2] = re, h0, h1
            excluded[n_ex, 3] = h2
            n_ex += 1
    f00, f01, f02, f11, f12, f22 = _fisher_at(rows, grown, d_ref, X, wa, we)
    finite, P = _safe_inverse_packed(f00, f01, f02, f11, f12, f22)
    finite = finite and _finite6(P[0], P[1], P[2], P[3], P[4], P[5])
    n_kept = int(wa.sum() + we.sum())
    n_all = n + n_has
    Pf = P if finite else (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    marginal = False
    for k in range(n_ex):
        r, g0, g1, g2 = excluded[k, 0], excluded[k, 1], excluded[k, 2], excluded[k, 3]
        if not r * r / (1.0 + _quad_packed(g0, g1, g2, Pf)) > cd:
            marginal = True
    Ps_finite, Ps = finite, P
    if grown:
        P0, u_out = P, (o0, o1, o2)
        if finite:
            finite, P = _test_inversion(rows, grown, d_ref, X, wa, we, P0, u_out, 10.0 * dmax,
                                        TEST_INVERSION_Z)
        if finite:
            Ps_finite, Ps = _test_inversion(rows, grown, d_ref, X, wa, we, P0, u_out,
                                            10.0 * dmax, STATUS_REGION_Z)
        else:
            Ps_finite = False
    nu = nan
    if finite and Ps_finite:
        nu = sqrt(_max0(_eig_extremes(Ps[0], Ps[1], Ps[2], Ps[3], Ps[4], Ps[5])[2])) / rho_min
        nu = nu if isfinite(nu) else nan
    dof = n_kept - 3 if n_kept - 3 > 1 else 1
    ok = (chi2 <= _upper_of(upper, dof) and nu <= max_nu
          and n_all - n_kept <= (n_all - 3) // 2 and not marginal and finite)
    if ok:
        ok = not _second_optimum(rows, grown, d_ref, X, wa, we, P, X_ls, q)
    return finite, (P if finite else _INF6), ok, nu, not marginal


@jit
def _second_optimum(rows, grown, d_ref, X, wa, we, P, ls, q):
    """robust_consensus.second_optimum for one problem (X, P finite; P packed)."""
    if not _finite3(ls):
        return False
    _, Pi = _safe_inverse_packed(P[0], P[1], P[2], P[3], P[4], P[5])
    if not _quad_packed(ls[0] - X[0], ls[1] - X[1], ls[2] - X[2], Pi) > q:
        return False
    X2 = _refit(rows, grown, d_ref, ls, wa, we)
    far = _quad_packed(X2[0] - X[0], X2[1] - X[1], X2[2] - X[2], Pi) > q
    close = _cost(rows, grown, d_ref, X2, wa, we) - _cost(rows, grown, d_ref, X, wa, we) < q
    return far and close


@jit
def _refine(rows, has, hasf, grown, d_ref, X_ml, c2, masks, upper, lower, max_nu, cd, q):
    """Steps 2-4 of one problem: (X, finite, P packed, ok, ν, wa, we)."""
    X, wa, we, X_ls, has_all, X_all = _consensus_fit(rows, has, hasf, grown, d_ref, X_ml, c2,
                                                     masks, upper, lower)
    finite, P, ok, nu, decisive = _assess(rows, has, grown, d_ref, X, wa, we, X_ls, upper,
                                          max_nu, cd, q)
    if not decisive and has_all and _finite3(X_all):
        # robust.confident_result: back to the fit of all the angles.
        X, wa, we = X_all, np.ones(rows.shape[0]), hasf.copy()
        finite, P, ok, nu, _ = _assess(rows, has, grown, d_ref, X, wa, we, X_ls, upper,
                                       max_nu, cd, q)
    return X, finite, P, ok, nu, wa, we


def consistent_one(bearings, x, P, probability):
    """robust._consistent for one problem on floats: checks (a)-(d) of
    :func:`.robust.consistency_status` at the fix ``x`` (3,) m with covariance ``P`` (3, 3)
    m² (nested lists, finite; constant σ): (passed, the step δ (3,) m or None). One pass over
    the stations for the whitened residuals, gradients, F and Gᵀr (the quantities of
    :func:`_terms`), then the step and the linearised residuals. Raises :class:`Fallback`
    where the batch path must decide."""
    x0, x1, x2 = x
    try:
        f00 = f01 = f02 = f11 = f12 = f22 = b0 = b1 = b2 = chi2 = 0.0
        rows = []
        rho_min = inf
        n_el = 0
        for (px, py, pz), az, el, sa, se in zip(
                bearings.positions[0].tolist(), bearings.azimuth[0].tolist(),
                bearings.elevation[0].tolist(), bearings.sigma_az[0].tolist(),
                bearings.sigma_el[0].tolist()):
            dx, dy, dz = x0 - px, x1 - py, x2 - pz
            rho2 = dx * dx + dy * dy
            rho = sqrt(rho2)
            e = az - atan2(dy, dx)
            e -= _TWO_PI * ceil((e - pi) / _TWO_PI)
            ra = e / sa
            a0, a1 = -dy / (rho2 * sa), dx / (rho2 * sa)
            f00 += a0 * a0
            f01 += a0 * a1
            f11 += a1 * a1
            b0 += ra * a0
            b1 += ra * a1
            chi2 += ra * ra
            if el == el:
                r2 = rho2 + dz * dz
                re = (el - atan2(dz, rho)) / se
                t = dz / (rho * r2 * se)
                h0, h1, h2 = -dx * t, -dy * t, rho / (r2 * se)
                f00 += h0 * h0
                f01 += h0 * h1
                f02 += h0 * h2
                f11 += h1 * h1
                f12 += h1 * h2
                f22 += h2 * h2
                b0 += re * h0
                b1 += re * h1
                b2 += re * h2
                chi2 += re * re
                n_el += 1
                rows.append((ra, a0, a1, re, h0, h1, h2))
            else:
                rows.append((ra, a0, a1, 0.0, 0.0, 0.0, 0.0))
            if rho < rho_min:
                rho_min = rho
        inv_f, Fi = _safe_inverse_packed(f00, f01, f02, f11, f12, f22)
        Pp = (P[0][0], P[0][1], P[0][2], P[1][1], P[1][2], P[2][2])
        inv_p, Pi = _safe_inverse_packed(*Pp)
        if not (inv_f and inv_p):
            return False, None
        i00, i01, i02, i11, i12, i22 = Fi
        d0 = i00 * b0 + i01 * b1 + i02 * b2
        d1 = i01 * b0 + i11 * b1 + i12 * b2
        d2 = i02 * b0 + i12 * b1 + i22 * b2
        chi2_min = chi2 - (d0 * b0 + d1 * b1 + d2 * b2)
        worst = 0.0
        for ra, a0, a1, re, h0, h1, h2 in rows:
            la = ra - (a0 * d0 + a1 * d1)
            le = re - (h0 * d0 + h1 * d1 + h2 * d2)
            worst = max(worst, la * la, le * le)
        nu = sqrt(max(_eig_extremes(*Pp)[2], 0.0)) / rho_min
    except (ZeroDivisionError, ValueError, OverflowError) as exc:
        raise Fallback(str(exc)) from exc
    return (chi2_min <= _upper(max(len(rows) + n_el - 3, 1), probability)
            and _quad_packed(d0, d1, d2, Pi) <= _upper(3, probability)
            and worst <= outlier_c2() and nu <= MAX_REGION_NONLINEARITY), (d0, d1, d2)


@jit
def _rows(pos, az, el, sa, se):
    """(rows (N, 7): px, py, pz, θ, ψ, 1/σ_θ, 1/σ_ψ with ψ and 1/σ_ψ 0 without elevation;
    has elevation (N,) bool; the same as 0/1) of one problem's arrays (ψ NaN: azimuth only).
    :class:`Fallback` where a 1/σ is not finite."""
    n = az.shape[0]
    rows = np.empty((n, 7))
    has = np.empty(n, dtype=np.bool_)
    hasf = np.empty(n)
    for k in range(n):
        h = isfinite(el[k])
        rows[k, 0], rows[k, 1], rows[k, 2] = pos[k, 0], pos[k, 1], pos[k, 2]
        rows[k, 3] = az[k]
        rows[k, 4] = el[k] if h else 0.0
        if not (sa[k] != 0.0 and (se[k] != 0.0 or not h)):
            raise Fallback('σ too small for floats')
        rows[k, 5] = 1.0 / sa[k]
        rows[k, 6] = 1.0 / se[k] if h else 0.0
        if not (isfinite(rows[k, 5]) and isfinite(rows[k, 6])):
            raise Fallback('σ too small for floats')
        has[k] = h
        hasf[k] = 1.0 if h else 0.0
    return rows, has, hasf


@jit
def _refine_arrays(pos, az, el, sa, se, grown, d_ref, X_ml, c2, masks, upper, lower, max_nu,
                   cd, q):
    """:func:`_refine` of one problem's arrays (:func:`_rows`), as FixResult arrays:
    (position (1, 3), covariance (1, 3, 3), ok, ν, excluded (1, N, 2) bool, finite)."""
    rows, has, hasf = _rows(pos, az, el, sa, se)
    X, finite, P, ok, nu, wa, we = _refine(rows, has, hasf, grown, d_ref, X_ml, c2, masks,
                                           upper, lower, max_nu, cd, q)
    n = rows.shape[0]
    position = np.empty((1, 3))
    position[0, 0], position[0, 1], position[0, 2] = X
    covariance = np.empty((1, 3, 3))
    covariance[0] = _full(P[0], P[1], P[2], P[3], P[4], P[5])
    excluded = np.zeros((1, n, 2), dtype=np.bool_)
    for k in range(n):
        excluded[0, k, 0] = wa[k] == 0.0
        excluded[0, k, 1] = has[k] and we[k] == 0.0
    return position, covariance, ok, nu, excluded, finite and _finite3(X)


def refine(bearings, X_ml, d_ref=None):
    """Steps 2-4 for one problem: (position (1, 3) m, covariance (1, 3, 3) m², ok, ν,
    excluded (1, N, 2) bool (azimuth, elevation), finite: position and covariance finite).

    ``bearings`` a one-problem BearingSet, ``X_ml`` the estimator's fix (3,) m (NaN allowed),
    ``d_ref`` m for range-grown σ. Raises :class:`Fallback` where the batch path must run.
    """
    grown = d_ref is not None
    masks, upper, lower = _tables(bearings.N)
    try:
        return _refine_arrays(
            plain_array(bearings.positions[0]), plain_array(bearings.azimuth[0]),
            plain_array(bearings.elevation[0]), plain_array(bearings.sigma_az[0]),
            plain_array(bearings.sigma_el[0]), grown, float(d_ref) if grown else 1.0,
            tuple(float(x) for x in X_ml), outlier_c2(), masks, upper, lower,
            max_nonlinearity(grown), outlier_c2(DECISIVE_PROBABILITY),
            _upper(3, MULTIMODE_PROBABILITY))
    except (ZeroDivisionError, ValueError, OverflowError) as exc:
        raise Fallback(str(exc)) from exc
