"""One-problem path of the maximum likelihood estimators ``mle`` and ``wmle`` on Python floats.

Why a second path: the batch iteration of :mod:`~bearing_loc_ros.core.estimators` is
vectorised over M problems; with M = 1 (the fusion node's epochs, ``bearing_loc locate`` with
one problem) its ~60 numpy calls per iteration on arrays of N ≤ 10 numbers cost far more than
the arithmetic (bench/bench_estimators.py: 0.55 ms per fix against scipy least_squares' 0.3 ms).
This module runs exactly the same algorithm (:func:`~bearing_loc_ros.core.estimators.
_levenberg_marquardt`: the pseudo-linear start of Wang, Zhang & Wu eq. (4), the Gauss-Newton
step of Zong & Cui 2015 eq. (8) with Levenberg-Marquardt damping, the range weights of
eqs. (9)-(11) for ``wmle``, the same stopping rules and statuses) with the same floating
point operations in the same order, station by station on Python floats. Its results match
the batch path to rounding (sums over stations are added in station order, as the batch
path does for M > 1): test/test_estimators_reference.py checks both against stored
reference fixes, and test/test_estimators.py compares the two paths directly.

Whenever the floats would need IEEE special values (a target on a station's vertical axis
divides by zero, a non-finite start) :func:`solve_one` returns None and the caller runs the
batch path, which handles them.
"""

import math

import numpy as np

from .crlb import safe_inverse
from .fix import FixResult, iterative_result, STATUS_DIVERGED, STATUS_MAX_ITERATIONS, STATUS_OK
from .single_floats import inverse3, normal_equations, pseudo_linear_rows, solve3
from .solvers import CHI2_STEP_TOL, COST_RTOL

_PI = math.pi
_TWO_PI = 2.0 * math.pi


class _Problem:
    """Per-station floats of one ML problem (estimators._MLProblem for M = 1)."""

    def __init__(self, bearings, d_ref):
        pos = bearings.positions[0].tolist()
        el = bearings.elevation[0].tolist()
        sel = bearings.sigma_el[0].tolist()
        self.stations = [
            (p[0], p[1], p[2], az, e if e == e else 0.0, 1.0 / saz,
             1.0 / s if e == e else 0.0)
            for p, az, e, saz, s in zip(pos, bearings.azimuth[0].tolist(), el,
                                        bearings.sigma_az[0].tolist(), sel)]
        self.n = len(pos)
        self.d_ref = d_ref
        self.n_measurements = self.n + sum(1 for e in el if e == e)

    def start(self):
        """Pseudo-linear X_LS (Wang, Zhang & Wu eq. (4)) as _MLProblem.pseudo_linear_start."""
        rows = []
        for px, py, pz, az, el, _, se in self.stations:
            h0, h1 = pseudo_linear_rows(az, el, se > 0)
            rows.append((h0[0], h0[1], *h1, h0[0] * px + h0[1] * py + h0[2] * pz,
                         h1[0] * px + h1[1] * py + h1[2] * pz))
        (a00, a01, a02, a11, a12, a22), (b0, b1, b2) = normal_equations(rows)
        det = (a00 * (a11 * a22 - a12 * a12) + a01 * (a02 * a12 - a01 * a22)
               + a02 * (a01 * a12 - a02 * a11))
        if not det > 1e-12 * ((a00 + a11 + a22) / 3.0) ** 3:
            return None
        return solve3(a00, a01, a02, a11, a12, a22, b0, b1, b2)

    def pack(self, x, y, z, old_factor=None):
        """(A (6), b (3), cost, rms range, old cost) and the range weights, as _MLProblem.pack.

        With ``d_ref`` (``wmle``) σ grows with range (Zong & Cui 2015 eqs. (9)-(11)): each
        station's whitened residuals and gradients are scaled by sqrt(d_ref²/d²), and the old
        cost uses the previous iterate's factors ``old_factor``; without it the factors are
        None and the old cost is the cost. Raises ZeroDivisionError (or another
        ArithmeticError) where the batch path would meet inf/NaN, for example a target on a
        station's vertical axis.
        """
        # A deliberate float twin of estimators._MLProblem.pack (the same operations in the
        # same order): the one-fix fast path the benchmark keeps (module docstring). The sums
        # are single_floats.normal_equations of the rows (ax, ay, 0), (ex, ey, ez), inlined:
        # a call per station would cost more than the sums.
        a00 = a01 = a02 = a11 = a12 = a22 = b0 = b1 = b2 = cost = old = s2 = 0.0
        atan2, sqrt, ceil = math.atan2, math.sqrt, math.ceil
        weighted = self.d_ref is not None
        d2 = self.d_ref * self.d_ref if weighted else 0.0
        factors = [] if weighted else None
        for k, (px, py, pz, az, el, sa, se) in enumerate(self.stations):
            dx = x - px
            dy = y - py
            dz = z - pz
            rho2 = dx * dx + dy * dy
            r2 = rho2 + dz * dz
            rho = sqrt(rho2)
            e_az = az - atan2(dy, dx)
            if not -_PI < e_az <= _PI:          # else the wrap below subtracts 0 exactly
                e_az -= _TWO_PI * ceil((e_az - _PI) / _TWO_PI)
            ra = sa * e_az
            re = se * (el - atan2(dz, rho))
            if weighted:
                factor = d2 / r2
                factors.append(factor)
                old += (ra * ra + re * re) * (factor if old_factor is None else old_factor[k])
                f = sqrt(factor)
                sa, se, ra, re = sa * f, se * f, ra * f, re * f
            qa = sa / rho2
            ax = -dy * qa
            ay = dx * qa
            t = se * dz / (rho * r2)
            ex = -dx * t
            ey = -dy * t
            ez = se * rho / r2
            a00 += ax * ax + ex * ex
            a01 += ax * ay + ex * ey
            a02 += ex * ez
            a11 += ay * ay + ey * ey
            a12 += ey * ez
            a22 += ez * ez
            b0 += ax * ra + ex * re
            b1 += ay * ra + ey * re
            b2 += ez * re
            cost += ra * ra + re * re
            s2 += r2
        return (a00, a01, a02, a11, a12, a22, b0, b1, b2, cost, sqrt(s2 / self.n),
                old if weighted else cost), factors


def _iterate(problem, x0, max_iterations, tolerance):
    """estimators._levenberg_marquardt for one problem: (X, packed A, iterations, conv, div)."""
    X = x0
    Q, F = problem.pack(*X)
    lam = 0.0
    scale0 = Q[10]
    rel_tol = max(CHI2_STEP_TOL / max(problem.n_measurements - 3, 1), COST_RTOL)
    it = 0
    conv = div = False
    isfinite, sqrt = math.isfinite, math.sqrt
    for _ in range(max_iterations):
        a00, a01, a02, a11, a12, a22, b0, b1, b2, cost = Q[:10]
        g = solve3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
        if lam > 0:
            k = 1.0 + lam
            step = solve3(a00 * k, a01, a02, a11 * k, a12, a22 * k, b0, b1, b2)
        else:
            step = g
        gn = sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        decrease = abs(b0 * g[0] + b1 * g[1] + b2 * g[2])
        if gn <= tolerance * Q[10] or decrease <= rel_tol * cost:
            it += 1
            conv = True
            break
        accept = False
        if isfinite(step[0]) and isfinite(step[1]) and isfinite(step[2]):
            Xt = (X[0] + step[0], X[1] + step[1], X[2] + step[2])
            Qt, Ft = problem.pack(*Xt, F)
            accept = Qt[11] <= cost
        if accept:
            X, Q, F = Xt, Qt, (F if F is None else Ft)
            lam = 0.0 if lam < 1e-6 else 0.1 * lam
        else:
            lam = max(10.0 * lam, 1e-3)
        it += 1
        if lam > 1e12 or Q[10] > 1e8 * scale0:
            div = True
            break
    return X, Q, it, conv, div


def solve_one(method, bearings, d_ref, opts):
    """FixResult of ``mle`` (``d_ref`` None) or ``wmle`` for a validated one-problem set.

    ``opts``: the parsed options (max_iterations, tolerance, initial). None when the problem
    needs the batch path's IEEE special values (see the module docstring).
    """
    problem = _Problem(bearings, d_ref)
    try:
        x0 = opts.get('initial')
        x0 = problem.start() if x0 is None else tuple(x0[0].tolist())
        if x0 is None or not all(math.isfinite(v) for v in x0):
            return None
        X, Q, it, conv, div = _iterate(problem, x0, opts['max_iterations'],
                                       opts['tolerance'])
    except (ArithmeticError, ValueError):      # division by zero, overflow, ceil(NaN)
        return None
    a00, a01, a02, a11, a12, a22 = Q[:6]
    x = np.array([X], dtype=float)
    status = STATUS_OK if conv else STATUS_DIVERGED if div else STATUS_MAX_ITERATIONS
    cov = inverse3(*Q[:6]) if math.isfinite(sum(Q[:6])) else None
    if cov is not None and all(math.isfinite(v) for v in X):
        # Well conditioned (the usual case): the cofactor inverse, within 1e-11 of LAPACK's.
        return FixResult(x, np.array([cov]), np.array([it]), np.array([conv]),
                         np.array([status]), method)
    info = np.array([[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]])
    # crlb.safe_inverse for one matrix (the same LAPACK calls, without its batch masks).
    w = np.linalg.eigvalsh(info) if math.isfinite(sum(Q[:6])) else None
    if w is None or not (w[0] > 1e-12 * abs(w[2]) and w[2] > 0) \
            or not all(math.isfinite(v) for v in X):
        return iterative_result(method, x, safe_inverse(info[None]), np.array([it]),
                                np.array([conv]), np.array([div]))
    cov = np.linalg.inv(info)[None]
    return FixResult(x, cov, np.array([it]), np.array([conv]), np.array([status]), method)
