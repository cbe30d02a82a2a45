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
   CONSISTENCY_PROBABILITY and the nonlinearity ν (below) is at most
   :func:`~bearing_loc_ros.core.robust_model.max_nonlinearity`; otherwise
   ``low_confidence`` (position and covariance kept, ``converged`` False). An exclusion is
   decisive when the bearing is an outlier also given the fix's own uncertainty: its
   whitened residuals r (k = 1 or 2 angles) against their predictive covariance,
   rᵀ (I + G P Gᵀ)⁻¹ r with G the whitened gradients and P the refit's covariance, exceed
   c², the level that excluded it (the 3D test of :mod:`.robust`, check (d), which asks for
   the stricter χ²₁ quantile of DECISIVE_PROBABILITY among its few stations; a window of
   hundreds of bearings holds many outliers between the two levels, and its small P leaves
   their residuals as they are). A refit whose exclusions are not all decisive, or are more
   than a minority of the redundant angles (at most ⌊(M − 2)/2⌋ of the M used angles: with
   three azimuths none, since any two of them intersect exactly and the data cannot tell
   which one is wrong), is dropped: the estimator's fit of every bearing is returned as
   ``low_confidence`` with nothing excluded (the data do not show that the bearings were
   outliers, and the fit of a subset can lie far from the fit of all of them).
   As in 3D, no fix is left ``max_iterations`` or ``diverged``: a finite one is
   ``low_confidence`` (at σ ≈ 10-15° an azimuth-only iteration can end on a station, the
   pole of that station's bearing), else ``degenerate_geometry``.

Range-grown σ (``wmle``): every fix is assessed (no screen). The covariance is widened by
:func:`test_inversion` to the level :data:`~bearing_loc_ros.core.robust_model.TEST_INVERSION_Z`
and ν is taken over the region at
:data:`~bearing_loc_ros.core.robust_model.STATUS_REGION_Z` (the 3D rule of :mod:`.robust`),
the larger of ν along the major axis and along ∇ Σ_k log ρ_k: without elevations a fix that
lands near the stations, where σ(d) is small, has a small round covariance while its region
runs outward, away from the nearest stations.

Nonlinearity ν = sqrt(λ_max(P_xy)) / min_k ρ_k (:func:`nonlinearity`): the radius of the
horizontal confidence region seen from the nearest station with a kept bearing, relative to
its horizontal range ρ_k. Azimuths are functions of (x − x_k, y − y_k) / ρ_k, so over the
region their second-order terms are ν times the first-order ones (the 3D ν of
:mod:`.robust`, in the plane of the solve); with ν large the region is a banana elongated in
range and the covariance understates its tail. The screen (step 1) keeps a fix only when
its ν passes too; a calm fix (residuals and χ² pass) with a large ν is ``low_confidence``
with nothing excluded. Measured on the Wang, Zhang & Wu (2006) stations with azimuth-only
receivers (config/scenarios/seed000_azimuth_only.yaml, 10,000 trials per σ): docs/
estimators.md, "Horizontal fixes at low SNR".

The bound evaluations of the test inversion (:func:`_bound_sigma_along`, :func:`_inversions`)
and the calm branch of one ``wmle`` fix (:func:`calm_grown_one`) are compiled
(:mod:`.jit`); the rest is numpy.

Units: m, rad; ENU, azimuth θ CCW from East, elevation ψ above the horizontal.
"""

import math

import numpy as np

from .conventions import azimuth_elevation, wrap_angle, wrap_angle_scalar
from .jit import jit, jit_numpy, plain_array
from .fix import FixResult, STATUS_DEGENERATE, STATUS_LOW_CONFIDENCE, STATUS_OK
from .robust import _c2, chi2_upper, CONSISTENCY_PROBABILITY
from .horizontal_single import inverse2 as _inverse2_py
from .robust_model import (_upper_cached, max_nonlinearity, STATUS_REGION_Z,
                           TEST_INVERSION_Z)

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
    """Step 1 (the screen) of a one-problem fix on Python floats: True, False or None
    (:func:`screen_one_nu` without its ν)."""
    return screen_one_nu(bs, result, use_el, d_ref)[0]


def screen_one_nu(bs, result, use_el, d_ref=None):
    """Step 1 (the screen) of a one-problem fix on Python floats: (True, False or None, ν).

    The test of core/horizontal.py ``screen_passed`` for M = 1: status ok, every whitened
    residual d_j² ≤ c² and Σ d_j² ≤ the χ²_dof quantile of CONSISTENCY_PROBABILITY (dof =
    used angles − 2), d_j² as in the module docstring (azimuth residual wrapped to (−π, π],
    σ grown by d/d_ref for ``wmle``), and ν ≤ max_nonlinearity (:func:`nonlinearity`,
    every station kept). None when a statistic lies within
    :data:`SCREEN_MARGIN` (relative) of its threshold: the caller then runs the vectorised
    test, whose residuals may differ from these in the last bits. ν is the fix's
    :func:`nonlinearity` over every station (the same operations on floats, tested) where
    the decision is True, else NaN.
    """
    nan = math.nan
    if str(result.status[0]) != STATUS_OK:
        return False, nan
    x, y, z = result.position[0].tolist()
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False, nan
    c2 = _c2()
    atan2, sqrt, pi = math.atan2, math.sqrt, math.pi
    total = 0.0
    n_angles = 0
    rho_min = math.inf
    for (px, py, pz), az, el, saz, sel, used in zip(
            bs.positions[0].tolist(), bs.azimuth[0].tolist(), bs.elevation[0].tolist(),
            bs.sigma_az[0].tolist(), bs.sigma_el[0].tolist(), use_el.tolist()):
        dx, dy, dz = x - px, y - py, z - pz
        rho = math.hypot(dx, dy)
        rho_min = min(rho_min, rho)
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
            return None, nan
        if abs(d2 - c2) <= SCREEN_MARGIN * c2:
            return None, nan
        if d2 > c2:
            return False, nan
        total += d2
    upper = float(chi2_upper(max(n_angles - 2, 1)))
    if abs(total - upper) <= SCREEN_MARGIN * upper:
        return None, nan
    if not total <= upper:
        return False, nan
    (a, b, _), (_, c, _), _ = result.covariance[0].tolist()
    lam = 0.5 * (a + c) + sqrt(0.25 * (a - c) ** 2 + b * b)
    nu = sqrt(lam) / rho_min if lam >= 0.0 and rho_min > 0.0 else math.nan
    limit = max_nonlinearity(d_ref is not None)
    if not math.isfinite(nu):
        return False, nan
    if abs(nu - limit) <= SCREEN_MARGIN * limit:
        return None, nan
    return (True, nu) if nu <= limit else (False, nan)


def nonlinearity(X, P, positions, kept=None):
    """ν (M,) of horizontal fixes (module docstring): sqrt(λ_max(P_xy)) / min_k ρ_k.

    X (M, 3) m, P (M, 3, 3) m², station positions (M, N, 3) m, ``kept`` (M, N) bool: the
    stations with a kept bearing (default all). λ_max of the 2 × 2 block in closed form,
    (a + c)/2 + sqrt(((a − c)/2)² + b²). NaN where P or X is not finite.
    """
    X = np.asarray(X, dtype=float)
    P = np.asarray(P, dtype=float)
    a, b, c = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
        lam = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
        rho = np.hypot(X[:, None, 0] - positions[..., 0], X[:, None, 1] - positions[..., 1])
        if kept is not None:
            rho = np.where(kept, rho, np.inf)
        nu = np.sqrt(lam) / rho.min(axis=-1)
    return np.where(np.isfinite(nu) & (lam >= 0.0), nu, np.nan)


def decisive(bs, X, P, excluded, use_el, d_ref=None):
    """True when every excluded bearing is an outlier also given the fix's uncertainty.

    Bearing j with k used angles (azimuth; elevation where ``use_el``), whitened residuals
    r (k,) at X and whitened gradients G (k, 3) (∂θ/∂X = (−Δy, Δx, 0)/ρ², ∂ψ/∂X =
    (−Δx Δz/(ρ d²), −Δy Δz/(ρ d²), ρ/d²), over σ grown by d/d_ref for ``wmle``): decisive
    when rᵀ (I + G P Gᵀ)⁻¹ r exceeds c², the exclusion level (module docstring, step 4).
    ``bs`` one problem, X (3,) m, P (3, 3) m², ``excluded`` and ``use_el`` (N,) bool. True
    when nothing is excluded; False where P is not finite.
    """
    idx = np.flatnonzero(excluded)
    if idx.size == 0:
        return True
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(X))):
        return False
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        # A station under the fix (ρ = 0) gives a non-finite q: not decisive.
        return _decisive(bs, X, P, idx, use_el, d_ref)


def _decisive(bs, X, P, idx, use_el, d_ref):
    d = X[None, :] - bs.positions[0][idx]
    rho2 = d[:, 0] ** 2 + d[:, 1] ** 2
    rho = np.sqrt(rho2)
    r2 = rho2 + d[:, 2] ** 2
    f = 1.0 if d_ref is None else np.sqrt(r2) / d_ref
    az_hat, el_hat = azimuth_elevation(d)
    s_az = bs.sigma_az[0][idx] * f
    ga = np.stack([-d[:, 1] / rho2, d[:, 0] / rho2, np.zeros(idx.size)], axis=-1) / s_az[:, None]
    ra = wrap_angle(bs.azimuth[0][idx] - az_hat) / s_az
    el = use_el[idx]
    c2 = _c2()
    for j in range(idx.size):
        G, r = [ga[j]], [ra[j]]
        if el[j]:
            s_el = bs.sigma_el[0][idx[j]] * (f if np.ndim(f) == 0 else f[j])
            t = d[j, 2] / (rho[j] * r2[j])
            G.append(np.array([-d[j, 0] * t, -d[j, 1] * t, rho[j] / r2[j]]) / s_el)
            r.append((bs.elevation[0][idx[j]] - el_hat[j]) / s_el)
        G, r = np.array(G), np.array(r)
        S = np.eye(len(r)) + G @ P @ G.T
        try:
            q = float(r @ np.linalg.solve(S, r))
        except np.linalg.LinAlgError:
            return False
        if not q > c2:
            return False
    return True


def test_inversion(bs, X, P, kept, use_el, d_ref, sigma_z=0.0, z=TEST_INVERSION_Z,
                   iterations=4, outward=False):
    """P (3, 3) widened along the major axis of its x-y block to the far side of the
    test-inversion region of level ``z``, m² (range-grown σ; :mod:`.robust`'s
    ``test_inversion_covariance`` in the plane of the solve).

    With σ_j = σ_ref,j d_j / d_ref the covariance P(X) of the horizontal solve (the bound
    of :func:`.horizontal_crlb.horizontal_crlb` at X with the stations' σ at X and the
    stated altitude's σ_z) grows with range. Along the major axis v of P_xy (oriented away
    from the kept stations) the far boundary t of {X: (X̂ − X)ᵀ P(X)⁻¹ (X̂ − X) ≤ z²} solves
    t = z s(X̂ + t v), s² = vᵀ P_xy(X) v, by four fixed-point steps from t = z s(X̂), t at
    most 10 times the largest station range; the variance along v becomes
    max(s(X̂)², (t/z)²). With ``outward`` the same along u = ∇ Σ_k log ρ_k / |∇ Σ_k log ρ_k|
    (ρ_k the horizontal ranges from the kept stations) instead of v: the direction in which
    the σ(d) of the nearest stations grow fastest. ``bs`` one problem, X (3,) m, ``kept`` and
    ``use_el`` (N,) bool. A matrix of +inf where P or the widening is not finite.
    """
    return _test_inversions(bs, X, P, kept, use_el, d_ref, sigma_z, ((z, outward),),
                            iterations)[0]


def _test_inversions(bs, X, P, kept, use_el, d_ref, sigma_z, specs, iterations=4):
    """:func:`test_inversion` for several (z, outward) ``specs`` at once: (K, 3, 3).

    Compiled (:func:`_inversions`): per spec, four bound evaluations of the kept stations.
    """
    P = np.asarray(P, dtype=float)
    X = np.asarray(X, dtype=float)
    K = len(specs)
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(X)) and np.any(kept)):
        return np.full((K, 3, 3), np.inf)
    return _inversions(plain_array(bs.positions[0][kept]), plain_array(bs.sigma_az[0][kept]),
                       plain_array(bs.sigma_el[0][kept]), use_el[kept], X,
                       np.ascontiguousarray(P[:3, :3]),
                       np.array([z for z, _ in specs], dtype=float),
                       np.array([o for _, o in specs], dtype=np.bool_), float(d_ref),
                       float(sigma_z), int(iterations))


@jit_numpy
def _inversions(pos, sa, se, has, X, P, zs, outward, d_ref, sigma_z, iterations):
    """:func:`_test_inversions` on the kept stations' arrays (numpy's arithmetic: a station
    under X gives inf or NaN, not an error): pos (n, 3) m, sa, se (n,) σ_ref rad, has (n,)
    elevations used; X (3,) m, P (3, 3) m² finite; zs, outward (K,). (K, 3, 3), +inf where
    the widening is not finite."""
    K = zs.shape[0]
    out = np.full((K, 3, 3), np.inf)
    _, V = np.linalg.eigh(np.ascontiguousarray(P[:2, :2]))
    m0, m1 = V[0, 1], V[1, 1]
    sx = sy = gx = gy = 0.0
    far = -np.inf
    for k in range(pos.shape[0]):
        h0, h1 = X[0] - pos[k, 0], X[1] - pos[k, 1]
        hy = math.hypot(h0, h1)
        sx += h0 / hy
        sy += h1 / hy
        q = h0 * h0 + h1 * h1
        gx += h0 / q
        gy += h1 / q
        e0, e1, e2 = pos[k, 0] - X[0], pos[k, 1] - X[1], pos[k, 2] - X[2]
        r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if r > far or math.isnan(r):
            far = r
    if m0 * sx + m1 * sy < 0.0:
        m0, m1 = -m0, -m1
    gn = math.hypot(gx, gy)
    u0, u1 = gx / gn, gy / gn
    t_max = 10.0 * far
    for kk in range(K):
        if outward[kk]:
            v0, v1 = u0, u1
        else:
            v0, v1 = m0, m1
        z = zs[kk]
        s0 = math.sqrt(max(v0 * (P[0, 0] * v0 + P[0, 1] * v1) + v1 * (P[1, 0] * v0 + P[1, 1] * v1),
                           0.0))
        t = z * s0
        for _ in range(iterations):
            st = _bound_sigma_along(X[0] + t * v0, X[1] + t * v1, X[2], v0, v1, pos, sa, se,
                                    has, d_ref, sigma_z)
            t = min(z * st, t_max) if math.isfinite(st) else t_max
        add = (t / z) ** 2 - s0 * s0
        add = add if add > 0.0 or math.isnan(add) else 0.0
        if math.isfinite(add):
            v = np.array([v0, v1, 0.0])
            for i in range(3):
                for j in range(3):
                    out[kk, i, j] = P[i, j] + add * (v[i] * v[j])
    return out


@jit_numpy
def _bound_sigma_along(x, y, z, v0, v1, pos, sa, se, has, d_ref, sigma_z):
    """sqrt(vᵀ P_xy v), m, of the horizontal bound at (x, y, z) with σ grown by d / d_ref.

    :func:`.horizontal_crlb.horizontal_crlb` of one point (the Fisher information of the
    angles, Zong & Cui 2015 eq. (7), the z prior by the Schur complement and the 2 × 2
    inverse with its rank test, :func:`.horizontal_single.inverse2`), for the fixed-point
    steps of :func:`_test_inversions`. (v0, v1) unit vector; per kept station ``pos`` (n, 3)
    m, σ_θ,ref ``sa``, σ_ψ,ref ``se`` (NaN without elevation), ``has`` elevation used.
    +inf where the bound is not finite (singular horizontal block, a station under the
    point: with numpy's error model the division by zero leaves the information not finite,
    which the rank test of the inverse refuses).
    """
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0         # Σ w_θ g_θ g_θᵀ
    e00 = e01 = e02 = e11 = e12 = e22 = 0.0         # Σ w_ψ g_ψ g_ψᵀ
    for k in range(pos.shape[0]):
        dx, dy, dz = x - pos[k, 0], y - pos[k, 1], z - pos[k, 2]
        f = math.sqrt(dx * dx + dy * dy + dz * dz) / d_ref
        rho2 = dx * dx + dy * dy
        rho = math.sqrt(rho2)
        r2 = rho2 + dz * dz
        w = 1.0 / (sa[k] * f) ** 2
        g0, g1 = -dy / rho2, dx / rho2
        a00 += w * g0 * g0
        a01 += w * g0 * g1
        a11 += w * g1 * g1
        sel = se[k] * f
        if has[k] and math.isfinite(sel):
            w = 1.0 / sel ** 2
            h0, h1, h2 = -dx * dz / (rho * r2), -dy * dz / (rho * r2), rho / r2
            e00 += w * h0 * h0
            e01 += w * h0 * h1
            e02 += w * h0 * h2
            e11 += w * h1 * h1
            e12 += w * h1 * h2
            e22 += w * h2 * h2
    j00, j01, j02 = a00 + e00, a01 + e01, a02 + e02
    j11, j12, j22 = a11 + e11, a12 + e12, a22 + e22
    if sigma_z == 0.0:
        s, q0, q1 = j22 + 1.0, 0.0, 0.0
    else:
        s, q0, q1 = j22 + 1.0 / sigma_z ** 2, j02, j12
    ok, p00, p01, p11 = _inverse2(j00 - q0 * q0 / s, j01 - q0 * q1 / s, j11 - q1 * q1 / s)
    if not ok:
        return math.inf
    return math.sqrt(max(v0 * p00 * v0 + v0 * p01 * v1 + v1 * p01 * v0 + v1 * p11 * v1,
                         0.0))


#: :func:`.conventions.wrap_angle_scalar` (residuals2's wrap_angle on one angle), compiled.
_wrap_angle = jit(wrap_angle_scalar)


#: :func:`.horizontal_single.inverse2`, compiled.
_inverse2_jit = jit(_inverse2_py)


@jit
def _inverse2(a, b, d):
    """:func:`.horizontal_single.inverse2`: (invertible, i00, i01, i11)."""
    inv = _inverse2_jit(a, b, d)
    if inv is None:
        return False, 0.0, 0.0, 0.0
    i00, i01, i11 = inv
    return True, i00, i01, i11


def calm_grown_one(bs, result, use_el, d_ref, sigma_z):
    """The calm branch of :func:`robust_fix` for one ``wmle`` fix, compiled: the FixResult
    it returns, or None where that branch does not decide (the fix is not ``ok`` or not
    finite, a residual or the χ² is not calm, or a statistic lies within
    :data:`SCREEN_MARGIN` of its threshold, where the array residuals may differ in the last
    bits): then :func:`robust_fix` runs.

    Calm: every d_j² ≤ c² and Σ d_j² ≤ the χ²_dof quantile of CONSISTENCY_PROBABILITY
    (dof = used angles − 2), σ grown by d/d_ref at the fix; then the covariance is widened
    and ν taken as :func:`_grown_assessment` does (``ok`` when ν ≤ max_nonlinearity),
    nothing excluded. ``bs`` one problem, ``use_el`` (N,) bool, ``d_ref`` and ``sigma_z`` m.
    """
    if str(result.status[0]) != STATUS_OK:
        return None
    n_angles = bs.N + int(np.count_nonzero(use_el))
    calm, cov, nu = _calm_grown(plain_array(bs.positions[0]), plain_array(bs.azimuth[0]),
                                plain_array(bs.elevation[0]), plain_array(bs.sigma_az[0]),
                                plain_array(bs.sigma_el[0]), use_el,
                                plain_array(result.position[0]),
                                plain_array(result.covariance[0, :3, :3]),
                                float(d_ref), float(sigma_z), _c2(),
                                _upper_cached(max(n_angles - 2, 1), CONSISTENCY_PROBABILITY),
                                SCREEN_MARGIN)
    if not calm:
        return None
    c = np.array(result.covariance, dtype=float)
    c[0, :3, :3] = cov
    ok = nu <= max_nonlinearity(True)
    # robust_fix's result: _with_nu(_assessed(...), ν, ok), built at once
    return FixResult(result.position, c, result.iterations,
                     result.converged if ok else np.zeros(1, dtype=bool),
                     result.status if ok else np.array([STATUS_LOW_CONFIDENCE]), result.method,
                     excluded=np.zeros((1, bs.N, 2), dtype=bool),
                     nonlinearity=np.array([nu], dtype=float))


@jit_numpy
def _calm_grown(pos, az, el, sa, se, use_el, X, P, d_ref, sigma_z, c2, upper, margin):
    """(calm and decided, widened covariance (3, 3), ν) of :func:`calm_grown_one`; not
    decided where X or P is not finite."""
    for i in range(3):
        if not math.isfinite(X[i]):
            return False, P, math.nan
        for j in range(3):
            if not math.isfinite(P[i, j]):
                return False, P, math.nan
    total = 0.0
    for k in range(pos.shape[0]):
        dx, dy, dz = X[0] - pos[k, 0], X[1] - pos[k, 1], X[2] - pos[k, 2]
        f = math.sqrt(dx * dx + dy * dy + dz * dz) / d_ref
        e = _wrap_angle(az[k] - math.atan2(dy, dx))
        d2 = (e / (sa[k] * f)) ** 2
        if use_el[k]:
            d2 += ((el[k] - math.atan2(dz, math.hypot(dx, dy))) / (se[k] * f)) ** 2
        if not (math.isfinite(d2) and d2 <= c2) or abs(d2 - c2) <= margin * c2:
            return False, P, math.nan
        total += d2
    if not total <= upper or abs(total - upper) <= margin * upper:
        return False, P, math.nan
    n = pos.shape[0]
    cov3 = _inversions(pos, sa, se, use_el, X, P,
                       np.array([TEST_INVERSION_Z, STATUS_REGION_Z, STATUS_REGION_Z]),
                       np.array([False, False, True]), d_ref, sigma_z, 4)
    nu = -math.inf
    for i in (1, 2):
        a, b, c = cov3[i, 0, 0], cov3[i, 0, 1], cov3[i, 1, 1]
        lam = 0.5 * (a + c) + math.sqrt(0.25 * ((a - c) * (a - c)) + b * b)
        rho = math.inf
        for k in range(n):
            r = math.hypot(X[0] - pos[k, 0], X[1] - pos[k, 1])
            rho = r if r < rho else rho
        v = math.sqrt(lam) / rho
        v = v if math.isfinite(v) and lam >= 0.0 else math.nan
        if math.isnan(v) or math.isnan(nu):
            nu = math.nan          # (numpy's max: NaN wins)
        elif v > nu:
            nu = v
    for i in range(3):
        for j in range(3):
            if not math.isfinite(cov3[0, i, j]):
                return True, cov3[0], math.nan
    return True, cov3[0], nu


def _grown_assessment(bs, X, P, kept, use_el, d_ref, sigma_z):
    """(covariance widened to TEST_INVERSION_Z, ν of the region at STATUS_REGION_Z) of a fix
    with range-grown σ (module docstring)."""
    cov, major, out = _test_inversions(
        bs, X, P, kept, use_el, d_ref, sigma_z,
        ((TEST_INVERSION_Z, False), (STATUS_REGION_Z, False), (STATUS_REGION_Z, True)))
    nu = nonlinearity(np.stack([X, X]), np.stack([major, out]), np.stack([bs.positions[0]] * 2),
                      np.stack([kept, kept])).max()
    return cov, (nu if np.all(np.isfinite(cov)) else np.nan)


def _assessed(fix, bs, kept, use_el, d_ref, sigma_z):
    """(``fix`` with its covariance widened for range-grown σ, its ν): ν as the status
    takes it (:func:`_grown_assessment` for range-grown σ, else :func:`nonlinearity`)."""
    x = np.asarray(fix.position[0], dtype=float)
    P = np.asarray(fix.covariance[0, :3, :3], dtype=float)
    if d_ref is None:
        return fix, nonlinearity(x[None], P[None], bs.positions, kept[None])[0]
    cov, nu = _grown_assessment(bs, x, P, kept, use_el, d_ref, sigma_z)
    c = np.array(fix.covariance, dtype=float)
    c[0, :3, :3] = cov
    return FixResult(fix.position, c, fix.iterations, fix.converged, fix.status,
                     fix.method), nu


def _with_nu(fix, nu, ok=True):
    """``fix`` (one problem) carrying ``nonlinearity`` ν; ``low_confidence`` unless ``ok``."""
    if not ok:
        fix = _low_confidence(fix)
    return FixResult(fix.position, fix.covariance, fix.iterations, fix.converged, fix.status,
                     fix.method, nonlinearity=np.array([nu], dtype=float))


def _not_assessed(result):
    """The estimator's fix of one problem, without a refit to assess: ``low_confidence``
    where its position is finite (it failed the screen, or its iteration did not converge:
    ``max_iterations`` at the likelihood's pole on a station, ``diverged``), else
    ``degenerate_geometry`` (no usable fix; NaN position, infinite covariance), as the 3D
    :func:`~bearing_loc_ros.core.robust.confident_result` leaves it."""
    if np.all(np.isfinite(result.position)):
        return _low_confidence(result)
    if str(result.status[0]) == STATUS_DEGENERATE:
        return result
    return FixResult(np.full_like(result.position, np.nan),
                     np.full_like(result.covariance, np.inf), result.iterations,
                     np.zeros(1, dtype=bool), np.array([STATUS_DEGENERATE]), result.method)


def _low_confidence(result):
    """``result`` (one problem) with status ``low_confidence`` and ``converged`` False."""
    return FixResult(result.position, result.covariance, result.iterations,
                     np.zeros(1, dtype=bool), np.array([STATUS_LOW_CONFIDENCE]), result.method)


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


def robust_fix(solve, bs, result, z0, use_el, d_ref=None, sigma_z=0.0):
    """Screened / consensus / refitted horizontal fix of one problem (module docstring).

    ``solve(subset_bearings, initial)`` runs the estimator on a one-problem BearingSet and
    returns its FixResult; ``result`` is its fix of all of ``bs``; z₀ (m) the stated
    altitude and ``sigma_z`` its σ (m); ``use_el`` (N,) the elevations used; ``d_ref`` the
    ``wmle`` reference range (m) or None. Returns (FixResult of one problem, excluded (N,)
    bool).
    """
    N = bs.N
    c2 = _c2()
    x = np.asarray(result.position[0], dtype=float)
    n_angles = N + int(np.count_nonzero(use_el))
    excluded = np.zeros(N, dtype=bool)
    limit = max_nonlinearity(d_ref is not None)
    if str(result.status[0]) == STATUS_OK and np.all(np.isfinite(x)):
        saz, sel = _sigmas(bs, x, d_ref)
        d2 = residuals2(bs, x[None], saz, sel, use_el)[0]
        if np.all(d2 <= c2) and d2.sum() <= chi2_upper(max(n_angles - 2, 1)):
            # Calm: no outlier to look for; ok when the region is well described.
            fix, nu = _assessed(result, bs, ~excluded, use_el, d_ref, sigma_z)
            return _with_nu(fix, nu, nu <= limit), excluded
    cands = pair_candidates(bs, z0)
    if np.all(np.isfinite(x)):
        cands = np.vstack([x[None], cands])
    if cands.shape[0] == 0:
        return _not_assessed(result), excluded
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
        fit = solve(bs.subset(inl), x)
        xn = np.asarray(fit.position[0], dtype=float)
        if not np.all(np.isfinite(xn)):
            break           # the last finite refit stands
        res, excluded, x = fit, ~inl, xn
    if res is None:
        return _not_assessed(result), np.zeros(N, dtype=bool)
    kept = ~excluded
    n_kept = int(np.count_nonzero(kept)) + int(np.count_nonzero(use_el & kept))
    s_az, s_el = _sigmas(bs, x, d_ref)
    d2 = residuals2(bs, x[None], s_az, s_el, use_el)[0]
    P = np.asarray(res.covariance[0, :3, :3], dtype=float)
    if (n_angles - n_kept > (n_angles - 2) // 2
            or not decisive(bs, x, P, excluded, use_el, d_ref)):
        # The data do not identify the excluded bearings as outliers (more than a minority
        # of the redundant angles, or not outliers given the fix's own uncertainty): the
        # estimator's fit of every bearing, low_confidence, nothing excluded.
        none = np.zeros(N, dtype=bool)
        if np.all(np.isfinite(result.position)):
            fix, nu = _assessed(result, bs, ~none, use_el, d_ref, sigma_z)
            return _with_nu(fix, nu, ok=False), none
        return _not_assessed(result), none
    res, nu = _assessed(res, bs, kept, use_el, d_ref, sigma_z)
    consistent = (d2[kept].sum() <= chi2_upper(max(n_kept - 2, 1), CONSISTENCY_PROBABILITY)
                  and nu <= limit)
    # A refit whose iteration did not converge (max_iterations, diverged) is low_confidence.
    return _with_nu(res, nu, str(res.status[0]) == STATUS_OK and consistent), excluded
