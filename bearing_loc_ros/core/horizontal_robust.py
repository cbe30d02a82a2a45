"""Robust horizontal fix (option ``robust`` of ``mle``/``wmle`` in the horizontal solve).

The horizontal counterpart of :mod:`~bearing_loc_ros.core.robust` (which serves the 3D
solve), built for many bearings per fix (a window of a moving station's bearings, several
hundred): its candidates cost O(K² N) with a bounded K instead of one fit per station subset.

With c² the χ²₁ quantile of :data:`~bearing_loc_ros.core.robust.OUTLIER_PROBABILITY`
(3.89 σ) and the whitened residual of bearing j at a horizontal point X = (x, y, z₀)

    d_j²(X) = wrap(θ_j − θ_j(X))² / σ_θj² [+ (ψ_j − ψ_j(X))² / σ_ψj² where elevations are used]

(Zong & Cui 2015 eq. (3); σ grown with range for ``wmle``, eqs. (9)-(10)):

1. **Screen.** The estimator's fix is kept as it is when every d_j² ≤ c² and the residual
   χ² = Σ d_j² is at most the χ²_dof quantile of CONSISTENCY_PROBABILITY (dof = angles − 2).
2. **Consensus.** Candidates: the fix itself and the intersections of every pair among K ≤
   :data:`MAX_PAIR_BEARINGS` azimuths spread evenly over the set (pairs cutting at less than
   :data:`MIN_CUT_ANGLE` or meeting behind a station are skipped). Each is scored by the
   truncated cost S(X) = Σ_j min(d_j², c²) (MSAC, Torr & Zisserman 2000); the best one starts
   the refit. One bad bearing among many changes S by at most c² at any point, so it cannot
   pull the start far.
3. **Refit.** The estimator on the inliers (d_j² ≤ c²) from that start; inliers recomputed at
   the new fix and the fit repeated until the set is stable (at most :data:`REFIT_ROUNDS`).
   The covariance is the estimator's own over the inliers (full likelihood of the kept
   bearings). Excluded bearings are reported in ``excluded`` (both angles).
4. **Assess.** ``ok`` when the inliers' χ² is at most the χ²_dof quantile of
   CONSISTENCY_PROBABILITY and at most half the bearings were excluded; otherwise
   ``low_confidence`` (position and covariance kept, ``converged`` False).

Units: m, rad; ENU, azimuth θ CCW from East, elevation ψ above the horizontal.
"""

import math

import numpy as np

from .conventions import azimuth_elevation, wrap_angle
from .fix import FixResult, STATUS_LOW_CONFIDENCE, STATUS_OK
from .robust import _c2, chi2_upper, CONSISTENCY_PROBABILITY

#: Bearings (evenly spread over the set) whose pairwise intersections are candidates.
MAX_PAIR_BEARINGS = 16
#: Smallest cut angle of a candidate pair, rad.
MIN_CUT_ANGLE = np.radians(2.0)
#: Rounds of inlier recomputation and refit.
REFIT_ROUNDS = 5


def residuals2(bs, X, sigma_az, sigma_el, use_el):
    """d² (C, N) of candidate points X (C, 3) for one problem (module docstring)."""
    d = X[:, None, :] - bs.positions[0][None]
    az_hat, el_hat = azimuth_elevation(d)
    d2 = wrap_angle(bs.azimuth[0] - az_hat) ** 2 / sigma_az ** 2
    if np.any(use_el):
        el = np.where(use_el, bs.elevation[0], 0.0)
        sel = np.where(use_el, sigma_el, 1.0)
        d2 = d2 + np.where(use_el, (el - el_hat) ** 2 / sel ** 2, 0.0)
    return d2


#: Relative margin of :func:`screen_one`: a statistic this close to its threshold is decided
#: by the vectorised screen (the float residuals differ from numpy's by a few ulps).
SCREEN_MARGIN = 1e-9


def screen_one(bs, result, use_el, d_ref=None):
    """Step 1 (the screen) of a one-problem fix on Python floats: True, False or None.

    The test of core/horizontal.py ``screen_passed`` for M = 1: status ok, every whitened
    residual d_j² ≤ c² and Σ d_j² ≤ the χ²_dof quantile of CONSISTENCY_PROBABILITY (dof =
    used angles − 2), d_j² as in the module docstring (azimuth residual wrapped to (−π, π],
    σ grown by d/d_ref for ``wmle``). None when a statistic lies within
    :data:`SCREEN_MARGIN` (relative) of its threshold: the caller then runs the vectorised
    test, whose residuals may differ from these in the last bits.
    """
    if str(result.status[0]) != STATUS_OK:
        return False
    x, y, z = result.position[0].tolist()
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    c2 = _c2()
    atan2, sqrt, pi = math.atan2, math.sqrt, math.pi
    total = 0.0
    n_angles = 0
    for (px, py, pz), az, el, saz, sel, used in zip(
            bs.positions[0].tolist(), bs.azimuth[0].tolist(), bs.elevation[0].tolist(),
            bs.sigma_az[0].tolist(), bs.sigma_el[0].tolist(), use_el.tolist()):
        dx, dy, dz = x - px, y - py, z - pz
        rho = math.hypot(dx, dy)
        if d_ref is not None:
            f = sqrt(dx * dx + dy * dy + dz * dz) / d_ref
            saz, sel = saz * f, sel * f
        e = math.remainder(az - atan2(dy, dx), 2.0 * pi)
        d2 = (e / saz) ** 2
        n_angles += 1
        if used:
            d2 += ((el - atan2(dz, rho)) / sel) ** 2
            n_angles += 1
        if not math.isfinite(d2):
            return None
        if abs(d2 - c2) <= SCREEN_MARGIN * c2:
            return None
        if d2 > c2:
            return False
        total += d2
    upper = float(chi2_upper(max(n_angles - 2, 1)))
    if abs(total - upper) <= SCREEN_MARGIN * upper:
        return None
    return total <= upper


def pair_candidates(bs, z0):
    """Intersections (C, 3) at z = z₀ of pairs among up to MAX_PAIR_BEARINGS azimuths."""
    N = bs.N
    k = min(N, MAX_PAIR_BEARINGS)
    idx = np.unique(np.round(np.linspace(0, N - 1, k)).astype(int))
    i, j = np.triu_indices(idx.size, 1)
    i, j = idx[i], idx[j]
    p = bs.positions[0, :, :2]
    th = bs.azimuth[0]
    u = np.stack([np.cos(th), np.sin(th)], axis=-1)
    det = u[i, 0] * u[j, 1] - u[i, 1] * u[j, 0]                  # sin(θ_j − θ_i)
    dp = p[j] - p[i]
    with np.errstate(divide='ignore', invalid='ignore'):
        ti = (dp[:, 0] * u[j, 1] - dp[:, 1] * u[j, 0]) / det
        tj = (dp[:, 0] * u[i, 1] - dp[:, 1] * u[i, 0]) / det
    ok = (np.abs(det) > np.sin(MIN_CUT_ANGLE)) & (ti > 0) & (tj > 0)
    xy = p[i[ok]] + ti[ok, None] * u[i[ok]]
    return np.column_stack([xy, np.full(xy.shape[0], z0)])


def _sigmas(bs, X, d_ref):
    if d_ref is None:
        return bs.sigma_az[0], bs.sigma_el[0]
    f = np.linalg.norm(X[None, :] - bs.positions[0], axis=-1) / d_ref
    return bs.sigma_az[0] * f, bs.sigma_el[0] * f


def robust_fix(solve, bs, result, z0, use_el, d_ref=None):
    """Screened / consensus / refitted horizontal fix of one problem (module docstring).

    ``solve(subset_bearings, initial)`` runs the estimator on a one-problem BearingSet and
    returns its FixResult; ``result`` is its fix of all of ``bs``; z₀ (m) the stated
    altitude; ``use_el`` (N,) the elevations used; ``d_ref`` the ``wmle`` reference range (m)
    or None. Returns (FixResult of one problem, excluded (N,) bool).
    """
    N = bs.N
    c2 = _c2()
    x = np.asarray(result.position[0], dtype=float)
    n_angles = N + int(np.count_nonzero(use_el))
    excluded = np.zeros(N, dtype=bool)
    if str(result.status[0]) == STATUS_OK and np.all(np.isfinite(x)):
        saz, sel = _sigmas(bs, x, d_ref)
        d2 = residuals2(bs, x[None], saz, sel, use_el)[0]
        if np.all(d2 <= c2) and d2.sum() <= chi2_upper(max(n_angles - 2, 1)):
            return result, excluded
    cands = pair_candidates(bs, z0)
    if np.all(np.isfinite(x)):
        cands = np.vstack([x[None], cands])
    if cands.shape[0] == 0:
        return result, excluded
    saz, sel = bs.sigma_az[0], bs.sigma_el[0]
    if d_ref is not None:
        f = np.linalg.norm(cands[:, None, :] - bs.positions[0][None], axis=-1) / d_ref
        saz, sel = saz * f, sel * f
    score = np.minimum(residuals2(bs, cands, saz, sel, use_el), c2).sum(axis=1)
    x = cands[int(np.argmin(score))]
    res = None
    for _ in range(REFIT_ROUNDS):
        s_az, s_el = _sigmas(bs, x, d_ref)
        inl = residuals2(bs, x[None], s_az, s_el, use_el)[0] <= c2
        if res is not None and np.array_equal(inl, ~excluded):
            break
        if np.count_nonzero(inl) < 2:
            break
        excluded = ~inl
        res = solve(bs.subset(inl), x)
        xn = np.asarray(res.position[0], dtype=float)
        if not np.all(np.isfinite(xn)):
            break
        x = xn
    if res is None:
        return result, np.zeros(N, dtype=bool)
    kept = ~excluded
    n_kept = int(np.count_nonzero(kept)) + int(np.count_nonzero(use_el & kept))
    s_az, s_el = _sigmas(bs, x, d_ref)
    d2 = residuals2(bs, x[None], s_az, s_el, use_el)[0]
    consistent = (d2[kept].sum() <= chi2_upper(max(n_kept - 2, 1), CONSISTENCY_PROBABILITY)
                  and np.count_nonzero(excluded) <= N // 2)
    status = np.array(res.status, dtype=object)
    conv = np.array(res.converged, dtype=bool)
    if str(status[0]) == STATUS_OK and not consistent:
        status[0], conv[0] = STATUS_LOW_CONFIDENCE, False
    return FixResult(res.position, res.covariance, res.iterations, conv, status.astype(str),
                     res.method), excluded
