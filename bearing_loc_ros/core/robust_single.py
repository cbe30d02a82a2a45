"""Steps 2-4 of the :mod:`.robust` docstring for one problem, on Python floats.

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

Each Levenberg-Marquardt iterate is evaluated in one pass over the stations (cost, Fisher
information and gradient together). The candidates of N ≥ 5 stations (up to N(N + 1)/2 + 2 of
them) are solved and scored as arrays: the station subsets' normal equations are one
product of the subset masks with the stations' packed equations, solved by cofactors.
3 × 3 inverses and solves are cofactor formulas where tr(A) tr(adj A) ≤ 1e5 det(A) (then
κ(A) ≤ 1e5: crlb.safe_inverse's rank test certainly passes and the result agrees with
LAPACK's to about κ ε); other matrices are decided as crlb.safe_inverse decides them, by
eigenvalues of the characteristic cubic (Smith 1961) where clear, else by LAPACK. Statuses,
exclusions and convergence flags are the batch path's; both refits accept a step within
the rounding of the cost (robust_consensus.ACCEPT_TOL) and so iterate to the same optimum
(measured against the batch path on the same input, 13,720 random problems of 3-10
stations, bench/one_fix_agreement.py --random: ≤ 1e-15 of the range for ``ok`` fixes,
≤ 8.5e-9 for ``low_confidence`` ones, whose refit can end at its iteration cap on a region
far from an ellipse; on the seed scenarios ≤ 5e-16 and ≤ 1.5e-9,
bench/one_fix_agreement.py; tested at 1e-9), covariances within 3e-8 of their largest
entry.

Where the floats cannot follow the batch path to rounding (a division by zero, a log of
zero, a rank test or major axis too close to call, a non-finite Fisher information),
:class:`Fallback` is raised and the caller runs the batch path. Units: m, rad; ENU,
azimuth θ CCW from East, elevation ψ above the horizontal.
"""

from math import acos, atan2, ceil, cos, inf, isfinite, log, nan, pi, sin, sqrt

import numpy as np

from .robust_consensus import _station_masks, ACCEPT_TOL, STEP_TOL
from .robust_model import (_upper_cached, CONSISTENCY_PROBABILITY, DECISIVE_PROBABILITY,
                           MAX_REGION_NONLINEARITY, max_nonlinearity, MULTIMODE_PROBABILITY,
                           outlier_c2, REFIT_ITERATIONS, REFIT_ROUNDS, STATUS_REGION_Z,
                           TEST_INVERSION_Z)

_TWO_PI = 2.0 * pi
_RCOND = 1e-12
_CLEAR = 1e-5
#: tr(A) tr(adj A) / det(A) bound below which a cofactor inverse is used (κ(A) ≤ this).
_TRACE_CLEAR = 1e5
#: Smallest N whose consensus candidates are solved and scored as arrays.
_ARRAY_CANDIDATES = 5
_INF3 = ((inf,) * 3,) * 3
_NAN3 = (nan, nan, nan)


class Fallback(Exception):
    """The float path cannot reproduce the batch path here: use the batch path."""


def _upper(dof, probability=CONSISTENCY_PROBABILITY):
    """robust_model.chi2_upper of one integer dof, as a float (cached)."""
    return _upper_cached(int(dof), probability)


class Problem:
    """One problem's stations as float tuples (σ are σ_ref for range growth; robust_model.Data).

    ``rows``: per station (px, py, pz, θ, ψ, 1/σ_θ, 1/σ_ψ), ψ and 1/σ_ψ 0 without elevation.
    """

    def __init__(self, bearings, d_ref):
        pos = bearings.positions[0].tolist()
        el = bearings.elevation[0].tolist()
        self.has = [isfinite(e) for e in el]
        self.hasf = [1.0 if h else 0.0 for h in self.has]
        self.rows = [(p[0], p[1], p[2], a, e if h else 0.0, 1.0 / sa, 1.0 / se if h else 0.0)
                     for p, a, e, sa, se, h in zip(pos, bearings.azimuth[0].tolist(), el,
                                                   bearings.sigma_az[0].tolist(),
                                                   bearings.sigma_el[0].tolist(), self.has)]
        if not all(isfinite(r[5]) and isfinite(r[6]) for r in self.rows):
            raise Fallback('σ too small for floats')
        self.d_ref = None if d_ref is None else float(d_ref)
        self.n = len(self.rows)
        self.n_has = sum(self.has)
        self._arrays = None

    def arrays(self):
        """(positions (3, N), θ, ψ, 1/σ_θ, 1/σ_ψ, has elevation) as arrays (N,), built once."""
        if self._arrays is None:
            px, py, pz, az, el, ia, ie = zip(*self.rows)
            self._arrays = (np.array([px, py, pz]), np.array(az), np.array(el), np.array(ia),
                            np.array(ie), np.array(self.has))
        return self._arrays


# --- 3 × 3 symmetric matrices (packed a00, a01, a02, a11, a12, a22) -------------------------

def _eig_extremes(A):
    """(λ_min, λ_mid, λ_max) of a finite symmetric 3 × 3 matrix (Smith 1961)."""
    a, b, c = A[0][0], A[1][1], A[2][2]
    d, e, f = A[0][1], A[1][2], A[0][2]
    q = (a + b + c) / 3.0
    aa, bb, cc = a - q, b - q, c - q
    r = sqrt((aa * aa + bb * bb + cc * cc + 2.0 * (d * d + e * e + f * f)) / 6.0)
    if not r > 0.0:
        return q, q, q
    det = (aa * (bb * cc - e * e) - d * (d * cc - e * f) + f * (d * e - bb * f)) / r ** 3
    phi = acos(min(1.0, max(-1.0, 0.5 * det))) / 3.0
    hi = q + 2.0 * r * cos(phi)
    lo = q + 2.0 * r * cos(phi + _TWO_PI / 3.0)
    return lo, 3.0 * q - hi - lo, hi


def _finite3(A):
    return all(map(isfinite, A[0] + A[1] + A[2]))


def _clear(A):
    """True when A (finite) is certainly well conditioned: λ_min > 1e-5 λ_max > 0.

    The closed-form λ_min is off by at most about sqrt(ε) λ_max (robust_consensus._psd_inverse),
    so then κ < 1e5: crlb.safe_inverse's rank test passes, and Gaussian elimination agrees
    with LAPACK's inverse to about κ ε.
    """
    lo, _, hi = _eig_extremes(A)
    return lo > _CLEAR * abs(hi) and hi > 0.0


def _rank_ok(A):
    """crlb.safe_inverse's test: λ_min > 1e-12 |λ_max| and λ_max > 0 (False if not finite).

    In closed form where the answer is clear, else by LAPACK as safe_inverse decides it.
    """
    if not _finite3(A):
        return False
    if _clear(A):
        return True
    w = np.linalg.eigvalsh(np.array(A, dtype=float))
    return bool(w[0] > _RCOND * abs(w[-1]) and w[-1] > 0)


def _lu_solve(A, B):
    """Solve A X = B (3 × 3; B a sequence of right-hand sides): Gaussian elimination with
    partial pivoting (the first largest pivot), unrolled. ZeroDivisionError if singular."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = A
    p = [0, 1, 2]
    if abs(a10) > abs(a00) and abs(a10) >= abs(a20):
        a00, a01, a02, a10, a11, a12 = a10, a11, a12, a00, a01, a02
        p[0], p[1] = 1, 0
    elif abs(a20) > abs(a00) and abs(a20) > abs(a10):
        a00, a01, a02, a20, a21, a22 = a20, a21, a22, a00, a01, a02
        p[0], p[2] = 2, 0
    if a00 == 0.0:
        raise ZeroDivisionError
    l10, l20 = a10 / a00, a20 / a00
    a11, a12 = a11 - l10 * a01, a12 - l10 * a02
    a21, a22 = a21 - l20 * a01, a22 - l20 * a02
    if abs(a21) > abs(a11):
        a11, a12, a21, a22 = a21, a22, a11, a12
        l10, l20 = l20, l10
        p[1], p[2] = p[2], p[1]
    if a11 == 0.0:
        raise ZeroDivisionError
    l21 = a21 / a11
    a22 = a22 - l21 * a12
    if a22 == 0.0:
        raise ZeroDivisionError
    out = []
    for b in B:
        y0 = b[p[0]]
        y1 = b[p[1]] - l10 * y0
        y2 = b[p[2]] - l20 * y0 - l21 * y1
        x2 = y2 / a22
        x1 = (y1 - a12 * x2) / a11
        out.append(((y0 - a01 * x1 - a02 * x2) / a00, x1, x2))
    return out


def _full(a00, a01, a02, a11, a12, a22):
    return [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]]


def _cofactors(a00, a01, a02, a11, a12, a22):
    """(adj A packed, det A, clear) of a symmetric A (floats, or arrays of K matrices).

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
    clear = ((a00 > 0.0) & (c22 > 0.0) & (det > 0.0) & (det < inf)
             & ((a00 + a11 + a22) * (c00 + c11 + c22) <= _TRACE_CLEAR * det))
    return (c00, c01, c02, c11, c12, c22), det, clear


def _cofactor_inverse(a00, a01, a02, a11, a12, a22):
    """A⁻¹ packed by cofactors where :func:`_cofactors` finds it clear, else None."""
    c, det, clear = _cofactors(a00, a01, a02, a11, a12, a22)
    if clear:
        i = 1.0 / det
        return c[0] * i, c[1] * i, c[2] * i, c[3] * i, c[4] * i, c[5] * i
    return None


def _safe_inverse_packed(a00, a01, a02, a11, a12, a22):
    """crlb.safe_inverse of one symmetric matrix: packed inverse, or None (+inf: it fails).

    :class:`Fallback` for an ill-conditioned matrix that passes the rank test (its inverse
    is the batch path's only to about κ ε).
    """
    out = _cofactor_inverse(a00, a01, a02, a11, a12, a22)
    if out is not None:
        return out
    A = _full(a00, a01, a02, a11, a12, a22)
    if not _finite3(A):
        return None
    if not _clear(A):
        if _rank_ok(A):
            raise Fallback('ill-conditioned information')
        return None
    c = _lu_solve(A, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))
    # (LU's inverse is symmetric only to rounding: the lower triangle as LAPACK's is unused)
    return c[0][0], c[1][0], c[2][0], c[1][1], c[2][1], c[2][2]


def _safe_inverse(A):
    """crlb.safe_inverse of one 3 × 3 symmetric matrix (nested lists; +inf when it fails)."""
    P = _safe_inverse_packed(A[0][0], A[0][1], A[0][2], A[1][1], A[1][2], A[2][2])
    return _INF3 if P is None else _full(*P)


def _quad_packed(v0, v1, v2, P):
    p00, p01, p02, p11, p12, p22 = P
    return (v0 * (p00 * v0 + p01 * v1 + p02 * v2) + v1 * (p01 * v0 + p11 * v1 + p12 * v2)
            + v2 * (p02 * v0 + p12 * v1 + p22 * v2))


def _quad(v, P, w):
    return sum(v[i] * P[i][j] * w[j] for i in range(3) for j in range(3))


def _solve_packed(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """A x = b for symmetric A: cofactors where clear (:func:`_cofactors`), else Gaussian
    elimination with partial pivoting (ZeroDivisionError if singular)."""
    (c00, c01, c02, c11, c12, c22), det, clear = _cofactors(a00, a01, a02, a11, a12, a22)
    if clear:
        return ((c00 * b0 + c01 * b1 + c02 * b2) / det, (c01 * b0 + c11 * b1 + c12 * b2) / det,
                (c02 * b0 + c12 * b1 + c22 * b2) / det)
    return _lu_solve(_full(a00, a01, a02, a11, a12, a22), ((b0, b1, b2),))[0]


# --- the likelihood on floats ----------------------------------------------------------------

def _terms(pb, X):
    """Per station at X: (ra, re, a0, a1, h0, h1, h2, dx, dy, dz, d).

    ra, re the whitened residuals, (a0, a1, 0) and (h0, h1, h2) the whitened gradients
    ga, ge, 1/m, (dx, dy, dz) = X − station and d its range, m: robust_model.Data.evaluate's
    quantities (σ grown with range when ``pb.d_ref`` is set), one station at a time.
    """
    x0, x1, x2 = X
    d_ref = pb.d_ref
    for px, py, pz, az, el, ia, ie in pb.rows:
        dx = x0 - px
        dy = x1 - py
        dz = x2 - pz
        rho2 = dx * dx + dy * dy
        r2 = rho2 + dz * dz
        rho = sqrt(rho2)
        d = sqrt(r2)
        e_az = az - atan2(dy, dx)
        e_az -= _TWO_PI * ceil((e_az - pi) / _TWO_PI)
        e_el = el - atan2(dz, rho)
        if d_ref is not None:
            f = d_ref / d
            ia *= f
            ie *= f
        s = ia / rho2
        t = dz / (rho * r2)
        yield (ia * e_az, ie * e_el, -(dy * s), dx * s, -(dx * t) * ie, -(dy * t) * ie,
               (rho / r2) * ie, dx, dy, dz, d)


def _state(pb, X, wa, we):
    """(L, F packed, ½∇L, Σ d²) at X: robust_consensus._refit's cost, information and gradient.

    L = Σ w (r² + log σ²); F = Σ w g gᵀ (+ Σ 2 (wa + we) u uᵀ / d² with range growth);
    ½∇L = −Σ w r g (+ Σ (wa (1 − ra²) + we (1 − re²)) u / d with range growth). One pass over
    the stations (:func:`_terms`): the refit's inner loop, so Σ w g gᵀ is accumulated here
    with the rest rather than by a second pass of :func:`_fisher_at`.
    """
    d_ref = pb.d_ref
    cost = f00 = f01 = f02 = f11 = f12 = f22 = g0 = g1 = g2 = sd2 = 0.0
    for (ra, re, a0, a1, h0, h1, h2, dx, dy, dz, d), w1, w2 in zip(_terms(pb, X), wa, we):
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
        if d_ref is not None:
            log_s2 = 2.0 * log(d / d_ref)
            cost += w1 * (ra * ra + log_s2) + w2 * (re * re + log_s2)
            k = (w1 * (1.0 - ra * ra) + w2 * (1.0 - re * re)) / d
            v = 2.0 * (w1 + w2) / (d * d)
            u0, u1, u2 = dx / d, dy / d, dz / d
            g0 += k * u0
            g1 += k * u1
            g2 += k * u2
            f00 += v * u0 * u0
            f01 += v * u0 * u1
            f02 += v * u0 * u2
            f11 += v * u1 * u1
            f12 += v * u1 * u2
            f22 += v * u2 * u2
        else:
            cost += w1 * (ra * ra) + w2 * (re * re)
    return (cost if isfinite(cost) else inf, (f00, f01, f02, f11, f12, f22), (g0, g1, g2), sd2)


def _residuals(pb, X):
    """Per station (ra, re, log σ²) at X (robust_model.Data.evaluate without gradients)."""
    x0, x1, x2 = X
    d_ref = pb.d_ref
    out = []
    for px, py, pz, az, el, ia, ie in pb.rows:
        dx = x0 - px
        dy = x1 - py
        dz = x2 - pz
        rho2 = dx * dx + dy * dy
        e_az = az - atan2(dy, dx)
        e_az -= _TWO_PI * ceil((e_az - pi) / _TWO_PI)
        e_el = el - atan2(dz, sqrt(rho2))
        if d_ref is not None:
            d = sqrt(rho2 + dz * dz)
            f = d_ref / d
            out.append(((ia * f) * e_az, (ie * f) * e_el, 2.0 * log(d / d_ref)))
        else:
            out.append((ia * e_az, ie * e_el, 0.0))
    return out


def _cost(pb, X, wa, we):
    """robust_consensus._cost of one problem: L(X) = Σ w (r² + log σ²), +inf if not finite."""
    c = 0.0
    for (ra, re, log_s2), w1, w2 in zip(_residuals(pb, X), wa, we):
        c += w1 * (ra * ra + log_s2) + w2 * (re * re + log_s2)
    return c if isfinite(c) else inf


def _inliers(pb, X, c2):
    wa, we = [], []
    for (ra, re, _), h in zip(_residuals(pb, X), pb.has):
        wa.append(1.0 if ra * ra <= c2 else 0.0)
        we.append(1.0 if h and re * re <= c2 else 0.0)
    return wa, we


def _solvable(wa, we):
    st = sum(1 for a, e in zip(wa, we) if a + e > 0)
    return st >= 2 and sum(we) >= 1 and sum(wa) + sum(we) >= 3


def _refit(pb, X0, wa, we, iterations=REFIT_ITERATIONS):
    """robust_consensus._refit for one problem (Levenberg-Marquardt on the full likelihood)."""
    X = tuple(X0)
    lam = 0.0
    cost, F, g, sd2 = _state(pb, X, wa, we)
    n = pb.n
    for _ in range(iterations):
        if not all(map(isfinite, F)):
            raise Fallback('non-finite information')
        f00, f01, f02, f11, f12, f22 = F
        try:
            s0, s1, s2 = _solve_packed(f00 + lam * f00, f01, f02, f11 + lam * f11, f12,
                                       f22 + lam * f22, -g[0], -g[1], -g[2])
        except (ZeroDivisionError, OverflowError):
            s0 = s1 = s2 = 0.0
        s0 = s0 if isfinite(s0) else 0.0
        s1 = s1 if isfinite(s1) else 0.0
        s2 = s2 if isfinite(s2) else 0.0
        Xt = (X[0] + s0, X[1] + s1, X[2] + s2)
        st = _state(pb, Xt, wa, we)
        ct = st[0]
        if ct < inf and ct <= cost + ACCEPT_TOL * (1.0 + abs(cost)):   # (ct +inf: not finite)
            X = Xt
            cost, F, g, sd2 = st
            lam = 0.1 * lam * (lam > 1e-6)
        else:
            lam = max(10.0 * lam, 1e-3)
        if sqrt(s0 * s0 + s1 * s1 + s2 * s2) <= STEP_TOL * sqrt(sd2 / n) or lam > 1e10:
            break
    return X


# --- step 2: consensus candidates ----------------------------------------------------------

def _station_equations(pb):
    """Per station the packed pseudo-linear normal equations (a00 … a22, b0, b1, b2)
    (Wang, Zhang & Wu eq. (4); robust_consensus._ls_candidates)."""
    out = []
    for (px, py, pz, az, el, _, _), h in zip(pb.rows, pb.hasf):
        s, c = sin(az), cos(az)
        sp, cp = sin(el), cos(el)
        q0, q1, q2 = h * c * sp, h * s * sp, -h * cp
        y1 = s * px + (-c) * py + 0.0 * pz
        y2 = q0 * px + q1 * py + q2 * pz
        out.append((s * s + q0 * q0, s * (-c) + q0 * q1, s * 0.0 + q0 * q2,
                    c * c + q1 * q1, (-c) * 0.0 + q1 * q2, 0.0 + q2 * q2,
                    s * y1 + q0 * y2, (-c) * y1 + q1 * y2, 0.0 * y1 + q2 * y2))
    return out


def _solve_candidate(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """The ls fix of one station subset: safe_inverse(A) b as the batch path decides it."""
    P = _cofactor_inverse(a00, a01, a02, a11, a12, a22)
    if P is not None:
        p00, p01, p02, p11, p12, p22 = P
        return (p00 * b0 + p01 * b1 + p02 * b2, p01 * b0 + p11 * b1 + p12 * b2,
                p02 * b0 + p12 * b1 + p22 * b2)
    A = _full(a00, a01, a02, a11, a12, a22)
    if not _finite3(A):
        return _NAN3
    if _clear(A):
        return _lu_solve(A, ((b0, b1, b2),))[0]
    if _rank_ok(A):
        # Ill-conditioned but invertible: LAPACK's inverse, as the batch path.
        return tuple((np.linalg.inv(np.array(A)) @ np.array([b0, b1, b2])).tolist())
    return _NAN3


def _score(pb, X, c2):
    """robust_consensus._score of one candidate (+inf if not finite)."""
    x0, x1, x2 = X
    d_ref = pb.d_ref
    s = 0.0
    for (px, py, pz, az, el, ia, ie), h in zip(pb.rows, pb.has):
        dx = x0 - px
        dy = x1 - py
        dz = x2 - pz
        rho2 = dx * dx + dy * dy
        e_az = az - atan2(dy, dx)
        e_az -= _TWO_PI * ceil((e_az - pi) / _TWO_PI)
        if d_ref is not None:
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
        if h:
            qe = ie * (el - atan2(dz, sqrt(rho2)))
            qe *= qe
            s += qe + log_s2 if qe <= c2 else c2
    return s if isfinite(s) else inf


def _best_candidate_floats(pb, x_ml, c2):
    eqs = _station_equations(pb)
    cand = [x_ml]
    for mask in _station_masks(pb.n).tolist():
        a = [0.0] * 9
        for k, e in zip(mask, eqs):
            if k:
                a = [x + y for x, y in zip(a, e)]
        cand.append(_solve_candidate(*a))
    best, best_s = 0, inf
    for k, C in enumerate(cand):
        if all(map(isfinite, C)):
            s = _score(pb, C, c2)
            if s < best_s:
                best, best_s = k, s
    return cand[best], cand[1]


def _best_candidate_arrays(pb, x_ml, c2):
    n = pb.n
    masks = _station_masks(n)
    S = masks @ np.array(_station_equations(pb))               # (K, 9)
    a00, a01, a02, a11, a12, a22, b0, b1, b2 = S.T
    with np.errstate(all='ignore'):
        (c00, c01, c02, c11, c12, c22), det, clear = _cofactors(a00, a01, a02, a11, a12, a22)
        i = 1.0 / det
        cand = np.empty((len(det) + 1, 3))
        cand[0] = x_ml
        cand[1:, 0] = (c00 * i) * b0 + (c01 * i) * b1 + (c02 * i) * b2
        cand[1:, 1] = (c01 * i) * b0 + (c11 * i) * b1 + (c12 * i) * b2
        cand[1:, 2] = (c02 * i) * b0 + (c12 * i) * b1 + (c22 * i) * b2
        if not clear.all():
            for k in np.flatnonzero(~clear).tolist():
                cand[k + 1] = _solve_candidate(*S[k].tolist())
        ok = np.isfinite(cand).all(axis=1)
        X = np.where(ok[:, None], cand, 0.0)
        pos, az, el, ia, ie, has = pb.arrays()
        dx = X[:, 0:1] - pos[0]
        dy = X[:, 1:2] - pos[1]
        dz = X[:, 2:3] - pos[2]
        rho2 = dx * dx + dy * dy
        e_az = az - np.arctan2(dy, dx)
        e_az -= _TWO_PI * np.ceil((e_az - pi) / _TWO_PI)
        e_el = el - np.arctan2(dz, np.sqrt(rho2))
        if pb.d_ref is not None:
            d = np.sqrt(rho2 + dz * dz)
            f = pb.d_ref / d
            qa = (ia * f) * e_az
            qe = (ie * f) * e_el
            log_s2 = 2.0 * np.log(d / pb.d_ref)
        else:
            qa = ia * e_az
            qe = ie * e_el
            log_s2 = 0.0
        qa *= qa
        qe *= qe
        qe = np.where(has, qe, 0.0)
        n_in = (qa <= c2) + (has & (qe <= c2)).astype(float)
        s = (np.minimum(qa, c2) + np.minimum(qe, c2) + log_s2 * n_in).sum(axis=-1)
        s = np.where(np.isfinite(s) & ok, s, np.inf)
    best = int(np.argmin(s))
    return tuple(cand[best].tolist()), tuple(cand[1].tolist())


def _best_candidate(pb, X_ml, c2):
    """Step 2: (the best-scoring candidate, the all-station ls fix).

    Candidates: the estimator's fix, the ls fix of all stations and of the subsets of
    robust_consensus._station_masks (leaving out one station and, for N ≥ 5, every pair; pairs
    of spread stations for large N); the first lowest MSAC
    score wins, as the batch path's argmin. On floats for N < 5, as arrays from N = 5 on.
    """
    x_ml = X_ml if all(map(isfinite, X_ml)) else _NAN3
    if pb.n >= _ARRAY_CANDIDATES:
        return _best_candidate_arrays(pb, x_ml, c2)
    return _best_candidate_floats(pb, x_ml, c2)


# --- step 3: refit -------------------------------------------------------------------------

def consensus_fit(pb, X_ml, c2):
    """robust_consensus.consensus_fit for one problem: (X, wa, we, the all-station ls fix,
    the rejected fit of all the angles or None)."""
    n = pb.n
    X, X_ls = _best_candidate(pb, X_ml, c2)
    X = tuple(x if isfinite(x) else 0.0 for x in X)
    wa, we = _inliers(pb, X, c2)
    for _ in range(REFIT_ROUNDS):
        if _solvable(wa, we):
            a, e = wa, we
        else:
            a, e = [1.0] * n, list(pb.hasf)
        Xa = _refit(pb, X, a, e)
        na, ne = _inliers(pb, Xa, c2)
        if not _solvable(na, ne):
            na, ne = a, e
        same = na == a and ne == e
        X, wa, we = Xa, na, ne
        if same:
            break
    X, wa, we, X_all = _prefer_all_bearings(pb, X, wa, we, X_ml, X_ls)
    return X, wa, we, X_ls, X_all


def _prefer_all_bearings(pb, X, wa, we, X_ml, X_ls):
    if all(a == 1.0 for a in wa) and all(e == 1.0 or not h for e, h in zip(we, pb.has)):
        return X, wa, we, None
    ones, she = [1.0] * pb.n, pb.hasf
    best, cost = None, inf
    for start in (X_ml, X_ls):
        if all(map(isfinite, start)):
            Xs = _refit(pb, start, ones, she)
            cs = _cost(pb, Xs, ones, she)
        else:
            Xs, cs = _refit(pb, X, ones, she), inf
        if best is None or cs < cost:
            best, cost = Xs, cs
    chi2 = sum(ra * ra + h * re * re for (ra, re, _), h in zip(_residuals(pb, best), she))
    if isfinite(cost) and chi2 <= _upper(pb.n + pb.n_has - 3):
        return best, [1.0] * pb.n, list(she), None
    return X, wa, we, (best if isfinite(cost) else None)


# --- step 4: assessment --------------------------------------------------------------------

def _fisher_at(pb, X, wa, we):
    """Σ w g gᵀ packed at X, 1/m² (robust_model.fisher of Data.evaluate's gradients)."""
    f00 = f01 = f02 = f11 = f12 = f22 = 0.0
    for (_, _, a0, a1, h0, h1, h2, *_), w1, w2 in zip(_terms(pb, X), wa, we):
        f00 += w1 * a0 * a0 + w2 * h0 * h0
        f01 += w1 * a0 * a1 + w2 * h0 * h1
        f02 += w2 * h0 * h2
        f11 += w1 * a1 * a1 + w2 * h1 * h1
        f12 += w2 * h1 * h2
        f22 += w2 * h2 * h2
    return f00, f01, f02, f11, f12, f22


def _test_inversion(pb, X, wa, we, P, u_out, t_max, z=TEST_INVERSION_Z, iterations=4):
    """robust_model.test_inversion_covariance for one problem (P finite, packed).

    ``u_out`` Σ of the unit lines of sight of the stations with a kept angle (orients the
    major axis away from them), ``t_max`` 10 × the largest finite station range, m.
    """
    M = _full(*P)
    lo, mid, hi = _eig_extremes(M)
    if not hi - mid > 1e-4 * abs(hi):
        raise Fallback('major axis too close to call')
    # Eigenvector of λ_max: the largest cross product of two rows of P − λ_max I.
    R = [[M[i][j] - (hi if i == j else 0.0) for j in range(3)] for i in range(3)]
    best = None
    for i, j in ((0, 1), (0, 2), (1, 2)):
        a, b = R[i], R[j]
        c = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
        nc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        if best is None or nc > best[0]:
            best = (nc, c)
    nc, c = best
    if not nc > 0.0:
        raise Fallback('no major axis')
    nc = sqrt(nc)
    v0, v1, v2 = c[0] / nc, c[1] / nc, c[2] / nc
    dot = v0 * u_out[0] + v1 * u_out[1] + v2 * u_out[2]
    if dot == 0.0:
        raise Fallback('major axis orientation')
    if dot < 0.0:
        v0, v1, v2 = -v0, -v1, -v2
    s0 = sqrt(max(_quad_packed(v0, v1, v2, P), 0.0))
    t = z * s0
    for _ in range(iterations):
        Pt = _safe_inverse_packed(*_fisher_at(pb, (X[0] + t * v0, X[1] + t * v1,
                                                   X[2] + t * v2), wa, we))
        st = sqrt(max(_quad_packed(v0, v1, v2, Pt), 0.0)) if Pt is not None else inf
        t = min(z * st, t_max) if isfinite(st) else t_max
    add = max((t / z) ** 2 - s0 * s0, 0.0)
    if not isfinite(add):
        return None
    v = (v0, v1, v2)
    p00, p01, p02, p11, p12, p22 = P
    return (p00 + add * v[0] * v[0], p01 + add * v[0] * v[1], p02 + add * v[0] * v[2],
            p11 + add * v[1] * v[1], p12 + add * v[1] * v[2], p22 + add * v[2] * v[2])


def assess(pb, X, wa, we, X_ls):
    """robust.assess for one problem: (P (nested lists), ok, ν, every exclusion decisive)."""
    grown = pb.d_ref is not None
    max_nu = max_nonlinearity(grown)
    chi2 = o0 = o1 = o2 = 0.0
    rho_min, dmax = inf, 0.0
    excluded = []               # (r, gradient) of the excluded angles
    terms = zip(_terms(pb, X), wa, we, pb.has)
    for (ra, re, a0, a1, h0, h1, h2, dx, dy, dz, d), w1, w2, h in terms:
        chi2 += w1 * ra * ra + w2 * re * re
        if w1 + w2 > 0:
            o0 += dx / d
            o1 += dy / d
            o2 += dz / d
            rho_min = min(rho_min, sqrt(dx * dx + dy * dy))
        if isfinite(d):
            dmax = max(dmax, d)
        if w1 == 0:
            excluded.append((ra, a0, a1, 0.0))
        if w2 == 0 and h:
            excluded.append((re, h0, h1, h2))
    P = _safe_inverse_packed(*_fisher_at(pb, X, wa, we))
    finite = P is not None and all(map(isfinite, P))
    n_kept = int(sum(wa) + sum(we))
    n_all = pb.n + pb.n_has
    Pf = P if finite else (0.0,) * 6
    cd = outlier_c2(DECISIVE_PROBABILITY)
    marginal = any(not r * r / (1.0 + _quad_packed(g0, g1, g2, Pf)) > cd
                   for r, g0, g1, g2 in excluded)
    Ps = P
    if grown:
        P0, u_out = P, (o0, o1, o2)
        P = _test_inversion(pb, X, wa, we, P0, u_out, 10.0 * dmax) if finite else None
        finite = P is not None
        Ps = (_test_inversion(pb, X, wa, we, P0, u_out, 10.0 * dmax, z=STATUS_REGION_Z)
              if finite else None)
    nu = nan
    if finite and Ps is not None:
        nu = sqrt(max(_eig_extremes(_full(*Ps))[2], 0.0)) / rho_min
        nu = nu if isfinite(nu) else nan
    ok = (chi2 <= _upper(max(n_kept - 3, 1)) and nu <= max_nu
          and n_all - n_kept <= (n_all - 3) // 2 and not marginal and finite)
    if ok:
        ok = not _second_optimum(pb, X, wa, we, P, X_ls)
    return (_full(*P) if finite else [list(r) for r in _INF3]), ok, nu, not marginal


def _second_optimum(pb, X, wa, we, P, ls):
    """robust_consensus.second_optimum for one problem (X, P finite; P packed)."""
    if not all(map(isfinite, ls)):
        return False
    q = _upper(3, MULTIMODE_PROBABILITY)
    Pi = _safe_inverse_packed(*P)
    Pi = (inf,) * 6 if Pi is None else Pi

    def dist2(Y):
        return _quad_packed(Y[0] - X[0], Y[1] - X[1], Y[2] - X[2], Pi)

    if not dist2(ls) > q:
        return False
    X2 = _refit(pb, ls, wa, we)
    far = dist2(X2) > q
    close = _cost(pb, X2, wa, we) - _cost(pb, X, wa, we) < q
    return far and close


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
        Fi = _safe_inverse_packed(f00, f01, f02, f11, f12, f22)
        Pp = (P[0][0], P[0][1], P[0][2], P[1][1], P[1][2], P[2][2])
        Pi = _safe_inverse_packed(*Pp)
        if Fi is None or Pi is None:
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
        nu = sqrt(max(_eig_extremes(_full(*Pp))[2], 0.0)) / rho_min
    except (ZeroDivisionError, ValueError, OverflowError) as exc:
        raise Fallback(str(exc)) from exc
    return (chi2_min <= _upper(max(len(rows) + n_el - 3, 1), probability)
            and _quad_packed(d0, d1, d2, Pi) <= _upper(3, probability)
            and worst <= outlier_c2() and nu <= MAX_REGION_NONLINEARITY), (d0, d1, d2)


def refine(bearings, X_ml, d_ref=None):
    """Steps 2-4 for one problem: (X (3,), P (3, 3), ok, ν, wa, we) as Python floats/lists.

    ``bearings`` a one-problem BearingSet, ``X_ml`` the estimator's fix (3,) m (NaN allowed),
    ``d_ref`` m for range-grown σ. Raises :class:`Fallback` where the batch path must run.
    """
    c2 = outlier_c2()
    try:
        pb = Problem(bearings, d_ref)
        X, wa, we, X_ls, X_all = consensus_fit(pb, tuple(X_ml), c2)
        P, ok, nu, decisive = assess(pb, X, wa, we, X_ls)
        if not decisive and X_all is not None and all(map(isfinite, X_all)):
            # robust.confident_result: back to the fit of all the angles.
            X, wa, we = X_all, [1.0] * pb.n, list(pb.hasf)
            P, ok, nu, _ = assess(pb, X, wa, we, X_ls)
    except (ZeroDivisionError, ValueError, OverflowError) as exc:
        raise Fallback(str(exc)) from exc
    return X, P, ok, nu, wa, we
