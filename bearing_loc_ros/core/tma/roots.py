"""The two ranges of a ground-speed prior (T8) and the choice between them (T23).

Conventions as :mod:`bearing_loc_ros.core.tma`: m, m/s, s, rad, ENU; x = (p0, v) the
relative state (T1)-(T3), v_o the observer's fitted velocity (T2).

With ``speed_reference`` 'ground' the prior |v + v_o| = v_c (T5) sets the scale r0 of the
relative track (p0, v) = r0 (e0, b) through the quadratic (T8)

    |b|² r0² + 2 (b·v_o) r0 + |v_o|² − v_c² = 0.

When the observer is faster than the target (|v_o| > v_c, an aircraft tracking a ship) and
b·v_o < 0, both roots are positive: two target tracks with the stated ground speed. For an
observer at constant velocity (δ ≡ 0, T3) they predict the same bearings exactly (the angles
of p_k = r0 (e0 + b τ_k) do not depend on r0), so no number of bearings tells them apart;
only an observer manoeuvre (δ ≠ 0) does.

(T23) Mirror root. For x = (p0, v) on the constraint, the other intersection of the ray
      {c x : c > 0} with |v + v_o| = v_c is k x with

          k = (|v_o|² − v_c²) / |v|²

      (the roots of (T8) have the product (|v_o|² − v_c²)/|b|², so r_other / r0 =
      (|v_o|² − v_c²) / (|b|² r0²)); substituting 2 v·v_o = v_c² − |v|² − |v_o|² shows
      |k v + v_o| = v_c. There is a second fix when k > 0 and k ≠ 1.

      Choice. Both candidates are fitted (``tma_mle`` refines each; the closed forms are
      evaluated as they stand) and their costs c = Σ e² (the residual χ² of (T19), −2 log
      likelihood up to a constant) compared: Λ = |c_a − c_b|, a log-likelihood ratio.
      Λ > χ²₁ quantile :data:`ROOT_PROBABILITY` (0.999: 10.83) takes the lower cost. Two
      fixes whose ranges at the first bearing differ by at most one CRLB range standard
      deviation (T15) are one fix (the lower cost is kept). Otherwise the bearings do not
      separate the two ranges: status ``unobservable`` (a range the geometry does not
      resolve, as (T18)), the two ranges in the reason.

      Why this level: in the linearised Gaussian model with predicted whitened bearings
      μ_a, μ_b at distance d = |μ_a − μ_b|, the truth a gives c_b − c_a ~ N(d², 4 d²), so
      the wrong root wins by more than the bound t with probability
      Φ(−(d² + t) / (2 d)) ≤ Φ(−√t) (the worst d is √t), and Φ(−√χ²₁(1 − α)) = α/2: at most
      0.05 % of confidently wrong choices, whatever the geometry.
"""

import numpy as np

from .. import chisq
from ..fix import STATUS_UNOBSERVABLE
from .confidence import residuals
from .observability import constrained_crlb, constraint_gradient, fisher_terms

#: Level of the root choice (T23): the lower-cost root is taken when the costs differ by
#: more than the χ²₁ quantile of this probability.
ROOT_PROBABILITY = 0.999
#: χ²₁ quantile of :data:`ROOT_PROBABILITY` (10.83).
ROOT_THRESHOLD = float(chisq.ppf(ROOT_PROBABILITY, 1))


def mirror_scale(v, v_o, speed):
    """k (M,) of (T23): k·(p0, v) is the second fix of the ground-speed prior, NaN where
    there is none (k ≤ 0, k = 1, or v not finite). v, v_o (M, 3) m/s, speed (M,) m/s."""
    v = np.asarray(v, dtype=float)
    vv = np.sum(v * v, axis=-1)
    with np.errstate(divide='ignore', invalid='ignore'):
        k = (np.sum(np.asarray(v_o, dtype=float) ** 2, axis=-1)
             - np.asarray(speed, dtype=float) ** 2) / vv
    ok = np.isfinite(k) & (k > 0) & (np.abs(k - 1.0) > 1e-12)
    return np.where(ok, k, np.nan)


def cost(data, p0, v):
    """Residual cost Σ e² (M,) of (T19) at (p0, v) (whitened angles, T17); inf where NaN."""
    fin = np.all(np.isfinite(p0), -1) & np.all(np.isfinite(v), -1)
    e, _ = residuals(data, np.where(fin[:, None], p0, 0.0), np.where(fin[:, None], v, 0.0))
    c = np.sum(e * e, axis=(1, 2))
    return np.where(fin & np.isfinite(c), c, np.inf)


def range_std(data, p0, v, speed_reference):
    """CRLB standard deviation (M,) of the range |p0| at the first bearing, m (T14)-(T15);
    inf where the bound is singular."""
    J = fisher_terms(p0, v, data.tau, data.delta, data.s_az, data.s_el).sum(1)
    C = constrained_crlb(J, constraint_gradient(v, data.v_o, speed_reference))
    e0 = p0 / np.linalg.norm(p0, axis=-1, keepdims=True)
    with np.errstate(invalid='ignore'):
        var = np.einsum('mi,mij,mj->m', e0, C[:, :3, :3], e0)
    return np.where(np.isfinite(var), np.sqrt(np.maximum(var, 0.0)), np.inf)


def choose(data, cand_a, cand_b, speed_reference):
    """The choice of (T23) between two candidate fixes of each problem.

    ``cand_a``, ``cand_b``: (p0 (M, 3), v (M, 3)); cand_b NaN where there is no second
    root. Returns (take_b (M,) bool, ambiguous (M,) bool, reason (M,) str, '' unless
    ambiguous). A problem without a finite cand_b keeps cand_a.
    """
    (pa, va), (pb, vb) = cand_a, cand_b
    M = data.M
    ca, cb = cost(data, pa, va), cost(data, pb, vb)
    has_b = np.isfinite(cb)
    take_b = has_b & (cb < ca)
    ambiguous = np.zeros(M, dtype=bool)
    reason = np.full(M, '', dtype=object)
    close = has_b & np.isfinite(ca) & (np.abs(cb - ca) <= ROOT_THRESHOLD)
    if not np.any(close):
        return take_b, ambiguous, reason
    i = np.nonzero(close)[0]
    sub = data.take(i)
    ra, rb = np.linalg.norm(pa[i], axis=-1), np.linalg.norm(pb[i], axis=-1)
    sd = range_std(sub, pa[i], va[i], speed_reference)
    apart = np.abs(ra - rb) > sd
    tau_l = sub.tau[:, -1:]
    for j in np.nonzero(apart)[0]:
        m = i[j]
        last = [np.linalg.norm(p + w * tau_l[j] - sub.delta[j, -1])
                for p, w in ((pa[m], va[m]), (pb[m], vb[m]))]
        ambiguous[m] = True
        reason[m] = (f'two ranges fit the ground speed prior ({min(last) / 1e3:.4g} and '
                     f'{max(last) / 1e3:.4g} km at the last bearing) and the bearings do '
                     f'not tell them apart (log-likelihood ratio {abs(cb[m] - ca[m]):.3g}, '
                     f'needs > {ROOT_THRESHOLD:.3g}): the observer is faster than the '
                     'target; a turn of the observer separates them')
    return take_b, ambiguous, reason


def resolve(data, p0, v, status, reason, ok, speed_reference, alternative=None):
    """Apply (T23) to fixes (p0, v) (M, 3) whose ``ok`` (M,) mask marks the candidates.

    ``alternative``: the second candidates (p0, v), default the mirrors k·(p0, v) of the
    fixes. Only 'ground' has a second root; 'relative' returns the inputs. Returns
    (p0, v, status, reason, take_b) with ambiguous fixes ``unobservable`` (state NaN).
    """
    p0, v = p0.copy(), v.copy()
    status, reason = status.copy(), reason.copy()
    take_b = np.zeros(data.M, dtype=bool)
    if speed_reference != 'ground' or not np.any(ok):
        return p0, v, status, reason, take_b
    if alternative is None:
        k = np.where(ok, mirror_scale(v, data.v_o, data.speed), np.nan)
        alternative = (k[:, None] * p0, k[:, None] * v)
    pb = np.where(ok[:, None], alternative[0], np.nan)
    vb = np.where(ok[:, None], alternative[1], np.nan)
    take_b, ambiguous, why = choose(data, (p0, v), (pb, vb), speed_reference)
    take_b &= ok & ~ambiguous
    p0[take_b], v[take_b] = pb[take_b], vb[take_b]
    amb = ok & ambiguous
    status[amb] = STATUS_UNOBSERVABLE
    reason[amb] = why[amb]
    p0[amb] = np.nan
    v[amb] = np.nan
    return p0, v, status, reason, take_b
