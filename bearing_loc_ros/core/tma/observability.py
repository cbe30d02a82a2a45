"""Fisher information, constrained CRLB and the observability gates of TMA (T14)-(T16), (T18).

The Cramér-Rao bound of the relative state x = (p0, v) under the speed constraint (Stoica &
Ng 1998; Lin et al. sec. 3.3) and :func:`finish`, shared by every TMA estimator: the target
state at the last bearing (T1), its covariance, the range gate that reports a range the
bound cannot resolve as unobservable, and the confidence tests (T19)-(T22) of
:mod:`.confidence` that mark a fix whose covariance would be too small ``low_confidence``.
Conventions as :mod:`bearing_loc_ros.core.tma`.
"""

import numpy as np

from ..crlb import angle_jacobians, safe_inverse
from ..fix import (FixResult, STATUS_LOW_CONFIDENCE, STATUS_MAX_ITERATIONS, STATUS_OK,
                   STATUS_UNOBSERVABLE)
from .confidence import assess
from .model import observer_track


def fisher_terms(p0, v, tau, delta, sigma_az, sigma_el):
    """Per-bearing Fisher information (M, K, 6, 6) of x = (p0, v) (T14).

    F_k = G_kᵀ diag(σ_θ⁻², σ_ψ⁻²) G_k with G_k = [∇θ; ∇ψ](p_k) · [I3, τ_k I3], p_k from (T3),
    ∇θ, ∇ψ from :func:`bearing_loc_ros.core.crlb.angle_jacobians` (Zong & Cui 2015 eqs. (6)-(8),
    Lin et al. sec. 3.3). Units: x in m and m/s.
    """
    p0 = np.asarray(p0, dtype=float)
    v = np.asarray(v, dtype=float)
    tau = np.asarray(tau, dtype=float)
    d = p0[:, None, :] + v[:, None, :] * tau[..., None] - delta
    # angle_jacobians differentiates the angles of (target − station): target 0, station −p_k.
    g_t, g_p = angle_jacobians(np.zeros((d.shape[0], 3)), -d)
    G = np.stack([g_t, g_p], axis=-2)                          # (M, K, 2, 3)
    G6 = np.concatenate([G, G * tau[..., None, None]], axis=-1)  # (M, K, 2, 6)
    w = np.stack([1.0 / np.asarray(sigma_az) ** 2, 1.0 / np.asarray(sigma_el) ** 2], axis=-1)
    return np.einsum('mkai,mka,mkaj->mkij', G6, w, G6)


def constraint_gradient(v, v_o, speed_reference='relative'):
    """Gradient (…, 6) of the speed constraint (T5) c(x) = |v (+ v_o)|² − v_c² in x = (p0, v)."""
    g = np.zeros(np.shape(v)[:-1] + (6,))
    g[..., 3:] = 2.0 * (np.asarray(v) + (np.asarray(v_o) if speed_reference == 'ground'
                                         else 0.0))
    return g


def constrained_crlb(J, grad):
    """Constrained CRLB (Stoica & Ng 1998) C = U (Uᵀ J U)⁻¹ Uᵀ (T15), shape (…, 6, 6).

    U (…, 6, 5) is an orthonormal basis of the null space of the constraint gradient ``grad``
    (…, 6) (broadcast to J's leading shape); J the Fisher information (…, 6, 6). inf where
    UᵀJU is singular (unobservable).
    """
    J = np.asarray(J, dtype=float)
    g = np.broadcast_to(np.asarray(grad, dtype=float), J.shape[:-1])
    Qm, _ = np.linalg.qr(g[..., :, None], mode='complete')
    U = Qm[..., :, 1:]
    red = np.swapaxes(U, -1, -2) @ J @ U
    inv = safe_inverse(red)
    out = np.full(J.shape, np.inf)
    fin = np.all(np.isfinite(inv), axis=(-2, -1))
    out[fin] = U[fin] @ inv[fin] @ np.swapaxes(U[fin], -1, -2)
    return out


def state_transform(tau_last):
    """T (…, 6, 6) mapping x = (p0, v) to the target state (position, velocity) at τ (T1)."""
    tau_last = np.asarray(tau_last, dtype=float)
    T = np.broadcast_to(np.eye(6), tau_last.shape + (6, 6)).copy()
    T[..., 0, 3] = T[..., 1, 4] = T[..., 2, 5] = tau_last
    return T


def tma_crlb(bearings, times, p0, v, speed_reference='relative'):
    """Constrained CRLB of the relative state x = (p0, v), (M, 6, 6), at a given state.

    Geometry (observer positions, times, σ) from ``bearings``/``times``; the measured angles
    are not used. For the target state at time τ use T C Tᵀ with :func:`state_transform`
    (v_o is known, so the target velocity has the covariance of v). (T14)-(T15).
    """
    t = np.broadcast_to(np.asarray(times, dtype=float), bearings.azimuth.shape)
    tau = t - t[:, :1]
    v_o, delta = observer_track(tau, bearings.positions)
    p0 = np.broadcast_to(np.asarray(p0, dtype=float), (bearings.M, 3))
    v = np.broadcast_to(np.asarray(v, dtype=float), (bearings.M, 3))
    J = fisher_terms(p0, v, tau, delta, bearings.sigma_az, bearings.sigma_el).sum(1)
    return constrained_crlb(J, constraint_gradient(v, v_o, speed_reference))


def finish(method, data, p0, v, status, reason, iterations, converged, opts):
    """Target state (T1), covariance (T15)-(T16), range gate (T18), confidence (T19)-(T22).

    With ``covariance`` on, an ``ok`` fix that passes the range gate is tested by
    :func:`.confidence.assess`; one that fails keeps its state and covariance with the
    status ``low_confidence`` (``converged`` False) and the failed tests in ``reason``.
    State NaN (covariance inf) unless the status is ok, max_iterations or low_confidence.
    """
    M = data.M
    tau_l = data.tau[:, -1]
    status = np.asarray(status, dtype=object).copy()
    reason = np.asarray(reason, dtype=object).copy()
    good = np.isin(status, (STATUS_OK, STATUS_MAX_ITERATIONS)) \
        & np.all(np.isfinite(p0), -1) & np.all(np.isfinite(v), -1)
    cov = np.full((M, 6, 6), np.inf)
    d_last = p0 + v * tau_l[:, None] - data.delta[:, -1]
    rng = np.linalg.norm(d_last, axis=-1)
    if opts['covariance'] and np.any(good):
        g = np.nonzero(good)[0]
        J = fisher_terms(p0[g], v[g], data.tau[g], data.delta[g], data.s_az[g],
                         data.s_el[g]).sum(1)
        C = constrained_crlb(J, constraint_gradient(v[g], data.v_o[g],
                                                    opts['speed_reference']))
        T = state_transform(tau_l[g])
        with np.errstate(invalid='ignore'):
            Cx = T @ C @ np.swapaxes(T, -1, -2)
        fin = np.all(np.isfinite(Cx), axis=(-2, -1))
        u = d_last[g] / rng[g, None]
        var_r = np.einsum('mi,mij,mj->m', u, np.where(fin[:, None, None], Cx[:, :3, :3], 0),
                          u)
        ratio = np.where(fin, np.sqrt(np.maximum(var_r, 0)) / rng[g], np.inf)
        gate = ratio > opts['max_range_ratio']
        cov[g] = Cx
        for i in np.nonzero(gate)[0]:
            m = g[i]
            status[m] = STATUS_UNOBSERVABLE
            reason[m] = (f'range not resolved: CRLB range std is {100 * ratio[i]:.3g}% of the '
                         f'range (limit {100 * opts["max_range_ratio"]:.3g}%)')
            good[m] = False
        chk = g[(status[g] == STATUS_OK) & ~gate]
        if len(chk):
            passed, why = assess(data.take(chk), p0[chk], v[chk], C[np.isin(g, chk)], opts)
            status[chk[~passed]] = STATUS_LOW_CONFIDENCE
            reason[chk[~passed]] = why[~passed]
    pos0 = data.obs[:, 0] + p0
    vel = v + data.v_o
    pos = pos0 + vel * tau_l[:, None]
    for arr in (pos0, vel, pos, p0, v):
        arr[~good] = np.nan
    rng = np.where(good, rng, np.nan)
    cov[~good] = np.inf
    converged = np.asarray(converged, dtype=bool) & good & (status != STATUS_LOW_CONFIDENCE)
    return FixResult(pos, cov, np.asarray(iterations, dtype=int), converged,
                     status.astype(str), 'tma_' + method, velocity=vel, t=data.t0 + tau_l,
                     t0=data.t0.copy(), position0=pos0, relative_position0=p0,
                     relative_velocity=v, observer_velocity=data.v_o.copy(), range=rng,
                     reason=reason.astype(str))
