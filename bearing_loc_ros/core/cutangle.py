"""Optimal cut angle of a 2D + 1D passive sensor pair (Wang, Su, Bai & Zhong (2009)).

Geometry (the paper's section 2, figs. 1-2), in the project's ENU convention (DESIGN.md):
sensor 1 is a 2D sensor (azimuth θ1 and elevation ε1) at the origin (0, 0, z1); sensor 2 is a
1D sensor (azimuth θ2 only) at (D, 0, ·) on the +x baseline; the target is above the baseline
(0 < θ1 < θ2 < π) and the cut angle is φ = θ2 − θ1. By the sine rule the horizontal ranges
are D1 = D sin θ2 / sin φ and D2 = D sin θ1 / sin φ, and the target is (eqs. (1)-(3))

    x = D1 cos θ1,   y = D1 sin θ1,   z = D1 tan ε1 + z1.

Noise: independent, zero-mean Gaussian; σ²_θ1 = k1 σ²_θ2 and σ²_ε1 = k2 σ²_θ2 (k1 > 0,
k2 ≥ 0). First-order propagation of eqs. (1)-(3) (appendix A) gives eq. (5),

    E_r² = σ_x² + σ_y² + σ_z² = D² σ²_θ2 f(θ1, θ2, ε1),

and the re-derived eq. (6) (the appendix is garbled in places; this is the result of
differentiating eqs. (1)-(3) ourselves, and it agrees with every legible term of the paper):

    f = [ k1 sin²θ2 (1 + cos²φ tan²ε1) + sin²θ1 / cos²ε1 ] / sin⁴φ
        + k2 sin²θ2 sin²φ / (cos⁴ε1 sin⁴φ).

Because three angles determine three coordinates, this first-order covariance is exactly the
Cramér-Rao lower bound of :mod:`bearing_loc_ros.core.crlb` for the same geometry
(``test_planning_cutangle.py`` checks it to 1e-9): the planner and the estimators speak about
the same error.

The optimum (section 4) is a stationary point of f in (θ1, θ2) at a fixed ε1, eq. (7):
∂f/∂θ1 = ∂f/∂θ2 = 0. It is *feasible* only if it is a minimum strictly inside the domain:
not at a sensor (D1, D2 > 0) and not on the baseline or its extension (θ1 ≠ 0, θ2 ≠ π,
φ ≠ 0, π). The infimum of f on the boundary of the domain is reached at two limit points,

    target on sensor 2's vertical axis (θ1 → 0, θ2 = π/2):  f → k1 + k2 / cos⁴ε1,
    target at sensor 1 (θ1 = π/2, θ2 → π):                  f → 1 / cos²ε1,

so an interior minimum is the optimum only if its f is below both limits; otherwise the
optimal "cut angle" is a limit case (φ → 90°) and is reported as infeasible, as the paper
does for k1 ≤ 0.5, k2 = 0 (section 5.2.1).

For two 1D sensors (k2 = 0, ε1 = 0) eq. (7) reduces to eq. (8), sin 2θ1 + k1 sin 2θ2 = 0,
whose θ1-roots for a given θ2 are eqs. (10)-(11); :func:`pure_bearing_stationary_points`
uses them as an independent solver for that case.
"""

from dataclasses import dataclass, field

import numpy as np

# Feasibility margins: a solution closer than this (rad) to θ1 = 0, θ2 = π, φ = 0 or φ = π,
# or with D1/D or D2/D below RANGE_MARGIN, is a limit case (Wang, Su, Bai & Zhong (2009),
# section 4).
ANGLE_MARGIN = np.radians(0.05)
RANGE_MARGIN = 1e-3


def _check_ratios(k1, k2, elevation):
    k1 = float(k1)
    k2 = float(k2)
    elevation = float(elevation)
    if not np.isfinite(k1) or k1 <= 0:
        raise ValueError(f'k1: must be finite and > 0 (sigma_theta1^2 / sigma_theta2^2), '
                         f'got {k1}')
    if not np.isfinite(k2) or k2 < 0:
        raise ValueError(f'k2: must be finite and >= 0 (sigma_eps1^2 / sigma_theta2^2), '
                         f'got {k2}')
    if not np.isfinite(elevation) or abs(elevation) >= np.radians(89.0):
        raise ValueError(f'elevation: |elevation| must be < 89 deg, got '
                         f'{np.degrees(elevation):g} deg')
    return k1, k2, elevation


def cut_angle_f(theta1, theta2, elevation=0.0, k1=1.0, k2=0.0):
    """Wang, Su, Bai & Zhong (2009) eq. (6): the normalised squared position error f(θ1, θ2, ε1).

    E_r² = D² σ²_θ2 f (eq. (5)); f = [k1 sin²θ2 (1 + cos²φ tan²ε1) + sin²θ1 / cos²ε1
    + k2 sin²θ2 sin²φ / cos⁴ε1] / sin⁴φ with φ = θ2 − θ1. Angles in radians (arrays
    broadcast); dimensionless result, +inf where sin φ = 0.
    """
    t1 = np.asarray(theta1, dtype=float)
    t2 = np.asarray(theta2, dtype=float)
    phi = t2 - t1
    S2 = np.sin(phi) ** 2
    C2 = np.cos(phi) ** 2
    tan2 = np.tan(elevation) ** 2
    a = 1.0 / np.cos(elevation) ** 2
    b = k2 * a * a
    s2 = np.sin(t2) ** 2
    s1 = np.sin(t1) ** 2
    with np.errstate(divide='ignore', invalid='ignore'):
        out = (k1 * s2 * (1.0 + C2 * tan2) + a * s1 + b * s2 * S2) / (S2 * S2)
    return np.where(S2 > 0, out, np.inf)


def _phi_terms(phi, tan2, k1, b):
    """W(φ) = k1 P + k1 tan²ε Q + b R and P = sin⁻⁴φ with first and second φ-derivatives.

    P = S⁻⁴, Q = C² S⁻⁴, R = S⁻² (S = sin φ, C = cos φ):
    P' = −4C/S⁵, P'' = 4/S⁴ + 20C²/S⁶; R' = −2C/S³, R'' = 2/S² + 6C²/S⁴;
    Q' = −2C/S³ − 4C³/S⁵, Q'' = 2/S² + 18C²/S⁴ + 20C⁴/S⁶.
    """
    S = np.sin(phi)
    C = np.cos(phi)
    S2 = S * S
    C2 = C * C
    P = 1.0 / (S2 * S2)
    P1 = -4.0 * C / (S2 * S2 * S)
    P2 = 4.0 / (S2 * S2) + 20.0 * C2 / (S2 * S2 * S2)
    Q = C2 * P
    Q1 = -2.0 * C / (S2 * S) - 4.0 * C2 * C / (S2 * S2 * S)
    Q2 = 2.0 / S2 + 18.0 * C2 / (S2 * S2) + 20.0 * C2 * C2 / (S2 * S2 * S2)
    R = 1.0 / S2
    R1 = -2.0 * C / (S2 * S)
    R2 = 2.0 / S2 + 6.0 * C2 / (S2 * S2)
    W = k1 * P + k1 * tan2 * Q + b * R
    W1 = k1 * P1 + k1 * tan2 * Q1 + b * R1
    W2 = k1 * P2 + k1 * tan2 * Q2 + b * R2
    return W, W1, W2, P, P1, P2


def cut_angle_derivatives(theta1, theta2, elevation=0.0, k1=1.0, k2=0.0):
    """Value, gradient and Hessian of Wang, Su, Bai & Zhong (2009) eq. (6) in (θ1, θ2) at fixed ε1.

    Write f = u W(φ) + a v P(φ) with u = sin²θ2, v = sin²θ1, a = 1/cos²ε1, b = k2/cos⁴ε1,
    W = k1 P + k1 tan²ε1 Q + b R (see :func:`_phi_terms`), ∂φ/∂θ1 = −1, ∂φ/∂θ2 = 1:

        ∂f/∂θ1 = a v' P − u W' − a v P'
        ∂f/∂θ2 = u' W + u W' + a v P'
        ∂²f/∂θ1² = a v'' P − 2 a v' P' + u W'' + a v P''
        ∂²f/∂θ2² = u'' W + 2 u' W' + u W'' + a v P''
        ∂²f/∂θ1∂θ2 = −u' W' − u W'' + a v' P' − a v P''

    with u' = sin 2θ2, u'' = 2 cos 2θ2, v' = sin 2θ1, v'' = 2 cos 2θ1. These are eq. (7)'s
    left-hand sides (the paper solves them with Newton's method). Returns (f, grad (..., 2),
    hess (..., 2, 2)); angles in radians.
    """
    t1 = np.asarray(theta1, dtype=float)
    t2 = np.asarray(theta2, dtype=float)
    t1, t2 = np.broadcast_arrays(t1, t2)
    tan2 = np.tan(elevation) ** 2
    a = 1.0 / np.cos(elevation) ** 2
    b = k2 * a * a
    with np.errstate(divide='ignore', invalid='ignore'):
        W, W1, W2, P, P1, P2 = _phi_terms(t2 - t1, tan2, k1, b)
        u, u1, u2 = np.sin(t2) ** 2, np.sin(2 * t2), 2.0 * np.cos(2 * t2)
        v, v1, v2 = np.sin(t1) ** 2, np.sin(2 * t1), 2.0 * np.cos(2 * t1)
        f = u * W + a * v * P
        g1 = a * v1 * P - u * W1 - a * v * P1
        g2 = u1 * W + u * W1 + a * v * P1
        h11 = a * v2 * P - 2 * a * v1 * P1 + u * W2 + a * v * P2
        h22 = u2 * W + 2 * u1 * W1 + u * W2 + a * v * P2
        h12 = -u1 * W1 - u * W2 + a * v1 * P1 - a * v * P2
    grad = np.stack([g1, g2], axis=-1)
    hess = np.stack([np.stack([h11, h12], axis=-1), np.stack([h12, h22], axis=-1)], axis=-2)
    return f, grad, hess


def boundary_limits(k1, k2=0.0, elevation=0.0):
    """Infimum of f (eq. (6)) at the two limit points of the domain.

    Wang, Su, Bai & Zhong (2009), section 4.
    Returns {'sensor2': (f, θ1, θ2), 'sensor1': (f, θ1, θ2)} with
    f → k1 + k2/cos⁴ε1 for the target on sensor 2's vertical axis (θ1 → 0, θ2 = π/2) and
    f → 1/cos²ε1 for the target at sensor 1 (θ1 = π/2, θ2 → π). Derivation: with θ1 → 0,
    f → k1 (1 + cos²θ2 tan²ε1)/sin²θ2 + k2/cos⁴ε1, smallest at θ2 = π/2; with θ2 → π,
    f → 1/(cos²ε1 sin²θ1), smallest at θ1 = π/2. Everywhere else on the boundary f → ∞.
    """
    ce2 = np.cos(elevation) ** 2
    return {'sensor2': (k1 + k2 / (ce2 * ce2), 0.0, np.pi / 2),
            'sensor1': (1.0 / ce2, np.pi / 2, np.pi)}


def two_sensor_geometry(theta1, theta2, elevation=0.0, baseline=1.0, z1=0.0, z2=0.0):
    """Station and target positions (m, ENU) of the two-sensor geometry.

    Wang, Su, Bai & Zhong (2009) figs. 1-2, eqs. (1)-(3): sensor 1 (2D) at (0, 0, z1),
    sensor 2 (1D) at (D, 0, z2); target at
    (D1 cos θ1, D1 sin θ1, z1 + D1 tan ε1) with D1 = D sin θ2 / sin(θ2 − θ1).
    Returns (positions (2, 3), target (3,)). The elevation of sensor 2 is irrelevant (1D).
    """
    D1 = baseline * np.sin(theta2) / np.sin(theta2 - theta1)
    target = np.array([D1 * np.cos(theta1), D1 * np.sin(theta1),
                       z1 + D1 * np.tan(elevation)])
    positions = np.array([[0.0, 0.0, z1], [baseline, 0.0, z2]])
    return positions, target


def _feasible_point(t1, t2):
    """True when (θ1, θ2) is strictly inside the domain: off the baseline, not at a sensor."""
    phi = t2 - t1
    if not (t1 > ANGLE_MARGIN and t2 < np.pi - ANGLE_MARGIN
            and ANGLE_MARGIN < phi < np.pi - ANGLE_MARGIN):
        return False
    s = np.sin(phi)
    return np.sin(t2) / s > RANGE_MARGIN and np.sin(t1) / s > RANGE_MARGIN


@dataclass
class CutAngleResult:
    """Optimal cut angle (Wang, Su, Bai & Zhong (2009)) for one (k1, k2, ε1).

    Attributes (angles in radians):
        k1, k2, elevation: the inputs.
        theta1, theta2, cut_angle: the optimum (φ = θ2 − θ1); for an infeasible case the limit
            point approached by the infimum (θ1 = 0, θ2 = π/2 or θ1 = π/2, θ2 = π).
        f_min: f at that point (eq. (6)); E_r = D σ_θ2 sqrt(f_min).
        feasible: True when the optimum is an interior minimum (section 4).
        reason: why it is infeasible ('' when feasible).
        iterations: Newton iterations of the accepted solution.
        gradient_norm: |∇f| at the solution.
        limits: the boundary infima of :func:`boundary_limits`.
        local_minima: every interior local minimum found, as (θ1, θ2, f) tuples.
    """

    k1: float
    k2: float
    elevation: float
    theta1: float
    theta2: float
    cut_angle: float
    f_min: float
    feasible: bool
    reason: str = ''
    iterations: int = 0
    gradient_norm: float = 0.0
    limits: dict = field(default_factory=dict)
    local_minima: list = field(default_factory=list)

    def as_dict(self):
        """JSON-ready dict in degrees (the CLI's output format)."""
        return {
            'k1': self.k1, 'k2': self.k2,
            'elevation_deg': float(np.degrees(self.elevation)),
            'theta1_deg': float(np.degrees(self.theta1)),
            'theta2_deg': float(np.degrees(self.theta2)),
            'cut_angle_deg': float(np.degrees(self.cut_angle)),
            'f_min': float(self.f_min),
            'feasible': bool(self.feasible),
            'reason': self.reason,
        }


def _newton(x, k1, k2, elevation, tol, max_iter):
    """Safeguarded Newton iteration on eq. (7), ∇f = 0, from x = (θ1, θ2).

    Step −(H + μI)⁻¹∇f with μ ≥ 0 the smallest shift making H + μI positive definite
    (μ = 0, the plain Newton step of the paper, near a minimum), halved until f decreases and
    the point stays in the open domain. Returns (x, iterations, |∇f|, left_domain).
    """
    f, g, H = cut_angle_derivatives(x[0], x[1], elevation, k1, k2)
    for it in range(1, max_iter + 1):
        gn = float(np.hypot(*g))
        if gn <= tol * max(1.0, abs(f)):
            return x, it - 1, gn, False
        lam_min = np.linalg.eigvalsh(H)[0]
        mu = 0.0 if lam_min > 1e-8 * max(1.0, abs(f)) else -lam_min + 1e-3 * max(1.0, abs(f))
        step = -np.linalg.solve(H + mu * np.eye(2), g)
        t = 1.0
        while True:
            xn = x + t * step
            inside = 0.0 < xn[0] < xn[1] < np.pi
            if inside:
                fn, gn_, Hn = cut_angle_derivatives(xn[0], xn[1], elevation, k1, k2)
                if np.isfinite(fn) and fn <= f + 1e-14 * abs(f):
                    break
            t *= 0.5
            if t < 1e-12:
                return x, it, float(np.hypot(*g)), True
        x, f, g, H = xn, fn, gn_, Hn
    return x, max_iter, float(np.hypot(*g)), False


def _grid_starts(k1, k2, elevation, n):
    """Coarse numeric start points (Wang, Su, Bai & Zhong (2009), section 4).

    f and G = (∂f/∂θ1)² + (∂f/∂θ2)² on an n-step grid of the triangle 0 < θ1 < θ2 < π; the
    starts are the grid's local minima of f and of G (the paper's G(x) = 0 search).
    """
    a = (np.arange(n) + 0.5) * np.pi / n
    T1, T2 = np.meshgrid(a, a, indexing='ij')
    f, g, _ = cut_angle_derivatives(T1, T2, elevation, k1, k2)
    valid = T2 > T1
    starts = []
    for field_ in (f, np.sum(g * g, axis=-1)):
        F = np.where(valid & np.isfinite(field_), field_, np.inf)
        P = np.pad(F, 1, constant_values=np.inf)
        neigh = np.min(np.stack([P[1 + di:n + 1 + di, 1 + dj:n + 1 + dj]
                                 for di in (-1, 0, 1) for dj in (-1, 0, 1)
                                 if (di, dj) != (0, 0)]), axis=0)
        mask = np.isfinite(F) & (F <= neigh)
        idx = np.argwhere(mask)
        order = np.argsort(F[mask])[:8]
        starts.extend((a[i], a[j]) for i, j in idx[order])
    return starts


def optimal_cut_angle(k1, k2=0.0, elevation=0.0, grid=120, tol=1e-11, max_iter=100):
    """Optimal cut angle φ = θ2 − θ1 minimising f (eq. (6)) at fixed ε1.

    Method (Wang, Su, Bai & Zhong (2009), section 4): coarse numeric start points from an
    n = ``grid`` step grid of f and G = |∇f|² over 0 < θ1 < θ2 < π, then Newton's method on
    eq. (7) (∇f = 0, safeguarded, see :func:`_newton`). A converged point is kept if its
    Hessian is positive definite (a minimum, not a saddle) and it is strictly inside the
    domain (not at a sensor, not on the baseline or its extension; margins ANGLE_MARGIN,
    RANGE_MARGIN). The best interior minimum is the optimum if its f is below both boundary
    limits (:func:`boundary_limits`); otherwise the result is the lower limit point with
    ``feasible=False`` and a reason.

    Args:
        k1: σ²_θ1 / σ²_θ2 (> 0). k2: σ²_ε1 / σ²_θ2 (≥ 0; 0 with ε1 = 0 is two 1D sensors).
        elevation: ε1, rad (|ε1| < 89°).
    Returns:
        :class:`CutAngleResult`. Raises ValueError naming k1, k2 or elevation on bad input.
    """
    k1, k2, elevation = _check_ratios(k1, k2, elevation)
    limits = boundary_limits(k1, k2, elevation)
    minima = []
    for start in _grid_starts(k1, k2, elevation, grid):
        x, it, gn, left = _newton(np.array(start, dtype=float), k1, k2, elevation, tol,
                                  max_iter)
        if left or gn > 1e-7 * max(1.0, limits['sensor1'][0]):
            continue
        if not _feasible_point(x[0], x[1]):
            continue
        f, _, H = cut_angle_derivatives(x[0], x[1], elevation, k1, k2)
        if np.linalg.eigvalsh(H)[0] <= 0:
            continue
        if not any(abs(x[0] - m[0]) < 1e-6 and abs(x[1] - m[1]) < 1e-6 for m in minima):
            minima.append((float(x[0]), float(x[1]), float(f), it, gn))
    minima.sort(key=lambda m: m[2])
    lim_name = min(limits, key=lambda k: limits[k][0])
    f_lim, l1, l2 = limits[lim_name]
    where = ('on sensor 2\'s vertical axis (theta1 -> 0, theta2 -> 90 deg)'
             if lim_name == 'sensor2' else 'at sensor 1 (theta1 -> 90 deg, theta2 -> 180 deg)')
    local = [(m[0], m[1], m[2]) for m in minima]
    if minima and minima[0][2] < f_lim * (1.0 - 1e-12):
        t1, t2, f, it, gn = minima[0]
        return CutAngleResult(k1, k2, elevation, t1, t2, t2 - t1, f, True, '', it, gn,
                              limits, local)
    if minima:
        reason = (f'the interior minimum (f = {minima[0][2]:.6g}) is worse than the limit '
                  f'{where} (f = {f_lim:.6g})')
    else:
        reason = f'no interior minimum: f decreases towards the limit {where}'
    return CutAngleResult(k1, k2, elevation, l1, l2, l2 - l1, f_lim, False, reason, 0, 0.0,
                          limits, local)


def cut_angle_table(k1_values, k2_values=(0.0,), elevation=0.0, **options):
    """Tables 1-4 of Wang, Su, Bai & Zhong (2009): :func:`optimal_cut_angle` per (k2, k1).

    k2 is the outer loop. Returns a list of :class:`CutAngleResult`.
    """
    return [optimal_cut_angle(k1, k2, elevation, **options)
            for k2 in k2_values for k1 in k1_values]


def pure_bearing_theta1(theta2, k1):
    """Wang, Su, Bai & Zhong (2009) eqs. (10)-(11): θ1 in [0, π] solving eq. (8) for a given θ2.

    With z = cos θ2 and λ = −k1 z sqrt(1 − z²) (eq. (11)), eq. (8) sin 2θ1 = −k1 sin 2θ2 = 2λ
    gives cos²θ1 = (1 ± sqrt(1 − 4λ²))/2, i.e. cos θ1 = ±sqrt(2 ± 2 sqrt(1 − 4λ²))/2 (eq. (10)).
    Returns an array (..., 4) of the four candidate θ1 (NaN where 4λ² > 1); two of them
    satisfy eq. (8) (the other two solve sin 2θ1 = −2λ).
    """
    z = np.cos(np.asarray(theta2, dtype=float))
    lam = -k1 * z * np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    with np.errstate(invalid='ignore'):
        root = np.sqrt(1.0 - 4.0 * lam * lam)
        c_plus = np.sqrt(2.0 + 2.0 * root) / 2.0
        c_minus = np.sqrt(2.0 - 2.0 * root) / 2.0
        cands = np.stack([c_plus, -c_plus, c_minus, -c_minus], axis=-1)
        return np.arccos(np.clip(cands, -1.0, 1.0))


def pure_bearing_stationary_points(k1, n=4000):
    """Interior stationary points of f for two 1D sensors (k2 = 0, ε1 = 0) via eqs. (8)-(11).

    For each θ2 on an n-point grid, eq. (10) gives the θ1 satisfying eq. (8) (∂f/∂θ1 +
    ∂f/∂θ2 = 0); the remaining condition ∂f/∂θ1 = 0 is solved along each branch by bracketing
    sign changes and bisection (scipy brentq). Independent of :func:`optimal_cut_angle`'s
    Newton solver; used to cross-check it. Returns a list of (θ1, θ2, f), rad.
    """
    from scipy.optimize import brentq
    k1, _, _ = _check_ratios(k1, 0.0, 0.0)
    t2 = np.linspace(1e-6, np.pi - 1e-6, n)

    def branch(th2, j):
        t1 = pure_bearing_theta1(th2, k1)[..., j]
        ok = np.abs(np.sin(2 * t1) + k1 * np.sin(2 * th2)) < 1e-9
        return t1, ok

    out = []
    for j in range(4):
        t1, ok = branch(t2, j)
        _, g, _ = cut_angle_derivatives(t1, t2, 0.0, k1, 0.0)
        g1 = np.where(ok & (t2 > t1), g[..., 0], np.nan)
        for i in np.flatnonzero(np.sign(g1[:-1]) * np.sign(g1[1:]) < 0):
            def h(x):
                return cut_angle_derivatives(branch(x, j)[0], x, 0.0, k1, 0.0)[1][..., 0]
            try:
                x2 = brentq(h, t2[i], t2[i + 1], xtol=1e-14)
            except ValueError:
                continue
            x1 = float(branch(x2, j)[0])
            fx = float(cut_angle_f(x1, x2, 0.0, k1, 0.0))
            # A sign change across a pole of ∂f/∂θ1 is not a root.
            if np.isfinite(fx) and abs(float(h(x2))) < 1e-6 * max(1.0, fx):
                out.append((x1, float(x2), fx))
    return out
