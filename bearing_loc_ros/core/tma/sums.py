"""Pseudo-linear moments of the TMA estimators and their accumulation (T6)-(T13).

Per-bearing 3x3 terms (:func:`bearing_terms`), their time moments (:class:`TmaSums`, the
sufficient statistics of ple/ctls/ctls6, Lin et al. sec. 3.2.1) in batch form
(:func:`batch_sums`) and for every prefix of a window (:func:`prefix_sums`, the batch form
of the recursion (T13)). Conventions as :mod:`bearing_loc_ros.core.tma`.
"""

from dataclasses import dataclass

import numpy as np

from ..conventions import los_vector


def bearing_terms(azimuth, elevation, sigma_az, sigma_el):
    """Per-bearing 3x3 terms of the pseudo-linear normal matrices (T6), (T10)-(T11), (T18).

    With h_θ = (−sin θ, cos θ, 0), h_ψ = (−sin ψ cos θ, −sin ψ sin θ, cos ψ) (the unit vectors
    normal to the line of sight u(θ, ψ) along increasing θ and ψ) and their derivatives
    h_θ' = ∂h_θ/∂θ = (−cos θ, −sin θ, 0), h_ψθ' = ∂h_ψ/∂θ = (sin ψ sin θ, −sin ψ cos θ, 0),
    h_ψψ' = ∂h_ψ/∂ψ = (−cos ψ cos θ, −cos ψ sin θ, −sin ψ):

        Ph = h_θ h_θᵀ/σ_θ² + h_ψ h_ψᵀ/σ_ψ²                       (row weights 1/σ², T7)
        Oh = h_θ' h_θ'ᵀ + (σ_θ²/σ_ψ²) h_ψθ' h_ψθ'ᵀ + h_ψψ' h_ψψ'ᵀ  (first-order E[ΔhᵀWΔh], T11)
        Qh = h_θ h_θᵀ/(σ_θ cos ψ)² + h_ψ h_ψᵀ/σ_ψ²                (constant-LOS test, T18)

    Angles in rad (ENU), σ in rad; arrays of any shape (...,) -> (..., 3, 3) each.
    """
    az = np.asarray(azimuth, dtype=float)
    el = np.asarray(elevation, dtype=float)
    st, ct, sp, cp = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    z = np.zeros_like(st)
    h_t = np.stack([-st, ct, z], axis=-1)
    h_p = np.stack([-sp * ct, -sp * st, cp], axis=-1)
    d_t = np.stack([-ct, -st, z], axis=-1)
    d_pt = np.stack([sp * st, -sp * ct, z], axis=-1)
    d_pp = np.stack([-cp * ct, -cp * st, -sp], axis=-1)
    w_t = 1.0 / np.asarray(sigma_az, dtype=float) ** 2
    w_p = 1.0 / np.asarray(sigma_el, dtype=float) ** 2

    def outer(a, b):
        return a[..., :, None] * b[..., None, :]

    Ph = w_t[..., None, None] * outer(h_t, h_t) + w_p[..., None, None] * outer(h_p, h_p)
    Oh = (outer(d_t, d_t) + (w_p / w_t)[..., None, None] * outer(d_pt, d_pt)
          + outer(d_pp, d_pp))
    Qh = ((w_t / cp ** 2)[..., None, None] * outer(h_t, h_t)
          + w_p[..., None, None] * outer(h_p, h_p))
    return Ph, Oh, Qh


@dataclass
class TmaSums:
    """Sufficient statistics of the pseudo-linear estimators, for any leading shape S.

    Moments with τ_r = t_k − t_ref (s): A_j = Σ τ_r^j Ph_k, B_j = Σ τ_r^j Oh_k (j = 0, 1, 2),
    Q = Σ Qh_k (see :func:`bearing_terms`); observer sums T1 = Σ τ_r, T2 = Σ τ_r²,
    O1 = Σ (o_k − o_ref), TO = Σ τ_r (o_k − o_ref); the first bearing of the window
    (t0, e0 = u(θ_0, ψ_0), o0, its Oh as ``B_first``) and the last (t_last, o_last).
    Adding a bearing adds its terms (Lin et al. sec. 3.2.1: P(k+1) = P(k) + ..., (T13)); the
    paper's P, Ω follow in O(1) from :meth:`paper_matrices`.
    """

    n: np.ndarray
    t_ref: np.ndarray
    o_ref: np.ndarray
    t0: np.ndarray
    e0: np.ndarray
    o0: np.ndarray
    B_first: np.ndarray
    t_last: np.ndarray
    o_last: np.ndarray
    A0: np.ndarray
    A1: np.ndarray
    A2: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    Q: np.ndarray
    T1: np.ndarray
    T2: np.ndarray
    O1: np.ndarray
    TO: np.ndarray

    def moments_at_t0(self):
        """(A0, A1, A2, B0, B1, B2) re-referenced to τ = t − t0 (shift c = t_ref − t0).

        Σ (τ + c)² X = A2 + 2c A1 + c² A0 and Σ (τ + c) X = A1 + c A0.
        """
        c = (self.t_ref - self.t0)[..., None, None]
        A1 = self.A1 + c * self.A0
        A2 = self.A2 + 2 * c * self.A1 + c * c * self.A0
        B1 = self.B1 + c * self.B0
        B2 = self.B2 + 2 * c * self.B1 + c * c * self.B0
        return self.A0, A1, A2, self.B0, B1, B2

    def paper_matrices(self):
        """The paper's P = AᵀWA and Ω (Lin et al. sec. 3.2.1; (T10)-(T11)), shape (S, 4, 4).

        Rows of A: a_k = [τ_k h_kᵀ, h_k·e0] (T9), k ≥ 1 (bearing 0 defines e0 and is taken as
        exact, as in the paper), i.e. P = L P6 Lᵀ with L = [[I3, 0], [0, e0ᵀ]] and
        P6 = [[A2, A1], [A1, A0]]; Ω likewise from the B moments without bearing 0.
        """
        A0, A1, A2, B0, B1, B2 = self.moments_at_t0()
        B0 = B0 - self.B_first
        e0 = self.e0
        return _lift(A0, A1, A2, e0), _lift(B0, B1, B2, e0)

    def observer_velocity(self):
        """v_o (T2) from the observer sums (shift invariant), m/s; 0 if one time only."""
        den = self.n * self.T2 - self.T1 ** 2
        num = self.n[..., None] * self.TO - self.T1[..., None] * self.O1
        good = den > 1e-12 * np.maximum(self.n * self.T2, 1e-300)
        return np.where(good[..., None], num / np.where(good, den, 1.0)[..., None], 0.0)


def _lift(X0, X1, X2, e0):
    """[[X2, X1 e0], [e0ᵀ X1, e0ᵀ X0 e0]] (S, 4, 4): the paper's 4x4 from the 6x6 moments."""
    S = X0.shape[:-2]
    out = np.empty(S + (4, 4))
    out[..., :3, :3] = X2
    c = np.einsum('...ij,...j->...i', X1, e0)
    out[..., :3, 3] = c
    out[..., 3, :3] = c
    out[..., 3, 3] = np.einsum('...i,...ij,...j->...', e0, X0, e0)
    return out


def prefix_sums(bearings, times):
    """:class:`TmaSums` of every prefix of every problem: leading shape (M, K).

    Entry [m, k] summarises bearings 0..k of problem m (t_ref = t0 = times[m, 0]), so the
    running ple/ctls estimate after every bearing costs one cumulative sum (used by the
    benchmark; (T13) in batch form).
    """
    t = np.broadcast_to(np.asarray(times, dtype=float), bearings.azimuth.shape)
    M, K = t.shape
    tau = t - t[:, :1]
    Ph, Oh, Qh = bearing_terms(bearings.azimuth, bearings.elevation, bearings.sigma_az,
                               bearings.sigma_el)
    w1 = tau[..., None, None]
    w2 = w1 * w1
    cs = np.cumsum
    o = bearings.positions - bearings.positions[:, :1]
    e0 = los_vector(bearings.azimuth[:, 0], bearings.elevation[:, 0])
    return TmaSums(
        n=np.broadcast_to(np.arange(1, K + 1, dtype=float), (M, K)).copy(),
        t_ref=np.repeat(t[:, :1], K, axis=1), o_ref=np.repeat(bearings.positions[:, :1], K, 1),
        t0=np.repeat(t[:, :1], K, axis=1), e0=np.repeat(e0[:, None], K, axis=1),
        o0=np.repeat(bearings.positions[:, :1], K, axis=1),
        B_first=np.repeat(Oh[:, :1], K, axis=1),
        t_last=t.copy(), o_last=bearings.positions.copy(),
        A0=cs(Ph, axis=1), A1=cs(w1 * Ph, axis=1), A2=cs(w2 * Ph, axis=1),
        B0=cs(Oh, axis=1), B1=cs(w1 * Oh, axis=1), B2=cs(w2 * Oh, axis=1),
        Q=cs(Qh, axis=1), T1=cs(tau, axis=1), T2=cs(tau * tau, axis=1),
        O1=cs(o, axis=1), TO=cs(tau[..., None] * o, axis=1))


def batch_sums(bearings, times):
    """:class:`TmaSums` of each whole problem (leading shape (M,)): the batch recomputation."""
    t = np.broadcast_to(np.asarray(times, dtype=float), bearings.azimuth.shape)
    tau = t - t[:, :1]
    Ph, Oh, Qh = bearing_terms(bearings.azimuth, bearings.elevation, bearings.sigma_az,
                               bearings.sigma_el)
    w1 = tau[..., None, None]
    o = bearings.positions - bearings.positions[:, :1]
    return TmaSums(
        n=np.full(t.shape[0], float(t.shape[1])), t_ref=t[:, 0].copy(),
        o_ref=bearings.positions[:, 0].copy(), t0=t[:, 0].copy(),
        e0=los_vector(bearings.azimuth[:, 0], bearings.elevation[:, 0]),
        o0=bearings.positions[:, 0].copy(), B_first=Oh[:, 0].copy(), t_last=t[:, -1].copy(),
        o_last=bearings.positions[:, -1].copy(),
        A0=Ph.sum(1), A1=(w1 * Ph).sum(1), A2=(w1 * w1 * Ph).sum(1),
        B0=Oh.sum(1), B1=(w1 * Oh).sum(1), B2=(w1 * w1 * Oh).sum(1), Q=Qh.sum(1),
        T1=tau.sum(1), T2=(tau * tau).sum(1), O1=o.sum(1),
        TO=np.einsum('mk,mki->mi', tau, o))
