"""Cramér-Rao bound of the horizontal solve (target altitude stated by the user).

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians; an azimuth-only (1D) bearing has elevation NaN.

Model. The horizontal solve estimates (x, y) when the target altitude z is not observed by
the bearings but stated: z₀ (m, world frame) with standard deviation σ_z (m; 0 = exactly
known). z is a parameter with the Gaussian prior N(z₀, σ_z²); the measurements are those of
Wang, Zhang & Wu eq. (1) / Zong & Cui 2015 eq. (3),

    θ_i = atan2(y − y_i, x − x_i) + n_i,   ψ_i = atan2(z − z_i, ρ_i) + m_i (2D stations only),

so the log-posterior of p = (x, y, z) is, up to a constant,

    −½ [ Σ_i e_θi² / σ_θi² + Σ_{i ∈ 2D} e_ψi² / σ_ψi² + (z − z₀)² / σ_z² ].

Its information matrix (the Bayesian, van Trees, information of a Gaussian prior; the
measurement part is the Fisher information of core/crlb.py) is

    J_p = J(p) + diag(0, 0, 1/σ_z²),
    J(p) = Σ_i ∇θ_i ∇θ_iᵀ / σ_θi² + Σ_{i ∈ 2D} ∇ψ_i ∇ψ_iᵀ / σ_ψi²     (Zong & Cui 2015 eq. (7)).

Write J_p = [[J_h, q], [qᵀ, s]] (J_h the 2 × 2 horizontal block, 1/m²). ∇θ_i has no z
component, so q and J(p)_zz come only from elevations. The bound is P = J_p⁻¹ by blocks
(Schur complement on z, s = J_zz + 1/σ_z²):

    P_h  = (J_h − q qᵀ / s)⁻¹,   P_hz = −P_h q / s,   P_zz = 1/s + qᵀ P_h q / s².

* Azimuth-only set: q = 0, J_zz = 0, so P = blockdiag(J_h⁻¹, σ_z²): the fix carries
  z = z₀ with variance σ_z² and zero x-y/z correlation (none is invented).
* With elevations the correlation is real: an elevation ψ_i ties the horizontal range to
  the height, ρ_i = (z − z_i) / tan ψ_i, so an error in the stated altitude moves (x, y).
* σ_z = 0 (exactly known altitude): z is fixed, a two-parameter problem;
  P = blockdiag(J_h(z₀)⁻¹, 0), J_h including the elevations' range information.

GDOP of the horizontal problem: sqrt(P_xx + P_yy) (m), the root of the smallest achievable
mean squared horizontal error.

Also here: the optimal cut angle of two azimuth-only sensors (Wang, Su, Bai & Zhong 2009,
two 1D sensors), derived in closed form from the trace of the 2 × 2 CRLB.
"""

from dataclasses import dataclass

import numpy as np

from .crlb import fisher_information

#: A 2 × 2 information block whose eigenvalue ratio is below this is singular (the threshold
#: of crlb.safe_inverse): the horizontal position is not observable (degenerate geometry).
RCOND = 1e-12


def _as_problem_vector(value, M, name):
    """``value`` (scalar or (M,)) as a float (M,) array; ValueError naming ``name``."""
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'{name}: not a number ({type(value).__name__})') from None
    except OverflowError:
        raise ValueError(f'{name}: beyond the float range, must be finite') from None
    if v.ndim > 1 or (v.ndim == 1 and v.shape[0] not in (1, M)):
        raise ValueError(f'{name}: expected a number or {M} numbers, got shape {v.shape}')
    return np.broadcast_to(v, (M,)).astype(float)


def prior_covariance(info, sigma_z):
    """Covariance P (M, 3, 3), m², of the Gaussian z prior combined with information ``info``.

    ``info`` (M, 3, 3), 1/m², is the measurement information J of (x, y, z) (its z row is zero
    for an azimuth-only set); ``sigma_z`` (M,) the prior standard deviation, m. Returns
    (P, ok): P by the block formulas of the module docstring (Schur complement on z, so a
    tiny σ_z never makes a 3 × 3 inversion ill-conditioned), σ_z = 0 giving
    blockdiag(J_h⁻¹, 0); ok (M,) False where the horizontal block is singular (eigenvalue
    ratio below :data:`RCOND`, or non-finite), and there P is +inf.
    """
    info = np.asarray(info, dtype=float)
    M = info.shape[0]
    sz = np.asarray(sigma_z, dtype=float)
    fixed = sz == 0.0
    Jh = info[:, :2, :2]
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        s = info[:, 2, 2] + np.where(fixed, 1.0, 1.0 / np.where(fixed, 1.0, sz) ** 2)
        q = np.where(fixed[:, None], 0.0, info[:, :2, 2])
        S = Jh - q[:, :, None] * q[:, None, :] / s[:, None, None]
    Ph, ok = inverse2(S)
    P = np.full((M, 3, 3), np.inf)
    if np.any(ok):
        Pho, qs, so = Ph[ok], q[ok] / s[ok, None], s[ok]
        Phq = np.einsum('mij,mj->mi', Pho, qs)          # P_h q / s
        P[ok, :2, :2] = Pho
        P[ok, :2, 2] = P[ok, 2, :2] = -Phq
        # 1/s + (q/s)ᵀ P_h (q/s): no (qᵀP_h q)/s², which is 0/0 once s² underflows (σ_z ≳ 1e77).
        pzz = 1.0 / so + np.einsum('mi,mi->m', qs, Phq)
        P[ok, 2, 2] = np.where(fixed[ok], 0.0, pzz)
        P[ok & fixed, :2, 2] = 0.0
        P[ok & fixed, 2, :2] = 0.0
    return P, ok


def inverse2(A):
    """Inverse of symmetric 2 × 2 matrices A (M, 2, 2) in closed form.

    Returns (A⁻¹, ok): ok False (and A⁻¹ = +inf) where A is not finite, not positive
    definite, or its eigenvalue ratio λ_min/λ_max is below :data:`RCOND`.
    """
    A = np.asarray(A, dtype=float)
    a, b, d = A[..., 0, 0], 0.5 * (A[..., 0, 1] + A[..., 1, 0]), A[..., 1, 1]
    with np.errstate(invalid='ignore', over='ignore'):
        tr = a + d
        det = a * d - b * b
        disc = np.sqrt(np.maximum(0.25 * (a - d) ** 2 + b * b, 0.0))
        lmax = 0.5 * tr + disc
        lmin = det / np.where(lmax > 0, lmax, 1.0)
        ok = np.isfinite(tr) & np.isfinite(det) & (lmax > 0) & (lmin > RCOND * lmax)
    out = np.full(A.shape, np.inf)
    if np.any(ok):
        inv_det = 1.0 / det[ok]
        out[ok, 0, 0] = d[ok] * inv_det
        out[ok, 1, 1] = a[ok] * inv_det
        out[ok, 0, 1] = out[ok, 1, 0] = -b[ok] * inv_det
    return out, ok


def horizontal_fisher(target, positions, sigma_az, sigma_el=None, has_elevation=False):
    """Measurement information J (M, 3, 3), 1/m², of (x, y, z) at ``target`` (M, 3).

    Zong & Cui 2015 eq. (7) via :func:`bearing_loc_ros.core.crlb.fisher_information`; the z
    coordinate of ``target`` is the (stated) altitude. Elevations count only where
    ``has_elevation`` is True and σ_ψ is finite; azimuth-only sets give a zero z row/column.
    """
    saz = np.asarray(sigma_az, dtype=float)
    sel = np.full(np.shape(saz), np.nan) if sigma_el is None else sigma_el
    return fisher_information(target, positions, saz, sel, has_elevation)


def horizontal_crlb(target, positions, sigma_az, sigma_el=None, has_elevation=False,
                    sigma_z=0.0):
    """CRLB (M, 3, 3), m², of the horizontal solve at ``target`` (M, 3) or (3,).

    ``target``'s z is the stated altitude z₀; ``sigma_z`` (m, scalar or (M,), ≥ 0) its
    standard deviation. Returns P of the module docstring: for σ_z = 0 blockdiag(J_h⁻¹, 0),
    otherwise (J + diag(0, 0, 1/σ_z²))⁻¹ (the Bayesian bound of the prior N(z₀, σ_z²)),
    +inf where the horizontal position is unobservable (e.g. all stations and the target on
    one line with no usable elevation). ``sigma_az``/``sigma_el`` (rad) broadcast to (M, N).
    """
    tgt = np.atleast_2d(np.asarray(target, dtype=float))
    J = horizontal_fisher(tgt, positions, sigma_az, sigma_el, has_elevation)
    sz = _as_problem_vector(sigma_z, J.shape[0], 'target_altitude_sigma')
    return prior_covariance(J, sz)[0]


def horizontal_crlb_for(target, bearings, sigma_z=0.0, use_elevations=True):
    """:func:`horizontal_crlb` for the geometry and σ of a BearingSet (M problems)."""
    has_el = bearings.has_elevation & bool(use_elevations)
    return horizontal_crlb(target, bearings.positions, bearings.sigma_az, bearings.sigma_el,
                           has_el, sigma_z)


def horizontal_gdop(cov):
    """Horizontal GDOP sqrt(P_xx + P_yy), m, of covariance(s) (..., 3, 3) or (..., 2, 2)."""
    P = np.asarray(cov, dtype=float)
    return np.sqrt(P[..., 0, 0] + P[..., 1, 1])


# ----------------------------------------------------------------------------------------------
# Optimal cut angle of two azimuth-only sensors (Wang, Su, Bai & Zhong 2009, 1D + 1D)


@dataclass
class TwoAzimuthCutAngle:
    """Optimal geometry of two azimuth-only sensors, baseline D on the +x axis.

    Attributes:
        cut_angle: φ = θ2 − θ1, rad (the optimum, or the limit φ → π/2 when not feasible).
        theta1, theta2: azimuths (rad, CCW from East) of the target from sensor 1 at the
            origin and sensor 2 at (D, 0).
        f: E_r² / (D² σ2²), the normalised trace of the 2 × 2 CRLB at the optimum.
        feasible: False when no interior optimum exists (the infimum is the limit of the
            target on the less accurate sensor).
        k: σ1² / σ2².
    """

    cut_angle: float
    theta1: float
    theta2: float
    f: float
    feasible: bool
    k: float


def two_azimuth_crlb_trace(theta1, theta2, sigma1, sigma2, baseline=1.0):
    """Trace (m²) of the 2 × 2 CRLB of two azimuth-only sensors (Wang, Su, Bai & Zhong 2009).

    Sensor 1 at the origin, sensor 2 at (D, 0) (D = ``baseline``, m); the target is seen at
    θ1, θ2 (rad, 0 < θ1 < θ2 < π). With ranges r1 = D sin θ2 / sin φ, r2 = D sin θ1 / sin φ
    (sine rule, φ = θ2 − θ1) the information is J = u1 u1ᵀ/(r1σ1)² + u2 u2ᵀ/(r2σ2)² (u_i the
    unit vectors across the lines of sight), det J = sin²φ / (r1σ1 r2σ2)², so

        trace J⁻¹ = (r1² σ1² + r2² σ2²) / sin²φ = D² (σ1² sin²θ2 + σ2² sin²θ1) / sin⁴φ,

    the paper's eq. (5)-(6) with k1 = σ1²/σ2², k2 = 0, ε1 = 0.
    """
    t1 = np.asarray(theta1, dtype=float)
    t2 = np.asarray(theta2, dtype=float)
    sphi = np.sin(t2 - t1)
    return baseline ** 2 * (sigma1 ** 2 * np.sin(t2) ** 2 + sigma2 ** 2 * np.sin(t1) ** 2) \
        / sphi ** 4


def optimal_cut_angle_two_azimuth(sigma1, sigma2):
    """Cut angle minimising the 2D CRLB trace of two azimuth-only sensors on a fixed baseline.

    Wang, Su, Bai & Zhong 2009 (two 1D sensors, their eqs. (5)-(11) with k2 = 0, ε1 = 0),
    solved here in closed form. Write k = σ1²/σ2², u = r1/D, v = r2/D. The trace of
    :func:`two_azimuth_crlb_trace` is D² σ2² (k u² + v²)/sin²φ with the triangle constraint
    u² + v² − 2uv cos φ = 1. At fixed φ the minimum of k u² + v² on that ellipse is the
    smaller generalised eigenvalue λ of (diag(k, 1), [[1, −c], [−c, 1]]), c = cos φ:
    λ = (1 + k − sqrt((1 + k)² − 4k sin²φ)) / (2 sin²φ). So f = λ/sin²φ depends on φ only
    through t = sin²φ: f(t) = 4k / (2t (a + sqrt(a² − 4kt))), a = 1 + k. Maximising
    t (a + q), q = sqrt(a² − 4kt), gives 3q² + 2aq − a² = 0, q = a/3, hence

        sin²φ* = 2 (1 + k)² / (9k),  φ* obtuse,  f* = 27 k² / (4 (1 + k)³),

    feasible iff sin²φ* ≤ 1, i.e. 1/2 ≤ k ≤ 2 (the paper's "ratio of accuracies above
    0.707"). Equal accuracies (k = 1): cos φ* = −1/3, φ* = 109.47° (the paper: "about 110°,
    isosceles triangle"). Outside [1/2, 2] there is no interior optimum; the infimum
    f = min(k, 1) is the limit of the target on the less accurate sensor, where φ → 90°
    (returned with feasible False, as the paper reports it).

    At fixed ranges r1, r2 instead of a fixed baseline, the trace (r1²σ1² + r2²σ2²)/sin²φ is
    smallest at φ = 90° for every σ1, σ2: the classical 90° rule is the fixed-range optimum.

    Args: sigma1, sigma2: azimuth standard deviations of sensor 1 (origin) and sensor 2,
    rad, finite > 0. Returns :class:`TwoAzimuthCutAngle`; ValueError naming a bad σ.
    """
    for name, s in (('sigma1', sigma1), ('sigma2', sigma2)):
        if isinstance(s, bool) or not np.isfinite(np.asarray(s, dtype=float)) or s <= 0:
            raise ValueError(f'{name}: must be a finite angle standard deviation > 0 (rad)')
    k = float(sigma1) ** 2 / float(sigma2) ** 2
    t = 2.0 * (1.0 + k) ** 2 / (9.0 * k)
    if t >= 1.0:
        # Limit on the less accurate sensor (the paper's eq. (9) points).
        if k < 1.0:
            return TwoAzimuthCutAngle(np.pi / 2, 0.0, np.pi / 2, k, False, k)
        return TwoAzimuthCutAngle(np.pi / 2, np.pi / 2, np.pi, 1.0, False, k)
    phi = np.pi - np.arcsin(np.sqrt(t))
    c = np.cos(phi)
    lam = (1.0 + k - (1.0 + k) / 3.0) / (2.0 * t)   # q = a/3
    # Eigenvector (k − λ) u + λ c v = 0 (or the second row when k = λ), scaled to the ellipse.
    u, v = -lam * c, k - lam
    if abs(v) < 1e-15 * max(1.0, k):
        u, v = 1.0 - lam, -lam * c
    norm = np.sqrt(u * u + v * v - 2.0 * u * v * c)
    u, v = abs(u) / norm, abs(v) / norm
    theta1 = float(np.arcsin(np.clip(v * np.sin(phi), -1.0, 1.0)))   # sine rule, θ1 < π/2
    f = 27.0 * k * k / (4.0 * (1.0 + k) ** 3)
    return TwoAzimuthCutAngle(float(phi), theta1, theta1 + float(phi), f, True, k)
