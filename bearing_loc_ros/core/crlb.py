"""Fisher information, Cramér-Rao lower bound and GDOP for bearing-only localization.

Measurement model (Wang, Zhang & Wu (2006) eq. (1); Zong & Cui (2015) eq. (3)): for station i
at s_i and target X, with d = X − s_i, ρ = hypot(d_x, d_y), r = |d|,

    θ_i = atan2(d_y, d_x),            ∇θ_i = (−d_y, d_x, 0) / ρ²,
    ψ_i = atan2(d_z, ρ),              ∇ψ_i = (−d_x d_z / (ρ r²), −d_y d_z / (ρ r²), ρ / r²).

With independent Gaussian errors, the Fisher information of X is (Zong & Cui (2015) eqs. (6)-(8))

    J(X) = Σ_i ∇θ_i ∇θ_iᵀ / σ_θi² + Σ_{i ∈ 2D} ∇ψ_i ∇ψ_iᵀ / σ_ψi²,

CRLB = J⁻¹ (m²) and GDOP = sqrt(trace(CRLB)) (m), the root of the smallest achievable mean
squared 3D position error of an unbiased estimator. Azimuth-only (1D) bearings contribute
only the θ term (Wang, Su, Bai & Zhong (2009)).
"""

import numpy as np


def angle_jacobians(target, positions):
    """Gradients of θ and ψ with respect to the target position.

    Args:
        target: (M, 3) or (3,) target positions, m.
        positions: (M, N, 3) or (N, 3) station positions, m.

    Returns:
        (grad_az, grad_el), each (M, N, 3), rad/m. Entries are NaN/inf where the target
        lies on a station's vertical axis (ρ = 0), where azimuth is undefined.
    """
    tgt = np.asarray(target, dtype=float)
    tgt = tgt[None] if tgt.ndim == 1 else tgt
    pos = np.asarray(positions, dtype=float)
    pos = pos[None] if pos.ndim == 2 else pos
    d = tgt[:, None, :] - pos
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    rho2 = dx * dx + dy * dy
    rho = np.sqrt(rho2)
    r2 = rho2 + dz * dz
    with np.errstate(divide='ignore', invalid='ignore'):
        g_az = np.stack([-dy / rho2, dx / rho2, np.zeros_like(dx)], axis=-1)
        g_el = np.stack([-dx * dz / (rho * r2), -dy * dz / (rho * r2), rho / r2], axis=-1)
    return g_az, g_el


def fisher_information(target, positions, sigma_az, sigma_el=None, has_elevation=True):
    """Fisher information matrix J (M, 3, 3), 1/m², of bearings about the target.

    ``sigma_az``/``sigma_el`` (rad) broadcast to (M, N); ``sigma_el`` NaN or ``has_elevation``
    False marks azimuth-only bearings. Zong & Cui (2015) eqs. (6)-(8).
    """
    g_az, g_el = angle_jacobians(target, positions)
    M, N = g_az.shape[:2]
    saz = np.broadcast_to(np.asarray(sigma_az, dtype=float), (M, N))
    sel = np.broadcast_to(np.asarray(saz if sigma_el is None else sigma_el, dtype=float),
                          (M, N))
    mask = np.broadcast_to(np.asarray(has_elevation, dtype=bool), (M, N)) & np.isfinite(sel)
    w_az = 1.0 / saz ** 2
    w_el = np.where(mask, 1.0 / np.where(mask, sel, 1.0) ** 2, 0.0)
    g_el = np.where(mask[..., None], g_el, 0.0)
    return (np.einsum('mn,mni,mnj->mij', w_az, g_az, g_az)
            + np.einsum('mn,mni,mnj->mij', w_el, g_el, g_el))


def crlb(target, positions, sigma_az, sigma_el=None, has_elevation=True):
    """Cramér-Rao lower bound J⁻¹ (M, 3, 3), m², for an unbiased estimate of the target.

    Returns inf-filled matrices where J is singular (unobservable geometry, for example a
    target on the line through two azimuth-only stations). See :func:`fisher_information`.
    """
    J = fisher_information(target, positions, sigma_az, sigma_el, has_elevation)
    return safe_inverse(J)


def crlb_for(target, bearings):
    """CRLB (M, 3, 3), m², at ``target`` (M, 3) for the geometry and σ of a BearingSet."""
    return crlb(target, bearings.positions, bearings.sigma_az, bearings.sigma_el,
                bearings.has_elevation)


def gdop(cov):
    """Geometric dilution of precision sqrt(trace(P)), m, of covariance(s) (..., 3, 3)."""
    return np.sqrt(np.trace(np.asarray(cov, dtype=float), axis1=-2, axis2=-1))


def safe_inverse(J, rcond=1e-12):
    """Invert symmetric positive semi-definite matrices (..., 3, 3).

    Matrices with reciprocal condition number below ``rcond`` (or non-finite entries) come
    back filled with +inf instead of a numerically meaningless inverse.
    """
    J = np.asarray(J, dtype=float)
    out = np.full(J.shape, np.inf)
    finite = np.all(np.isfinite(J), axis=(-2, -1))
    if not np.any(finite):
        return out
    Jf = J[finite]
    w = np.linalg.eigvalsh(Jf)
    ok = (w[..., 0] > rcond * np.abs(w[..., -1])) & (w[..., -1] > 0)
    inv = np.full(Jf.shape, np.inf)
    if np.any(ok):
        inv[ok] = np.linalg.inv(Jf[ok])
    out[finite] = inv
    return out
