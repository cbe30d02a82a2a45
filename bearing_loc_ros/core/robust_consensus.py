"""Consensus and refit of a maximum likelihood fix (steps 2-3 of the :mod:`.robust` docstring).

Candidates from the pseudo-linear ``ls`` fix (Wang, Zhang & Wu eq. (4)) of station subsets,
an MSAC score with the log σ² term, and Levenberg-Marquardt on the full negative
log-likelihood of the inliers (Zong & Cui 2015 eqs. (3)-(11) with the log σ(d) term).
Units: m, rad. Re-exported from :mod:`.robust`.
"""

from functools import lru_cache
from itertools import combinations

import numpy as np

from .crlb import safe_inverse
from .robust_model import (chi2_band, chi2_upper, fisher, MULTIMODE_PROBABILITY, outlier_c2,
                           REFIT_ITERATIONS, REFIT_ROUNDS)


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
    inv = _psd_inverse(Ak.reshape(-1, 3, 3)).reshape(Ak.shape)
    return np.einsum('mkij,mkj->mki', inv, bk)


def _psd_inverse(A, rcond=1e-12):
    """:func:`.crlb.safe_inverse` of symmetric (K, 3, 3), its rank test mostly in closed form.

    The same inverse (``np.linalg.inv``) and the same test, smallest eigenvalue above
    ``rcond`` times the largest and the largest positive (+inf where it fails or A is not
    finite). The extreme eigenvalues come from the trigonometric solution of the
    characteristic cubic (Smith 1961), a few elementwise operations on the K matrices (the
    consensus tests up to N(N + 1)/2 + 1 of them per problem) instead of LAPACK. Its smallest
    eigenvalue can be off by up to about sqrt(ε) λ_max when the two smallest nearly
    coincide, so every matrix whose closed-form λ_min is below :data:`_CLOSED_FORM_CLEAR`
    λ_max (or not finite) is decided by LAPACK's ``eigvalsh``, as in safe_inverse.
    """
    a, b, c = A[:, 0, 0], A[:, 1, 1], A[:, 2, 2]
    d, e, f = A[:, 0, 1], A[:, 1, 2], A[:, 0, 2]
    with np.errstate(all='ignore'):
        q = (a + b + c) / 3.0
        aa, bb, cc = a - q, b - q, c - q
        r = np.sqrt((aa * aa + bb * bb + cc * cc + 2.0 * (d * d + e * e + f * f)) / 6.0)
        det = (aa * (bb * cc - e * e) - d * (d * cc - e * f) + f * (d * e - bb * f)) / r ** 3
        phi = np.arccos(np.clip(0.5 * det, -1.0, 1.0)) / 3.0
        hi = np.where(r > 0.0, q + 2.0 * r * np.cos(phi), q)
        lo = np.where(r > 0.0, q + 2.0 * r * np.cos(phi + 2.0 * np.pi / 3.0), q)
    finite = np.all(np.isfinite(A), axis=(-2, -1))
    ok = (lo > _CLOSED_FORM_CLEAR * np.abs(hi)) & (hi > 0.0) & finite
    unclear = ~ok & finite
    if unclear.any():
        w = np.linalg.eigvalsh(A[unclear])
        ok[unclear] = (w[:, 0] > rcond * np.abs(w[:, -1])) & (w[:, -1] > 0)
    out = np.full(A.shape, np.inf)
    if ok.any():
        out[ok] = np.linalg.inv(A[ok])
    return out


#: Closed-form λ_min / λ_max above which a matrix certainly passes the 1e-12 rank test
#: (the closed form's error is at most about sqrt(ε) ≈ 1.5e-8 of λ_max).
_CLOSED_FORM_CLEAR = 1e-5


#: Largest N whose consensus tries every subset leaving out one or two stations.
MAX_SUBSET_STATIONS = 16


@lru_cache(maxsize=64)
def _station_masks(N):
    """Station subsets of the consensus (K, N) of 0/1: all stations, then

    - N ≤ :data:`MAX_SUBSET_STATIONS`: leaving out each station and, for N ≥ 5, each pair
      (1 + N + N(N − 1)/2 subsets);
    - larger N: every pair among :data:`MAX_SUBSET_STATIONS` stations spread evenly over
      the set (minimal subsets, as in RANSAC; 121 subsets whatever N). Leaving out one or two
      of hundreds of stations barely moves the all-station fix, and scoring N²/2 candidates
      over N stations costs O(N³) time and memory (3 GB at N = 400).
    """
    rows = [np.ones(N)]
    if N > MAX_SUBSET_STATIONS:
        idx = np.unique(np.round(np.linspace(0, N - 1, MAX_SUBSET_STATIONS)).astype(int))
        for i, j in combinations(idx.tolist(), 2):
            m = np.zeros(N)
            m[[i, j]] = 1.0
            rows.append(m)
        return np.array(rows)
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
    """MSAC score with the log σ² of the inliers (:mod:`.robust` docstring step 2), (M, K)."""
    ra, re, _, _, _, _, log_s2 = data.evaluate(X, gradients=False)
    has = data.has_el if X.ndim == 2 else data.has_el[:, None]
    qa, qe = ra * ra, np.where(has, re * re, 0.0)
    ina, ine = qa <= c2, has & (qe <= c2)
    s = (np.minimum(qa, c2) + np.minimum(qe, c2) + log_s2 * (ina + ine.astype(float)))
    s = s.sum(axis=-1)
    return np.where(np.isfinite(s), s, np.inf)


#: A refit step is taken when L does not increase by more than ACCEPT_TOL (1 + |L|): above
#: the rounding of L near its minimum (whitened angle differences lose a few ulp of 1/σ
#: each), far below any change of L that matters. A strict L_new ≤ L stops the iteration
#: wherever rounding first rejects a step, up to ~1e-7 of the fix's σ short of the optimum;
#: the batch and one-problem paths round differently, so they stopped at different points
#: (1e-8 of the range apart at σ_ref 2°, Zong & Cui scenario). With the tolerance both
#: iterate on to the step criterion.
ACCEPT_TOL = 1e-12
#: A refit stops when its step is below STEP_TOL of the rms station range.
STEP_TOL = 1e-10


def _refit(data, X0, wa, we, iterations=REFIT_ITERATIONS):
    """Levenberg-Marquardt on L(X) = Σ w_j (r_j² + log σ_j²) over M problems -> X (M, 3).

    Fisher scoring step: (F + λ diag F) Δ = −½∇L with F = Σ w_j g_j g_jᵀ (+ Σ w_j 2 u uᵀ/d²,
    the information of σ(d) under range growth), ½∇L = Σ_j w_j [−r_j g_j + (1 − r_j²) u_k/d_k]
    with range growth (the σ(d) and log σ(d) derivatives) and −Σ w_j r_j g_j without. A step
    is taken when L does not increase beyond its rounding (:data:`ACCEPT_TOL`); λ ×10 on
    rejection, ÷10 on acceptance. A problem stops when its step is below :data:`STEP_TOL`
    of its rms range or λ > 1e10 (each problem on its own: the result does not depend on
    the other problems of the batch).
    """
    grow = data.d_ref is not None
    out = np.array(X0, dtype=float)
    if not out.shape[0]:
        return out
    live = np.arange(out.shape[0])          # the problems still iterating (rows of X …)
    X = out.copy()
    lam = np.zeros(X.shape[0])

    def parts(data, X, wa, we):
        ra, re, ga, ge, u, d, log_s2 = data.evaluate(X)
        if grow:
            cost = (wa * (ra * ra + log_s2) + we * (re * re + log_s2)).sum(axis=-1)
        else:               # log σ² = 0: r² + 0 is r² (r² ≥ +0)
            cost = (wa * (ra * ra) + we * (re * re)).sum(axis=-1)
        return cost, ra, re, ga, ge, u, d

    cost, ra, re, ga, ge, u, d = parts(data, X, wa, we)
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
                step = -_solve_rows(Fd, grad)
        step = np.where(np.isfinite(step), step, 0.0)
        Xt = X + step
        ct, rat, ret, gat, get, ut, dt = parts(data, Xt, wa, we)
        acc = np.isfinite(ct) & (ct <= cost + ACCEPT_TOL * (1.0 + np.abs(cost)))
        if acc.all():
            X, cost, ra, re, ga, ge, u, d = Xt, ct, rat, ret, gat, get, ut, dt
        elif acc.any():
            X = np.where(acc[:, None], Xt, X)
            cost = np.where(acc, ct, cost)
            ra, re = np.where(acc[:, None], rat, ra), np.where(acc[:, None], ret, re)
            ga = np.where(acc[:, None, None], gat, ga)
            ge = np.where(acc[:, None, None], get, ge)
            if grow:
                u = np.where(acc[:, None, None], ut, u)
            d = np.where(acc[:, None], dt, d)
        lam = np.where(acc, 0.1 * lam * (lam > 1e-6), np.maximum(10.0 * lam, 1e-3))
        # rms range and step length (np.mean and np.linalg.norm's operations, without
        # their Python overhead)
        scale = np.sqrt((d * d).sum(axis=-1) / d.shape[-1])
        stop = (np.sqrt((step * step).sum(axis=-1)) <= STEP_TOL * scale) | (lam > 1e10)
        if stop.any():
            # Finished problems leave the arrays: the others iterate on alone (each row's
            # arithmetic is its own, so the result is the same).
            out[live[stop]] = X[stop]
            go = ~stop
            if not go.any():
                return out
            live = live[go]
            X, cost, lam, ra, re, ga, ge, d = (X[go], cost[go], lam[go], ra[go], re[go],
                                               ga[go], ge[go], d[go])
            u = u[go] if grow else u
            wa, we = wa[go], we[go]
            data = data.take(go)
    out[live] = X
    return out


def _solve_rows(A, b):
    """A x = b for (M, 3, 3) A, (M, 3) b, problem by problem, as each alone would be solved.

    The batch ``np.linalg.solve`` raises for all M when one A is singular; each problem then
    gets what its own call gives (``solve``, or x = safe_inverse(A) b where it raises), so
    that no problem's refit depends on the others of its batch.
    """
    x = np.empty(b.shape)
    for m in range(A.shape[0]):
        try:
            x[m] = np.linalg.solve(A[m:m + 1], b[m:m + 1, :, None])[0, :, 0]
        except np.linalg.LinAlgError:
            x[m] = safe_inverse(A[m:m + 1])[0] @ b[m]
    return x


def _inliers(data, X, c2):
    ra, re, *_ = data.evaluate(X, gradients=False)
    wa = (ra * ra <= c2).astype(float)
    we = (data.has_el & (re * re <= c2)).astype(float)
    return wa, we


def _solvable(data, wa, we):
    """At least two stations with a kept angle, one kept elevation, three kept angles."""
    st = ((wa + we) > 0).sum(axis=-1)
    return (st >= 2) & (we.sum(axis=-1) >= 1) & ((wa + we).sum(axis=-1) >= 3)


def consensus_fit(data, X_ml, c2=None, with_all=False):
    """Steps 2-3 of the :mod:`.robust` docstring for M problems: (X (M, 3), wa, we (M, N)).

    ``X_ml`` (M, 3) is the estimator's own fix (a candidate; NaN allowed). wa, we are the
    inlier indicators of the azimuths and elevations (1 kept, 0 excluded). With
    ``with_all``, a fourth item X_all (M, 3): the fit of all the angles that
    :func:`_prefer_all_bearings` tried and rejected for a fit with exclusions (NaN where
    nothing was excluded or that fit is not finite).
    """
    c2 = outlier_c2() if c2 is None else c2
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
    X, wa, we, X_all = _prefer_all_bearings(data, X, wa, we, X_ml, cand[:, 1])
    return (X, wa, we, X_all) if with_all else (X, wa, we)


def _cost(data, X, wa, we):
    """Full negative log-likelihood L(X) = Σ w_j (r_j² + log σ_j²) (:mod:`.robust` step 3)."""
    ra, re, _, _, _, _, log_s2 = data.evaluate(X, gradients=False)
    c = (wa * (ra * ra + log_s2) + we * (re * re + log_s2)).sum(axis=-1)
    return np.where(np.isfinite(c), c, np.inf)


def _prefer_all_bearings(data, X, wa, we, X_ml, X_ls):
    """Keep every bearing when a consistent fit of all of them exists (steps 2-3).

    A bearing is called an outlier only when no fit of *all* the bearings passes the
    residual χ² test: for the problems with an excluded angle, the full likelihood of all
    angles is refitted from the estimator's fix and from the all-station ``ls`` fix, the
    better one kept (with range-grown σ, not a refit whose χ² is below the lower quantile of
    the two-sided band :func:`.robust_model.chi2_band`: it has run out in range, where σ(d)
    covers any residual); if its χ² ≤ the χ²_dof quantile of
    :data:`.robust_model.CONSISTENCY_PROBABILITY` it replaces the fit with exclusions. (At
    low SNR a subset can fit a wrong point closer to the stations, where range-grown σ are
    small, and exclude the good bearings that contradict it.) Returns (X, wa, we, X_all),
    X_all (M, 3) the rejected fit of all the angles (NaN where none was rejected or it is
    not finite), to which :func:`.robust.confident_result` returns when the exclusions do
    not hold up.
    """
    has = data.has_el
    X_all = np.full(X.shape, np.nan)
    exc = np.any(wa == 0, axis=-1) | np.any(has & (we == 0), axis=-1)
    idx = np.flatnonzero(exc)
    if not idx.size:
        return X, wa, we, X_all
    sub = data.take(idx)
    ones = np.ones_like(sub.az)
    she = sub.has_el.astype(float)
    # Both starts (the estimator's fix, the all-station ls fix) in one refit of 2K rows
    # (each row's refit is independent of the others).
    n = idx.size
    starts = np.concatenate([X_ml[idx], X_ls[idx]])
    good = np.all(np.isfinite(starts), axis=-1)
    both = data.take(np.concatenate([idx, idx]))
    ones2, she2 = np.concatenate([ones, ones]), np.concatenate([she, she])
    Xs = _refit(both, np.where(good[:, None], starts, np.concatenate([X[idx], X[idx]])),
                ones2, she2)
    cs = np.where(good, _cost(both, Xs, ones2, she2), np.inf)
    if data.d_ref is not None:
        # A refit that ran out in range, where σ(d) covers any residual, is no fit of the
        # angles: its χ² lies below the band (its iterations can end on the way out, at a
        # lower L than the fit near the stations).
        ra2, re2, *_ = both.evaluate(Xs, gradients=False)
        dof2 = both.az.shape[1] + both.has_el.sum(axis=-1) - 3
        cs = np.where((ra2 * ra2 + she2 * re2 * re2).sum(axis=-1) < chi2_band(dof2)[0],
                      np.inf, cs)
    better = cs[n:] < cs[:n]
    best = np.where(better[:, None], Xs[n:], Xs[:n])
    cost = np.where(better, cs[n:], cs[:n])
    ra, re, *_ = sub.evaluate(best, gradients=False)
    chi2 = (ra * ra + she * re * re).sum(axis=-1)
    dof = sub.az.shape[1] + sub.has_el.sum(axis=-1) - 3
    use = np.isfinite(cost) & (chi2 <= chi2_upper(dof))
    if use.any():
        X, wa, we = X.copy(), wa.copy(), we.copy()
        k = idx[use]
        X[k] = best[use]
        wa[k] = 1.0
        we[k] = has[k].astype(float)
    rest = ~use & np.isfinite(cost)
    X_all[idx[rest]] = best[rest]
    return X, wa, we, X_all


def second_optimum(data, X, wa, we, P, probability=MULTIMODE_PROBABILITY):
    """(M,) True where the likelihood has a second optimum the fix's covariance does not cover.

    Step 4 (e) of the :mod:`.robust` docstring. The pseudo-linear ``ls`` fix of all stations
    (Wang, Zhang & Wu eq. (4)) is the start: where it lies outside the fix's ellipsoid
    (Mahalanobis distance² (X_ls − X̂)ᵀ P⁻¹ (X_ls − X̂) above q = the χ²₃ quantile of
    ``probability``), the full likelihood L of the fix's inliers (``wa``, ``we``) is
    refitted from it. A refit X₂ that stays outside the ellipsoid (distance² > q) with
    L(X₂) − L(X̂) < q lies inside the likelihood-ratio confidence region of that level (Wilks
    1938; the region is {X: L(X) − L(X̂) ≤ χ²₃ quantile}): the region has a second component
    that no single ellipsoid describes, and a consumer trusting P could be wrong by the
    distance to X₂. ``X`` (M, 3) m, ``P`` (M, 3, 3) m²; False where P is not finite.
    """
    M, N = data.az.shape
    q = float(chi2_upper(3, probability))
    finite = np.all(np.isfinite(P), axis=(-2, -1)) & np.all(np.isfinite(X), axis=-1)
    Pi = safe_inverse(np.where(finite[:, None, None], P, np.eye(3)))
    ls = _ls_candidates(data, np.ones((1, N)))[:, 0]

    def dist2(Y):
        dY = Y - X
        with np.errstate(invalid='ignore', over='ignore'):
            return np.einsum('mi,mij,mj->m', dY, Pi, dY)

    idx = np.flatnonzero(finite & np.all(np.isfinite(ls), axis=-1) & (dist2(ls) > q))
    out = np.zeros(M, dtype=bool)
    if not idx.size:
        return out
    sub = data.take(idx)
    a, e = wa[idx], we[idx]
    X2 = _refit(sub, ls[idx], a, e)
    dY = X2 - X[idx]
    with np.errstate(invalid='ignore', over='ignore'):
        far = np.einsum('mi,mij,mj->m', dY, Pi[idx], dY) > q
    close = _cost(sub, X2, a, e) - _cost(sub, X[idx], a, e) < q
    out[idx] = far & close
    return out
