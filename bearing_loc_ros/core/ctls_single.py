"""One-problem path of Abatzoglou-Mendel constrained TLS (``ctls_am``) on Python floats.

Why a second path: the batch Newton iteration of :mod:`~bearing_loc_ros.core.constrained_tls`
is vectorised over M problems with (M, N, 2, 2) blocks and einsum; with M = 1 (the fusion
node's epochs) its ~150 numpy calls per iteration cost ~1.5 ms per fix, 25 times the maximum
likelihood fix (bench/bench_estimators.py). This module runs the same algorithm (Wang, Zhang &
Wu eqs. (9)-(20), appendix A and (30) with G⁻¹ = P_E = diag(σ_θ², σ_ψ²): the same 2 × 2
blocks F_1..F_4, H_X, S, the same
gradient T_n and Hessian H_n, the same safeguards, backtracking, stopping rules and statuses;
see :func:`~bearing_loc_ros.core.constrained_tls.constrained_tls`) station by station on
Python floats; the 3 × 3 eigenvalue tests and inverses use the same numpy calls. Results match
the batch path to rounding (test/test_estimators.py compares them, and
test/test_estimators_reference.py checks both against stored fixes).

Whenever floats would need IEEE special values (division by zero, overflow, a degenerate
start) :func:`solve_one` returns None and the caller runs the batch path.
"""

import math

import numpy as np

from .fix import FixResult, iterative_result, STATUS_DIVERGED, STATUS_MAX_ITERATIONS, STATUS_OK
from .solvers import CHI2_STEP_TOL, COST_RTOL


def _inv2(a, b, c, d):
    """solvers.inv2 for one 2 × 2 matrix [[a, b], [c, d]] (NaN where singular)."""
    det = a * d - b * c
    inv_det = 1.0 / det if det != 0 else math.nan
    return d * inv_det, -b * inv_det, -c * inv_det, a * inv_det


def _well_conditioned(A):
    """True when the symmetric 3 × 3 ``A`` (nested lists) certainly has eigenvalues
    w0 > 1e-12 |w2| and w2 > 0 (the test of crlb.safe_inverse), without an eigensolver.

    Positive leading minors make A positive definite; then w0 = det/(w1 w2) ≥ det/w2² and
    w2 ≤ trace, so det > 1e-12 trace³ implies w0 > 1e-12 w2. False means "not certain" (the
    caller asks numpy's eigvalsh, as the batch path does).
    """
    a00, a01, a02 = A[0]
    a11, a12, a22 = A[1][1], A[1][2], A[2][2]
    det = (a00 * (a11 * a22 - a12 * a12) + a01 * (a02 * a12 - a01 * a22)
           + a02 * (a01 * a12 - a02 * a11))
    tr = a00 + a11 + a22
    return a00 > 0 and a00 * a11 - a01 * a01 > 0 and det > 0 and det > 1e-12 * tr * tr * tr


def _safe_test(A):
    """crlb.safe_inverse's test (w0 > 1e-12 |w2| and w2 > 0) for one symmetric 3 × 3."""
    if _well_conditioned(A):
        return True
    w = np.linalg.eigvalsh(np.array(A))
    return bool(w[0] > 1e-12 * abs(w[2]) and w[2] > 0)


def _blocks(th, ps, has_el, x, y, z):
    """F_1..F_4 (Wang, Zhang & Wu eq. (9)) of one station as four (f00, f10, f11) triples
    (f01 is always 0); the elevation row and column are zero for a 1D station."""
    c, s, cp, sp = math.cos(th), math.sin(th), math.cos(ps), math.sin(ps)
    if not has_el:
        return ((-c, 0.0, 0.0), (-s, 0.0, 0.0), (0.0, 0.0, 0.0), (-(c * x + s * y), 0.0, 0.0))
    return ((-c, s * sp, -c * cp), (-s, -c * sp, -s * cp), (0.0, 0.0, -sp),
            (-(c * x + s * y), s * sp * x - c * sp * y, -(c * cp * x + s * cp * y + sp * z)))


def _h_rows(th, ps, has_el):
    """Rows of the pseudo-linear system (pseudo_linear.pseudo_linear_system) of one station."""
    st, ct = math.sin(th), math.cos(th)
    if not has_el:
        return (st, -ct, 0.0), (0.0, 0.0, 0.0)
    sp, cp = math.sin(ps), math.cos(ps)
    return (st, -ct, 0.0), (ct * sp, st * sp, -cp)


def _station(p, th, ps, s_az, s_el, has_el, pe=None):
    """Fixed per-station floats of the CTLS cost (one row of _CTLSProblem).

    (px, py, pz, has_el, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10,
    h11, h12, y0, y1, g0, g1, g2, g3, pa, pe): F_j = [[Fja, 0], [Fjc, Fjd]] (F_3's first row
    and F_2's first column are 0), the pseudo-linear rows h0 = (h00, h01, 0), h1 and their
    right-hand sides y = h·p, G⁻¹ = [[g0, g1], [g2, g3]] and P_E = diag(pa, pe).
    """
    ps = ps if has_el else 0.0
    F = _blocks(th, ps, has_el, *p)
    h0, h1 = _h_rows(th, ps, has_el)
    if pe is None:
        pe = (s_az * s_az, s_el * s_el if has_el else 0.0)
    gi = (pe[0], 0.0, 0.0, pe[1])                       # G⁻¹ = P_E (Abatzoglou-Mendel)
    y0 = h0[0] * p[0] + h0[1] * p[1] + h0[2] * p[2]
    y1 = h1[0] * p[0] + h1[1] * p[1] + h1[2] * p[2]
    return (p[0], p[1], p[2], has_el, *F[0], *F[1], F[2][2], *F[3], h0[0], h0[1], *h1, y0, y1,
            *gi, *pe)


def cost(stations, X):
    """f(X) of Wang, Zhang & Wu eq. (11) (constrained_tls._CTLSProblem.cost)."""
    x, y, z = X
    f = 0.0
    for (_, _, _, has_el, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10,
         h11, h12, y0, y1, g0, g1, g2, g3, _, _) in stations:
        a = x * F0a + y * F1a - F3a                         # H_X = Σ a_j F_j − F_4
        c = x * F0c + y * F1c - F3c
        d = x * F0d + y * F1d + z * F2d - F3d
        k00, k01 = a * g0, a * g1                           # H_X G⁻¹
        k10, k11 = c * g0 + d * g2, c * g1 + d * g3
        s00, s01, s10 = k00 * a, k00 * c + k01 * d, k10 * a  # S = H_X G⁻¹ H_Xᵀ
        s11 = k10 * c + k11 * d if has_el else 1.0
        det = s00 * s11 - s01 * s10
        inv = 1.0 / det if det != 0 else math.nan
        r0 = h00 * x + h01 * y - y0                         # r = H X − Y
        r1 = h10 * x + h11 * y + h12 * z - y1
        f += r0 * (s11 * inv * r0 - s01 * inv * r1) + r1 * (-s10 * inv * r0 + s00 * inv * r1)
    return f


def derivatives(stations, X):
    """f, T_n (3), H_n and its Gauss-Newton part (3 × 3 nested lists), appendix A.

    Per station (see constrained_tls._CTLSProblem.derivatives): U = S⁻¹r, B3 column j =
    F_jᵀU, B1 = H_X G⁻¹ B3, K = (H_X G⁻¹)ᵀU, B2 column j = F_j K, D = H − B1 − B2,
    T += 2 Uᵀ(H − B1), H_gn += 2 DᵀS⁻¹D, H_n = H_gn − 2 Σ B3ᵀG⁻¹B3.
    """
    x, y, z = X
    f = t0 = t1 = t2 = 0.0
    g00 = g01 = g02 = g11 = g12 = g22 = 0.0
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    for (_, _, _, has_el, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10,
         h11, h12, y0, y1, g0, g1, g2, g3, _, _) in stations:
        a = x * F0a + y * F1a - F3a
        c = x * F0c + y * F1c - F3c
        d = x * F0d + y * F1d + z * F2d - F3d
        k00, k01 = a * g0, a * g1
        k10, k11 = c * g0 + d * g2, c * g1 + d * g3
        s00, s01, s10 = k00 * a, k00 * c + k01 * d, k10 * a
        s11 = k10 * c + k11 * d if has_el else 1.0
        det = s00 * s11 - s01 * s10
        inv = 1.0 / det if det != 0 else math.nan
        si0, si1, si2, si3 = s11 * inv, -s01 * inv, -s10 * inv, s00 * inv
        r0 = h00 * x + h01 * y - y0
        r1 = h10 * x + h11 * y + h12 * z - y1
        u0 = si0 * r0 + si1 * r1
        u1 = si2 * r0 + si3 * r1
        f += r0 * u0 + r1 * u1
        # B3 = [F_jᵀU] (rows 0, 1 of columns 0, 1, 2)
        p0, p1, p2 = F0a * u0 + F0c * u1, F1a * u0 + F1c * u1, 0.0
        q0, q1, q2 = F0d * u1, F1d * u1, F2d * u1
        # B1 = H_X G⁻¹ B3
        m0, m1, m2 = k00 * p0 + k01 * q0, k00 * p1 + k01 * q1, k00 * p2 + k01 * q2
        n0, n1, n2 = k10 * p0 + k11 * q0, k10 * p1 + k11 * q1, k10 * p2 + k11 * q2
        # K = (H_X G⁻¹)ᵀU; B2 = [F_j K]
        w0 = k00 * u0 + k10 * u1
        w1 = k01 * u0 + k11 * u1
        e0, e1, e2 = h00 - m0 - F0a * w0, h01 - m1 - F1a * w0, -m2
        o0 = h10 - n0 - (F0c * w0 + F0d * w1)
        o1 = h11 - n1 - (F1c * w0 + F1d * w1)
        o2 = h12 - n2 - F2d * w1
        t0 += 2.0 * (u0 * (h00 - m0) + u1 * (h10 - n0))
        t1 += 2.0 * (u0 * (h01 - m1) + u1 * (h11 - n1))
        t2 += 2.0 * (u0 * (0.0 - m2) + u1 * (h12 - n2))
        # Dᵀ S⁻¹ (rows i) times D (columns j)
        a0, b0 = e0 * si0 + o0 * si2, e0 * si1 + o0 * si3
        a1, b1 = e1 * si0 + o1 * si2, e1 * si1 + o1 * si3
        a2, b2 = e2 * si0 + o2 * si2, e2 * si1 + o2 * si3
        g00 += 2.0 * (a0 * e0 + b0 * o0)
        g01 += 2.0 * (a0 * e1 + b0 * o1)
        g02 += 2.0 * (a0 * e2 + b0 * o2)
        g11 += 2.0 * (a1 * e1 + b1 * o1)
        g12 += 2.0 * (a1 * e2 + b1 * o2)
        g22 += 2.0 * (a2 * e2 + b2 * o2)
        # B3ᵀ G⁻¹ (rows i) times B3 (columns j)
        v0, z0 = p0 * g0 + q0 * g2, p0 * g1 + q0 * g3
        v1, z1 = p1 * g0 + q1 * g2, p1 * g1 + q1 * g3
        v2, z2 = p2 * g0 + q2 * g2, p2 * g1 + q2 * g3
        c00 += 2.0 * (v0 * p0 + z0 * q0)
        c01 += 2.0 * (v0 * p1 + z0 * q1)
        c02 += 2.0 * (v0 * p2 + z0 * q2)
        c11 += 2.0 * (v1 * p1 + z1 * q1)
        c12 += 2.0 * (v1 * p2 + z1 * q2)
        c22 += 2.0 * (v2 * p2 + z2 * q2)
    Hg = [[g00, g01, g02], [g01, g11, g12], [g02, g12, g22]]
    Hn = [[g00 - c00, g01 - c01, g02 - c02], [g01 - c01, g11 - c11, g12 - c12],
          [g02 - c02, g12 - c12, g22 - c22]]
    return f, [t0, t1, t2], Hn, Hg


def _solve3(A, b):
    """solvers.solve3 for one system (cofactors); NaN where det ≤ 0."""
    a00, a01, a02, a11, a12, a22 = A[0][0], A[0][1], A[0][2], A[1][1], A[1][2], A[2][2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv_det = 1.0 / det if det > 0 else math.nan
    b0, b1, b2 = b
    return ((c00 * b0 + c01 * b1 + c02 * b2) * inv_det,
            (c01 * b0 + (a00 * a22 - a02 * a02) * b1 + (a01 * a02 - a00 * a12) * b2) * inv_det,
            (c02 * b0 + (a01 * a02 - a00 * a12) * b1 + (a00 * a11 - a01 * a01) * b2) * inv_det)


def _stations(bearings):
    pos = bearings.positions[0].tolist()
    el = bearings.elevation[0].tolist()
    return [_station(tuple(p), th, e, sa, se, e == e)
            for p, th, e, sa, se in zip(pos, bearings.azimuth[0].tolist(), el,
                                        bearings.sigma_az[0].tolist(),
                                        bearings.sigma_el[0].tolist())]


def _ls_start(stations):
    """X_LS (Wang, Zhang & Wu eq. (4)) as pseudo_linear.ls: None where ls is degenerate."""
    a00 = a01 = a02 = a11 = a12 = a22 = b0 = b1 = b2 = 0.0
    for st in stations:
        h00, h01, h10, h11, h12, y0, y1 = st[14:21]
        a00 += h00 * h00 + h10 * h10
        a01 += h00 * h01 + h10 * h11
        a02 += h10 * h12
        a11 += h01 * h01 + h11 * h11
        a12 += h11 * h12
        a22 += h12 * h12
        b0 += h00 * y0 + h10 * y1
        b1 += h01 * y0 + h11 * y1
        b2 += h12 * y1
    A = [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]]
    if not _safe_test(A):
        return None
    X = (np.linalg.inv(np.array(A)) @ np.array([b0, b1, b2])).tolist()
    # pseudo_linear._closed_form_result: a start on a station is degenerate.
    dist = [math.dist(X, st[:3]) for st in stations]
    scale = 1.0 + max(abs(c) for st in stations for c in st[:3]) + max(dist)
    if any(d <= 1e-9 * scale for d in dist):
        return None
    return tuple(X)


def _covariance(stations, X):
    """P_ΔX of Wang, Zhang & Wu eq. (30) at X (constrained_tls._CTLSProblem.covariance).

    Everything at the angles predicted from X: P = A⁻¹BA⁻¹, A = Σ HᵀS⁻¹H,
    B = Σ HᵀS⁻¹QS⁻¹H, Q = H_X P_E H_Xᵀ (eq. (29)).
    """
    x, y, z = X
    A = [[0.0] * 3 for _ in range(3)]
    B = [[0.0] * 3 for _ in range(3)]
    for st in stations:
        px, py, pz, has_el = st[:4]
        dx, dy, dz = x - px, y - py, z - pz
        th = math.atan2(dy, dx)
        ps = math.atan2(dz, math.hypot(dx, dy)) if has_el else 0.0
        (_, _, _, _, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10, h11, h12,
         _, _, g0, g1, g2, g3, pa, pe) = _station(st[:3], th, ps, 0.0, 0.0, has_el,
                                                  pe=st[25:27])
        a = x * F0a + y * F1a - F3a
        c = x * F0c + y * F1c - F3c
        d = x * F0d + y * F1d + z * F2d - F3d
        k00, k01 = a * g0, a * g1
        k10, k11 = c * g0 + d * g2, c * g1 + d * g3
        s00, s01, s10 = k00 * a, k00 * c + k01 * d, k10 * a
        s11 = k10 * c + k11 * d if has_el else 1.0
        det = s00 * s11 - s01 * s10
        inv = 1.0 / det if det != 0 else math.nan
        si0, si1, si2, si3 = s11 * inv, -s01 * inv, -s10 * inv, s00 * inv
        q00, q01, q11 = a * pa * a, a * pa * c, c * pa * c + d * pe * d
        m00, m01 = si0 * q00 + si1 * q01, si0 * q01 + si1 * q11
        m10, m11 = si2 * q00 + si3 * q01, si2 * q01 + si3 * q11
        n00, n01 = m00 * si0 + m01 * si2, m00 * si1 + m01 * si3
        n10, n11 = m10 * si0 + m11 * si2, m10 * si1 + m11 * si3
        # A += Hᵀ S⁻¹ H and B += Hᵀ (S⁻¹ Q S⁻¹) H, rows h0 = (h00, h01, 0), h1 = (h10, h11, h12)
        for i, (hi0, hi1) in enumerate(((h00, h10), (h01, h11), (0.0, h12))):
            ai0, ai1 = hi0 * si0 + hi1 * si2, hi0 * si1 + hi1 * si3
            bi0, bi1 = hi0 * n00 + hi1 * n10, hi0 * n01 + hi1 * n11
            A[i][0] += ai0 * h00 + ai1 * h10
            A[i][1] += ai0 * h01 + ai1 * h11
            A[i][2] += ai0 * 0.0 + ai1 * h12
            B[i][0] += bi0 * h00 + bi1 * h10
            B[i][1] += bi0 * h01 + bi1 * h11
            B[i][2] += bi0 * 0.0 + bi1 * h12
    B = np.array(B)
    if not (all(math.isfinite(v) for row in A for v in row) and _safe_test(A)
            and np.isfinite(B).all()):
        return np.full((1, 3, 3), np.inf)
    Ainv = np.linalg.inv(np.array(A))
    return (Ainv @ B @ Ainv)[None]


def solve_one(name, bearings, opts):
    """FixResult of ``ctls_am`` (``name``) for a validated one-problem set, or None.

    ``opts``: parsed options (step_decay, max_iterations, tolerance, initial).
    """
    try:
        stations = _stations(bearings)
        x0 = opts.get('initial')
        X = _ls_start(stations) if x0 is None else tuple(x0[0].tolist())
        if X is None:
            return None
        return _iterate(name, stations, X, opts)
    except (ArithmeticError, ValueError):       # division by zero, overflow, NaN in math
        return None


def _iterate(name, stations, X, opts):
    """The Newton iteration of constrained_tls.constrained_tls for one problem."""
    n_meas = sum(2 if st[3] else 1 for st in stations)
    rel_tol = max(CHI2_STEP_TOL / max(n_meas - 3, 1), COST_RTOL)
    mu, tol = opts['step_decay'], opts['tolerance']
    isfinite = math.isfinite
    it = 0
    conv = div = flat = False
    done = False
    for n in range(opts['max_iterations']):
        f, T, Hn, Hgn = derivatives(stations, X)
        scale = math.sqrt(sum((X[0] - st[0]) ** 2 + (X[1] - st[1]) ** 2 + (X[2] - st[2]) ** 2
                              for st in stations) / len(stations))
        pd = False
        if all(isfinite(v) for row in Hn for v in row):
            if _well_conditioned(Hn):
                pd = True
            else:
                w = np.linalg.eigvalsh(np.array(Hn))
                pd = w[0] > 1e-12 * abs(w[2])
        step = _solve3(Hn if pd else Hgn, T)
        step = (-step[0], -step[1], -step[2])
        it += 1
        usable = isfinite(step[0]) and isfinite(step[1]) and isfinite(step[2]) and isfinite(f)
        small = math.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]) \
            <= tol * scale
        flat = usable and 0.5 * abs(T[0] * step[0] + T[1] * step[1] + T[2] * step[2]) \
            <= rel_tol * abs(f)
        accepted = False
        if usable:
            t = mu ** n
            for _ in range(41):
                Xt = (X[0] + t * step[0], X[1] + t * step[1], X[2] + t * step[2])
                ft = cost(stations, Xt)
                if isfinite(ft) and ft <= f:
                    X, accepted = Xt, True
                    break
                t *= 0.5
        stalled = not (small and usable) and not accepted
        if (small and usable) or (stalled and flat):
            conv = done = True
            break
        if stalled:
            div = done = True
            break
    if not done and flat:
        conv = True
    P = _covariance(stations, X)
    x = np.array([X], dtype=float)
    if not (np.isfinite(P).all() and np.isfinite(x).all()):
        return iterative_result(name, x, P, np.array([it]), np.array([conv]), np.array([div]))
    status = STATUS_OK if conv else STATUS_DIVERGED if div else STATUS_MAX_ITERATIONS
    return FixResult(x, P, np.array([it]), np.array([conv]), np.array([status]), name)
