"""Whitened residuals, Fisher information, nonlinearity and χ² tests of the robust ML fix.

The measurement model and the statistics that :mod:`.robust` (screen, assess) and
:mod:`.robust_consensus` (consensus and refit) share; the method is described in the
:mod:`.robust` docstring (Zong & Cui 2015 eqs. (3)-(11)). Units: m, rad; ENU, azimuth θ CCW
from East, elevation ψ above the horizontal. Re-exported from :mod:`.robust`.
"""

from functools import lru_cache

import numpy as np
from . import chisq as _chi2

from .crlb import safe_inverse

#: Probability of the per-angle outlier threshold c² = χ²₁ quantile (3.89 σ).
OUTLIER_PROBABILITY = 0.9999
#: Probability of the residual χ² consistency test of an ``ok`` fix.
CONSISTENCY_PROBABILITY = 0.999
#: Largest range σ / range (:func:`nonlinearity`) accepted by callers of that function.
MAX_NONLINEARITY = 0.1
#: Largest nonlinearity ν (:func:`region_nonlinearity`) of an ``ok`` fix, constant σ
#: (``mle``); calibrated by measurement (:mod:`.robust` docstring).
MAX_REGION_NONLINEARITY = 0.2
#: The same for range-grown σ (``wmle``).
MAX_REGION_NONLINEARITY_GROWN = 0.1
#: An excluded angle must be an outlier also given the fix's uncertainty: its predictive
#: residual r² / (1 + gᵀPg) must exceed the χ²₁ quantile of this probability (4.9 σ).
DECISIVE_PROBABILITY = 1.0 - 1e-6
#: Level of the likelihood-ratio region that must not hold a second optimum of an ``ok``
#: fix (χ²₃ quantile 21.1: the level of a confidently wrong fix).
MULTIMODE_PROBABILITY = 0.9999
#: Level z of the test-inversion covariance along the range axis (range-grown σ).
TEST_INVERSION_Z = 1.5
#: Level z of the test-inversion region whose nonlinearity ν decides whether a fix with
#: range-grown σ is ``ok``: the Mahalanobis radius of a confidently wrong fix, the square
#: root of the χ²₃ quantile of MULTIMODE_PROBABILITY (4.59).
STATUS_REGION_Z = float(np.sqrt(_chi2.ppf(MULTIMODE_PROBABILITY, 3)))
#: Rounds of inlier recomputation and refit.
REFIT_ROUNDS = 3
#: Levenberg-Marquardt iterations per refit. A fix whose region is far from an ellipse (ν of
#: 3 and more) converges slowly and can end at this cap. It is not raised: with range-grown
#: σ the full likelihood has no lower bound at a station (along the station's own bearing
#: its residual stays 0 while log σ² → −∞), and more iterations let such a refit run on
#: toward the station.
REFIT_ITERATIONS = 40


@lru_cache(maxsize=16)
def outlier_c2(p=OUTLIER_PROBABILITY):
    """The χ²₁ quantile of probability ``p``: the per-angle outlier threshold c² on r²."""
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

    def evaluate(self, X, gradients=True):
        """Whitened residuals and gradients at X (M, 3) (or (M, K, 3) candidates).

        Returns ra, re (…, N) whitened residuals r = (measured − predicted)/σ (azimuth
        wrapped to (−π, π]); ga, ge (…, N, 3) whitened gradients ∇h/σ, 1/m (the angle
        gradients of Zong & Cui 2015 eq. (6)); u (…, N, 3) unit lines of sight; d (…, N)
        ranges, m; log_s2 (…, N) log σ_j² up to a constant (2 log(d/d_ref) with range
        growth, 0 otherwise). With ``gradients`` False, ga, ge and u are None (the same
        residuals, ranges and log σ², for scores and inlier tests).
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
            if not gradients:
                return ra, re, None, None, None, d, log_s2
            # ga = [−dy, dx, 0] ia/ρ², ge = [−dx t, −dy t, ρ/r²] ie: filled in place (the
            # same operations as stacking the columns, without the temporaries).
            ga = np.empty(dv.shape)
            s = ia / rho2
            np.multiply(dy, s, out=ga[..., 0])
            np.negative(ga[..., 0], out=ga[..., 0])
            np.multiply(dx, s, out=ga[..., 1])
            np.multiply(s, 0.0, out=ga[..., 2])
            t = dz / (rho * r2)
            ge = np.empty(dv.shape)
            np.multiply(dx, t, out=ge[..., 0])
            np.negative(ge[..., 0], out=ge[..., 0])
            np.multiply(dy, t, out=ge[..., 1])
            np.negative(ge[..., 1], out=ge[..., 1])
            np.divide(rho, r2, out=ge[..., 2])
            ge *= ie[..., None]
            u = dv / d[..., None]
        return ra, re, ga, ge, u, d, log_s2


def whitened_residuals(bearings, X, d_ref=None):
    """(ra, re) (M, N): residuals / σ at X (M, 3), σ grown with range when ``d_ref`` is set.

    re is 0 for azimuth-only bearings. Zong & Cui 2015 eq. (5) with W of eq. (4) or (11).
    """
    ra, re, *_ = Data(bearings, d_ref).evaluate(np.asarray(X, dtype=float), gradients=False)
    return ra, re


def fisher(ga, ge, wa, we):
    """Fisher information Σ_j w_j g_j g_jᵀ (…, 3, 3), 1/m², of the (weighted) angles."""
    return (np.einsum('...n,...ni,...nj->...ij', wa, ga, ga)
            + np.einsum('...n,...ni,...nj->...ij', we, ge, ge))


def nonlinearity(P, u, d, present):
    """ν = max_k sqrt(u_kᵀ P u_k) / d_k over stations ``present`` (…, N); NaN if none.

    P (…, 3, 3) m², u (…, N, 3) unit lines of sight, d (…, N) ranges, m (:mod:`.robust` docstring).
    """
    with np.errstate(invalid='ignore', divide='ignore'):
        v = np.einsum('...ni,...ij,...nj->...n', u, P, u)
        nu = np.sqrt(np.maximum(v, 0.0)) / d
    nu = np.where(present, nu, -np.inf)
    out = nu.max(axis=-1)
    return np.where(np.isfinite(out), out, np.nan)


def horizontal_ranges(data, X):
    """ρ_k = |(X − S_k)_xy| (M, N), m: the horizontal ranges of the stations of ``data`` from
    X (M, 3) (the same operations as :meth:`Data.evaluate`'s ρ, so the same bits)."""
    dv = X[..., None, :] - data.pos
    dx, dy = dv[..., 0], dv[..., 1]
    return np.sqrt(dx * dx + dy * dy)


def region_nonlinearity(P, rho, present):
    """ν = sqrt(λ_max(P)) / min_k ρ_k over stations ``present`` (…, N); NaN if none.

    P (…, 3, 3) m², ρ (…, N) horizontal ranges, m (an azimuth's curvature scale, never
    above the range d_k an elevation's scale). The angular radius of the confidence region
    seen from the nearest station (:mod:`.robust` docstring); NaN where P is not finite.
    """
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    lam = np.linalg.eigvalsh(np.where(finite[..., None, None], P, 0.0))[..., -1]
    rho_min = np.where(present, rho, np.inf).min(axis=-1)
    with np.errstate(invalid='ignore', divide='ignore'):
        nu = np.sqrt(np.maximum(lam, 0.0)) / rho_min
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
    if dof.dtype.kind in 'iu':
        # Integer dof (every caller here): one cached quantile per value, the same numbers.
        return np.array([_upper_cached(k, probability) for k in dof.ravel().tolist()],
                        dtype=float).reshape(dof.shape)
    ok = dof >= 1
    return np.where(ok, _chi2.ppf(probability, np.where(ok, dof, 1)), np.inf)


@lru_cache(maxsize=1024)
def _upper_cached(dof, probability):
    """:func:`chi2_upper` of one integer dof, as a float."""
    return float(_chi2.ppf(probability, dof)) if dof >= 1 else np.inf
