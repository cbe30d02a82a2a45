"""Confidence and robustness of a maximum likelihood fix: consensus, full likelihood, status.

One mechanism serves three purposes: low-SNR bearings (no range run-away, an honest status),
outlier bearings (multipath: tens of degrees off) and a station whose σ claim is wrong (the
fusion's per-station trust, :mod:`~bearing_loc_ros.core.station_trust`, feeds it σ it does
not take on trust). It runs after the Gauss-Newton maximum likelihood estimate X̂ of
Zong & Cui 2015 eqs. (3)-(11) (``mle``, ``wmle``):

1. **Screen** (cheap, every converged fix with constant σ). With the σ the estimator
   assumes at X̂, the whitened residuals r_j = e_j / σ_j of the M_meas angles are computed.
   The fix is kept as it is when every |r_j| ≤ c (c² = χ²₁ quantile of
   :data:`OUTLIER_PROBABILITY`), the residual χ² = Σ r_j² lies inside the two-sided χ²_dof
   band (dof = M_meas − 3) and the nonlinearity ν (below) is at most
   :data:`MAX_REGION_NONLINEARITY`. At high SNR this is every fix but a fraction of 1e-3, so
   the estimator stays the efficient ML of the paper. A fix the estimator did not converge
   on (``max_iterations``, ``diverged``: a run-away in range) always goes on to step 2, and
   with range-grown σ (``wmle``, σ_j = σ_ref,j d_k / d_ref, eqs. (9)-(10)) every fix does.
2. **Consensus**. Candidate points: X̂, the pseudo-linear ``ls`` fix of all bearings
   (Wang, Zhang & Wu eq. (4)) and the ``ls`` fixes leaving out one station and, for N ≥ 5,
   every pair of stations. Each is scored by the truncated (mixture) negative
   log-likelihood S(X) = Σ_j min(r_j², c²) + Σ_{inliers} log σ_j², the MSAC score (Torr &
   Zisserman 2000) with the log σ term of the exact Gaussian likelihood, so that a
   range-grown σ cannot buy a small score by running away in range. The best candidate
   starts step 3.
3. **Refit.** Maximum likelihood on the inliers (|r_j| ≤ c), Levenberg-Marquardt on the
   *full* negative log-likelihood L(X) = Σ_j w_j (r_j² + log σ_j²), w_j ∈ {0, 1}: for
   ``wmle`` the log σ(d) term the paper's cost omits is included, whose absence makes the
   paper's cost fall toward 0 as the range grows (an attractor at infinity). Inliers are
   recomputed at the new estimate and the fit repeated until the set is stable (at most
   :data:`REFIT_ROUNDS`). A bearing is called an outlier only when no fit of all the
   bearings passes the residual χ² test (:func:`_prefer_all_bearings`): at low SNR a subset
   can fit a wrong point near the stations, where range-grown σ are small. Excluded
   bearings are reported per angle.
4. **Assess** (every fix that went through steps 2-3). The covariance is the inverse
   Fisher information over the inliers at the estimate; for range-grown σ it is widened
   along its major axis to the far side of the test-inversion region
   (:func:`test_inversion_covariance`): the covariance at the estimate understates the
   region toward larger range, where σ(d) is larger. The fix is ``ok`` only when (a) the
   residual χ² ≤ the χ²_dof quantile of :data:`CONSISTENCY_PROBABILITY`, (b) ν ≤
   :func:`max_nonlinearity`, (c) at most ⌊(M_meas − 3)/2⌋ angles were excluded and (d) every
   exclusion is decisive: the excluded angle is an outlier also given the fix's own
   uncertainty, r² / (1 + gᵀPg) > the χ²₁ quantile of :data:`DECISIVE_PROBABILITY`, g the
   whitened gradient. Otherwise ``low_confidence`` (position and covariance kept,
   ``converged`` False).

Nonlinearity ν = sqrt(λ_max(P)) / min_k d_k (:func:`region_nonlinearity`): the radius of
the confidence region seen from the nearest station, relative to its range. The angles are
functions of X / d_k, so their second-order terms over the confidence region are ν times
the first-order ones (the parameter-effects curvature of Bates & Watts 1980 for a bearing);
with ν small the error ellipsoid describes the confidence region, with ν large the region
is a banana elongated in range and a Gaussian covariance understates its tail.

With range-grown σ, ν is computed from the widened covariance (step 4): computed at the
estimate alone, it selects at large σ the fixes that landed short in range (where σ(d)
and hence ν are small), and those were the confidently wrong ones.

Calibration (``bench/low_snr.py --acceptance``, 2000 trials per σ, joint, azimuth and
elevation sweeps): the largest ν bound at which the ``ok`` fixes' confident-wrong share
(Mahalanobis error above the χ²₃ 0.9999 quantile) stays at the level it has for small ν.
Constant σ (six stations, σ 1°-5°): 0.2 (ok share at 5° 33 % with 0.1, 99.7 % with 0.2,
the confident-wrong share unchanged at 0-3 fixes in 2000). Range-grown σ (Zong & Cui 2015
scenario, σ_ref 0.5°-5°): 0.1 (with 0.12 or 0.15 the failures of either criterion grow
from 3 to 5 and 13 of the 24 sweep points). The test-inversion level z = 2
(:data:`TEST_INVERSION_Z`) brought the ok fixes' mean NEES to 3 ± its 99 % band at
σ_ref ≥ 1°; larger z over-covers the bulk (mean NEES 2.3-2.5 at z = 4.6), and without
the widening the mean NEES was 3.5-3.9 at σ_ref ≥ 1°.

Units: m, rad; ENU, azimuth θ CCW from East, elevation ψ above the horizontal.
"""

from functools import lru_cache
from itertools import combinations
import math

import numpy as np
from scipy.stats import chi2 as _chi2

from .crlb import safe_inverse

#: Probability of the per-angle outlier threshold c² = χ²₁ quantile (3.89 σ).
OUTLIER_PROBABILITY = 0.9999
#: Probability of the residual χ² consistency test of an ``ok`` fix.
CONSISTENCY_PROBABILITY = 0.999
#: Largest range σ / range (:func:`nonlinearity`) accepted by callers of that function.
MAX_NONLINEARITY = 0.1
#: Largest nonlinearity ν (:func:`region_nonlinearity`) of an ``ok`` fix, constant σ
#: (``mle``); calibrated by measurement (module docstring).
MAX_REGION_NONLINEARITY = 0.2
#: The same for range-grown σ (``wmle``).
MAX_REGION_NONLINEARITY_GROWN = 0.1
#: An excluded angle must be an outlier also given the fix's uncertainty: its predictive
#: residual r² / (1 + gᵀPg) must exceed the χ²₁ quantile of this probability (4.9 σ).
DECISIVE_PROBABILITY = 1.0 - 1e-6
#: Level z of the test-inversion covariance along the range axis (range-grown σ).
TEST_INVERSION_Z = 2.0
#: Rounds of inlier recomputation and refit.
REFIT_ROUNDS = 3
#: Levenberg-Marquardt iterations per refit.
REFIT_ITERATIONS = 40


@lru_cache(maxsize=16)
def _c2(p=OUTLIER_PROBABILITY):
    return float(_chi2.ppf(p, 1))


def max_nonlinearity(grown):
    """Largest ν of an ``ok`` fix: range-grown σ (``grown`` True) or constant σ."""
    return MAX_REGION_NONLINEARITY_GROWN if grown else MAX_REGION_NONLINEARITY


class Data:
    """Per-angle arrays of M problems of N bearings (the σ are σ_ref for range growth).

    ``pos`` (M, N, 3) m; ``az``, ``el`` (M, N) rad (el 0 where absent); ``ia``, ``ie``
    (M, N) inverse σ_ref, 1/rad (ie 0 where there is no elevation); ``d_ref`` m or None.
    """

    def __init__(self, bearings, d_ref=None):
        self.pos = bearings.positions
        has_el = bearings.has_elevation
        self.az = bearings.azimuth
        self.el = np.where(has_el, bearings.elevation, 0.0)
        self.ia = 1.0 / bearings.sigma_az
        self.ie = np.where(has_el, 1.0 / np.where(has_el, bearings.sigma_el, 1.0), 0.0)
        self.has_el = has_el
        self.d_ref = None if d_ref is None else float(d_ref)

    def take(self, idx):
        """The problems ``idx`` only."""
        out = object.__new__(Data)
        for k in ('pos', 'az', 'el', 'ia', 'ie', 'has_el'):
            setattr(out, k, getattr(self, k)[idx])
        out.d_ref = self.d_ref
        return out

    def evaluate(self, X):
        """Whitened residuals and gradients at X (M, 3) (or (M, K, 3) candidates).

        Returns ra, re (…, N) whitened residuals r = (measured − predicted)/σ (azimuth
        wrapped to (−π, π]); ga, ge (…, N, 3) whitened gradients ∇h/σ, 1/m (the angle
        gradients of Zong & Cui 2015 eq. (6)); u (…, N, 3) unit lines of sight; d (…, N)
        ranges, m; log_s2 (…, N) log σ_j² up to a constant (2 log(d/d_ref) with range
        growth, 0 otherwise).
        """
        if X.ndim == 3:              # (M, K, 3) candidates: broadcast over K
            pos, az, el = self.pos[:, None], self.az[:, None], self.el[:, None]
            ia, ie = self.ia[:, None], self.ie[:, None]
        else:
            pos, az, el, ia, ie = self.pos, self.az, self.el, self.ia, self.ie
        with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
            dv = X[..., None, :] - pos
            dx, dy, dz = dv[..., 0], dv[..., 1], dv[..., 2]
            rho2 = dx * dx + dy * dy
            r2 = rho2 + dz * dz
            rho = np.sqrt(rho2)
            d = np.sqrt(r2)
            e_az = az - np.arctan2(dy, dx)
            e_az -= 2.0 * np.pi * np.ceil((e_az - np.pi) / (2.0 * np.pi))
            e_el = el - np.arctan2(dz, rho)
            if self.d_ref is not None:
                f = self.d_ref / d
                ia, ie = ia * f, ie * f
                log_s2 = 2.0 * np.log(d / self.d_ref)
            else:
                log_s2 = np.zeros_like(d)
            ra, re = ia * e_az, ie * e_el
            ga = np.stack([-dy, dx, np.zeros_like(dx)], axis=-1) * (ia / rho2)[..., None]
            t = dz / (rho * r2)
            ge = np.stack([-dx * t, -dy * t, rho / r2], axis=-1) * ie[..., None]
            u = dv / d[..., None]
        return ra, re, ga, ge, u, d, log_s2


def whitened_residuals(bearings, X, d_ref=None):
    """(ra, re) (M, N): residuals / σ at X (M, 3), σ grown with range when ``d_ref`` is set.

    re is 0 for azimuth-only bearings. Zong & Cui 2015 eq. (5) with W of eq. (4) or (11).
    """
    ra, re, *_ = Data(bearings, d_ref).evaluate(np.asarray(X, dtype=float))
    return ra, re


def fisher(ga, ge, wa, we):
    """Fisher information Σ_j w_j g_j g_jᵀ (…, 3, 3), 1/m², of the (weighted) angles."""
    return (np.einsum('...n,...ni,...nj->...ij', wa, ga, ga)
            + np.einsum('...n,...ni,...nj->...ij', we, ge, ge))


def nonlinearity(P, u, d, present):
    """ν = max_k sqrt(u_kᵀ P u_k) / d_k over stations ``present`` (…, N); NaN if none.

    P (…, 3, 3) m², u (…, N, 3) unit lines of sight, d (…, N) ranges, m (module docstring).
    """
    with np.errstate(invalid='ignore', divide='ignore'):
        v = np.einsum('...ni,...ij,...nj->...n', u, P, u)
        nu = np.sqrt(np.maximum(v, 0.0)) / d
    nu = np.where(present, nu, -np.inf)
    out = nu.max(axis=-1)
    return np.where(np.isfinite(out), out, np.nan)


def region_nonlinearity(P, d, present):
    """ν = sqrt(λ_max(P)) / min_k d_k over stations ``present`` (…, N); NaN if none.

    P (…, 3, 3) m², d (…, N) ranges, m. The angular radius of the confidence region seen
    from the nearest station (module docstring); NaN where P is not finite.
    """
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    lam = np.linalg.eigvalsh(np.where(finite[..., None, None], P, 0.0))[..., -1]
    dmin = np.where(present, d, np.inf).min(axis=-1)
    with np.errstate(invalid='ignore', divide='ignore'):
        nu = np.sqrt(np.maximum(lam, 0.0)) / dmin
    return np.where(finite & np.isfinite(nu), nu, np.nan)


def test_inversion_covariance(data, X, wa, we, P, z=TEST_INVERSION_Z, iterations=4):
    """P widened along its major axis to the far side of the test-inversion region, m².

    With range-grown σ the covariance P(X) = (Σ w g gᵀ)⁻¹ at a point X grows with its range.
    The confidence region of the truth is {X: (X̂ − X)ᵀ P(X)⁻¹ (X̂ − X) ≤ z²}, the points whose
    own covariance puts the estimate X̂ within z σ. Along the major axis v of P(X̂) (oriented
    away from the stations) its far boundary t solves t = z s(X̂ + t v), s(X)² = vᵀ P(X) v,
    by fixed-point iteration from t = z s(X̂), t at most 10 times the largest station range
    (where the region has no far boundary the fix is not ``ok`` anyway: its ν is large).
    The variance along v becomes max(s(X̂)², (t / z)²); P is unchanged across v.
    """
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    Pf = np.where(finite[:, None, None], P, 0.0)
    _, V = np.linalg.eigh(Pf)
    v = V[..., -1]
    _, _, _, _, u, d, _ = data.evaluate(X)
    t_max = 10.0 * np.max(np.where(np.isfinite(d), d, 0.0), axis=-1)
    out = np.sum(u * ((wa + we) > 0)[..., None], axis=1)
    v = v * np.where(np.sum(v * out, axis=-1) < 0, -1.0, 1.0)[:, None]
    s0 = np.sqrt(np.maximum(np.einsum('mi,mij,mj->m', v, Pf, v), 0.0))
    t = z * s0
    for _ in range(iterations):
        _, _, ga, ge, _, _, _ = data.evaluate(X + t[:, None] * v)
        Pt = safe_inverse(fisher(ga, ge, wa, we))
        st = np.sqrt(np.maximum(np.einsum('mi,mij,mj->m', v, Pt, v), 0.0))
        t = np.where(np.isfinite(st), np.minimum(z * st, t_max), t_max)
    add = np.maximum((t / z) ** 2 - s0 * s0, 0.0)
    with np.errstate(invalid='ignore'):
        Pw = P + add[:, None, None] * np.einsum('mi,mj->mij', v, v)
    bad = ~finite | ~np.isfinite(add)
    return np.where(bad[:, None, None], np.inf, Pw)


def chi2_band(dof, probability=CONSISTENCY_PROBABILITY):
    """(lower, upper) quantiles of χ²_dof: (1 − p)/2 and (1 + p)/2 (dof ≥ 1; (0, inf) else)."""
    dof = np.asarray(dof)
    ok = dof >= 1
    safe = np.where(ok, dof, 1)
    lo = np.where(ok, _chi2.ppf(0.5 * (1.0 - probability), safe), 0.0)
    hi = np.where(ok, _chi2.ppf(0.5 * (1.0 + probability), safe), np.inf)
    return lo, hi


def chi2_upper(dof, probability=CONSISTENCY_PROBABILITY):
    """The ``probability`` quantile of χ²_dof (inf for dof < 1: nothing to test)."""
    dof = np.asarray(dof)
    ok = dof >= 1
    return np.where(ok, _chi2.ppf(probability, np.where(ok, dof, 1)), np.inf)


def _ls_candidates(data, masks):
    """Pseudo-linear LS (Wang, Zhang & Wu eq. (4)) for station masks (K, N) -> (M, K, 3)."""
    az, el, has = data.az, data.el, data.has_el
    s, c = np.sin(az), np.cos(az)
    sp, cp = np.sin(el), np.cos(el)
    m = has.astype(float)
    rows = np.stack([np.stack([s, -c, np.zeros_like(s)], -1),
                     np.stack([m * c * sp, m * s * sp, -m * cp], -1)], axis=-2)  # (M,N,2,3)
    y = np.einsum('mnkj,mnj->mnk', rows, data.pos)
    A = np.einsum('mnki,mnkj->mnij', rows, rows)
    b = np.einsum('mnki,mnk->mni', rows, y)
    Ak = np.einsum('kn,mnij->mkij', masks, A)
    bk = np.einsum('kn,mni->mki', masks, b)
    inv = safe_inverse(Ak.reshape(-1, 3, 3)).reshape(Ak.shape)
    return np.einsum('mkij,mkj->mki', inv, bk)


def _station_masks(N):
    """Station subsets of the consensus: all, leave one out, leave two out (N ≥ 5)."""
    rows = [np.ones(N)]
    for k in range(N):
        m = np.ones(N)
        m[k] = 0.0
        rows.append(m)
    if N >= 5:
        for i, j in combinations(range(N), 2):
            m = np.ones(N)
            m[[i, j]] = 0.0
            rows.append(m)
    return np.array(rows)


def _score(data, X, c2):
    """MSAC score with the log σ² of the inliers (module docstring step 2), (M, K)."""
    ra, re, _, _, _, _, log_s2 = data.evaluate(X)
    has = data.has_el if X.ndim == 2 else data.has_el[:, None]
    qa, qe = ra * ra, np.where(has, re * re, 0.0)
    ina, ine = qa <= c2, has & (qe <= c2)
    s = (np.minimum(qa, c2) + np.minimum(qe, c2) + log_s2 * (ina + ine.astype(float)))
    s = s.sum(axis=-1)
    return np.where(np.isfinite(s), s, np.inf)


def _refit(data, X0, wa, we, iterations=REFIT_ITERATIONS):
    """Levenberg-Marquardt on L(X) = Σ w_j (r_j² + log σ_j²) over M problems -> X (M, 3).

    Fisher scoring step: (F + λ diag F) Δ = −½∇L with F = Σ w_j g_j g_jᵀ (+ Σ w_j 2 u uᵀ/d²,
    the information of σ(d) under range growth), ½∇L = Σ_j w_j [−r_j g_j + (1 − r_j²) u_k/d_k]
    with range growth (the σ(d) and log σ(d) derivatives) and −Σ w_j r_j g_j without. A step
    is taken when L does not increase; λ ×10 on rejection, ÷10 on acceptance. A problem
    stops when its step is below 1e-10 of its rms range or λ > 1e10 (each problem on its
    own: the result does not depend on the other problems of the batch).
    """
    grow = data.d_ref is not None
    X = X0.copy()
    lam = np.zeros(X.shape[0])
    done = np.zeros(X.shape[0], dtype=bool)

    def parts(X):
        ra, re, ga, ge, u, d, log_s2 = data.evaluate(X)
        cost = (wa * (ra * ra + log_s2) + we * (re * re + log_s2)).sum(axis=-1)
        return cost, ra, re, ga, ge, u, d

    cost, ra, re, ga, ge, u, d = parts(X)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    for _ in range(iterations):
        F = fisher(ga, ge, wa, we)
        grad = -(np.einsum('mn,mni->mi', wa * ra, ga) + np.einsum('mn,mni->mi', we * re, ge))
        if grow:
            k = (wa * (1.0 - ra * ra) + we * (1.0 - re * re)) / d
            grad = grad + np.einsum('mn,mni->mi', k, u)
            F = F + np.einsum('mn,mni,mnj->mij', 2.0 * (wa + we) / (d * d), u, u)
        diag = np.einsum('mii->mi', F)
        Fd = F + lam[:, None, None] * np.einsum('mi,ij->mij', diag, np.eye(3))
        with np.errstate(all='ignore'):
            try:
                step = -np.linalg.solve(Fd, grad[..., None])[..., 0]
            except np.linalg.LinAlgError:
                step = -np.einsum('mij,mj->mi', safe_inverse(Fd), grad)
        step = np.where(np.isfinite(step), step, 0.0)
        Xt = X + step
        ct, rat, ret, gat, get, ut, dt = parts(Xt)
        acc = np.isfinite(ct) & (ct <= cost) & ~done
        X = np.where(acc[:, None], Xt, X)
        cost = np.where(acc, ct, cost)
        ra, re = np.where(acc[:, None], rat, ra), np.where(acc[:, None], ret, re)
        ga = np.where(acc[:, None, None], gat, ga)
        ge = np.where(acc[:, None, None], get, ge)
        u = np.where(acc[:, None, None], ut, u)
        d = np.where(acc[:, None], dt, d)
        lam = np.where(done, lam,
                       np.where(acc, 0.1 * lam * (lam > 1e-6), np.maximum(10.0 * lam, 1e-3)))
        scale = np.sqrt(np.mean(d * d, axis=-1))
        done |= (np.linalg.norm(step, axis=-1) <= 1e-10 * scale) | (lam > 1e10)
        if np.all(done):
            break
    return X


def _inliers(data, X, c2):
    ra, re, *_ = data.evaluate(X)
    wa = (ra * ra <= c2).astype(float)
    we = (data.has_el & (re * re <= c2)).astype(float)
    return wa, we


def _solvable(data, wa, we):
    """At least two stations with a kept angle, one kept elevation, three kept angles."""
    st = ((wa + we) > 0).sum(axis=-1)
    return (st >= 2) & (we.sum(axis=-1) >= 1) & ((wa + we).sum(axis=-1) >= 3)


def consensus_fit(data, X_ml, c2=None):
    """Steps 2-3 of the module docstring for M problems: (X (M, 3), wa, we (M, N)).

    ``X_ml`` (M, 3) is the estimator's own fix (a candidate; NaN allowed). wa, we are the
    inlier indicators of the azimuths and elevations (1 kept, 0 excluded).
    """
    c2 = _c2() if c2 is None else c2
    M, N = data.az.shape
    masks = _station_masks(N)
    cand = _ls_candidates(data, masks)                       # (M, K, 3)
    cand = np.concatenate([np.where(np.isfinite(X_ml), X_ml, np.nan)[:, None], cand], axis=1)
    score = _score(data, np.where(np.isfinite(cand), cand, 0.0), c2)
    score = np.where(np.all(np.isfinite(cand), axis=-1), score, np.inf)
    best = np.argmin(score, axis=1)
    X = cand[np.arange(M), best]
    X = np.where(np.isfinite(X), X, 0.0)
    wa, we = _inliers(data, X, c2)
    active = np.arange(M)
    for _ in range(REFIT_ROUNDS):
        # Only problems whose inlier set changed are refitted again (each problem's result
        # is independent of the batch it is in).
        sub = data.take(active)
        a, e = wa[active], we[active]
        good = _solvable(sub, a, e)
        a = np.where(good[:, None], a, 1.0)
        e = np.where(good[:, None], e, sub.has_el.astype(float))
        Xa = _refit(sub, X[active], a, e)
        na, ne = _inliers(sub, Xa, c2)
        solvable = _solvable(sub, na, ne)[:, None]
        na, ne = np.where(solvable, na, a), np.where(solvable, ne, e)
        same = np.all((na == a) & (ne == e), axis=-1)
        X[active], wa[active], we[active] = Xa, na, ne
        active = active[~same]
        if not active.size:
            break
    return _prefer_all_bearings(data, X, wa, we, X_ml, cand[:, 1])


def _cost(data, X, wa, we):
    """Full negative log-likelihood L(X) = Σ w_j (r_j² + log σ_j²) (module docstring step 3)."""
    ra, re, _, _, _, _, log_s2 = data.evaluate(X)
    c = (wa * (ra * ra + log_s2) + we * (re * re + log_s2)).sum(axis=-1)
    return np.where(np.isfinite(c), c, np.inf)


def _prefer_all_bearings(data, X, wa, we, X_ml, X_ls):
    """Keep every bearing when a consistent fit of all of them exists (steps 2-3).

    A bearing is called an outlier only when no fit of *all* the bearings passes the
    residual χ² test: for the problems with an excluded angle, the full likelihood of all
    angles is refitted from the estimator's fix and from the all-station ``ls`` fix, the
    better one kept; if its χ² ≤ the χ²_dof quantile of :data:`CONSISTENCY_PROBABILITY` it
    replaces the fit with exclusions. (At low SNR a subset can fit a wrong point closer to
    the stations, where range-grown σ are small, and exclude the good bearings that
    contradict it.)
    """
    has = data.has_el
    exc = np.any(wa == 0, axis=-1) | np.any(has & (we == 0), axis=-1)
    idx = np.flatnonzero(exc)
    if not idx.size:
        return X, wa, we
    sub = data.take(idx)
    ones = np.ones_like(sub.az)
    she = sub.has_el.astype(float)
    best, cost = None, None
    for start in (X_ml[idx], X_ls[idx]):
        good = np.all(np.isfinite(start), axis=-1)
        Xs = _refit(sub, np.where(good[:, None], start, X[idx]), ones, she)
        cs = np.where(good, _cost(sub, Xs, ones, she), np.inf)
        if best is None:
            best, cost = Xs, cs
        else:
            better = cs < cost
            best = np.where(better[:, None], Xs, best)
            cost = np.where(better, cs, cost)
    ra, re, *_ = sub.evaluate(best)
    chi2 = (ra * ra + she * re * re).sum(axis=-1)
    dof = sub.az.shape[1] + sub.has_el.sum(axis=-1) - 3
    use = np.isfinite(cost) & (chi2 <= chi2_upper(dof))
    if use.any():
        X, wa, we = X.copy(), wa.copy(), we.copy()
        k = idx[use]
        X[k] = best[use]
        wa[k] = 1.0
        we[k] = has[k].astype(float)
    return X, wa, we


def assess(data, X, wa, we, probability=CONSISTENCY_PROBABILITY, max_nu=None):
    """Step 4 of the module docstring: (covariance (M, 3, 3), ok (M,), chi2, dof, ν).

    ``ok``: χ² ≤ the χ²_dof ``probability`` quantile, ν ≤ ``max_nu`` (default
    :func:`max_nonlinearity`), at most ⌊(M_meas − 3)/2⌋ angles excluded, and every
    excluded angle decisive (predictive residual r² / (1 + gᵀPg) above the χ²₁ quantile of
    :data:`DECISIVE_PROBABILITY`). The covariance is (Σ w g gᵀ)⁻¹, m², for range-grown σ
    widened by :func:`test_inversion_covariance`.
    """
    grown = data.d_ref is not None
    max_nu = max_nonlinearity(grown) if max_nu is None else max_nu
    ra, re, ga, ge, u, d, _ = data.evaluate(X)
    P = safe_inverse(fisher(ga, ge, wa, we))
    chi2 = (wa * ra * ra + we * re * re).sum(axis=-1)
    n_kept = (wa + we).sum(axis=-1)
    n_all = data.az.shape[1] + data.has_el.sum(axis=-1)
    dof = (n_kept - 3).astype(int)
    present = (wa + we) > 0
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    Pf = np.where(finite[:, None, None], P, 0.0)
    with np.errstate(invalid='ignore', divide='ignore'):
        qa = ra * ra / (1.0 + np.einsum('mni,mij,mnj->mn', ga, Pf, ga))
        qe = re * re / (1.0 + np.einsum('mni,mij,mnj->mn', ge, Pf, ge))
    cd = _c2(DECISIVE_PROBABILITY)
    marginal = ((wa == 0) & ~(qa > cd)) | ((we == 0) & data.has_el & ~(qe > cd))
    if grown:
        P = test_inversion_covariance(data, X, wa, we, P)
    nu = region_nonlinearity(P, d, present)
    excluded = n_all - n_kept
    ok = ((chi2 <= chi2_upper(dof, probability)) & (nu <= max_nu)
          & (excluded <= np.floor((n_all - 3) / 2.0)) & ~marginal.any(axis=-1)
          & np.all(np.isfinite(P), axis=(-2, -1)))
    return P, ok, chi2, dof, nu


def screen(data, X, P, probability=CONSISTENCY_PROBABILITY, c2=None, max_nu=None):
    """Step 1: (M,) True where the fix needs the consensus and refit (module docstring)."""
    c2 = _c2() if c2 is None else c2
    max_nu = max_nonlinearity(data.d_ref is not None) if max_nu is None else max_nu
    ra, re, _, _, _, d, _ = data.evaluate(X)
    qa, qe = ra * ra, re * re
    chi2 = (qa + qe).sum(axis=-1)
    dof = data.az.shape[1] + data.has_el.sum(axis=-1) - 3
    lo, hi = chi2_band(dof, probability)
    nu = region_nonlinearity(P, d, np.ones_like(d, dtype=bool))
    calm = ((qa.max(axis=-1) <= c2) & (qe.max(axis=-1) <= c2) & (chi2 >= lo) & (chi2 <= hi)
            & (nu <= max_nu))
    return ~calm


def screen_one(bearings, x, d_ref, P, c2=None, probability=CONSISTENCY_PROBABILITY,
               max_nu=None):
    """:func:`screen` for one problem on Python floats (the fusion's one-fix path).

    ``x`` (3,) m, ``P`` (3, 3) m² (array or nested lists); True when the fix needs the
    consensus and refit. The same decisions as :func:`screen` (tested).
    """
    c2 = _c2() if c2 is None else c2
    max_nu = max_nonlinearity(d_ref is not None) if max_nu is None else max_nu
    pos = bearings.positions[0].tolist()
    az = bearings.azimuth[0].tolist()
    el = bearings.elevation[0].tolist()
    sa = bearings.sigma_az[0].tolist()
    se = bearings.sigma_el[0].tolist()
    x0, x1, x2 = x
    chi2 = 0.0
    n = 0
    dmin = math.inf
    for (px, py, pz), a, e, s1, s2 in zip(pos, az, el, sa, se):
        dx, dy, dz = x0 - px, x1 - py, x2 - pz
        rho = math.hypot(dx, dy)
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        f = d / d_ref if d_ref is not None else 1.0
        ea = a - math.atan2(dy, dx)
        ea -= 2.0 * math.pi * math.ceil((ea - math.pi) / (2.0 * math.pi))
        q = (ea / (s1 * f)) ** 2
        if q > c2:
            return True
        chi2 += q
        n += 1
        if e == e:
            q = ((e - math.atan2(dz, rho)) / (s2 * f)) ** 2
            if q > c2:
                return True
            chi2 += q
            n += 1
        dmin = min(dmin, d)
    lo, hi = _band_cached(n - 3, probability)
    if not lo <= chi2 <= hi:
        return True
    lam = _lambda_max(P.tolist() if hasattr(P, 'tolist') else P)
    return not math.sqrt(max(lam, 0.0)) <= max_nu * dmin


def _lambda_max(p):
    """Largest eigenvalue of a symmetric 3 × 3 matrix (nested lists), closed form.

    The trigonometric solution of the characteristic cubic (Smith 1961): with q = tr/3,
    B = (A − qI)/r, r² = tr((A − qI)²)/6, λ_max = q + 2r cos(acos(det B / 2) / 3).
    NaN for a non-finite matrix.
    """
    a, b, c = p[0][0], p[1][1], p[2][2]
    d, e, f = p[0][1], p[1][2], p[0][2]
    off = d * d + e * e + f * f
    q = (a + b + c) / 3.0
    if off == 0.0:
        return max(a, b, c)
    aa, bb, cc = a - q, b - q, c - q
    r = math.sqrt((aa * aa + bb * bb + cc * cc + 2.0 * off) / 6.0)
    if not r > 0.0:
        return q if r == 0.0 else math.nan
    det = (aa * (bb * cc - e * e) - d * (d * cc - e * f) + f * (d * e - bb * f)) / r ** 3
    phi = math.acos(min(1.0, max(-1.0, det / 2.0))) / 3.0
    return q + 2.0 * r * math.cos(phi)


_BANDS = {}


def _band_cached(dof, probability):
    key = (dof, probability)
    if key not in _BANDS:
        lo, hi = chi2_band(dof, probability)
        _BANDS[key] = (float(lo), float(hi))
    return _BANDS[key]


def confident_result(result, bearings, d_ref=None):
    """The estimator's FixResult after screen, consensus, refit and assessment (module doc).

    ``result``: an ``mle`` (``d_ref`` None) or ``wmle`` (``d_ref`` = reference range, m)
    FixResult of ``bearings``. Problems of status ``degenerate_geometry`` are returned
    unchanged. Every ``ok``, ``max_iterations`` or ``diverged`` problem ends ``ok`` or
    ``low_confidence`` with a finite position, or ``degenerate_geometry`` when no usable
    fix exists; ``excluded`` (M, N, 2) and
    ``nonlinearity`` (M,) are filled. A problem that passes the screen keeps the
    estimator's own position, covariance and status.
    """
    from .fix import (FixResult, STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_LOW_CONFIDENCE,
                      STATUS_MAX_ITERATIONS, STATUS_OK)
    M, N = bearings.M, bearings.N
    if M == 1 and d_ref is None and str(result.status[0]) == STATUS_OK:
        # One calm fix (the fusion's and locate's usual case): screened on Python floats and
        # returned as it is, without the array bookkeeping below (same result).
        x = result.position[0].tolist()
        P = result.covariance[0].tolist()
        if all(map(math.isfinite, x)) and all(map(math.isfinite, P[0] + P[1] + P[2])) \
                and not screen_one(bearings, x, None, P):
            return FixResult(result.position, result.covariance, result.iterations,
                             result.converged, result.status, result.method,
                             excluded=np.zeros((1, N, 2), dtype=bool),
                             nonlinearity=np.full(1, np.nan))
    pos = np.array(result.position, dtype=float)
    cov = np.array(result.covariance, dtype=float)
    status = np.array(result.status, dtype=object)
    conv = np.array(result.converged, dtype=bool)
    excluded = np.zeros((M, N, 2), dtype=bool)
    nu = np.full(M, np.nan)
    usable = np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
    if d_ref is not None:
        # Range-grown σ: the paper's cost has its attractor at infinite range, so every fix
        # is refitted on the full likelihood (the screen would keep the paper's estimate).
        trigger = np.ones(M, dtype=bool)
    elif M == 1 and usable[0] and status[0] == STATUS_OK:
        trigger = np.array([screen_one(bearings, pos[0].tolist(), d_ref, cov[0])])
    else:
        data = Data(bearings, d_ref)
        trigger = np.ones(M, dtype=bool)
        calm_idx = np.flatnonzero(usable & (status == STATUS_OK))
        if calm_idx.size:
            sub = data.take(calm_idx)
            trigger[calm_idx] = screen(sub, pos[calm_idx], cov[calm_idx])
    # A fix the estimator did not converge on (max_iterations, diverged: typically a run-away
    # in range) always goes to the consensus, with its own position as one candidate when
    # finite; degenerate geometry stays as it is.
    trigger = np.where(status == STATUS_OK, trigger & usable,
                       (status == STATUS_MAX_ITERATIONS) | (status == STATUS_DIVERGED))
    idx = np.flatnonzero(trigger)
    if idx.size:
        data = Data(bearings, d_ref).take(idx)
        start = np.where(np.all(np.isfinite(pos[idx]), axis=1)[:, None], pos[idx], np.nan)
        X, wa, we = consensus_fit(data, start)
        P, ok, _, _, nux = assess(data, X, wa, we)
        finite = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
        # No finite refit (e.g. a target far beyond the baseline): the estimator's own
        # finite fix is kept, as low_confidence, without exclusions.
        own = ~finite & usable[idx]
        keep = finite | own
        pos[idx] = np.where(finite[:, None], X, np.where(own[:, None], pos[idx], np.nan))
        cov[idx] = np.where(finite[:, None, None], P,
                            np.where(own[:, None, None], cov[idx], np.inf))
        ok &= finite
        status[idx] = np.where(keep, np.where(ok, STATUS_OK, STATUS_LOW_CONFIDENCE),
                               STATUS_DEGENERATE)
        conv[idx] = ok
        excluded[idx, :, 0] = finite[:, None] & (wa == 0)
        excluded[idx, :, 1] = finite[:, None] & data.has_el & (we == 0)
        nu[idx] = np.where(finite, nux, np.nan)
    return FixResult(pos, cov, result.iterations, conv, status.astype(str), result.method,
                     excluded=excluded, nonlinearity=nu)
