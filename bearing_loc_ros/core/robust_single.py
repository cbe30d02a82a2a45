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
range-grown σ, nonlinearity ν, second optimum). Eigenvalues of 3 × 3 symmetric matrices
come from the trigonometric solution of the characteristic cubic (Smith 1961), linear
solves from Gaussian elimination with partial pivoting. Statuses, exclusions and
convergence flags are the batch path's; positions agree within the refit's stopping
resolution (it stops at steps below 1e-10 of the rms station range, and rounding decides on
which step: measured ≤ 5e-9 of the range, tested at 1e-7), covariances within 1.3e-7 of
their largest entry.

Where the floats cannot follow the batch path to rounding (a division by zero, a log of
zero, a rank test or major axis too close to call), :class:`Fallback` is raised and the
caller runs the batch path. Units: m, rad; ENU, azimuth θ CCW from East, elevation ψ above
the horizontal.
"""

import math

import numpy as np

from .robust_consensus import _ls_candidates as _ls_candidates_batch
from .robust_consensus import _score as _score_batch
from .robust_consensus import _station_masks
from .robust_model import (_upper_cached, CONSISTENCY_PROBABILITY, Data,
                           DECISIVE_PROBABILITY, max_nonlinearity, MULTIMODE_PROBABILITY,
                           outlier_c2, REFIT_ITERATIONS, REFIT_ROUNDS, TEST_INVERSION_Z)

_TWO_PI = 2.0 * math.pi
_RCOND = 1e-12
_CLEAR = 1e-5
_INF3 = ((math.inf,) * 3,) * 3


class Fallback(Exception):
    """The float path cannot reproduce the batch path here: use the batch path."""


def _upper(dof, probability=CONSISTENCY_PROBABILITY):
    """robust_model.chi2_upper of one integer dof, as a float (cached)."""
    return _upper_cached(int(dof), probability)


class Problem:
    """One problem's per-angle lists (σ are σ_ref for range growth; see robust_model.Data)."""

    def __init__(self, bearings, d_ref):
        self.pos = bearings.positions[0].tolist()
        self.az = bearings.azimuth[0].tolist()
        el = bearings.elevation[0].tolist()
        self.has = [math.isfinite(e) for e in el]
        self.el = [e if h else 0.0 for e, h in zip(el, self.has)]
        self.ia = [1.0 / s for s in bearings.sigma_az[0].tolist()]
        se = bearings.sigma_el[0].tolist()
        self.ie = [1.0 / s if h else 0.0 for s, h in zip(se, self.has)]
        self.d_ref = None if d_ref is None else float(d_ref)
        self.n = len(self.az)
        self.hasf = [1.0 if h else 0.0 for h in self.has]

    def evaluate(self, X, gradients=True):
        """Per station (ra, re, ga, ge, u, d, log_s2): robust_model.Data.evaluate on floats."""
        x0, x1, x2 = X
        d_ref = self.d_ref
        out = []
        for (px, py, pz), az, el, ia, ie in zip(self.pos, self.az, self.el, self.ia, self.ie):
            dx, dy, dz = x0 - px, x1 - py, x2 - pz
            rho2 = dx * dx + dy * dy
            r2 = rho2 + dz * dz
            rho = math.sqrt(rho2)
            d = math.sqrt(r2)
            e_az = az - math.atan2(dy, dx)
            e_az -= _TWO_PI * math.ceil((e_az - math.pi) / _TWO_PI)
            e_el = el - math.atan2(dz, rho)
            if d_ref is not None:
                f = d_ref / d
                ia, ie = ia * f, ie * f
                log_s2 = 2.0 * math.log(d / d_ref)
            else:
                log_s2 = 0.0
            ra, re = ia * e_az, ie * e_el
            if not gradients:
                out.append((ra, re, None, None, None, d, log_s2))
                continue
            s = ia / rho2
            t = dz / (rho * r2)
            out.append((ra, re, (-(dy * s), dx * s, s * 0.0),
                        (-(dx * t) * ie, -(dy * t) * ie, (rho / r2) * ie),
                        (dx / d, dy / d, dz / d), d, log_s2))
        return out


def _fisher(ev, wa, we):
    """Σ w g gᵀ as packed (a00, a01, a02, a11, a12, a22), 1/m²."""
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for (_, _, ga, ge, _, _, _), w1, w2 in zip(ev, wa, we):
        g0, g1, g2 = ga
        h0, h1, h2 = ge
        a00 += w1 * g0 * g0 + w2 * h0 * h0
        a01 += w1 * g0 * g1 + w2 * h0 * h1
        a02 += w1 * g0 * g2 + w2 * h0 * h2
        a11 += w1 * g1 * g1 + w2 * h1 * h1
        a12 += w1 * g1 * g2 + w2 * h1 * h2
        a22 += w1 * g2 * g2 + w2 * h2 * h2
    return [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]]


def _eig_extremes(A):
    """(λ_min, λ_mid, λ_max) of a finite symmetric 3 × 3 matrix (Smith 1961)."""
    a, b, c = A[0][0], A[1][1], A[2][2]
    d, e, f = A[0][1], A[1][2], A[0][2]
    q = (a + b + c) / 3.0
    aa, bb, cc = a - q, b - q, c - q
    r = math.sqrt((aa * aa + bb * bb + cc * cc + 2.0 * (d * d + e * e + f * f)) / 6.0)
    if not r > 0.0:
        return q, q, q
    det = (aa * (bb * cc - e * e) - d * (d * cc - e * f) + f * (d * e - bb * f)) / r ** 3
    phi = math.acos(min(1.0, max(-1.0, 0.5 * det))) / 3.0
    hi = q + 2.0 * r * math.cos(phi)
    lo = q + 2.0 * r * math.cos(phi + _TWO_PI / 3.0)
    return lo, 3.0 * q - hi - lo, hi


def _finite3(A):
    return all(map(math.isfinite, A[0] + A[1] + A[2]))


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


def _safe_inverse(A):
    """crlb.safe_inverse of one 3 × 3 symmetric matrix (nested lists; +inf when it fails).

    :class:`Fallback` for an ill-conditioned matrix that passes the rank test (its inverse
    is the batch path's only to about κ ε).
    """
    if not _finite3(A):
        return _INF3
    if not _clear(A):
        if _rank_ok(A):
            raise Fallback('ill-conditioned information')
        return _INF3
    c = _lu_solve(A, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))
    return tuple(tuple(c[j][i] for j in range(3)) for i in range(3))


def _quad(v, P, w):
    return sum(v[i] * P[i][j] * w[j] for i in range(3) for j in range(3))


def _ls_candidates(pb, masks):
    """Pseudo-linear LS (Wang, Zhang & Wu eq. (4)) of each station mask -> list of (3,)."""
    per = []
    for (px, py, pz), az, el, h in zip(pb.pos, pb.az, pb.el, pb.hasf):
        s, c = math.sin(az), math.cos(az)
        sp, cp = math.sin(el), math.cos(el)
        r1 = (s, -c, 0.0)
        r2 = (h * c * sp, h * s * sp, -h * cp)
        y1 = r1[0] * px + r1[1] * py + r1[2] * pz
        y2 = r2[0] * px + r2[1] * py + r2[2] * pz
        A = [[r1[i] * r1[j] + r2[i] * r2[j] for j in range(3)] for i in range(3)]
        b = [r1[i] * y1 + r2[i] * y2 for i in range(3)]
        per.append((A, b))
    out = []
    for mask in masks:
        A = [[0.0] * 3 for _ in range(3)]
        b = [0.0] * 3
        for k, (An, bn) in zip(mask, per):
            if k:
                for i in range(3):
                    b[i] += bn[i]
                    for j in range(3):
                        A[i][j] += An[i][j]
        if not _finite3(A) or _clear(A):
            out.append(_lu_solve(A, (b,))[0] if _finite3(A) else (math.nan,) * 3)
        elif _rank_ok(A):
            # Ill-conditioned but invertible: LAPACK's inverse, as the batch path.
            out.append(tuple((np.linalg.inv(np.array(A)) @ np.array(b)).tolist()))
        else:
            out.append((math.nan,) * 3)
    return out


def _score(pb, X, c2):
    s = 0.0
    for (ra, re, *_, log_s2), h in zip(pb.evaluate(X, False), pb.has):
        qa = ra * ra
        qe = re * re if h else 0.0
        n_in = (qa <= c2) + (h and qe <= c2)
        s += min(qa, c2) + min(qe, c2) + log_s2 * n_in
    return s if math.isfinite(s) else math.inf


def _inliers(pb, X, c2):
    ev = pb.evaluate(X, False)
    wa = [1.0 if e[0] * e[0] <= c2 else 0.0 for e in ev]
    we = [1.0 if h and e[1] * e[1] <= c2 else 0.0 for e, h in zip(ev, pb.has)]
    return wa, we


def _solvable(wa, we):
    st = sum(1 for a, e in zip(wa, we) if a + e > 0)
    return st >= 2 and sum(we) >= 1 and sum(wa) + sum(we) >= 3


def _cost_of(ev, wa, we):
    c = 0.0
    for (ra, re, *_, log_s2), w1, w2 in zip(ev, wa, we):
        c += w1 * (ra * ra + log_s2) + w2 * (re * re + log_s2)
    return c if math.isfinite(c) else math.inf


def _refit(pb, X0, wa, we, iterations=REFIT_ITERATIONS):
    """robust_consensus._refit for one problem (Levenberg-Marquardt on the full likelihood)."""
    grow = pb.d_ref is not None
    X = tuple(X0)
    lam = 0.0
    ev = pb.evaluate(X)
    cost = _cost_of(ev, wa, we)
    for _ in range(iterations):
        (f00, f01, f02), (_, f11, f12), (_, _, f22) = _fisher(ev, wa, we)
        g0 = g1 = g2 = 0.0
        for (ra, re, ga, ge, u, d, _), w1, w2 in zip(ev, wa, we):
            a, e = w1 * ra, w2 * re
            g0 -= a * ga[0] + e * ge[0]
            g1 -= a * ga[1] + e * ge[1]
            g2 -= a * ga[2] + e * ge[2]
            if grow:
                k = (w1 * (1.0 - ra * ra) + w2 * (1.0 - re * re)) / d
                v = 2.0 * (w1 + w2) / (d * d)
                u0, u1, u2 = u
                g0 += k * u0
                g1 += k * u1
                g2 += k * u2
                f00 += v * u0 * u0
                f01 += v * u0 * u1
                f02 += v * u0 * u2
                f11 += v * u1 * u1
                f12 += v * u1 * u2
                f22 += v * u2 * u2
        Fd = ((f00 + lam * f00, f01, f02), (f01, f11 + lam * f11, f12),
              (f02, f12, f22 + lam * f22))
        try:
            step = _lu_solve(Fd, ((-g0, -g1, -g2),))[0]
        except (ZeroDivisionError, OverflowError):
            step = (0.0, 0.0, 0.0)
        step = tuple(s if math.isfinite(s) else 0.0 for s in step)
        Xt = (X[0] + step[0], X[1] + step[1], X[2] + step[2])
        evt = pb.evaluate(Xt)
        ct = _cost_of(evt, wa, we)
        if math.isfinite(ct) and ct <= cost:
            X, ev, cost = Xt, evt, ct
            lam = 0.1 * lam * (lam > 1e-6)
        else:
            lam = max(10.0 * lam, 1e-3)
        scale = math.sqrt(sum(e[5] * e[5] for e in ev) / len(ev))
        if math.sqrt(sum(s * s for s in step)) <= 1e-10 * scale or lam > 1e10:
            break
    return X


def _best_candidate(pb, bearings, X_ml, c2):
    """Step 2: (the best-scoring candidate, the all-station ls fix).

    On floats for N ≤ 5; from N = 6 on, the N(N + 1)/2 + 2 candidates are scored by the
    batch path's own vectorised code on this one problem (one numpy evaluation of all of them
    costs less than a float loop over them; measured equal at N = 6).
    """
    n = pb.n
    x_ml = X_ml if all(map(math.isfinite, X_ml)) else (math.nan,) * 3
    if n >= 6:
        data = Data(bearings, pb.d_ref)
        cand = _ls_candidates_batch(data, _station_masks(n))
        cand = np.concatenate([np.array(x_ml, dtype=float)[None, None], cand], axis=1)
        score = _score_batch(data, np.where(np.isfinite(cand), cand, 0.0), c2)
        score = np.where(np.all(np.isfinite(cand), axis=-1), score, np.inf)
        return tuple(cand[0, int(np.argmin(score[0]))].tolist()), tuple(cand[0, 1].tolist())
    cand = [x_ml] + _ls_candidates(pb, _station_masks(n).tolist())
    best, best_s = 0, math.inf
    for k, C in enumerate(cand):
        if all(map(math.isfinite, C)):
            s = _score(pb, C, c2)
            if s < best_s:
                best, best_s = k, s
    return cand[best], cand[1]


def consensus_fit(pb, bearings, X_ml, c2):
    """robust_consensus.consensus_fit for one problem: (X, wa, we, the all-station ls fix)."""
    n = pb.n
    X, X_ls = _best_candidate(pb, bearings, X_ml, c2)
    X = tuple(x if math.isfinite(x) else 0.0 for x in X)
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
    X, wa, we = _prefer_all_bearings(pb, X, wa, we, X_ml, X_ls)
    return X, wa, we, X_ls


def _prefer_all_bearings(pb, X, wa, we, X_ml, X_ls):
    if all(a == 1.0 for a in wa) and all(e == 1.0 or not h for e, h in zip(we, pb.has)):
        return X, wa, we
    ones, she = [1.0] * pb.n, pb.hasf
    best, cost = None, math.inf
    for start in (X_ml, X_ls):
        if all(map(math.isfinite, start)):
            Xs = _refit(pb, start, ones, she)
            cs = _cost_of(pb.evaluate(Xs, False), ones, she)
        else:
            Xs, cs = _refit(pb, X, ones, she), math.inf
        if best is None or cs < cost:
            best, cost = Xs, cs
    chi2 = sum(e[0] * e[0] + h * e[1] * e[1] for e, h in zip(pb.evaluate(best, False), she))
    if math.isfinite(cost) and chi2 <= _upper(pb.n + sum(pb.has) - 3):
        return best, [1.0] * pb.n, list(she)
    return X, wa, we


def _test_inversion(pb, X, wa, we, P, present, z=TEST_INVERSION_Z, iterations=4):
    """robust_model.test_inversion_covariance for one problem (P finite)."""
    lo, mid, hi = _eig_extremes(P)
    if not hi - mid > 1e-4 * abs(hi):
        raise Fallback('major axis too close to call')
    # Eigenvector of λ_max: the largest cross product of two rows of P − λ_max I.
    R = [[P[i][j] - (hi if i == j else 0.0) for j in range(3)] for i in range(3)]
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
    nc = math.sqrt(nc)
    v = [c[0] / nc, c[1] / nc, c[2] / nc]
    ev = pb.evaluate(X)
    t_max = 10.0 * max(e[5] if math.isfinite(e[5]) else 0.0 for e in ev)
    out = [sum(e[4][i] for e, p in zip(ev, present) if p) for i in range(3)]
    dot = v[0] * out[0] + v[1] * out[1] + v[2] * out[2]
    if dot == 0.0:
        raise Fallback('major axis orientation')
    if dot < 0.0:
        v = [-v[0], -v[1], -v[2]]
    s0 = math.sqrt(max(_quad(v, P, v), 0.0))
    t = z * s0
    for _ in range(iterations):
        ev = pb.evaluate((X[0] + t * v[0], X[1] + t * v[1], X[2] + t * v[2]))
        Pt = _safe_inverse(_fisher(ev, wa, we))
        st = math.sqrt(max(_quad(v, Pt, v), 0.0)) if _finite3(Pt) else math.inf
        t = min(z * st, t_max) if math.isfinite(st) else t_max
    add = max((t / z) ** 2 - s0 * s0, 0.0)
    if not math.isfinite(add):
        return _INF3
    return tuple(tuple(P[i][j] + add * v[i] * v[j] for j in range(3)) for i in range(3))


def _lambda_max(P):
    return _eig_extremes(P)[2]


def assess(pb, X, wa, we, X_ls):
    """robust.assess for one problem: (P, ok, ν)."""
    grown = pb.d_ref is not None
    max_nu = max_nonlinearity(grown)
    ev = pb.evaluate(X)
    P = _safe_inverse(_fisher(ev, wa, we))
    finite = _finite3(P)
    chi2 = sum(w1 * e[0] * e[0] + w2 * e[1] * e[1] for e, w1, w2 in zip(ev, wa, we))
    n_kept = int(sum(wa) + sum(we))
    n_all = pb.n + sum(pb.has)
    present = [w1 + w2 > 0 for w1, w2 in zip(wa, we)]
    Pf = P if finite else ((0.0,) * 3,) * 3
    cd = outlier_c2(DECISIVE_PROBABILITY)
    marginal = False
    for (ra, re, ga, ge, *_), w1, w2, h in zip(ev, wa, we, pb.has):
        if w1 == 0 and not ra * ra / (1.0 + _quad(ga, Pf, ga)) > cd:
            marginal = True
        if w2 == 0 and h and not re * re / (1.0 + _quad(ge, Pf, ge)) > cd:
            marginal = True
    if grown and finite:
        P = _test_inversion(pb, X, wa, we, P, present)
    elif grown:
        P = _INF3
    finite = _finite3(P)
    nu = math.nan
    if finite:
        dmin = min((e[5] for e, p in zip(ev, present) if p), default=math.inf)
        nu = math.sqrt(max(_lambda_max(P), 0.0)) / dmin
        nu = nu if math.isfinite(nu) else math.nan
    ok = (chi2 <= _upper(n_kept - 3) and nu <= max_nu
          and n_all - n_kept <= math.floor((n_all - 3) / 2.0) and not marginal and finite)
    if ok:
        ok = not _second_optimum(pb, X, wa, we, P, X_ls)
    return P, ok, nu


def _second_optimum(pb, X, wa, we, P, ls):
    """robust_consensus.second_optimum for one problem (X, P finite)."""
    q = _upper(3, MULTIMODE_PROBABILITY)
    Pi = _safe_inverse(P)
    if not all(map(math.isfinite, ls)):
        return False

    def dist2(Y):
        dY = (Y[0] - X[0], Y[1] - X[1], Y[2] - X[2])
        return _quad(dY, Pi, dY)

    if not dist2(ls) > q:
        return False
    X2 = _refit(pb, ls, wa, we)
    far = dist2(X2) > q
    close = (_cost_of(pb.evaluate(X2, False), wa, we)
             - _cost_of(pb.evaluate(X, False), wa, we)) < q
    return far and close


def refine(bearings, X_ml, d_ref=None):
    """Steps 2-4 for one problem: (X (3,), P (3, 3), ok, ν, wa, we) as Python floats/lists.

    ``bearings`` a one-problem BearingSet, ``X_ml`` the estimator's fix (3,) m (NaN allowed),
    ``d_ref`` m for range-grown σ. Raises :class:`Fallback` where the batch path must run.
    """
    pb = Problem(bearings, d_ref)
    c2 = outlier_c2()
    try:
        X, wa, we, X_ls = consensus_fit(pb, bearings, tuple(X_ml), c2)
        P, ok, nu = assess(pb, X, wa, we, X_ls)
    except (ZeroDivisionError, ValueError, OverflowError) as exc:
        raise Fallback(str(exc)) from exc
    return X, P, ok, nu, wa, we
