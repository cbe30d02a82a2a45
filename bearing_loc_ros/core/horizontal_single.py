"""One-problem path of the horizontal ``mle`` and ``wmle`` on Python floats.

Why a second path: the horizontal iteration of :mod:`.horizontal_ml` is vectorised over M
problems; with M = 1 (one fix at a time: the fusion node's epochs, ``bearing_loc locate``
with one problem) its numpy calls on arrays of N ≤ 10 numbers cost far more than the
arithmetic (bench/bench_estimators.py: about 1 ms per fix, against 0.05 ms for the 3D ``mle``
on floats). This module runs exactly the same algorithm on Python floats, station by
station: the start (Wang, Zhang & Wu eq. (4) on the plane-reduced, σ-whitened system of
:mod:`.horizontal_estimators`), the Gauss-Newton step of Zong & Cui 2015 eq. (8) with the z
prior and Levenberg-Marquardt damping (the iteration of core/ml_single.py, itself the float
twin of core/estimators.py ``_levenberg_marquardt``: same damping, stopping rules and
statuses), the range weights of eqs. (9)-(11) for ``wmle``, the prior-combined covariance of
:func:`.horizontal_crlb.prior_covariance` and the station-line test of
:func:`.horizontal_estimators.on_station_line`. The per-station terms are the same floating
point operations as :func:`.horizontal_ml.ml_terms`, in the same order (the information
matrix comes out bit for bit); the residuals differ in the last bit where numpy's
``arctan2`` and the C library's ``atan2`` round differently (a few per cent of arguments), so
the two paths agree to rounding (test/test_horizontal_single.py compares them on random
problems, degenerate ones included).

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the
horizontal, radians; σ in rad; z₀, σ_z in m.

Whenever the floats would meet IEEE special values (a target on a station's vertical axis,
a singular start, an overflow), or the stations are collinear and the azimuths do not
clearly rule out a target on their line, :func:`solve_one` returns None and the caller runs
the batch path, which handles them.
"""

import math

import numpy as np

from .fix import (FixResult, STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_MAX_ITERATIONS,
                  STATUS_OK)
from .horizontal_crlb import RCOND
from .horizontal_estimators import LINE_CHI2_TAIL
from .ml_single import _iterate

_PI = math.pi
_TWO_PI = 2.0 * math.pi
#: Margin of the float station-line test: scatter eigenvalue ratios below this multiple of
#: the collinearity threshold of :func:`.horizontal_estimators.on_station_line` take the
#: χ² test (closed-form 2 × 2 eigenvalues carry an error of a few ε λ_max, far below it).
_LINE_MARGIN = 2.0


class _Problem:
    """Per-station floats of one horizontal ML problem (horizontal_ml.PlaneMLProblem, M = 1).

    ``stations``: (x_i, y_i, z_i, θ_i, ψ_i (0 unused), 1/σ_θi², 1/σ_ψi² (0 unused), used).
    """

    def __init__(self, p, d_ref):
        use = p.use_el[0].tolist()
        self.stations = [
            (x, y, z, az, el, 1.0 / (sa * sa), 1.0 / (se * se) if u else 0.0, u)
            for x, y, z, az, el, sa, se, u in zip(
                p.px[0].tolist(), p.py[0].tolist(), p.pz[0].tolist(), p.az[0].tolist(),
                p.el[0].tolist(), p.saz[0].tolist(), p.sel[0].tolist(), use)]
        self.n = len(use)
        self.z0 = float(p.z0[0])
        self.sz = float(p.sz[0])
        self.fixed = self.sz == 0.0
        self.wz = 0.0 if self.fixed else 1.0 / (self.sz * self.sz)
        self.d_ref = d_ref
        self.n_el = sum(use)
        self.n_measurements = self.n + self.n_el + 1

    def start(self):
        """``ls`` (x, y) of horizontal_estimators.solve_ls, or None where it is singular."""
        sin, cos = math.sin, math.cos
        a00 = a01 = a10 = a11 = b0 = b1 = 0.0
        z0 = self.z0
        for px, py, pz, az, el, wa, we, used in self.stations:
            st, ct = sin(az), cos(az)
            y0 = st * px - ct * py
            a00 += st * wa * st
            a01 += st * wa * -ct
            a10 += -ct * wa * st
            a11 += -ct * wa * -ct
            b0 += st * wa * y0
            b1 += -ct * wa * y0
            if used:
                sp, cp = sin(el), cos(el)
                h0, h1 = ct * sp, st * sp
                y1 = ct * sp * px + st * sp * py + cp * (z0 - pz)
                a00 += h0 * we * h0
                a01 += h0 * we * h1
                a10 += h1 * we * h0
                a11 += h1 * we * h1
                b0 += h0 * we * y1
                b1 += h1 * we * y1
        inv = inverse2(a00, 0.5 * (a01 + a10), a11)
        if inv is None:
            return None
        i00, i01, i11 = inv
        return i00 * b0 + i01 * b1, i01 * b0 + i11 * b1

    def pack(self, x, y, z, old_factor=None):
        """(A (6), b (3), cost, rms range, old cost) with the prior, as PlaneMLProblem.pack.

        The terms of :func:`.horizontal_ml.ml_terms` (Zong & Cui 2015 eqs. (3)-(8); with
        ``d_ref`` the weights d_ref²/d² of eqs. (9)-(11), the old cost under the previous
        iterate's ``old_factor``) plus the z prior; returns also X's own weight factors
        (None without ``d_ref``). Raises ArithmeticError (or ValueError) where the batch
        path would meet inf/NaN, for example a target on a station's vertical axis.
        """
        # The float twin of horizontal_ml.ml_terms + PlaneMLProblem.pack (the same
        # per-station operations); the azimuth and elevation sums are kept apart as the
        # batch path's two einsums are.
        aa00 = aa01 = aa11 = ba0 = ba1 = 0.0
        ae00 = ae01 = ae02 = ae11 = ae12 = ae22 = be0 = be1 = be2 = 0.0
        cost = old = s2 = 0.0
        atan2, sqrt, ceil = math.atan2, math.sqrt, math.ceil
        weighted = self.d_ref is not None
        d2 = self.d_ref * self.d_ref if weighted else 0.0
        factors = [] if weighted else None
        for k, (px, py, pz, az, el, wa, we, used) in enumerate(self.stations):
            dx = x - px
            dy = y - py
            dz = z - pz
            rho2 = dx * dx + dy * dy
            r2 = rho2 + dz * dz
            e_az = az - atan2(dy, dx)
            if not -_PI < e_az <= _PI:          # else the wrap below subtracts 0 exactly
                e_az -= _TWO_PI * ceil((e_az - _PI) / _TWO_PI)
            wa0, we0 = wa, we
            if weighted:
                own = d2 / r2
                factors.append(own)
                wa, we = wa * own, we * own
            gx, gy = -dy / rho2, dx / rho2
            aa00 += wa * gx * gx
            aa01 += wa * gx * gy
            aa11 += wa * gy * gy
            ba0 += wa * gx * e_az
            ba1 += wa * gy * e_az
            c = wa * e_az * e_az
            if used:
                rho = sqrt(rho2)
                e_el = el - atan2(dz, rho)
                t = rho * r2
                hx, hy, hz = -dx * dz / t, -dy * dz / t, rho / r2
                ae00 += we * hx * hx
                ae01 += we * hx * hy
                ae02 += we * hx * hz
                ae11 += we * hy * hy
                ae12 += we * hy * hz
                ae22 += we * hz * hz
                be0 += we * hx * e_el
                be1 += we * hy * e_el
                be2 += we * hz * e_el
                c += we * e_el * e_el
            if weighted and old_factor is not None:
                fo = old_factor[k]
                co = wa0 * fo * e_az * e_az
                if used:
                    co += we0 * fo * e_el * e_el
                old += co
            cost += c
            s2 += r2
        if not weighted or old_factor is None:
            old = cost
        dzp = z - self.z0
        wz = self.wz
        prior = wz * dzp * dzp
        if self.fixed:
            a02 = a12 = 0.0
            a22 = 1.0
            b2 = 0.0
        else:
            a02, a12, a22 = ae02, ae12, ae22 + wz
            b2 = be2 - wz * dzp
        return (aa00 + ae00, aa01 + ae01, a02, aa11 + ae11, a12, a22, ba0 + be0, ba1 + be1,
                b2, cost + prior, sqrt(s2 / self.n), old + prior), factors


def inverse2(a, b, d):
    """horizontal_crlb.inverse2 of one symmetric 2 × 2 [[a, b], [b, d]]: (i00, i01, i11) or None.

    None where A is not finite, not positive definite or λ_min/λ_max ≤ RCOND (any units).
    """
    tr = a + d
    det = a * d - b * b
    h = a - d
    disc = math.sqrt(max(0.25 * (h * h) + b * b, 0.0))
    lmax = 0.5 * tr + disc
    lmin = det / (lmax if lmax > 0 else 1.0)
    if not (math.isfinite(tr) and math.isfinite(det) and lmax > 0 and lmin > RCOND * lmax):
        return None
    inv_det = 1.0 / det
    return d * inv_det, -b * inv_det, a * inv_det


def _covariance(problem, Q):
    """horizontal_crlb.prior_covariance from the packed state at the fix: 3 × 3 list or None.

    The measurement information is Q's A without the prior (the z row is Q's minus 1/σ_z²,
    which the Schur complement adds back: s = J_zz + 1/σ_z² is Q's a22 itself).
    """
    a00, a01, a02, a11, a12, a22 = Q[:6]
    if problem.fixed:
        inv = inverse2(a00, a01, a11)
        if inv is None:
            return None
        i00, i01, i11 = inv
        return [[i00, i01, 0.0], [i01, i11, 0.0], [0.0, 0.0, 0.0]]
    s = a22
    q0, q1 = a02, a12
    inv = inverse2(a00 - q0 * q0 / s, 0.5 * ((a01 - q0 * q1 / s) + (a01 - q1 * q0 / s)),
                   a11 - q1 * q1 / s)
    if inv is None:
        return None
    i00, i01, i11 = inv
    h0, h1 = i00 * q0 + i01 * q1, i01 * q0 + i11 * q1
    c0, c1 = -h0 / s, -h1 / s
    pzz = 1.0 / s + (q0 * h0 + q1 * h1) / (s * s)
    return [[i00, i01, c0], [i01, i11, c1], [c0, c1, pzz]]


def _on_line_clear(problem):
    """False when the station-line test certainly does not flag the problem, else None.

    Only azimuth-only problems whose stations are collinear to within the margin can be
    flagged (horizontal_estimators.on_station_line); those take the batch test.
    """
    if problem.n_el:
        return False
    n = problem.n
    mx = sum(s[0] for s in problem.stations) / n
    my = sum(s[1] for s in problem.stations) / n
    cxx = cxy = cyy = 0.0
    for s in problem.stations:
        u, v = s[0] - mx, s[1] - my
        cxx += u * u
        cxy += u * v
        cyy += v * v
    disc = math.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
    lmax = 0.5 * (cxx + cyy) + disc
    lmin = (cxx * cyy - cxy * cxy) / lmax if lmax > 0 else 0.0
    if not lmax > 0:
        return None
    if lmin > _LINE_MARGIN * 1e-6 * lmax:
        return False
    # Collinear (or nearly): the χ² of the azimuths against the line, φ its direction (the
    # principal axis of the scatter). Clearly above the quantile: not on the line.
    from . import chisq
    phi = 0.5 * math.atan2(2.0 * cxy, cxx - cyy)
    stat = 0.0
    for s in problem.stations:
        delta = (s[3] - phi + 0.5 * _PI) % _PI - 0.5 * _PI
        stat += delta * delta * s[5]
    if stat > (1.0 + 1e-6) * float(chisq.isf(LINE_CHI2_TAIL, n)):
        return False
    return None


def solve_one(p, method, d_ref, opts):
    """FixResult of horizontal ``mle`` (``d_ref`` None) or ``wmle`` for a one-problem ``p``.

    ``p``: a :class:`.horizontal_estimators.HorizontalProblem` with M = 1; ``opts`` the
    parsed options and ``initial`` the parsed start ((1, 3), z NaN when not given) or None.
    None when the problem needs the batch path (module docstring).
    """
    try:
        problem = _Problem(p, d_ref)        # 1/σ_z² underflows for σ_z below ~1e-162
        x0 = opts.get('initial')
        if x0 is None:
            xy = problem.start()
            if xy is None:
                return None
            X0 = (xy[0], xy[1], problem.z0)
        else:
            x, y, z = x0[0].tolist()
            keep = math.isfinite(z) and not problem.fixed
            X0 = (x, y, z if keep else problem.z0)
        if not all(math.isfinite(v) for v in X0):
            return None
        X, Q, it, conv, div = _iterate(problem, X0, opts['max_iterations'], opts['tolerance'])
        if not (all(math.isfinite(v) for v in X) and all(math.isfinite(v) for v in Q)):
            return None
        cov = _covariance(problem, Q)
    except (ArithmeticError, ValueError):      # division by zero, overflow, ceil(NaN)
        return None
    on_line = _on_line_clear(problem)
    if on_line is None:
        return None
    status = STATUS_OK if conv else STATUS_DIVERGED if div else STATUS_MAX_ITERATIONS
    if cov is not None and not all(math.isfinite(v) for row in cov for v in row):
        return None
    if cov is None:
        return FixResult(np.full((1, 3), np.nan), np.full((1, 3, 3), np.inf), np.array([it]),
                         np.array([False]), np.array([STATUS_DEGENERATE]), method)
    return FixResult(np.array([X], dtype=float), np.array([cov], dtype=float), np.array([it]),
                     np.array([conv]), np.array([status]), method)
