"""Per-station trust: each station's real bearing error scale, estimated from its residuals.

A station's σ claim is not taken on trust. After every fix, each station k in it is tested
against the fix of the *others* (leave-one-out, computed exactly for the linearised model
from the full fix, without re-solving; Cook 1977's deletion residual): with J_k its (1 or
2) × 3 angle Jacobian, e_k its residual at the fix X̂ and P the fix covariance,

    δ_k = (I − J_k P J_kᵀ R_k⁻¹)⁻¹ e_k,   var(δ_k) = R_k + J_k P_(−k) J_kᵀ,
    P_(−k) = (P⁻¹ − J_kᵀ R_k⁻¹ J_k)⁻¹,

δ_k being station k's residual at the fix of the others and R_k = diag(σ²) the variance
the fix weighted it with. Over a window of recent fixes the excess of δ_k² beyond what the
others' uncertainty explains estimates the station's own error variance,

    σ̂_k² = median over the window of mean_angles(δ_k² − [J_k P_(−k) J_kᵀ]_diag),

(the median: an occasional outlier, which the robust fix excludes, does not inflate a
station's σ; a consistent bias does). A station whose window statistic
Σ d_k² (d_k² = δ_kᵀ (R_claim + J_k P_(−k) J_kᵀ)⁻¹ δ_k, with the *claimed* σ; χ² with Σ dof
degrees of freedom when the claim holds) exceeds the χ² quantile of
:data:`SUSPECT_PROBABILITY` is *suspect* and named in the diagnostics. Only a suspect
station is scaled: its σ is used as σ_eff = max(σ_claim · s_k, σ_floor) with
s_k = sqrt(max(1, σ̂_k² / σ_claim²)) (never below the claim); every other station has
s_k = 1. The gate is needed because a single excess sample has the standard deviation
√2 · J_k P_(−k) J_kᵀ / σ_claim² per angle, which is large when the others determine the
fix poorly (three stations: up to ~100× the claim's variance), so the raw median of a few
samples scales honest stations by several times. Until a station has
:data:`MIN_SAMPLES` residuals its σ is also floored at the median σ its peers claim: an
unverified claim better than the rest of the network is not believed. Pure Python/numpy;
the fusion keeps one :class:`StationTrust` per pipeline.
Angles in rad, positions in m; ENU, azimuth CCW from East, elevation above the horizontal.
"""

from collections import deque
from dataclasses import replace
import math
import statistics

import numpy as np
from . import chisq as _chi2

#: Fixes in a station's residual window.
DEFAULT_WINDOW = 20
#: A station is suspect when its windowed deletion χ² exceeds this quantile.
SUSPECT_PROBABILITY = 0.9999
#: Samples before a station's scale is used (fewer: its claim, floored).
MIN_SAMPLES = 3
#: A station is testable only if the others determine the fix: the smallest eigenvalue of
#: P_(−k) must exceed this fraction of the largest. Below it P_(−k) is the inverse of a
#: numerically singular information (two 2D stations: the one left gives two angles for
#: three unknowns; cond ~1e16) whose eigenvalues' signs are rounding noise.
MIN_EIGEN_RATIO = 1e-10


class StationTrust:
    """Error scales of stations from their leave-one-out residual history (module doc).

    ``sigma_floor``: rad, the smallest σ any bearing is used with (0: none); ``floors``:
    per-station floors {station: rad} overriding it. ``window``: fixes remembered.
    """

    def __init__(self, window=DEFAULT_WINDOW, sigma_floor=0.0, floors=None,
                 probability=SUSPECT_PROBABILITY):
        if int(window) < 1:
            raise ValueError(f'window: must be >= 1, got {window}')
        f = float(sigma_floor)
        if not (math.isfinite(f) and f >= 0.0):
            raise ValueError(f'sigma_floor: must be finite and >= 0 rad, got {sigma_floor}')
        self.window = int(window)
        self.sigma_floor = f
        self.floors = {str(k): float(v) for k, v in (floors or {}).items()}
        self.probability = float(probability)
        self._hist = {}
        self._quantiles = {}
        self._scales = {}      # station -> s_k of its current window (dropped on change)
        self._deferred = []    # update() arguments not applied yet (defer_update)

    # ------------------------------------------------------------------ use
    def scale(self, station):
        """s_k ≥ 1 (module docstring); 1 until :data:`MIN_SAMPLES` fixes were seen.

        Kept per station until its window changes (it is read for every bearing of every
        epoch; the window changes once per fix)."""
        if self._deferred:
            self.settle()
        s = self._scales.get(station)
        if s is None:
            s = self._scales[station] = self._window_scale(self._hist.get(station))
        return s

    def _window_scale(self, h):
        if not h or len(h) < MIN_SAMPLES or not self._significant(h):
            return 1.0
        # statistics.median: the value np.median gives (the middle one, or the mean of the
        # two), without its ~30 µs per call.
        excess = float(statistics.median([x / n for x, n, _, _ in h]))
        return math.sqrt(max(1.0, excess))

    def floor(self, station):
        """σ floor of ``station``, rad."""
        return self.floors.get(station, self.sigma_floor)

    def verified(self, station):
        """True once ``station`` has :data:`MIN_SAMPLES` leave-one-out residuals."""
        if self._deferred:
            self.settle()
        h = self._hist.get(station)
        return bool(h) and len(h) >= MIN_SAMPLES

    def effective(self, bearing, peer_sigma=0.0):
        """``bearing`` with σ_eff = max(σ_claim · s_k, floor) (the same object if unchanged).

        A station not yet :meth:`verified` is also floored at ``peer_sigma`` (rad; the
        fusion passes the median σ claimed by the other stations of the epoch): a claim
        better than its peers' is used only once the residual history supports it.
        """
        s = self.scale(bearing.station)
        fl = self.floor(bearing.station)
        if not self.verified(bearing.station):
            fl = max(fl, float(peer_sigma))
        saz = max(bearing.sigma_azimuth * s, fl)
        sel = bearing.sigma_elevation
        if sel == sel:
            sel = max(sel * s, fl)
        if saz == bearing.sigma_azimuth and (sel == bearing.sigma_elevation or sel != sel):
            return bearing
        return replace(bearing, sigma_azimuth=saz, sigma_elevation=sel)

    def suspects(self):
        """Stations whose windowed deletion χ² is inconsistent with their σ (sorted)."""
        if self._deferred:
            self.settle()
        return sorted(st for st, h in self._hist.items()
                      if len(h) >= MIN_SAMPLES and self._significant(h))

    def _significant(self, h):
        """True when the window ``h``'s Σ d² exceeds the χ² quantile of its Σ dof."""
        d2 = sum(x for _, _, x, _ in h)
        dof = sum(n for _, n, _, _ in h)
        q = self._quantiles.get(dof)
        if q is None:
            q = self._quantiles[dof] = float(_chi2.ppf(self.probability, dof))
        return d2 > q

    def forget(self, station):
        """Drop the history of ``station``."""
        self.settle()
        self._hist.pop(station, None)
        self._scales.pop(station, None)

    def reset(self):
        """Drop every history (a time jump)."""
        self._deferred.clear()
        self._hist.clear()
        self._scales.clear()

    # ------------------------------------------------------------------ update
    def defer_update(self, bearings, claims, position, covariance, outside=()):
        """:meth:`update` later: at :meth:`settle` or before the trust is next read.

        The fusion defers the deletion residuals of a fix (~0.4 ms at 10 stations) until
        the fix is published; they only matter for the next epoch, and every reader settles
        first, so the results are those of calling :meth:`update` at once."""
        self._deferred.append((bearings, claims, np.array(position, dtype=float),
                               np.array(covariance, dtype=float), outside))

    def settle(self):
        """Apply the deferred updates, in order."""
        deferred, self._deferred = self._deferred, []
        for args in deferred:
            self._update(*args)

    def update(self, bearings, claims, position, covariance, outside=()):
        """Record the deletion residuals of a fix.

        ``bearings``: the Bearings in the fix, with the σ it weighted them with; ``outside``:
        Bearings of the epoch left out of it (their residual at the fix is already a
        leave-one-out residual: δ = e, P_(−k) = P); ``claims``:
        {station: (σ_θ, σ_ψ)} the stations' own claims, rad; ``position`` (3,) m and
        ``covariance`` (3, 3) m² of the fix (the estimator's, before any inflation).
        Returns {station: d_k²} of the stations that could be tested (a station whose
        removal leaves the fix undetermined is not testable).
        """
        if self._deferred:
            self.settle()
        return self._update(bearings, claims, position, covariance, outside)

    def _update(self, bearings, claims, position, covariance, outside):
        x = np.asarray(position, dtype=float)
        P = np.asarray(covariance, dtype=float)
        try:
            F = np.linalg.inv(P)
        except np.linalg.LinAlgError:
            return {}
        items = [(b, True) for b in bearings] + [(b, False) for b in outside]
        rows = deletion_residuals(items, claims, x, P, F)
        out = {}
        for b, row in zip((b for b, _ in items), rows):
            if row is None:
                continue
            excess, k, d2 = row
            h = self._hist.setdefault(b.station, deque(maxlen=self.window))
            h.append((excess, k, d2, k))
            # Here, off the fusion's latency path (settle), not at the next epoch's use.
            self._scales[b.station] = self._window_scale(h)
            out[b.station] = d2
        return out


def deletion_residual(b, inside, claims, x, P, F):
    """(excess, dof, d²) of one bearing at the fix (module doc), or None when untestable.

    ``inside``: the bearing was in the fix (δ from the deletion formula), else δ = e and
    P_(−k) = P. ``x`` (3,) m, ``P`` (3, 3) m² and ``F`` = P⁻¹ of the fix. The plain
    definition; :func:`deletion_residuals` computes the same for a whole epoch at once.
    """
    J, e, R = _angles(b, x)
    if J is None:
        return None
    Rinv = np.diag(1.0 / R)
    if inside:
        try:
            P_others = np.linalg.inv(F - J.T @ Rinv @ J)
        except np.linalg.LinAlgError:
            return None
        w = np.linalg.eigvalsh(0.5 * (P_others + P_others.T))
        if not (np.all(np.isfinite(w)) and w[0] > MIN_EIGEN_RATIO * w[-1]):
            return None
        A = np.eye(len(R)) - J @ P @ J.T @ Rinv
    else:
        P_others, A = P, np.eye(len(R))
    V = J @ P_others @ J.T
    c = claims.get(b.station, (b.sigma_azimuth, b.sigma_elevation))
    c2 = np.array([c[0] ** 2] + ([c[1] ** 2] if len(R) == 2 else []))
    try:
        delta = np.linalg.solve(A, e)
        d2 = float(delta @ np.linalg.solve(np.diag(c2) + V, delta))
    except np.linalg.LinAlgError:
        return None
    if not math.isfinite(d2):
        return None
    return float(np.sum((delta ** 2 - np.diag(V)) / c2)), len(R), d2


def deletion_residuals(items, claims, x, P, F):
    """:func:`deletion_residual` of every (bearing, inside) of ``items``, in one numpy pass.

    The fusion's fast path (one call per epoch instead of ~10 small numpy calls per
    station: at 50 stations 2.4 → 0.4 ms per epoch, bench/bench_fusion_latency.py). A
    1D bearing is padded to two angles with a zero Jacobian row, zero weight and unit
    claim, which adds only exact zeros; results equal the per-bearing path to rounding
    (tests). Falls back to that path when a matrix of the stack is singular.
    """
    n = len(items)
    if n == 0:
        return []
    pos = np.array([b.position for b, _ in items], dtype=float).reshape(n, 3)
    az = np.array([b.azimuth for b, _ in items], dtype=float)
    el = np.array([b.elevation for b, _ in items], dtype=float)
    two = el == el
    inside = np.array([i for _, i in items], dtype=bool)
    d = x - pos
    rho2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
    usable = rho2 > 0.0
    if not usable.all():
        rho2 = np.where(usable, rho2, 1.0)
    r2 = rho2 + d[:, 2] * d[:, 2]
    rho = np.sqrt(rho2)
    ea = az - np.arctan2(d[:, 1], d[:, 0])
    ea -= 2.0 * math.pi * np.ceil((ea - math.pi) / (2.0 * math.pi))
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = -d[:, 1] / rho2
    J[:, 0, 1] = d[:, 0] / rho2
    J[:, 1, 0] = np.where(two, -d[:, 0] * d[:, 2] / (rho * r2), 0.0)
    J[:, 1, 1] = np.where(two, -d[:, 1] * d[:, 2] / (rho * r2), 0.0)
    J[:, 1, 2] = np.where(two, rho / r2, 0.0)
    e = np.stack([ea, np.where(two, el - np.arctan2(d[:, 2], rho), 0.0)], axis=1)
    saz = np.array([b.sigma_azimuth for b, _ in items], dtype=float)
    sel = np.array([b.sigma_elevation for b, _ in items], dtype=float)
    Rinv = np.zeros((n, 2, 2))
    Rinv[:, 0, 0] = 1.0 / saz ** 2
    Rinv[:, 1, 1] = np.where(two, 1.0 / np.where(two, sel, 1.0) ** 2, 0.0)
    claim = [claims.get(b.station, (b.sigma_azimuth, b.sigma_elevation)) for b, _ in items]
    c2 = np.ones((n, 2))
    c2[:, 0] = np.array([c[0] for c in claim], dtype=float) ** 2
    c2[two, 1] = np.array([c[1] for c in claim], dtype=float)[two] ** 2
    Jt = J.transpose(0, 2, 1)
    eye = np.broadcast_to(np.eye(2), (n, 2, 2))
    ok = usable.copy()
    P_others = np.broadcast_to(P, (n, 3, 3)).copy()
    A = eye.copy()
    try:
        with np.errstate(all='ignore'):
            if inside.any():
                Ji, Jti, Ri = J[inside], Jt[inside], Rinv[inside]
                Po = np.linalg.inv(F - Jti @ Ri @ Ji)
                w = np.linalg.eigvalsh(0.5 * (Po + Po.transpose(0, 2, 1)))
                ok[inside] &= np.isfinite(w).all(axis=1) & (w[:, 0] > MIN_EIGEN_RATIO
                                                            * w[:, -1])
                P_others[inside] = Po
                A[inside] = eye[inside] - Ji @ P @ Jti @ Ri
            V = J @ P_others @ Jt
            delta = np.linalg.solve(A, e[..., None])
            M = V + c2[:, :, None] * eye
            d2 = (delta.transpose(0, 2, 1) @ np.linalg.solve(M, delta))[:, 0, 0]
            excess = np.sum((delta[..., 0] ** 2 - np.diagonal(V, axis1=1, axis2=2)) / c2,
                            axis=1)
    except np.linalg.LinAlgError:
        return [deletion_residual(b, i, claims, x, P, F) for b, i in items]
    ok &= np.isfinite(d2)
    k = np.where(two, 2, 1)
    return [(ex, kk, dd) if good else None for ex, kk, dd, good in
            zip(excess.tolist(), k.tolist(), d2.tolist(), ok.tolist())]


def _angles(b, x):
    """(J (k, 3), e (k,), R (k,)) of bearing ``b`` at ``x``: angle gradients, residuals
    (measured − predicted, azimuth wrapped), variances; (None, None, None) on the axis."""
    d = x - np.asarray(b.position, dtype=float)
    rho2 = d[0] * d[0] + d[1] * d[1]
    if not rho2 > 0.0:
        return None, None, None
    r2 = rho2 + d[2] * d[2]
    rho = math.sqrt(rho2)
    ea = b.azimuth - math.atan2(d[1], d[0])
    ea -= 2.0 * math.pi * math.ceil((ea - math.pi) / (2.0 * math.pi))
    J = [[-d[1] / rho2, d[0] / rho2, 0.0]]
    e = [ea]
    R = [b.sigma_azimuth ** 2]
    if b.elevation == b.elevation:
        J.append([-d[0] * d[2] / (rho * r2), -d[1] * d[2] / (rho * r2), rho / r2])
        e.append(b.elevation - math.atan2(d[2], rho))
        R.append(b.sigma_elevation ** 2)
    return np.array(J), np.array(e), np.array(R)
