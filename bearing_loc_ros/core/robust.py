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
   every pair of stations (above :data:`.robust_consensus.MAX_SUBSET_STATIONS` stations:
   the ``ls`` fixes of the pairs among that many spread evenly over the set). Each is
   scored by the truncated (mixture) negative log-likelihood S(X) = Σ_j min(r_j², c²) +
   Σ_{inliers} log σ_j², the MSAC score (Torr & Zisserman 2000) with the log σ term of the
   exact Gaussian likelihood, so that a
   range-grown σ cannot buy a small score by running away in range. The best candidate
   starts step 3.
3. **Refit.** Maximum likelihood on the inliers (|r_j| ≤ c), Levenberg-Marquardt on the
   *full* negative log-likelihood L(X) = Σ_j w_j (r_j² + log σ_j²), w_j ∈ {0, 1}: for
   ``wmle`` the log σ(d) term the paper's cost omits is included, whose absence makes the
   paper's cost fall toward 0 as the range grows (an attractor at infinity). Inliers are
   recomputed at the new estimate and the fit repeated until the set is stable (at most
   :data:`REFIT_ROUNDS`). A bearing is called an outlier only when no fit of all the
   bearings passes the residual χ² test (:func:`.robust_consensus._prefer_all_bearings`): at
   low SNR a subset can fit a wrong point near the stations, where range-grown σ are small.
   With range-grown σ a fit of all the bearings whose χ² is below the lower quantile of its
   band has run out in range (σ(d) there covers any residual) and does not count.
   Excluded bearings are reported per angle.
4. **Assess** (every fix that went through steps 2-3). The covariance is the inverse
   Fisher information over the inliers at the estimate; for range-grown σ it is widened
   along its major axis to the far side of the test-inversion region of level
   :data:`TEST_INVERSION_Z` (:func:`test_inversion_covariance`): the covariance at the
   estimate understates the region toward larger range, where σ(d) is larger. The fix is
   ``ok`` only when (a) the residual χ² ≤ the χ²_dof quantile of
   :data:`CONSISTENCY_PROBABILITY` (dof at least 1: an exactly determined fix of three
   angles must fit them), (b) ν ≤ :func:`max_nonlinearity` (for range-grown σ, ν
   of the test-inversion region of level :data:`STATUS_REGION_Z`, the Mahalanobis radius
   of a confidently wrong fix: the linearisation must hold out to the level at which the
   fix is judged), (c) at most ⌊(M_meas − 3)/2⌋ angles were excluded and (d) every
   exclusion is decisive: the excluded angle is an outlier also given the fix's own
   uncertainty, r² / (1 + gᵀPg) > the χ²₁ quantile of :data:`DECISIVE_PROBABILITY`, g the
   whitened gradient, and (e) the likelihood has no second optimum outside the covariance
   (:func:`.robust_consensus.second_optimum`): refitted from the all-station ``ls`` fix,
   it must return inside the ellipsoid of level q (χ²₃ quantile of
   :data:`MULTIMODE_PROBABILITY`) or end with L higher by more than q. Otherwise
   ``low_confidence`` (position and covariance kept, ``converged`` False), except that a
   fix failing (d) returns to the fit of all the angles from step 3 (its χ² failed the
   test, so it stays ``low_confidence``, with nothing excluded): the data do not show
   that the excluded angles are outliers, and a subset fit can lie far from the optimum
   of all of them (Wang, Zhang & Wu 2006 geometry at 1.5 mrad: 6 km against 0.23 km).

Nonlinearity ν = sqrt(λ_max(P)) / min_k ρ_k (:func:`region_nonlinearity`), ρ_k the
horizontal range of station k: the radius of the confidence region seen from the nearest
station, relative to its range. An azimuth is a function of the horizontal offset over ρ_k
(an elevation of the offset over d_k ≥ ρ_k), so the second-order terms of the angles over
the confidence region are at most ν times the first-order ones (the parameter-effects
curvature of Bates & Watts 1980 for a bearing); with ν small the error ellipsoid describes
the confidence region, with ν large the region is a banana elongated in range, or wraps
around a station's vertical axis, and a Gaussian covariance understates its tail.

With range-grown σ, ν is computed from a widened covariance (step 4): computed at the
estimate alone, it selects at large σ the fixes that landed short in range (where σ(d)
and hence ν are small), and those were the confidently wrong ones. It is widened to the
far side of the region of level :data:`STATUS_REGION_Z` (4.59), not to the reported
covariance's level :data:`TEST_INVERSION_Z`: a fix whose region is an ellipse out to 1.5σ
but a banana at 4.6σ is exactly one whose truth can lie beyond the confidently wrong level.

Calibration (``bench/low_snr.py --acceptance``, 2000 trials per σ, joint, azimuth and
elevation sweeps): the largest ν bound at which the ``ok`` fixes' confident-wrong share
(Mahalanobis error above the χ²₃ 0.9999 quantile) stays at the level it has for small ν.
Constant σ (six stations, σ 1°-5°): 0.2 (ok share at 5° 33 % with 0.1, 99.7 % with 0.2,
the confident-wrong share unchanged at 0-3 fixes in 2000). Range-grown σ (Zong & Cui 2015
scenario, σ_ref 0.5°-5°): 0.1 (with 0.12 or 0.15 the failures of either criterion grow
from 3 to 5 and 13 of the 24 sweep points). Without the widening the mean NEES was 3.5-3.9
at σ_ref ≥ 1°; widened to z = 2 for both the covariance and ν it was 2.74-2.87 at σ_ref
0.5°, and 16 of the 24 sweep points failed a criterion over ``--seeds 0,1,2,3,4`` (11 over
seeds 5-9), the pooled confident-wrong share 0.048 % (0.070 %). With ν taken at
:data:`STATUS_REGION_Z` the ``ok`` fixes are the ones whose region is an ellipse out to
that level; they need less widening, and z = 1.5 for the covariance brings their mean NEES
into its band (z = 1, 1.1, 1.25, 1.5: 5, 4, 3, 3 failing points; at z = 2 the low σ_ref
points are conservative again). Seeds 0-4: 3 failing points, pooled 0.023 %; seeds 5-9,
not used to choose: 5 failing points, pooled 0.058 %. The price is availability: the ok
fixes fall from 58,670 to 34,238 of the 240,000 trials (at σ_ref 0.5° from 64 % to 41 %).
A status level of z = 3 or 4 instead of 4.59 fails 8 and 6 points. The second-optimum
check (e) measures distances with the reported covariance, so the smaller level 1.5 also
makes it stricter; the figures above include that.

Second optimum (e): at σ_ref 5° (σ ≈ 30° at 6 km) one ``ok`` ``wmle`` fix in 8 sweep
points × 2000 trials lay 0.85 km from a station, 5.7 km short of the target, with a
stated σ of 70 m (NEES 1e4); the refit from the ``ls`` fix found an optimum near the
target with L only 12.8 higher. The level is the confident-wrong one (χ²₃ 0.9999 = 21.1):
a second optimum inside the likelihood-ratio region of that level (Wilks 1938) can be the
truth at that level. Over three seeds of the acceptance run (35 000 ``ok`` fixes of
``wmle``) it marks two more fixes ``low_confidence``: second optima 20.7 and 20.9 higher,
regions of two components around fixes that were right; every other refit that ended
outside its ellipsoid was 23-102 higher.

Tail and mean NEES, measured (seeds 0-2 of the acceptance run, 2000 trials per point,
before the status level :data:`STATUS_REGION_Z`, with z = 2 for the covariance and ν).
The remaining confidently wrong ``ok`` fixes are calm fixes that landed short in range:
along the outward major axis the error in units of its σ has mean −0.25 to −0.49 and
skewness −0.4 to −0.8 for ``wmle`` (σ_ref 0.5°-2°), mean −0.02 to −0.08 and skewness −0.1
to −0.5 for constant σ (1°-5°); the truth mostly lies at a NEES of 7-14 under its own
covariance, 21-42 under the smaller one at the estimate. One ellipsoid cannot describe
both the bulk and that tail. Range-grown σ (ν ≤ 0.1, seed 0): widening to the
test-inversion boundary at z = 1, 1.5, 2, 3 gives 7, 6, 3, 4 failing sweep points of 24
with 14, 9, 4, 1 confidently wrong fixes (as z grows the tail shrinks, the mean NEES
falls below its band at σ_ref 0.5°-1°, the ``ok`` fixes drop from 14 600 to 9 400;
over seeds 0-2, 15 failing points with z = 2 and 21 with z = 3); the two-sided
test-inversion width fails 10, the second moment of the test-inversion distribution
(Gauss-Hermite, 6 nodes; its widening vanishes to second order in ν) 9 (mean NEES
2.9-3.1 at 0.5° but 3.3 at 1°, 13 confidently wrong). Constant σ: any of these widenings
pushes the mean NEES below its band at 6-9 of 15 points or cuts the ``ok`` share at 5°
from 99.7 % to 60-91 %, with the tail unchanged. Moving the estimate by its second-order
bias (Cox & Snell 1968, the Gaussian model with the σ(d) terms) lowers the RMSE by 1-3 %
but hardly moves the error along the outward axis (mean −0.05 σ → −0.09 σ at a constant
3°, −0.25 σ → −0.18 σ for ``wmle`` at 0.5°) and leaves the tail as it was. Hence no
widening for constant σ, and for range-grown σ the status level above. The rate that
remains, pooled over the sweep points (``bench/low_snr.py --acceptance`` prints it with
its exact 95 % Poisson bound; ``--seeds 0,1,2,3,4`` pools 10 000 trials per point), is
0.02-0.06 % for range-grown σ and 0.04 % for constant σ, below 0.1 % but 2-6 times the
Gaussian 0.01 %; at 0.04 % a point of 2000 trials shows 2 or more such fixes (0.10 %)
with probability 0.19: the 0.10-0.15 % of single sweep points.

Units: m, rad; ENU, azimuth θ CCW from East, elevation ψ above the horizontal.

Modules: :mod:`.robust_model` (residuals, Fisher information, nonlinearity, χ² bands),
:mod:`.robust_consensus` (steps 2-3) and this one (steps 1 and 4, :func:`confident_result`);
every public name is importable from here. One problem per call (the fusion node, ``bearing_loc
locate`` on one problem) runs steps 2-4 on Python floats (:mod:`.robust_single`, the same
statuses and exclusions as the batch path, positions within about 1e-8 of the range),
falling back to the arrays where floats cannot follow them.
"""

from dataclasses import replace
import math

import numpy as np

from .crlb import safe_inverse
from .solvers import spd_inverse3
from .fix import STATUS_OK as _STATUS_OK
# Re-exported: the model and the consensus are part of this module's interface.
from .robust_consensus import consensus_fit, second_optimum  # noqa: F401
from .robust_model import (chi2_band, chi2_upper, CONSISTENCY_PROBABILITY,  # noqa: F401
                           Data, DECISIVE_PROBABILITY, fisher, horizontal_ranges,
                           MAX_NONLINEARITY,
                           MAX_REGION_NONLINEARITY, MAX_REGION_NONLINEARITY_GROWN,
                           max_nonlinearity, MULTIMODE_PROBABILITY, nonlinearity,
                           OUTLIER_PROBABILITY, outlier_c2,
                           REFIT_ITERATIONS, REFIT_ROUNDS, region_nonlinearity,
                           STATUS_REGION_Z, TEST_INVERSION_Z, test_inversion_covariance,
                           _upper_cached,
                           whitened_residuals)

#: The former private name of :func:`outlier_c2`.
_c2 = outlier_c2


def assess(data, X, wa, we, probability=CONSISTENCY_PROBABILITY, max_nu=None,
           decisive=False):
    """Step 4 of the module docstring: (covariance (M, 3, 3), ok (M,), chi2, dof, ν).

    With ``decisive``, a sixth item (M,) bool: every excluded angle is decisive (check (d)
    below; True where nothing is excluded).

    ``ok``: χ² ≤ the χ²_max(dof, 1) ``probability`` quantile, ν ≤ ``max_nu`` (default
    :func:`max_nonlinearity`), at most ⌊(M_meas − 3)/2⌋ angles excluded, every
    excluded angle decisive (predictive residual r² / (1 + gᵀPg) above the χ²₁ quantile of
    :data:`DECISIVE_PROBABILITY`) and no second optimum of the likelihood outside the
    covariance (:func:`.robust_consensus.second_optimum`). The covariance is (Σ w g gᵀ)⁻¹,
    m², for range-grown σ widened by :func:`test_inversion_covariance`.
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
    cd = outlier_c2(DECISIVE_PROBABILITY)
    marginal = ((wa == 0) & ~(qa > cd)) | ((we == 0) & data.has_el & ~(qe > cd))
    if grown:
        # The covariance: widened to the test-inversion level; ν: the region out to the
        # level of a confidently wrong fix (module docstring).
        Ps = test_inversion_covariance(data, X, wa, we, P, z=STATUS_REGION_Z)
        P = test_inversion_covariance(data, X, wa, we, P)
        Ps = np.where(np.all(np.isfinite(P), axis=(-2, -1))[:, None, None], Ps, np.inf)
    else:
        Ps = P
    nu = region_nonlinearity(Ps, horizontal_ranges(data, X), present)
    excluded = n_all - n_kept
    # dof 0 (three angles kept): the fit is exactly determined and its χ² should vanish;
    # it is held to the χ²₁ quantile (as the horizontal solve holds dof ≤ 0), so an
    # iteration that stopped short of an exact fit is not ok.
    ok = ((chi2 <= chi2_upper(np.maximum(dof, 1), probability)) & (nu <= max_nu)
          & (excluded <= np.floor((n_all - 3) / 2.0)) & ~marginal.any(axis=-1)
          & np.all(np.isfinite(P), axis=(-2, -1)))
    idx = np.flatnonzero(ok)
    if idx.size:
        ok[idx] = ~second_optimum(data.take(idx), X[idx], wa[idx], we[idx], P[idx])
    if decisive:
        return P, ok, chi2, dof, nu, ~marginal.any(axis=-1)
    return P, ok, chi2, dof, nu


def screen(data, X, P, probability=CONSISTENCY_PROBABILITY, c2=None, max_nu=None,
           two_sided=True):
    """Step 1: (M,) True where the fix needs the consensus and refit (module docstring).

    ``data`` (:class:`Data`, M problems), X (M, 3) m, P (M, 3, 3) m². Calm (False) when every
    whitened residual has r_j² ≤ ``c2``, the residual χ² lies inside the two-sided χ²_dof band
    of ``probability`` (dof = M_meas − 3) and ν = sqrt(λ_max(P)) / min_k ρ_k ≤ ``max_nu``.
    A non-finite X or P fails the screen. The same decisions as :func:`screen_one` (tested);
    computed by :func:`screen_station_major` on station-major copies of ``data``. With
    ``two_sided`` False the χ² test is the assessment's one-sided one (χ² at most the
    χ²_max(dof, 1) ``probability`` quantile; :func:`consistency_status`).
    """
    def rows(v):
        return np.ascontiguousarray(v.T)

    pos = data.pos
    return screen_station_major(
        rows(pos[..., 0]), rows(pos[..., 1]), rows(pos[..., 2]), rows(data.az), rows(data.el),
        rows(data.ia), rows(data.ie), data.az.shape[1] + rows(data.has_el).sum(axis=0),
        data.d_ref, X, P, probability, c2, max_nu, two_sided)


def screen_station_major(px, py, pz, az, el, ia, ie, n_meas, d_ref, X, P,
                         probability=CONSISTENCY_PROBABILITY, c2=None, max_nu=None,
                         two_sided=True):
    """:func:`screen` on station-major (N, M) arrays, as the ML iteration keeps them.

    ``px``, ``py``, ``pz`` station positions, m; ``az``, ``el`` measured angles, rad (el 0
    where absent); ``ia``, ``ie`` inverse σ (σ_ref for range growth), 1/rad (ie 0 where
    there is no elevation); ``n_meas`` (M,) measured angles per problem; ``d_ref`` m or None
    (:class:`Data`'s fields, transposed). One evaluation of the whitened residuals (a few
    elementwise operations and row reductions), then :func:`screen_decision`.
    """
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        dx = X[:, 0] - px
        dy = X[:, 1] - py
        dz = X[:, 2] - pz
        rho2 = dx * dx + dy * dy
        r2 = rho2 + dz * dz
        e_az = az - np.arctan2(dy, dx)
        e_az -= 2.0 * np.pi * np.ceil((e_az - np.pi) / (2.0 * np.pi))
        e_el = el - np.arctan2(dz, np.sqrt(rho2))
        if d_ref is not None:
            f = d_ref / np.sqrt(r2)
            ia, ie = ia * f, ie * f
        qa = ia * e_az
        qa *= qa
        qe = ie * e_el
        qe *= qe
        chi2 = (qa + qe).sum(axis=0)
        worst = np.maximum(qa, qe).max(axis=0)
    return screen_decision(chi2, worst, rho2.min(axis=0), n_meas, P, d_ref is not None,
                           probability, c2, max_nu, two_sided)


def screen_decision(chi2, worst, rho2min, n_meas, P, grown=False,
                    probability=CONSISTENCY_PROBABILITY, c2=None, max_nu=None,
                    two_sided=True):
    """:func:`screen` from its statistics: (M,) True where the fix needs the consensus.

    ``chi2`` Σ r_j² and ``worst`` max_j r_j² of the whitened residuals at the fix,
    ``rho2min`` min_k ρ_k² (horizontal ranges), m², ``n_meas`` measured angles (all (M,)),
    P (M, 3, 3) m², ``grown`` for range-grown σ (the ν bound). The estimator may hand these
    from its own last evaluation (``mle``: the same numbers in the same order as
    :func:`screen_station_major`). A few
    operations on (M,) arrays, since at high SNR nearly every fix is calm: the χ² band is
    looked up per distinct dof, and the ν test needs no eigenvalues: λ_max(P) < t ⇔ tI − P
    positive definite ⇔ its three leading principal minors are positive (Sylvester's
    criterion), t = (``max_nu`` min_k ρ_k)². A non-finite P or ρ fails the screen.
    """
    c2 = outlier_c2() if c2 is None else c2
    max_nu = max_nonlinearity(grown) if max_nu is None else max_nu
    with np.errstate(invalid='ignore', over='ignore'):
        t = max_nu * max_nu * rho2min
        a = t - P[:, 0, 0]
        b = t - P[:, 1, 1]
        c = t - P[:, 2, 2]
        p01, p02, p12 = P[:, 0, 1], P[:, 0, 2], P[:, 1, 2]
        det = (a * (b * c - p12 * p12) - p01 * p01 * c - b * p02 * p02
               - 2.0 * p01 * p12 * p02)
        if two_sided:
            lo, hi = _band_table(n_meas - 3, probability)
        else:
            lo, hi = 0.0, chi2_upper(np.maximum(n_meas - 3, 1).astype(int), probability)
        calm = ((worst <= c2) & (chi2 >= lo) & (chi2 <= hi) & (t < np.inf) & (a > 0.0)
                & (a * b > p01 * p01) & (det > 0.0))
    return ~calm


def screen_one(bearings, x, d_ref, P, c2=None, probability=CONSISTENCY_PROBABILITY,
               max_nu=None, two_sided=True):
    """:func:`screen` for one problem on Python floats (the fusion's one-fix path).

    ``x`` (3,) m, ``P`` (3, 3) m² (array or nested lists); True when the fix needs the
    consensus and refit. The same decisions as :func:`screen` (tested).
    """
    c2 = outlier_c2() if c2 is None else c2
    max_nu = max_nonlinearity(d_ref is not None) if max_nu is None else max_nu
    pos = bearings.positions[0].tolist()
    az = bearings.azimuth[0].tolist()
    el = bearings.elevation[0].tolist()
    sa = bearings.sigma_az[0].tolist()
    se = bearings.sigma_el[0].tolist()
    x0, x1, x2 = x
    chi2 = 0.0
    n = 0
    rho_min = math.inf
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
        rho_min = min(rho_min, rho)
    if two_sided:
        lo, hi = _band_cached(n - 3, probability)
    else:
        lo, hi = 0.0, _upper_cached(max(n - 3, 1), probability)
    if not lo <= chi2 <= hi:
        return True
    lam = _lambda_max(P.tolist() if hasattr(P, 'tolist') else P)
    return not math.sqrt(max(lam, 0.0)) <= max_nu * rho_min


def _lambda_max(p):
    """Largest eigenvalue of a symmetric 3 × 3 matrix (nested lists), closed form.

    The trigonometric solution of the characteristic cubic (Smith 1961): with q = tr/3,
    B = (A − qI)/r, r² = tr((A − qI)²)/6, λ_max = q + 2r cos(acos(det B / 2) / 3).
    NaN for a non-finite matrix.
    """
    try:
        return _lambda_max_cubic(p)
    except (OverflowError, ZeroDivisionError):
        # Entries beyond ~1e100 m² or below ~1e-100 m² overflow or underflow the cubic's
        # powers: LAPACK gives the same λ_max there (NaN for a non-finite matrix).
        m = np.asarray(p, dtype=float)
        return float(np.linalg.eigvalsh(m)[-1]) if np.all(np.isfinite(m)) else math.nan


def _lambda_max_cubic(p):
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


def _band_table(dof, probability):
    """(lo, hi) of :func:`chi2_band` for the integer dof (M,), one quantile per value."""
    if dof.size == 0:
        return np.zeros((2, 0))
    d0, d1 = int(dof.min()), int(dof.max())
    if d0 == d1:
        return _band_cached(d0, probability)
    table = np.array([_band_cached(k, probability) for k in range(d0, d1 + 1)])
    return table[dof - d0].T


def consistency_status(result, bearings, probability=CONSISTENCY_PROBABILITY):
    """``result`` with every ``ok`` fix that fails a consistency check marked
    ``low_confidence`` (``converged`` False), and the covariance of every fix that passes
    widened to P + δδᵀ; positions unchanged.

    The status rule of the estimators without option ``robust`` (``ls``, ``tls``, ``ctls``,
    ``ctls_am``; their option ``consistency``). Such a fix X̂ is not the maximum likelihood
    fix, so its residuals are judged after one Gauss-Newton step toward it (Zong & Cui 2015
    eq. (8)): with r the whitened residuals at X̂, G their whitened gradients, F = GᵀG and
    δ = F⁻¹Gᵀr the step, the fix is ``ok`` only when
    (a) χ²_min = rᵀr − δᵀFδ (the predicted χ² at the likelihood's optimum) is at most the
    χ²_max(dof, 1) quantile of ``probability`` (dof = M_meas − 3): the data are consistent;
    (b) δᵀP⁻¹δ ≤ the χ²₃ quantile of ``probability``, P the estimator's covariance: the
    optimum lies inside the fix's own confidence region (X̂ − X_ML has covariance P − F⁻¹
    ≤ P for an unbiased estimator, so this rarely fails by chance; it fails for a biased
    pseudo-linear fix, a fix behind a station or a CTLS stop at a spurious minimum);
    (c) every linearised residual at X̂ + δ, (r − Gδ)_j², is at most c² (:func:`outlier_c2`,
    3.9σ): no outlier angle;
    (d) ν = sqrt(λ_max(P)) / min_k ρ_k ≤ :data:`MAX_REGION_NONLINEARITY` (0.2; module
    docstring): the covariance describes the confidence region.
    A fix that passes reports P + δδᵀ: δ estimates its offset from the likelihood's optimum,
    so the covariance bounds the mean squared error of a biased pseudo-linear fix (many
    bearings or low SNR) and not only its spread (an unbiased, nearly efficient fix has
    δ small against P and keeps about P; a less efficient one, such as ``ctls``, whose fixes
    scatter about the optimum by about their own σ, gets a conservative covariance).
    Units: m, rad; bearing σ as given (constant σ). One problem on Python floats
    (:func:`.robust_single.consistent_one`, the same decisions), a batch as arrays.
    """
    if bearings.M == 1:
        # One problem (the fusion's and locate's case): on floats, no array bookkeeping.
        if result.status[0] != _STATUS_OK:
            return result
        x, C = result.position[0].tolist(), result.covariance[0].tolist()
        good = False
        if all(map(math.isfinite, x + C[0] + C[1] + C[2])):
            # (imported here: the compiled one-problem module loads numba, which a process
            # that never solves one problem need not pay for)
            from .robust_single import consistent_one, Fallback
            try:
                good, delta = consistent_one(bearings, x, C, probability)
            except Fallback:
                good = None         # the batch path below decides
        if good:
            d = np.array([delta])
            return replace(result, covariance=result.covariance + d[:, :, None] * d[:, None, :])
        if good is not None:
            return mark_low_confidence(result, [True])
    from .bearings import BearingSet
    status = np.asarray(result.status)
    X = np.asarray(result.position, dtype=float)
    P = np.asarray(result.covariance, dtype=float)
    ok = ((status == _STATUS_OK) & np.all(np.isfinite(X), axis=1)
          & np.all(np.isfinite(P), axis=(1, 2)))
    idx = np.flatnonzero(ok)
    bad = (status == _STATUS_OK) & ~ok
    if idx.size:
        sub = BearingSet(bearings.positions[idx], bearings.azimuth[idx],
                         bearings.elevation[idx], bearings.sigma_az[idx],
                         bearings.sigma_el[idx])
        good, delta = _consistent(Data(sub, None), X[idx], P[idx], probability)
        bad[idx] = ~good
        d = np.where(good[:, None], delta, 0.0)
        P = P.copy()
        P[idx] += d[:, :, None] * d[:, None, :]
        result = replace(result, covariance=P)
    return mark_low_confidence(result, bad)


def mark_low_confidence(result, bad):
    """``result`` with the problems ``bad`` (M,) bool made ``low_confidence`` and not
    converged (position and covariance kept); ``result`` itself when none is."""
    from .fix import STATUS_LOW_CONFIDENCE, STATUSES
    bad = np.asarray(bad, dtype=bool)
    if not bad.any():
        return result
    wide = f'<U{max(map(len, STATUSES))}'
    return replace(result, status=np.where(bad, STATUS_LOW_CONFIDENCE,
                                           np.asarray(result.status)).astype(wide),
                   converged=np.asarray(result.converged, dtype=bool) & ~bad)


def _consistent(data, X, P, probability):
    """((M,) bool, δ (M, 3) m): checks (a)-(d) of :func:`consistency_status` at fixes X (M, 3)
    with covariances P (M, 3, 3), all finite, and the step δ: (a), (c) and (d) by
    :func:`screen_decision` (its
    one-sided χ² test) on χ²_min and the linearised residuals, (b) here."""
    ra, re, ga, ge, _, _, _ = data.evaluate(X)
    ra = np.where(np.isfinite(ra), ra, np.inf)
    re = np.where(data.has_el, re, 0.0)
    ge = np.where(data.has_el[..., None], ge, 0.0)
    F = fisher(ga, ge, np.ones_like(ra), data.has_el.astype(float))
    b = np.einsum('mn,mni->mi', ra, ga) + np.einsum('mn,mni->mi', re, ge)
    with np.errstate(invalid='ignore', over='ignore'):
        delta = np.einsum('mij,mj->mi', spd_inverse3(F), b)
        # (≥ 0: rounding can leave a tiny negative where the fix fits the data exactly,
        # and screen_decision's one-sided band starts at 0)
        chi2_min = np.maximum((ra * ra + re * re).sum(axis=-1)
                              - np.einsum('mi,mi->m', delta, b), 0.0)
        m2 = np.einsum('mi,mi->m', delta, np.einsum('mij,mj->mi', spd_inverse3(P), delta))
        la = ra - np.einsum('mni,mi->mn', ga, delta)
        le = re - np.einsum('mni,mi->mn', ge, delta)
        worst = np.maximum(la * la, le * le).max(axis=-1)
        rho2min = (horizontal_ranges(data, X) ** 2).min(axis=-1)
    n_meas = data.az.shape[1] + data.has_el.sum(axis=-1)
    return (~screen_decision(chi2_min, worst, rho2min, n_meas, P, probability=probability,
                             two_sided=False)
            & (m2 <= chi2_upper(np.full(len(X), 3), probability))), delta


def confident_result(result, bearings, d_ref=None, screen_stats=None):
    """The estimator's FixResult after screen, consensus, refit and assessment (module doc).

    ``result``: an ``mle`` (``d_ref`` None) or ``wmle`` (``d_ref`` = reference range, m)
    FixResult of ``bearings``. Problems of status ``degenerate_geometry`` are returned
    unchanged. Every ``ok``, ``max_iterations`` or ``diverged`` problem ends ``ok`` or
    ``low_confidence`` with a finite position, or ``degenerate_geometry`` when no usable
    fix exists; ``excluded`` (M, N, 2) and
    ``nonlinearity`` (M,) are filled. A problem that passes the screen keeps the
    estimator's own position, covariance and status. ``screen_stats``: optionally the
    screen's statistics (chi2, worst, rho2min, n_meas) at the result's positions, from the
    estimator's last evaluation (:func:`screen_decision`; the same decisions as
    :func:`screen`, tested), instead of evaluating the residuals again.
    """
    from .bearings import BearingSet
    from .fix import (FixResult, STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_LOW_CONFIDENCE,
                      STATUS_MAX_ITERATIONS, STATUS_OK, STATUSES)
    M, N = bearings.M, bearings.N
    if M == 1:
        # One problem (the fusion's and locate's case): on Python floats, without the array
        # bookkeeping below (the same decisions; robust_single for steps 2-4).
        out = _confident_one(result, bearings, d_ref)
        if out is not None:
            return out
    status = np.asarray(result.status)
    is_ok = status == STATUS_OK
    if d_ref is not None:
        # Range-grown σ: the paper's cost has its attractor at infinite range, so every fix
        # is refitted on the full likelihood (the screen would keep the paper's estimate).
        trigger = np.ones(M, dtype=bool)
    elif M == 1:
        trigger = np.array([not (np.all(np.isfinite(result.position))
                                 and np.all(np.isfinite(result.covariance)))
                            or screen_one(bearings, result.position[0].tolist(), d_ref,
                                          result.covariance[0])])
    elif screen_stats is not None:
        # Every row is screened (a row's decision depends on that row alone; a non-finite
        # fix fails it).
        trigger = screen_decision(*screen_stats, result.covariance)
    else:
        trigger = screen(Data(bearings, d_ref), result.position, result.covariance)
    # A fix the estimator did not converge on (max_iterations, diverged: typically a run-away
    # in range) always goes to the consensus, with its own position as one candidate when
    # finite; degenerate geometry stays as it is, and so does an ok fix without a finite
    # position and covariance.
    if not is_ok.all():
        trigger = np.where(is_ok, trigger, (status == STATUS_MAX_ITERATIONS)
                           | (status == STATUS_DIVERGED))
    idx = np.flatnonzero(trigger)
    usable = (np.all(np.isfinite(result.position[idx]), axis=1)
              & np.all(np.isfinite(result.covariance[idx]), axis=(1, 2)))
    keep = usable | ~is_ok[idx]
    if not keep.all():
        idx, usable = idx[keep], usable[keep]
    if not idx.size:
        # Every fix passed the screen (the usual case at high SNR): the estimator's result.
        return FixResult(result.position, result.covariance, result.iterations,
                         result.converged, result.status, result.method,
                         excluded=np.zeros((M, N, 2), dtype=bool),
                         nonlinearity=np.full(M, np.nan))
    pos = np.array(result.position, dtype=float)
    cov = np.array(result.covariance, dtype=float)
    status = status.astype(f'<U{max(map(len, STATUSES))}')     # room for every status
    conv = np.array(result.converged, dtype=bool)
    excluded = np.zeros((M, N, 2), dtype=bool)
    nu = np.full(M, np.nan)
    data = Data(BearingSet(bearings.positions[idx], bearings.azimuth[idx],
                           bearings.elevation[idx], bearings.sigma_az[idx],
                           bearings.sigma_el[idx]), d_ref)
    start = np.where(np.all(np.isfinite(pos[idx]), axis=1)[:, None], pos[idx], np.nan)
    X, wa, we, X_all = consensus_fit(data, start, with_all=True)
    P, ok, _, _, nux, decisive = assess(data, X, wa, we, decisive=True)
    back = np.flatnonzero(~decisive & np.all(np.isfinite(X_all), axis=1))
    if back.size:
        # Exclusions the fix's own uncertainty does not support: the fit of all the angles
        # (ML of the full likelihood; low_confidence, as its χ² failed the test).
        X[back], wa[back], we[back] = X_all[back], 1.0, data.has_el[back]
        P[back], ok[back], _, _, nux[back] = assess(data.take(back), X[back], wa[back],
                                                    we[back])
    finite = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
    # No finite refit (e.g. a target far beyond the baseline): the estimator's own
    # finite fix is kept, as low_confidence, without exclusions.
    own = ~finite & usable
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
    return FixResult(pos, cov, result.iterations, conv, status, result.method,
                     excluded=excluded, nonlinearity=nu)


def _confident_one(result, bearings, d_ref):
    """:func:`confident_result` of one problem on Python floats, or None for the array path.

    The same decisions in the same order: the screen (:func:`screen_one`; every fix with
    range-grown σ, every ``max_iterations`` or ``diverged`` fix goes on), steps 2-4 by
    :func:`.robust_single.refine` (None where it raises :class:`.robust_single.Fallback`),
    and the same statuses, exclusions and fallbacks to the estimator's own fix.
    """
    from .fix import (FixResult, STATUS_DEGENERATE, STATUS_DIVERGED, STATUS_LOW_CONFIDENCE,
                      STATUS_MAX_ITERATIONS, STATUS_OK, STATUSES)
    from .robust_single import Fallback, refine
    N = bearings.N
    status = str(result.status[0])
    x = result.position[0].tolist()
    C = result.covariance[0].tolist()
    x_finite = all(map(math.isfinite, x))
    usable = x_finite and all(map(math.isfinite, C[0] + C[1] + C[2]))
    if status == STATUS_OK:
        # An ok fix without a finite position and covariance stays as it is.
        trigger = usable and (d_ref is not None or screen_one(bearings, x, None, C))
    else:
        trigger = status in (STATUS_MAX_ITERATIONS, STATUS_DIVERGED)
    if not trigger:
        return FixResult(result.position, result.covariance, result.iterations,
                         result.converged, result.status, result.method,
                         excluded=np.zeros((1, N, 2), dtype=bool),
                         nonlinearity=np.full(1, np.nan))
    try:
        pos, cov, ok, nu, excluded, finite = refine(bearings,
                                                    x if x_finite else [math.nan] * 3, d_ref)
    except Fallback:
        return None
    if finite:
        status = STATUS_OK if ok else STATUS_LOW_CONFIDENCE
    else:
        # No finite refit: the estimator's own finite fix is kept, as low_confidence,
        # without exclusions (else no usable fix).
        ok, nu = False, math.nan
        excluded = np.zeros((1, N, 2), dtype=bool)
        if usable:
            status = STATUS_LOW_CONFIDENCE
            pos = np.array(result.position, dtype=float)
            cov = np.array(result.covariance, dtype=float)
        else:
            status = STATUS_DEGENERATE
            pos, cov = np.full((1, 3), np.nan), np.full((1, 3, 3), np.inf)
    return FixResult(pos, cov, result.iterations, np.array([ok]),
                     np.array([status], dtype=f'<U{max(map(len, STATUSES))}'), result.method,
                     excluded=excluded, nonlinearity=np.array([nu], dtype=float))
