"""One-problem path of the closed forms ``ls`` and ``tls`` on Python floats.

Why a second path: :func:`~bearing_loc_ros.core.pseudo_linear.ls` and
:func:`~bearing_loc_ros.core.pseudo_linear.tls` are vectorised over M problems; with M = 1
(the fusion node's epochs, ``bearing_loc locate`` with one problem) their numpy calls on
arrays of N ≤ 10 numbers cost several times the arithmetic, which made these closed forms
slower per fix than the iterative ``mle`` (bench/bench_estimators.py). This module computes
the same quantities station by station on floats: the pseudo-linear rows of Wang, Zhang & Wu
eqs. (2)-(3) (:func:`.single_floats.pseudo_linear_rows`), the normal equations of eq. (4),
the TLS eigenvalue refinement of eq. (5) and the first-order covariance (HᵀH)⁻¹HᵀΣH(HᵀH)⁻¹.
The sums run in station order; results match the batch path to rounding (the 3 × 3 inverses
by cofactors, :func:`.single_floats.inverse3`, agree with LAPACK's to ≤ 1e-11 relative).

Where the floats would meet a case the batch path decides (an inverse that is singular or
too ill-conditioned for cofactors, a non-finite solution, a solution on a station),
:func:`solve_one` returns None and the caller runs the batch path, which handles them.
"""

import math

import numpy as np

from .fix import FixResult, STATUS_DEGENERATE, STATUS_OK
from .single_floats import inverse3, normal_equations, pseudo_linear_rows


def _stations(bearings):
    """Per station ((h00, h01, h10, h11, h12, y0, y1), (x, y, z) m, σ_θ² rad², σ_ψ² rad² or
    0 for an azimuth-only station): the pseudo-linear rows h_θ = (h00, h01, 0) and
    h_ψ = (h10, h11, h12) with right-hand sides y = h·p (Wang, Zhang & Wu eq. (3))."""
    out = []
    for p, th, ps, sa, se in zip(bearings.positions[0].tolist(),
                                 bearings.azimuth[0].tolist(),
                                 bearings.elevation[0].tolist(),
                                 bearings.sigma_az[0].tolist(),
                                 bearings.sigma_el[0].tolist()):
        has = ps == ps
        h0, h1 = pseudo_linear_rows(th, ps, has)
        row = (h0[0], h0[1], h1[0], h1[1], h1[2], h0[0] * p[0] + h0[1] * p[1],
               h1[0] * p[0] + h1[1] * p[1] + h1[2] * p[2])
        out.append((row, p, sa * sa, se * se if has else 0.0))
    return out


def _times(Ai, b):
    """A⁻¹ b for A⁻¹ as nested lists, b (3,)."""
    return [Ai[i][0] * b[0] + Ai[i][1] * b[1] + Ai[i][2] * b[2] for i in range(3)]


def _on_a_station(stations, x):
    """pseudo_linear._closed_form_result's test: x within 1e-9 × (1 m + largest |station
    coordinate| + largest station range) of a station."""
    dist = [math.dist(x, p) for _, p, _, _ in stations]
    scale = 1.0 + max(abs(c) for _, p, _, _ in stations for c in p) + max(dist)
    return any(d <= 1e-9 * scale for d in dist)


def _covariance(stations, x, Ai):
    """(HᵀH)⁻¹ HᵀΣH (HᵀH)⁻¹ at x, m² (pseudo_linear._pseudo_linear_covariance): Σ =
    diag(ρ² σ_θ², r² σ_ψ²) with ρ, r the horizontal and slant ranges from each station."""
    B = [[0.0] * 3 for _ in range(3)]
    for (h00, h01, h10, h11, h12, _, _), p, va, ve in stations:
        dx, dy, dz = x[0] - p[0], x[1] - p[1], x[2] - p[2]
        rho2 = dx * dx + dy * dy
        wa, we = rho2 * va, (rho2 + dz * dz) * ve
        ha, he = (h00, h01, 0.0), (h10, h11, h12)
        for i in range(3):
            for j in range(i, 3):
                B[i][j] += wa * ha[i] * ha[j] + we * he[i] * he[j]
    for i in range(3):
        for j in range(i):
            B[i][j] = B[j][i]
    AB = [[sum(Ai[i][k] * B[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    return [[sum(AB[i][k] * Ai[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def _result(stations, x, Ai, method):
    """The FixResult of one finite solution x, or None where the batch path must decide."""
    if not all(map(math.isfinite, x)) or _on_a_station(stations, x):
        return None
    cov = np.array([_covariance(stations, x, Ai)])
    ok = np.ones(1, dtype=bool)
    return FixResult(np.array([x]), cov, np.zeros(1, dtype=int), ok.copy(),
                     np.where(ok, STATUS_OK, STATUS_DEGENERATE), method)


def solve_one(method, bearings):
    """``ls`` or ``tls`` (``method``) for a validated one-problem BearingSet, or None.

    ls (Wang, Zhang & Wu eq. (4)): X = (HᵀH)⁻¹HᵀY. tls (eq. (5)), as
    :func:`~bearing_loc_ros.core.pseudo_linear.tls`: λ the smallest eigenvalue of the 4 × 4
    normal matrix of [−Y H], three fixed-point steps X ← (HᵀH − λI)⁻¹HᵀY,
    λ ← ‖HX − Y‖² / (1 + ‖X‖²), then X = (HᵀH − λI)⁻¹HᵀY. Units m; covariance m² (the
    first-order LS sandwich for both). None where the batch path must answer (module
    docstring).
    """
    stations = _stations(bearings)
    A, b = normal_equations(row for row, _, _, _ in stations)
    Ai_ls = inverse3(*A)
    if Ai_ls is None:
        return None
    if method == 'ls':
        return _result(stations, _times(Ai_ls, b), Ai_ls, 'ls')
    a00, a01, a02, a11, a12, a22 = A
    yy = sum(y0 * y0 + y1 * y1 for (*_, y0, y1), _, _, _ in stations)
    C4 = np.array([[yy, -b[0], -b[1], -b[2]], [-b[0], a00, a01, a02],
                   [-b[1], a01, a11, a12], [-b[2], a02, a12, a22]])
    if not np.all(np.isfinite(C4)):
        return None
    lam = float(np.linalg.eigvalsh(C4)[0])
    for step in range(4):               # three refinements of λ, then the solution
        Ai = inverse3(a00 - lam, a01, a02, a11 - lam, a12, a22 - lam)
        if Ai is None:
            return None
        x = _times(Ai, b)
        if step == 3:
            break
        r2 = 0.0
        for (h00, h01, h10, h11, h12, y0, y1), _p, _va, _ve in stations:
            ra = h00 * x[0] + h01 * x[1] - y0
            re = h10 * x[0] + h11 * x[1] + h12 * x[2] - y1
            r2 += ra * ra + re * re
        new = r2 / (1.0 + x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
        lam = new if math.isfinite(new) else lam
    return _result(stations, x, Ai_ls, 'tls')
