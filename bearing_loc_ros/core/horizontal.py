"""Horizontal localization and the ``dimension`` selection (``auto | 3d | horizontal``).

Conventions (DESIGN.md): ENU metres, azimuth θ CCW from East, elevation ψ above the horizontal,
radians; an azimuth-only (1D) bearing has elevation NaN.

Most direction-finding networks measure azimuth only, and azimuths never fix the height. The
horizontal solve estimates (x, y) with the target altitude stated by the user: z₀ (m, world
frame) with standard deviation σ_z (m, 0 = exactly known), a Gaussian prior N(z₀, σ_z²) on z
(:mod:`.horizontal_crlb` derives the bound; :mod:`.horizontal_estimators`,
:mod:`.horizontal_ctls` and :mod:`.horizontal_ml` hold the estimators). Elevations present are
still used: with the altitude known, a 2D station's elevation gives the horizontal range
ρ_i = (z₀ − z_i)/tan ψ_i. The fix carries z = z₀ (``mle``/``wmle`` with σ_z > 0 and
elevations: the posterior z), variance σ_z² for an azimuth-only set (otherwise the posterior
variance) and no x-y/z correlation unless elevations create one.

Dimension selection, per problem (:func:`select_dimension`):

* ``3d``: the 3D estimators of core/estimators.py (they need at least one elevation).
* ``horizontal``: always the horizontal solve (``target_altitude`` required), for example for
  ground emitters whose elevations are spoiled by multipath (option ``use_elevations=False``
  then ignores them).
* ``auto``: 3D when the set observes the height (:func:`height_observed`), else horizontal.
  Without a stated altitude a set with any elevation is solved in 3D (as before the
  horizontal mode existed: the 3D estimator reports ``degenerate_geometry`` where the
  height is not observed); an azimuth-only set then raises ``target_altitude: required``.
  With ``use_elevations=False`` no set observes the height: ``auto`` solves every set
  horizontally, and ``3d`` is a ValueError naming ``use_elevations``.

Height observed: at least one elevation, a 3D pseudo-linear solution (Wang, Zhang & Wu
eq. (4)) exists, and the 3D Fisher information J (Zong & Cui 2015 eq. (7), core/crlb.py)
evaluated there has eigenvalue ratio λ_min/λ_max ≥ :data:`HEIGHT_RCOND` = 1e-6, i.e. the
worst-determined direction's CRLB standard deviation is at most 1000 times the best one's.
One elevation is not always enough: with every station and the target on one vertical
plane, a single elevation constrains only a combination of the along-line position and the
height (J has rank 2); two elevations from that plane triangulate it.
"""

from dataclasses import replace

import numpy as np

from . import horizontal_estimators as _h
from . import horizontal_ml as _ml
from .bearings import BearingSet, simulate_bearings as _simulate
from .crlb import fisher_information
from .estimator_spec import CONSISTENCY, DIMENSIONS, ROBUST, ROBUST_ON
from .estimators import DEFAULT_ESTIMATOR, locate as locate_3d, ls as ls_3d
from .fix import FixResult
from .robust_model import CONSISTENCY_PROBABILITY

__all__ = ['DIMENSIONS', 'ESTIMATORS', 'height_observed', 'locate', 'locate_horizontal',
           'select_dimension', 'simulate_bearings']
SOLVE_3D = '3d'
SOLVE_HORIZONTAL = 'horizontal'
#: Minimum eigenvalue ratio of the 3D Fisher information for ``auto`` to solve in 3D.
HEIGHT_RCOND = 1e-6


def _constrained_tls(weighting):
    def run(p, **options):
        from .horizontal_ctls import constrained_tls
        return constrained_tls(p, weighting, **options)
    return run


#: Horizontal estimators by name (the same names as the 3D ones).
ESTIMATORS = {
    'ls': _h.ls,
    'tls': _h.tls,
    'ctls': _constrained_tls('paper'),
    'ctls_am': _constrained_tls('am'),
    'mle': _ml.mle,
    'wmle': _ml.wmle,
}
OPTION_DEFAULTS = _h.OPTION_DEFAULTS
#: Horizontal estimators that take option ``robust`` (as their 3D namesakes do).
ROBUST_ESTIMATORS = ('mle', 'wmle')


def _wrap(result, solve, z0, sz):
    M = result.position.shape[0]
    return FixResult(position=result.position, covariance=result.covariance,
                     iterations=result.iterations, converged=result.converged,
                     status=result.status, method=result.method,
                     excluded=result.excluded, nonlinearity=result.nonlinearity,
                     solve=np.full(M, solve, dtype=object).astype(str),
                     target_altitude=np.broadcast_to(np.asarray(z0, dtype=float), (M,)).copy(),
                     target_altitude_sigma=np.broadcast_to(np.asarray(sz, dtype=float),
                                                           (M,)).copy())


def _method(method):
    if method is None:
        return DEFAULT_ESTIMATOR
    if not isinstance(method, str) or method not in ESTIMATORS:
        raise ValueError(f'method: unknown estimator {method!r}; choose one of '
                         f'{sorted(ESTIMATORS)}')
    return method


def locate_horizontal(method, bearings, target_altitude, target_altitude_sigma=0.0,
                      use_elevations=True, **options):
    """Horizontal fix of M problems with estimator ``method`` (None = ``mle``).

    Args:
        method: ``ls``, ``tls``, ``ctls``, ``ctls_am``, ``mle`` or ``wmle``.
        bearings: BearingSet (M, N), any mix of 1D/2D bearings, N ≥ 2.
        target_altitude: z₀, m, world frame (scalar or (M,)), finite.
        target_altitude_sigma: σ_z, m (scalar or (M,)), finite ≥ 0; 0 = exactly known.
        use_elevations: use the measured elevations (range information given z₀).
        options: estimator options (see :mod:`.horizontal_estimators`); ``mle`` and ``wmle``
            also take ``robust`` (:mod:`.horizontal_robust`: screen, pairwise consensus,
            refit without outlier bearings, status ok or low_confidence, ``excluded``),
            default true for ``mle`` and false for ``wmle``, as in 3D; the others take
            ``consistency`` (default true, as in 3D: :func:`consistency_status`).

    Returns a FixResult (core.fix) with ``solve`` = ``'horizontal'``: position (M, 3) with
    z = z₀ (or its posterior), covariance (M, 3, 3) (z block σ_z² for azimuth-only sets).
    Raises ``ValueError`` naming the field for bad input
    (:func:`.horizontal_estimators.prepare`).
    """
    method = _method(method)
    options = dict(options)
    given = 'robust' in options
    # The 3D namesakes' defaults: ``mle`` robust (the default estimator), ``wmle`` opt-in.
    robust = options.pop('robust', ROBUST_ON.default if method == 'mle' else ROBUST.default)
    if method in ROBUST_ESTIMATORS:
        robust = ROBUST.validate(robust)
    elif given:
        raise ValueError(f'options.robust: unknown option for estimator {method!r} (accepted '
                         f'by {", ".join(ROBUST_ESTIMATORS)})')
    else:
        robust = False
    consistency = False
    if method not in ROBUST_ESTIMATORS:
        consistency = CONSISTENCY.validate(options.pop('consistency', CONSISTENCY.default))
    p = _h.prepare(bearings, target_altitude, target_altitude_sigma, use_elevations)
    res = ESTIMATORS[method](p, **options)
    if consistency:
        res = consistency_status(res, p)
    if not robust:
        return _wrap(res, SOLVE_HORIZONTAL, p.z0, p.sz)
    return _wrap(_robust(method, bearings, res, p, options), SOLVE_HORIZONTAL, p.z0, p.sz)


def _robust(method, bearings, res, p, options):
    """Problem by problem :func:`.horizontal_robust.robust_fix`; FixResult with ``excluded``."""
    from .horizontal_robust import calm_grown_one, nonlinearity, robust_fix, screen_one_nu
    from .estimator_spec import DEFAULT_REFERENCE_RANGE
    d_ref = (options.get('reference_range', DEFAULT_REFERENCE_RANGE) if method == 'wmle'
             else None)
    names = ('position', 'covariance', 'iterations', 'converged', 'status')

    def nu_of(fields, excluded):
        # ν of every ok or low_confidence fix over the stations it kept (NaN otherwise), where
        # robust_fix did not report the ν its status took.
        nu = nonlinearity(fields['position'], fields['covariance'][:, :3, :3],
                          bearings.positions, ~excluded[:, :, 0])
        return np.where(np.isin(fields['status'], ('ok', 'low_confidence')), nu, np.nan)

    if bearings.M == 1 and d_ref is None:
        calm, nu = screen_one_nu(bearings, res, p.use_el[0], d_ref)
        if calm:
            # One fix that passes the screen (decided on floats): kept as it is, with the
            # ν the screen took.
            fields = {k: np.array(getattr(res, k)) for k in names}
            return FixResult(method=method, excluded=np.zeros((1, bearings.N, 2), dtype=bool),
                             nonlinearity=np.array([nu]), **fields)
    if bearings.M == 1 and d_ref is not None:
        # One wmle fix whose residuals are calm (decided compiled): robust_fix's calm branch.
        fix = calm_grown_one(bearings, res, p.use_el[0], d_ref, float(p.sz[0]))
        if fix is not None and np.isnan(fix.nonlinearity[0]):
            fields = {k: np.array(getattr(fix, k)) for k in names}
            fix = FixResult(method=method, excluded=fix.excluded,
                            nonlinearity=nu_of(fields, fix.excluded), **fields)
        if fix is not None:
            return fix
    fields = {k: np.array(getattr(res, k)) for k in names}
    fields['status'] = fields['status'].astype(object)
    excluded = np.zeros((bearings.M, bearings.N, 2), dtype=bool)
    opts = {k: v for k, v in options.items() if k != 'initial'}
    # Range-grown σ: every fix is assessed (its covariance is widened, robust_fix).
    todo = (np.ones(bearings.M, dtype=bool) if d_ref is not None
            else ~screen_passed(bearings, res, p, d_ref))
    assessed = np.full(bearings.M, np.nan)      # ν as robust_fix's status took it
    for m in np.flatnonzero(todo).tolist():
        bs = bearings.problem(m)
        z0, sz, use_el = float(p.z0[m]), float(p.sz[m]), p.use_el[m]

        def solve(sub, x0, z0=z0, sz=sz, use_el=use_el):
            q = _h.prepare(sub, z0, sz, bool(np.any(use_el)))
            return ESTIMATORS[method](q, initial=x0, **opts)

        one = FixResult(*(fields[k][m:m + 1] for k in names), method)
        out, ex = robust_fix(solve, bs, one, z0, use_el, d_ref, sz)
        for k in fields:
            fields[k][m] = getattr(out, k)[0]
        if out.nonlinearity is not None:
            assessed[m] = out.nonlinearity[0]
        excluded[m, :, 0] = ex
        excluded[m, :, 1] = ex & bearings.has_elevation[m]
    fields['status'] = fields['status'].astype(str)
    missing = np.isnan(assessed)
    nu = np.where(missing, nu_of(fields, excluded), assessed) if missing.any() else assessed
    return FixResult(method=method, excluded=excluded, nonlinearity=nu, **fields)


#: Gauss-Newton iterations of the horizontal consistency check (:func:`consistency_status`).
CONSISTENCY_ITERATIONS = 5


def consistency_status(res, p, probability=CONSISTENCY_PROBABILITY):
    """``res`` (a horizontal FixResult of problem ``p``) with every ``ok`` fix that fails a
    consistency check marked ``low_confidence`` (``converged`` False) and every one that
    passes widened to P + δδᵀ.

    The horizontal twin of :func:`.robust.consistency_status` (option ``consistency`` of
    ``ls``, ``tls``, ``ctls``, ``ctls_am``). Unknowns x, y and, when σ_z > 0, z with the
    stated altitude as one more measurement (z₀ − z)/σ_z; measurements the azimuths and the
    used elevations, whitened by their σ. These fixes hold z = z₀, which with σ_z > 0 and an
    elevation lies far from the likelihood's optimum, where one linearised step predicts
    it poorly; so Gauss-Newton (Zong & Cui 2015 eq. (8), F = GᵀG, step F⁻¹Gᵀr, G the
    whitened gradients of crlb.angle_jacobians) runs from the fix X̂ for up to
    :data:`CONSISTENCY_ITERATIONS` steps while the χ² falls, to X*. The fix is ``ok`` only
    when χ²(X*) is at most the χ²_max(dof, 1) quantile of ``probability`` (dof = angles −
    2), δ = X* − X̂ has δᵀP⁻¹δ at most the χ²_k quantile (k = 2, or 3 with σ_z > 0; P the
    fix's covariance over the same unknowns), no angle residual at X* is beyond 3.9σ and
    ν ≤ 0.2 (:func:`.horizontal_robust.nonlinearity`). A fix that passes reports P + δδᵀ
    (as in 3D: the covariance covers the bias of a pseudo-linear fix, which with hundreds of
    bearings in window mode is several of its σ). Units: m, rad.
    """
    from .crlb import safe_inverse
    from .fix import STATUS_OK
    from .horizontal_robust import nonlinearity
    from .robust import mark_low_confidence
    from .robust_model import chi2_upper, MAX_REGION_NONLINEARITY, outlier_c2
    status = np.asarray(res.status)
    X = np.asarray(res.position, dtype=float)
    P = np.asarray(res.covariance, dtype=float)
    ok = ((status == STATUS_OK) & np.all(np.isfinite(X), axis=1)
          & np.all(np.isfinite(P), axis=(1, 2)))
    bad = (status == STATUS_OK) & ~ok
    idx = np.flatnonzero(ok)
    if idx.size:
        q = p.take(idx)
        X0 = X[idx]
        vertical = q.sz > 0.0
        with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
            Xk = X0.copy()
            r2, F, b = _plane_terms(q, Xk, vertical)
            chi2 = r2.sum(axis=-1)
            for _ in range(CONSISTENCY_ITERATIONS):
                Xt = Xk + np.einsum('mij,mj->mi', safe_inverse(F), b)
                r2t, Ft, bt = _plane_terms(q, Xt, vertical)
                chi2t = r2t.sum(axis=-1)
                take = chi2t < chi2            # NaN: not taken
                if not take.any():
                    break
                Xk[take], r2[take], F[take], b[take] = Xt[take], r2t[take], Ft[take], bt[take]
                chi2 = np.where(take, chi2t, chi2)
            delta = Xk - X0
            Pq = P[idx].copy()
            Pq[~vertical, 2, :] = Pq[~vertical, :, 2] = 0.0
            Pq[~vertical, 2, 2] = 1.0
            m2 = np.einsum('mi,mi->m', delta, np.einsum('mij,mj->mi', safe_inverse(Pq), delta))
            worst = r2[:, :-1].max(axis=-1)           # the angles, not the altitude prior
            n_angles = q.N + np.count_nonzero(q.use_el, axis=1)
            nu = nonlinearity(X0, P[idx], np.stack([q.px, q.py, q.pz], axis=-1))
            good = ((chi2 <= chi2_upper(np.maximum(n_angles - 2, 1), probability))
                    & (m2 <= chi2_upper(np.where(vertical, 3, 2), probability))
                    & (worst <= outlier_c2()) & (nu <= MAX_REGION_NONLINEARITY))
        bad[idx] = ~good
        widened = P.copy()
        Pi = widened[idx]
        Pi[good] += delta[good][:, :, None] * delta[good][:, None, :]
        widened[idx] = Pi
        res = replace(res, covariance=widened)
    return mark_low_confidence(res, bad)


def _plane_terms(q, X, vertical):
    """(r² (M, 2N + 1), F (M, 3, 3), Gᵀr (M, 3)) of :func:`consistency_status` at X (M, 3):
    the squared whitened residuals of the azimuths, the used elevations (0 where unused) and
    the altitude prior (last column, 0 without σ_z), the information F = GᵀG and Gᵀr; with
    σ_z = 0 (``vertical`` False) z is held, F's z row and column are the unit vector and
    Gᵀr's z entry 0."""
    from .conventions import wrap_angle
    from .crlb import angle_jacobians
    pos = np.stack([q.px, q.py, q.pz], axis=-1)
    d = X[:, None, :] - pos
    ra = wrap_angle(q.az - np.arctan2(d[..., 1], d[..., 0])) / q.saz
    sel = np.where(q.use_el, q.sel, 1.0)
    el_pred = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    re = np.where(q.use_el, (q.el - el_pred) / sel, 0.0)
    ga, ge = angle_jacobians(X, pos)
    ga = ga / q.saz[..., None]
    ge = np.where(q.use_el[..., None], ge / sel[..., None], 0.0)
    sz = np.where(vertical, q.sz, 1.0)
    rz = np.where(vertical, (q.z0 - X[:, 2]) / sz, 0.0)
    F = np.einsum('mni,mnj->mij', ga, ga) + np.einsum('mni,mnj->mij', ge, ge)
    F[:, 2, 2] += np.where(vertical, 1.0 / (sz * sz), 0.0)
    b = np.einsum('mn,mni->mi', ra, ga) + np.einsum('mn,mni->mi', re, ge)
    b[:, 2] += rz / sz
    F[~vertical, 2, :] = F[~vertical, :, 2] = 0.0
    F[~vertical, 2, 2] = 1.0
    b[~vertical, 2] = 0.0
    r2 = np.concatenate([ra * ra, re * re, (rz * rz)[:, None]], axis=-1)
    return r2, F, b


def screen_passed(bearings, res, p, d_ref=None):
    """(M,) bool: fixes that pass the robust screen (:mod:`.horizontal_robust` step 1),
    vectorised over problems: status ok, every d² ≤ c², Σ d² at most the χ²_dof quantile
    (dof = used angles − 2) and ν ≤ max_nonlinearity (:func:`.horizontal_robust.nonlinearity`);
    those are kept as they are, the others go to :func:`.horizontal_robust.robust_fix`."""
    from .horizontal_robust import _c2, chi2_upper, max_nonlinearity, nonlinearity
    from .conventions import azimuth_elevation
    X = np.asarray(res.position, dtype=float)
    ok = (np.asarray(res.status) == 'ok') & np.all(np.isfinite(X), axis=1)
    Xs = np.where(ok[:, None], X, 0.0)
    d = Xs[:, None, :] - bearings.positions
    az, el = azimuth_elevation(d)
    f = 1.0 if d_ref is None else np.linalg.norm(d, axis=-1) / d_ref
    with np.errstate(invalid='ignore', divide='ignore'):
        d2 = (np.angle(np.exp(1j * (bearings.azimuth - az))) / (bearings.sigma_az * f)) ** 2
        d2e = np.where(p.use_el, (np.where(p.use_el, bearings.elevation, 0.0) - el) ** 2
                       / (np.where(p.use_el, bearings.sigma_el, 1.0) * f) ** 2, 0.0)
    d2 = d2 + d2e
    n_angles = bearings.N + np.count_nonzero(p.use_el, axis=1)
    nu = nonlinearity(Xs, np.asarray(res.covariance, dtype=float)[:, :3, :3],
                      bearings.positions)
    with np.errstate(invalid='ignore'):
        calm_nu = nu <= max_nonlinearity(d_ref is not None)
    return (ok & np.all(d2 <= _c2(), axis=1) & calm_nu
            & (d2.sum(axis=1) <= chi2_upper(np.maximum(n_angles - 2, 1))))


def _subset(bearings, idx):
    """Problems ``idx`` of a BearingSet (no validation)."""
    return BearingSet(bearings.positions[idx], bearings.azimuth[idx], bearings.elevation[idx],
                      bearings.sigma_az[idx], bearings.sigma_el[idx], bearings.stations)


def height_observed(bearings):
    """(M,) bool: does each problem observe the target height? (module docstring criterion)."""
    if not isinstance(bearings, BearingSet):
        raise ValueError(f'bearings: expected a BearingSet, got {type(bearings).__name__}')
    n_el = np.count_nonzero(bearings.has_elevation, axis=1)
    out = np.zeros(bearings.M, dtype=bool)
    idx = np.flatnonzero((n_el >= 1) & (bearings.N + n_el >= 3) & (bearings.N >= 2))
    if idx.size == 0:
        return out
    sub = _subset(bearings, idx)
    x = ls_3d(sub, consistency=False).position
    finite = np.all(np.isfinite(x), axis=1)
    J = fisher_information(np.where(finite[:, None], x, 0.0), sub.positions, sub.sigma_az,
                           sub.sigma_el, sub.has_elevation)
    good = finite & np.all(np.isfinite(J), axis=(1, 2))
    w = np.linalg.eigvalsh(np.where(good[:, None, None], J, np.eye(3)))
    out[idx] = good & (w[:, -1] > 0) & (w[:, 0] >= HEIGHT_RCOND * w[:, -1])
    return out


def select_dimension(bearings, dimension='auto', use_elevations=True):
    """The solve (``'3d'`` or ``'horizontal'``) of each problem, (M,) str array.

    ``dimension``: ``auto`` (3D where :func:`height_observed`, else horizontal), ``3d`` or
    ``horizontal`` (forced). ValueError naming ``dimension`` for another value.
    ``use_elevations`` False: the elevations are ignored, so no problem observes the height:
    ``auto`` gives horizontal everywhere and ``3d`` is a ValueError naming
    ``use_elevations``. (:func:`locate` with ``auto`` and no stated altitude keeps the 3D
    solve for every set with an elevation it may use.)
    """
    if dimension not in DIMENSIONS:
        raise ValueError(f'dimension: must be one of {", ".join(DIMENSIONS)}, got {dimension!r}')
    if not use_elevations:
        if dimension == SOLVE_3D:
            raise ValueError('use_elevations: false leaves nothing to observe the height; the '
                             '3d solve needs elevations (use dimension auto or horizontal '
                             'with target_altitude)')
        return np.full(bearings.M, SOLVE_HORIZONTAL, dtype=object).astype(str)
    if dimension == 'auto':
        return np.where(height_observed(bearings), SOLVE_3D, SOLVE_HORIZONTAL)
    return np.full(bearings.M, dimension, dtype=object).astype(str)


def locate(method, bearings, dimension='auto', target_altitude=None, target_altitude_sigma=0.0,
           use_elevations=True, **options):
    """Fix of M problems in the selected dimension; returns a FixResult (core.fix).

    3D problems go to core/estimators.py ``locate`` (``target_altitude`` is not used there);
    horizontal ones to :func:`locate_horizontal`. With ``auto``, a problem that does not
    observe the height and has no ``target_altitude`` raises ``ValueError('target_altitude:
    ...')``. A batch whose problems select different solves is split and merged.
    """
    method = _method(method)
    if not isinstance(bearings, BearingSet):
        raise ValueError(f'bearings: expected a BearingSet, got {type(bearings).__name__}')
    use_elevations = _h.check_bool(use_elevations, 'use_elevations')
    solves = select_dimension(bearings, dimension, use_elevations)
    if dimension == 'auto' and target_altitude is None and use_elevations:
        # No altitude stated: a set with an elevation keeps the 3D solve (which reports
        # degenerate_geometry itself where the height is not observed).
        any_el = np.any(bearings.has_elevation, axis=1)
        solves = np.where(any_el, SOLVE_3D, solves)
    horiz = solves == SOLVE_HORIZONTAL
    if np.any(horiz) and target_altitude is None:
        why = ('dimension is horizontal' if dimension == SOLVE_HORIZONTAL else
               'use_elevations is false' if not use_elevations else
               'the bearings do not observe the height (no usable elevation geometry)')
        raise ValueError(f'target_altitude: required because {why}; state the target altitude '
                         '(m, world frame) and its standard deviation')
    if np.all(horiz):
        return locate_horizontal(method, bearings, target_altitude, target_altitude_sigma,
                                 use_elevations, **options)
    if not np.any(horiz):
        res = locate_3d(method, bearings, **options)
        return _wrap(res, SOLVE_3D, np.nan, np.nan)
    M = bearings.M
    i_h, i_3 = np.flatnonzero(horiz), np.flatnonzero(~horiz)
    z0 = np.broadcast_to(np.asarray(target_altitude, dtype=float), (M,))
    sz = np.broadcast_to(np.asarray(target_altitude_sigma, dtype=float), (M,))
    opt_h, opt_3 = dict(options), dict(options)
    if options.get('initial') is not None:
        x0 = np.asarray(options['initial'], dtype=float)
        if x0.ndim == 2 and x0.shape[0] == M:
            opt_h['initial'], opt_3['initial'] = x0[i_h], x0[i_3]
    rh = locate_horizontal(method, _subset(bearings, i_h), z0[i_h], sz[i_h], use_elevations,
                           **opt_h)
    r3 = locate_3d(method, _subset(bearings, i_3), **opt_3)
    out = _wrap(r3, SOLVE_3D, np.nan, np.nan)
    fields = ('position', 'covariance', 'iterations', 'converged', 'status', 'solve',
              'target_altitude', 'target_altitude_sigma')
    merged = {}
    for name in fields:
        a3 = getattr(out, name)
        ah = getattr(rh, name)
        arr = np.empty((M,) + a3.shape[1:], dtype=np.result_type(a3, ah))
        arr[i_3], arr[i_h] = a3, ah
        merged[name] = arr
    # Robust results of either side: exclusions (nothing excluded where a side has none) and
    # ν (NaN where a side has none).
    for name, shape, fill in (('excluded', (bearings.N, 2), False),
                              ('nonlinearity', (), np.nan)):
        parts = [(getattr(r, name), idx) for r, idx in ((out, i_3), (rh, i_h))]
        if all(a is None for a, _ in parts):
            continue
        arr = np.full((M,) + shape, fill, dtype=bool if fill is False else float)
        for a, idx in parts:
            if a is not None:
                arr[idx] = a
        merged[name] = arr
    return FixResult(method=method, **merged)


def simulate_bearings(target, positions, sigma_az, sigma_el=None, has_elevation=False, rng=None):
    """Noisy bearings of any 1D/2D mix, azimuth-only sets included, as a BearingSet.

    Same model as core/bearings.py ``simulate_bearings`` (Wang, Zhang & Wu eq. (1) with the
    additive Gaussian noise of eq. (6)): θ_i = θ_i* + n_i, ψ_i = ψ_i* + m_i, for targets
    ``target`` (M, 3) or (3,) and stations ``positions`` (N, 3) or (M, N, 3), m; σ (rad)
    scalars or broadcastable to (M, N); ``has_elevation`` a bool or (N,) mask (default:
    azimuth only); ``rng`` a numpy Generator (None: noise-free). The set is checked with the
    field rules of BearingSet.validate without the 3D demand for an elevation.
    """
    return _simulate(target, positions, sigma_az, sigma_el, has_elevation, rng,
                     require_elevation=False)
