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

Coordinates: the caller (constrained_tls.constrained_tls) hands both paths the same bearings
centred on the station centroid c (station_centroid, summed in the same order on both paths)
and shifts option ``initial`` and the estimate by c. CTLS-AM is translation invariant in exact
arithmetic (f, T_n, H_n and eq. (30) depend on X and p_i only through X − p_i, X_LS moves
with the origin), so this only removes rounding: with UTM-like coordinates (~1e7 m) the
pseudo-linear residual h_i X − h_i p_i cancels ~1e7 m to metres and f carried 1e-11..1e-10
relative rounding, and the two paths stopped differently (``ok`` against ``max_iterations``
or ``diverged``, fixes ~1e-8 of the range apart).

Whenever floats would need IEEE special values (division by zero, overflow, a degenerate
start) :func:`solve_one` returns None and the caller runs the batch path.
"""

import math

import numpy as np

from .fix import FixResult, iterative_result, STATUS_DIVERGED, STATUS_MAX_ITERATIONS, STATUS_OK
from .jit import jit
from .single_floats import inverse3, normal_equations, solve3
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


def _station(p, th, ps, s_az, s_el, has_el):
    """Fixed per-station floats of the CTLS cost (one row of _CTLSProblem).

    (px, py, pz, has_el, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10,
    h11, h12, y0, y1, g0, g1, g2, g3, pa, pe): F_j = [[Fja, 0], [Fjc, Fjd]] of Wang, Zhang &
    Wu eq. (9) (F_3's first row and F_2's first column are 0; the elevation row and column
    are 0 for a 1D station), the pseudo-linear rows h0 = (h00, h01, 0), h1
    (single_floats.pseudo_linear_rows) and their right-hand sides y = h·p,
    G⁻¹ = [[g0, g1], [g2, g3]] = P_E = diag(pa, pe) (Abatzoglou-Mendel).
    """
    x, y, z = p
    c, s = math.cos(th), math.sin(th)
    if has_el:
        cp, sp = math.cos(ps), math.sin(ps)
        F = (-c, s * sp, -c * cp, -s, -c * sp, -s * cp, -sp,
             -(c * x + s * y), s * sp * x - c * sp * y, -(c * cp * x + s * cp * y + sp * z))
        h1 = (c * sp, s * sp, -cp)
        pe = (s_az * s_az, s_el * s_el)
    else:
        F = (-c, 0.0, 0.0, -s, 0.0, 0.0, 0.0, -(c * x + s * y), 0.0, 0.0)
        h1 = (0.0, 0.0, 0.0)
        pe = (s_az * s_az, 0.0)
    y0 = s * x + -c * y + 0.0 * z
    y1 = h1[0] * x + h1[1] * y + h1[2] * z
    return (x, y, z, has_el, *F, s, -c, *h1, y0, y1, pe[0], 0.0, 0.0, pe[1], *pe)


# cost() and derivatives() share their first lines (H_X, S⁻¹ and r of one station): kept inline
# on purpose, a function call per station would cost more than the arithmetic it shares. Both
# use G⁻¹ = P_E = diag(g0, g3) (Abatzoglou-Mendel): the terms of the general 2 × 2 products
# with G⁻¹'s zero off-diagonal entries, F_3's zero first row and F_2's zero first column are
# left out (they add exact zeros in constrained_tls._CTLSProblem).

@jit
def cost(table, X):
    """f(X) of Wang, Zhang & Wu eq. (11) (constrained_tls._CTLSProblem.cost); ``table`` the
    stations' rows of :func:`_station` as an array (N, 27) (:func:`_table`)."""
    x, y, z = X
    f = 0.0
    for k in range(table.shape[0]):
        (has_el, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10, h11, h12, y0,
         y1, g0) = _row(table, k)[3:22]
        g3 = table[k, 24]
        a = x * F0a + y * F1a - F3a                         # H_X = Σ a_j F_j − F_4
        c = x * F0c + y * F1c - F3c
        d = x * F0d + y * F1d + z * F2d - F3d
        k00, k10 = a * g0, c * g0                           # H_X G⁻¹ (k01 = 0)
        s00, s01, s10 = k00 * a, k00 * c, k10 * a           # S = H_X G⁻¹ H_Xᵀ
        s11 = k10 * c + d * g3 * d if has_el else 1.0
        det = s00 * s11 - s01 * s10
        inv = 1.0 / det if det != 0 else math.nan
        r0 = h00 * x + h01 * y - y0                         # r = H X − Y
        r1 = h10 * x + h11 * y + h12 * z - y1
        f += r0 * (s11 * inv * r0 - s01 * inv * r1) + r1 * (-s10 * inv * r0 + s00 * inv * r1)
    return f


@jit
def derivatives(table, X):
    """f, T_n (3), H_n and its Gauss-Newton part (3 × 3 nested tuples), appendix A.

    Per station (see constrained_tls._CTLSProblem.derivatives): U = S⁻¹r, B3 column j =
    F_jᵀU, B1 = H_X G⁻¹ B3, K = (H_X G⁻¹)ᵀU, B2 column j = F_j K, D = H − B1 − B2,
    T += 2 Uᵀ(H − B1), H_gn += 2 DᵀS⁻¹D, H_n = H_gn − 2 Σ B3ᵀG⁻¹B3. Also returns the rms
    distance of X from the stations (m), the scale of the step test. ``table`` as for
    :func:`cost`.
    """
    x, y, z = X
    f = t0 = t1 = t2 = s2 = 0.0
    g00 = g01 = g02 = g11 = g12 = g22 = 0.0
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    for k in range(table.shape[0]):
        (px, py, pz, has_el, F0a, F0c, F0d, F1a, F1c, F1d, F2d, F3a, F3c, F3d, h00, h01, h10,
         h11, h12, y0, y1, g0) = _row(table, k)[:22]
        g3 = table[k, 24]
        a = x * F0a + y * F1a - F3a
        c = x * F0c + y * F1c - F3c
        d = x * F0d + y * F1d + z * F2d - F3d
        k00, k10 = a * g0, c * g0
        k11 = d * g3
        s00, s01, s10 = k00 * a, k00 * c, k10 * a
        s11 = k10 * c + k11 * d if has_el else 1.0
        det = s00 * s11 - s01 * s10
        inv = 1.0 / det if det != 0 else math.nan
        si0, si1, si2, si3 = s11 * inv, -s01 * inv, -s10 * inv, s00 * inv
        r0 = h00 * x + h01 * y - y0
        r1 = h10 * x + h11 * y + h12 * z - y1
        u0 = si0 * r0 + si1 * r1
        u1 = si2 * r0 + si3 * r1
        f += r0 * u0 + r1 * u1
        # B3 = [F_jᵀU]: rows p (p2 = 0) and q
        p0, p1 = F0a * u0 + F0c * u1, F1a * u0 + F1c * u1
        q0, q1, q2 = F0d * u1, F1d * u1, F2d * u1
        # B1 = H_X G⁻¹ B3: rows m (m2 = 0) and n
        m0, m1 = k00 * p0, k00 * p1
        n0, n1, n2 = k10 * p0 + k11 * q0, k10 * p1 + k11 * q1, k11 * q2
        # K = (H_X G⁻¹)ᵀU; B2 = [F_j K]; D = H − B1 − B2: rows e (e2 = 0) and o
        w0 = k00 * u0 + k10 * u1
        w1 = k11 * u1
        e0, e1 = h00 - m0 - F0a * w0, h01 - m1 - F1a * w0
        o0 = h10 - n0 - (F0c * w0 + F0d * w1)
        o1 = h11 - n1 - (F1c * w0 + F1d * w1)
        o2 = h12 - n2 - F2d * w1
        t0 += u0 * (h00 - m0) + u1 * (h10 - n0)
        t1 += u0 * (h01 - m1) + u1 * (h11 - n1)
        t2 += u1 * (h12 - n2)
        # Dᵀ S⁻¹ (rows i) times D (columns j); then B3ᵀ G⁻¹ B3 in the same form (both 3 × 3
        # sums of two rank-one terms per station, inlined in this hot loop on purpose).
        a0, b0 = e0 * si0 + o0 * si2, e0 * si1 + o0 * si3
        a1, b1 = e1 * si0 + o1 * si2, e1 * si1 + o1 * si3
        g00 += a0 * e0 + b0 * o0
        g01 += a0 * e1 + b0 * o1
        g02 += b0 * o2
        g11 += a1 * e1 + b1 * o1
        g12 += b1 * o2
        g22 += o2 * si3 * o2
        # B3ᵀ G⁻¹ (rows i) times B3 (columns j)
        v0, z0 = p0 * g0, q0 * g3
        v1, z1 = p1 * g0, q1 * g3
        c00 += v0 * p0 + z0 * q0
        c01 += v0 * p1 + z0 * q1
        c02 += z0 * q2
        c11 += v1 * p1 + z1 * q1
        c12 += z1 * q2
        c22 += q2 * g3 * q2
        dx, dy, dz = x - px, y - py, z - pz
        s2 += dx * dx + dy * dy + dz * dz
    # The factors 2 of T and H are applied to the sums (scaling by 2 is exact).
    g00, g01, g02, g11, g12, g22 = 2.0 * g00, 2.0 * g01, 2.0 * g02, 2.0 * g11, 2.0 * g12, \
        2.0 * g22
    c00, c01, c02, c11, c12, c22 = 2.0 * c00, 2.0 * c01, 2.0 * c02, 2.0 * c11, 2.0 * c12, \
        2.0 * c22
    Hg = ((g00, g01, g02), (g01, g11, g12), (g02, g12, g22))
    Hn = ((g00 - c00, g01 - c01, g02 - c02), (g01 - c01, g11 - c11, g12 - c12),
          (g02 - c02, g12 - c12, g22 - c22))
    return f, (2.0 * t0, 2.0 * t1, 2.0 * t2), Hn, Hg, math.sqrt(s2 / table.shape[0])


@jit
def _row(table, k):
    """Row k of the station table as a tuple of 27 floats (has_el 1.0 or 0.0)."""
    r = table[k]
    return (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8], r[9], r[10], r[11], r[12],
            r[13], r[14], r[15], r[16], r[17], r[18], r[19], r[20], r[21], r[22], r[23], r[24],
            r[25], r[26])


def _table(stations):
    """The rows of :func:`_station` as a float array (N, 27), for the compiled loops."""
    return np.array(stations, dtype=float)


def _stations(bearings):
    pos = bearings.positions[0].tolist()
    el = bearings.elevation[0].tolist()
    return [_station(tuple(p), th, e, sa, se, e == e)
            for p, th, e, sa, se in zip(pos, bearings.azimuth[0].tolist(), el,
                                        bearings.sigma_az[0].tolist(),
                                        bearings.sigma_el[0].tolist())]


def _ls_start(stations):
    """X_LS (Wang, Zhang & Wu eq. (4)) as pseudo_linear.ls: None where ls is degenerate."""
    (a00, a01, a02, a11, a12, a22), b = normal_equations(st[14:21] for st in stations)
    A = [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]]
    if not _safe_test(A):
        return None
    X = solve3(a00, a01, a02, a11, a12, a22, *b)
    # pseudo_linear._closed_form_result: a start on a station is degenerate.
    dist = [math.dist(X, st[:3]) for st in stations]
    scale = 1.0 + max(abs(c) for st in stations for c in st[:3]) + max(dist)
    if any(d <= 1e-9 * scale for d in dist):
        return None
    return tuple(X)


def _covariance(stations, X):
    """P_ΔX of Wang, Zhang & Wu eq. (30) at X (constrained_tls._CTLSProblem.covariance).

    Everything at the angles predicted from X: P = A⁻¹BA⁻¹, A = Σ HᵀS⁻¹H,
    B = Σ HᵀS⁻¹QS⁻¹H, Q = H_X P_E H_Xᵀ (eq. (29)). With G⁻¹ = P_E, Q = S and B = A; at the
    predicted angles H_X = diag(−ρ, −r) (ρ horizontal, r slant range), so S = diag(ρ² σ_θ²,
    r² σ_ψ²) and A = Σ h_θ h_θᵀ/(ρ σ_θ)² + h_ψ h_ψᵀ/(r σ_ψ)² with the rows h_θ = (sin θ, −cos θ,
    0) = (dy, −dx, 0)/ρ and h_ψ = (cos θ sin ψ, sin θ sin ψ, −cos ψ) = (dx dz/ρ, dy dz/ρ, −ρ)/r:
    the Fisher information of the bearings (Zong & Cui 2015 eq. (7)), P = A⁻¹AA⁻¹ = CRLB,
    symmetric (the cofactor inverse is symmetric by construction; the LAPACK product is
    symmetrised, (P + Pᵀ)/2, as in the batch path).
    """
    x, y, z = X
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for st in stations:
        dx, dy, dz = x - st[0], y - st[1], z - st[2]
        rho2 = dx * dx + dy * dy
        wa = 1.0 / (rho2 * rho2 * st[25])                  # h_θ h_θᵀ/(ρ² σ_θ²), h_θ ρ
        a00 += dy * dy * wa
        a01 -= dy * dx * wa
        a11 += dx * dx * wa
        if st[3]:
            r2 = rho2 + dz * dz
            q = dz / rho2
            ex, ey = dx * q, dy * q                          # h_ψ = (ex, ey, −1) ρ/r
            we = rho2 / (r2 * r2 * st[26])
            a00 += ex * ex * we
            a01 += ex * ey * we
            a02 -= ex * we
            a11 += ey * ey * we
            a12 -= ey * we
            a22 += we
    A = [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]]
    finite = all(math.isfinite(v) for row in A for v in row)
    Ainv = inverse3(a00, a01, a02, a11, a12, a22) if finite else None
    if Ainv is not None:
        # Well conditioned (the usual case): A⁻¹AA⁻¹ = A⁻¹ by cofactors, within 1e-11 of
        # the LAPACK products below.
        return np.array([Ainv])
    if not (finite and _safe_test(A)):
        return np.full((1, 3, 3), np.inf)
    A = np.array(A)
    Ainv = np.linalg.inv(A)
    P = Ainv @ A @ Ainv
    return (0.5 * (P + P.T))[None]            # symmetrised, as the batch path


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
        return _iterate(name, stations, _table(stations), X, opts)
    except (ArithmeticError, ValueError):       # division by zero, overflow, NaN in math
        return None


def _iterate(name, stations, table, X, opts):
    """The Newton iteration of constrained_tls.constrained_tls for one problem."""
    n_meas = sum(2 if st[3] else 1 for st in stations)
    rel_tol = max(CHI2_STEP_TOL / max(n_meas - 3, 1), COST_RTOL)
    mu, tol = opts['step_decay'], opts['tolerance']
    isfinite = math.isfinite
    it = 0
    conv = div = flat = False
    done = False
    D = None
    for n in range(opts['max_iterations']):
        f, T, Hn, Hgn, scale = D if D is not None else derivatives(table, X)
        D = None
        pd = False
        h0, h1, h2 = Hn                                  # symmetric: 6 distinct entries
        if isfinite(h0[0]) and isfinite(h0[1]) and isfinite(h0[2]) and isfinite(h1[1]) \
                and isfinite(h1[2]) and isfinite(h2[2]):
            if _well_conditioned(Hn):
                pd = True
            else:
                w = np.linalg.eigvalsh(np.array(Hn))
                pd = w[0] > 1e-12 * abs(w[2])
        H = Hn if pd else Hgn
        step = solve3(H[0][0], H[0][1], H[0][2], H[1][1], H[1][2], H[2][2], *T)
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
            for k in range(41):
                Xt = (X[0] + t * step[0], X[1] + t * step[1], X[2] + t * step[2])
                if k == 0 and not small:
                    # The full step is usually accepted: its derivatives (whose f is the
                    # cost, bit for bit) serve the next iteration instead of a second pass.
                    Dt = derivatives(table, Xt)
                    ft = Dt[0]
                else:
                    Dt, ft = None, cost(table, Xt)
                if isfinite(ft) and ft <= f:
                    X, accepted, D = Xt, True, Dt
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
