"""Solving one epoch with χ² outlier gating.

With the fix X̂, station i's normalized residual is

    d_i² = (wrap(θ_i − θ_i(X̂)) / σ_θi)² + ((ψ_i − ψ_i(X̂)) / σ_ψi)²

(the Gaussian measurement model of Zong & Cui 2015 eq. (3); second term only for a station
that measures elevation), compared with the χ² quantile of probability ``outlier_gate`` with
k_i = 1 (azimuth only) or 2 (azimuth + elevation) degrees of freedom. The worst offender is
dropped and the fix recomputed while enough stations remain. Angles in rad, ENU convention
(azimuth counter-clockwise from East, elevation above the horizontal; Wang, Zhang & Wu
eq. (1)).
"""

from dataclasses import replace
from functools import lru_cache
import math
import statistics

import numpy as np

from .. import chisq
from .. import estimators as _estimators
from .. import registry as _registry
from ..bearings import BearingSet
from ..conventions import azimuth_elevation, wrap_angle, wrap_angle_scalar
from ..crlb import angle_jacobians
from ..fix import STATUS_LOW_CONFIDENCE
from .results import (BAD_COVARIANCE, DEGENERATE_GEOMETRY, Epoch, ESTIMATOR_ERROR,
                      INCONSISTENT_BEARINGS, NO_ELEVATION, NOT_CONVERGED, OK, TOO_FEW_STATIONS)

#: Epoch reason of a fix that failed its consistency checks (estimator status
#: ``low_confidence``, core.robust): position and covariance are set, but it is no fix.
LOW_CONFIDENCE = 'low_confidence'
_FLOAT_MAX = float(np.finfo(float).max)      # np.nan_to_num's value for +inf


@lru_cache(maxsize=64)
def gate_threshold(probability, dof):
    """χ² gate: the ``probability`` quantile of χ² with ``dof`` degrees of freedom.

    p = 0.999 gives 10.83 (k = 1) and 13.82 (k = 2); p >= 1 disables the gate (inf).
    """
    p = float(probability)
    if p >= 1.0:
        return math.inf
    if dof not in (1, 2):
        raise ValueError(f'dof: expected 1 or 2, got {dof}')
    return float(chisq.ppf(p, dof))


def normalized_residuals(bearings, position, position_covariance=None):
    """Squared normalized angle residuals of a BearingSet at estimate(s) ``position``.

    Args:
        bearings: BearingSet (M problems, N stations).
        position: (M, 3) or (3,) estimate X̂, m.
        position_covariance: optional (M, N, 3, 3) or (N, 3, 3) station position
            covariance P_i, m²; it inflates each angle variance by gᵀ P_i g, g the angle's
            gradient (first-order propagation; the gradients of Zong & Cui 2015 eq. (6)).

    Returns:
        d2 (M, N): (wrap(θ_i − θ_i(X̂)) / σ_θ)² + ((ψ_i − ψ_i(X̂)) / σ_ψ)² (second term only
        for 2D stations); NaN where the estimate lies on the station's vertical axis.
        dof (M, N) int: 1 (azimuth only) or 2.
    Units: dimensionless; angles in rad, ENU convention (Wang, Zhang & Wu eq. (1)).
    """
    x = np.atleast_2d(np.asarray(position, dtype=float))
    az_hat, el_hat = azimuth_elevation(x[:, None, :] - bearings.positions)
    var_az = bearings.sigma_az ** 2
    has_el = bearings.has_elevation
    var_el = np.where(has_el, np.nan_to_num(bearings.sigma_el, nan=1.0) ** 2, 1.0)
    if position_covariance is not None:
        P = np.asarray(position_covariance, dtype=float)
        P = np.broadcast_to(P if P.ndim == 4 else P[None], bearings.positions.shape + (3,))
        g_az, g_el = angle_jacobians(x, bearings.positions)
        with np.errstate(invalid='ignore'):
            var_az = var_az + np.einsum('mni,mnij,mnj->mn', g_az, P, g_az)
            var_el = var_el + np.where(has_el, np.einsum('mni,mnij,mnj->mn', g_el, P, g_el),
                                       0.0)
    with np.errstate(invalid='ignore'):
        d2 = wrap_angle(bearings.azimuth - az_hat) ** 2 / var_az
        d2 = d2 + np.where(has_el, (np.nan_to_num(bearings.elevation) - el_hat) ** 2 / var_el,
                           0.0)
    rho = np.hypot(x[:, None, 0] - bearings.positions[..., 0],
                   x[:, None, 1] - bearings.positions[..., 1])
    d2 = np.where(rho > 0.0, d2, np.nan)
    dof = np.where(has_el, 2, 1)
    return d2, dof


def residuals_one(bearings, position, sigma_az, sigma_el):
    """:func:`normalized_residuals` of one problem without station position covariance, on
    Python floats: the same d² bit for bit, as lists, or None where floats cannot follow
    numpy (a zero variance: Python raises where numpy gives inf; a non-finite offset).

    Args:
        bearings: BearingSet with M = 1 (its positions, angles and has_elevation).
        position: (3,) estimate X̂, m.
        sigma_az, sigma_el: (1, N) σ the estimator assumes (core.registry.noise_sigmas), rad.

    Returns:
        (d2, dof): lists of N floats and ints, d2 = (wrap(θ_i − θ_i(X̂)) / σ_θ)²
        + ((ψ_i − ψ_i(X̂)) / σ_ψ)² (second term only for 2D stations; NaN where X̂ lies on
        the station's vertical axis), dof 1 or 2. θ(X̂), ψ(X̂) come from the same numpy
        call as in :func:`normalized_residuals` (numpy's and libm's atan2 and hypot differ
        in the last bit); the rest is IEEE arithmetic in the same order.
    Units: dimensionless; angles in rad, ENU convention (Wang, Zhang & Wu eq. (1)).
    """
    x = np.asarray(position, dtype=float)[None]
    delta = x[:, None, :] - bearings.positions
    az_hat, el_hat = azimuth_elevation(delta)
    d = delta[0].tolist()
    if not all(math.isfinite(c) for di in d for c in di[:2]):
        return None
    az_hat, el_hat = az_hat[0].tolist(), el_hat[0].tolist()
    az, el = bearings.azimuth[0].tolist(), bearings.elevation[0].tolist()
    saz, sel = sigma_az[0].tolist(), sigma_el[0].tolist()
    d2, dof = [], []
    for i, a in enumerate(az):
        s = saz[i]
        var_az = s * s
        if var_az == 0.0:
            return None
        w = wrap_angle_scalar(a - az_hat[i])
        v = w * w / var_az
        e = el[i]
        if math.isfinite(e):
            se = sel[i]
            # np.nan_to_num(σ_ψ, nan=1.0)
            if not math.isfinite(se):
                se = 1.0 if math.isnan(se) else math.copysign(_FLOAT_MAX, se)
            var_el = se * se
            if var_el == 0.0:
                return None
            r = e - el_hat[i]
            v = v + r * r / var_el
            dof.append(2)
        else:
            v = v + 0.0
            dof.append(1)
        di = d[i]
        d2.append(v if (di[0] != 0.0 or di[1] != 0.0) else math.nan)
    return d2, dof


def count_reason(bearings, horizontal=False):
    """No-fix reason of BearingSet.validate's counting rules (at least two stations, one
    elevation, three angles), or None; checked without building arrays. ``horizontal``
    (a target altitude is stated, core.horizontal): two azimuths suffice."""
    n = len(bearings)
    if horizontal:
        return TOO_FEW_STATIONS if n < 2 else None
    n_el = sum(1 for b in bearings if not math.isnan(b.elevation))
    if n < 2 or n + n_el < 3:
        return TOO_FEW_STATIONS
    if n_el == 0:
        return NO_ELEVATION
    return None


def horizontal_capable(kwargs):
    """True when the solve options in ``kwargs`` allow a horizontal solve (a target
    altitude stated and ``dimension`` not ``3d``); otherwise they are dropped from
    ``kwargs`` (the 3D solve, as without them)."""
    if kwargs.get('target_altitude') is not None and kwargs.get('dimension') != '3d':
        return True
    for k in _registry.SOLVE_OPTION_SPECS:
        kwargs.pop(k, None)
    return False


def ignores_elevations(kwargs):
    """True when the solve options ``kwargs`` say ``use_elevations`` false (a bool or
    numpy bool, validated by core.registry)."""
    return not bool(kwargs.get('use_elevations', True))


def ignoring_elevations(bearings, kwargs):
    """``bearings`` as the solve sees them: with option ``use_elevations`` false (in the
    solve options ``kwargs``) every bearing is azimuth-only (elevation and its σ NaN), so
    neither the estimator, the χ² gate nor the station trust uses an elevation the user
    said to ignore (a multipath-spoiled elevation would otherwise get its station dropped
    as an outlier). The bearings are copies then."""
    if not ignores_elevations(kwargs):
        return list(bearings)
    return [replace(b, elevation=math.nan, sigma_elevation=math.nan) for b in bearings]


def without_elevations(bs):
    """The BearingSet ``bs`` with every elevation (and its σ) NaN: azimuth-only."""
    nan = np.full(bs.elevation.shape, np.nan)
    return BearingSet(bs.positions, bs.azimuth, nan, bs.sigma_az, nan.copy(), bs.stations)


def covariance_ok(cov):
    """True for a finite, positive semi-definite covariance with a positive largest
    eigenvalue (relative round-off −1e-9 tolerated), m².

    The eigenvalues λ of the symmetric part ½(C + Cᵀ) decide (λ_max > 0 and
    λ_min ≥ −1e-9 λ_max). A 3 × 3 matrix whose Cholesky factorisation completes in floats
    with positive pivots (:func:`cholesky_positive`) passes without them: the factor is
    exact for a matrix within 3 γ₄ max C_ii ≈ 1.3e-15 λ_max of C (Higham, Accuracy and
    Stability of Numerical Algorithms, thm. 10.3), so λ_min ≥ −1.3e-15 λ_max, far inside
    the tolerance; the rest goes to LAPACK.
    """
    c = cov.tolist() if isinstance(cov, np.ndarray) and cov.shape == (3, 3) else None
    if c is not None:
        flat = c[0] + c[1] + c[2]
        if not all(map(math.isfinite, flat)):
            return False
        if cholesky_positive(c):
            return True
    if not np.all(np.isfinite(cov)):
        return False
    lam = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    return bool(lam[-1] > 0.0 and lam[0] >= -1e-9 * lam[-1])


def cholesky_positive(c):
    """True when the Cholesky factorisation of the symmetric part of the finite 3 × 3
    matrix ``c`` (nested lists of floats) completes in floats with positive pivots and
    diagonal entries within [1e-140, 1e140] (no under- or overflow in the products);
    False means "undecided" (the caller asks LAPACK), not "indefinite"."""
    a00, a11, a22 = c[0][0], c[1][1], c[2][2]
    if not (1e-140 <= a00 <= 1e140 and 1e-140 <= a11 <= 1e140 and 1e-140 <= a22 <= 1e140):
        return False
    a01 = 0.5 * (c[0][1] + c[1][0])
    a02 = 0.5 * (c[0][2] + c[2][0])
    a12 = 0.5 * (c[1][2] + c[2][1])
    r00 = math.sqrt(a00)
    r01, r02 = a01 / r00, a02 / r00
    d1 = a11 - r01 * r01
    if not d1 > 0.0:
        return False
    r11 = math.sqrt(d1)
    r12 = (a12 - r01 * r02) / r11
    d2 = a22 - r02 * r02 - r12 * r12
    return d2 > 0.0


def _trusted_set(bearings):
    """One-problem BearingSet (M = 1) of validated Bearings with exactly 3-coordinate
    positions: the same arrays as ``BearingSet.from_bearings(..., validate=False)`` without
    its reshaping and copies (~9 µs instead of ~23 µs at N = 10; kept because the fusion
    latency benchmark at 50 stations × 10 Hz pays it N times per second per station)."""
    el = np.array([[b.elevation for b in bearings]], dtype=float)
    sel = np.array([[b.sigma_elevation for b in bearings]], dtype=float)
    return BearingSet(np.array([[b.position for b in bearings]], dtype=float),
                      np.array([[b.azimuth for b in bearings]], dtype=float), el,
                      np.array([[b.sigma_azimuth for b in bearings]], dtype=float),
                      np.where(np.isfinite(el), sel, np.nan), [b.station for b in bearings])


def solve_epoch(bearings, estimator, options=None, min_stations=2, outlier_gate=0.999,
                validated=False, trust=None, station_positions=True):
    """Fix from aligned bearings (one per station) with χ² outlier gating -> :class:`Epoch`.

    Loop: check the counts (at least ``min_stations`` stations, one elevation, three angles:
    BearingSet.validate's rules), run the estimator (core.registry), accept only a converged
    ``ok`` result with finite position and a finite positive semi-definite covariance;
    compute each station's d² (:func:`normalized_residuals` with the σ the estimator
    assumes, core.registry.noise_sigmas, and the station position covariance) and, if the
    worst ratio d_i² / gate_threshold(outlier_gate, k_i) exceeds 1, drop that station and
    repeat, as long as the remaining set is still solvable; if it is not, the epoch has no
    fix (``inconsistent_bearings``). Returns an :class:`Epoch` without stamps (the caller
    sets them): ``bearings`` = used, ``rejected`` = dropped by the gate, ``result`` = the
    estimator's FixResult of the last solve. Never raises for bad geometry or estimator
    failures (they become reasons); the estimator's own exceptions become
    ``estimator_error`` with the message in ``detail``. ``validated=True`` (the fusion
    pipeline, whose bearings passed Bearing.validate on arrival) skips a second check of the
    same fields, builds the BearingSet directly and calls the estimator function directly:
    same result, ~60 µs less per estimation at N = 10.

    Horizontal solve (core.horizontal): when ``options`` state ``target_altitude`` and
    ``dimension`` is not ``3d``, the estimator runs through core.registry.solve with the
    solve options, two azimuths suffice (no ``no_elevation``), the gate uses the same d² at
    the fix (z = the stated altitude) and ``dof`` = angles − 2 for a horizontal fix.

    Robustness (core.robust, core.station_trust): an estimator that declares option
    ``robust`` (or ``consistency``) runs with it on (off when ``outlier_gate`` is 1, which
    disables every outlier test) unless ``options`` says otherwise; its outlier bearings
    (any angle excluded) count as rejected and the fix is recomputed without them, and a fix
    it assesses ``low_confidence`` becomes an Epoch of reason ``low_confidence`` that
    carries position and covariance; with ``consistency`` the first such fix gets one drop of
    the gate's worst station and a re-solve first. With ``trust``
    (a :class:`~bearing_loc_ros.core.station_trust.StationTrust`) every bearing is used with
    its σ_eff and the deletion residuals of the final solve update the trust (deferred:
    applied by ``trust.settle()`` once the fix is out, or before the trust is next read).

    Station position covariance (``station_positions``, default on): when a bearing states
    one, the set is first solved as it is (the gate counts gᵀ P_i g); the estimator then runs
    with each station's σ scaled by :func:`station_position_factors` at that fix, so that
    its weights, robust screen and covariance count the position error too (the gate keeps
    the stated σ with gᵀ P_i g). Without this a 5 m station position σ (a KrakenSDR's GPS)
    gave fixes with a mean NEES of 5.8 against 3.

    With the gate on (``outlier_gate`` < 1): a ``degenerate_geometry`` set gets, once, the
    drop of the station its peers' fix refutes most among the likeliest culprits
    (:func:`_refuted_station`: one station can make the set singular, e.g. a claimed σ of
    1e-9 rad); and a fix that needed a drop but has no redundancy left (residual degrees of
    freedom ≤ 0, such as two azimuths in the plane) is ``low_confidence`` with no trust
    update: nothing in the data confirms the stations kept, and with three azimuth-only
    stations any pair fits exactly, so the drop may have removed an honest one.
    """
    options = dict(options or {})
    used = list(bearings)
    claims = {}
    if trust is not None:
        claims = {b.station: (b.sigma_azimuth, b.sigma_elevation) for b in used}
        # statistics.median: np.median's value (the middle one or the mean of the two).
        peer = float(statistics.median([b.sigma_azimuth for b in used])) if used else 0.0
        used = [trust.effective(b, peer) for b in used]
    rejected = []
    kwargs = _registry.scoped_options(estimator, options)
    for name in ('robust', 'consistency'):
        if name not in kwargs and _registry.spec(estimator).accepts(name):
            kwargs[name] = float(outlier_gate) < 1.0     # gate 1: no outlier handling
    # Option consistency checks every fix (inside the estimator). A single outlier makes the
    # fix of the whole set fail it: the gate's worst station is then dropped once and the
    # fix recomputed (and checked again). Only once: a closed-form fix dragged by an
    # outlier can make the gate pick honest stations, and repeated drops would go on until
    # too few stations are left to show the outlier.
    gating = float(outlier_gate) < 1.0
    retry = bool(kwargs.get('consistency', False)) and gating
    degenerate_tried = False
    horizontal = horizontal_capable(kwargs)
    used = ignoring_elevations(used, kwargs)
    if validated and not horizontal:
        make_set = _trusted_set

        def solve(bs):
            return _estimators.ESTIMATORS[estimator](bs, **kwargs)
    else:
        def make_set(b):
            return BearingSet.from_bearings(b, validate=False)

        def solve(bs):
            return _registry.solve(estimator, bs, **kwargs)
    factors = {}
    if station_positions and any(np.any(b.position_covariance) for b in used):
        first = solve_epoch(used, estimator, options, min_stations, outlier_gate, validated,
                            station_positions=False)
        if first.position is not None and all(map(math.isfinite, first.position.tolist())):
            pcov = [np.asarray(b.position_covariance, dtype=float) for b in used]
            factors = station_position_factors(make_set(used), pcov, first.position,
                                               estimator, kwargs)

    def run(bs):
        return solve(_scaled(bs, factors) if factors else bs)
    while True:
        if len(used) < int(min_stations):
            return Epoch(TOO_FEW_STATIONS, estimator=estimator, bearings=used,
                         rejected=rejected, detail=f'{len(used)} < min_stations {min_stations}')
        reason = count_reason(used, horizontal)
        if reason is not None:
            return Epoch(reason, estimator=estimator, bearings=used, rejected=rejected,
                         detail=f'{len(used)} station(s)')
        bs = make_set(used)
        try:
            res = run(bs)
        except Exception as exc:  # noqa: B902 - any estimator failure is a counted no-fix
            return Epoch(ESTIMATOR_ERROR, estimator=estimator, bearings=used,
                         rejected=rejected, detail=f'{type(exc).__name__}: {exc}')
        status = str(res.status[0])
        pos = np.asarray(res.position[0], dtype=float)
        cov = np.asarray(res.covariance[0], dtype=float)
        common = dict(estimator=estimator, bearings=used, rejected=rejected, status=status,
                      iterations=int(res.iterations[0]), result=res)
        if status == _estimators.STATUS_DEGENERATE:
            if gating and not degenerate_tried:
                # One station can make the set singular (a claimed σ of 1e-9 rad, a
                # position 1000 km off): drop the one the others' fix refutes most.
                degenerate_tried = True
                drop = _refuted_station(run, make_set, used, estimator, kwargs, outlier_gate,
                                        min_stations, horizontal)
                if drop is not None:
                    rejected = rejected + [used[drop]]
                    used = used[:drop] + used[drop + 1:]
                    continue
            return Epoch(DEGENERATE_GEOMETRY, **common)
        finite = all(map(math.isfinite, pos.ravel().tolist()))
        excluded = getattr(res, 'excluded', None)
        if excluded is not None and finite:
            # A station with an excluded angle is an outlier station (the gate's unit):
            # dropped and the fix recomputed, while the rest stays solvable.
            out = {i for i, x in enumerate(excluded[0].any(axis=1).tolist()) if x}
            remaining = [b for i, b in enumerate(used) if i not in out]
            if out and len(remaining) >= int(min_stations) \
                    and count_reason(remaining, horizontal) is None:
                rejected = rejected + [b for i, b in enumerate(used) if i in out]
                used = remaining
                continue
        if status == STATUS_LOW_CONFIDENCE:
            if retry and finite and excluded is None:
                retry = False
                _, _, worst, excess_worst = _gate_at(estimator, bs, used, pos, kwargs,
                                                     outlier_gate)
                remaining = used[:worst] + used[worst + 1:]
                if excess_worst > 1.0 and len(remaining) >= int(min_stations) \
                        and count_reason(remaining, horizontal) is None:
                    rejected = rejected + [used[worst]]
                    used = remaining
                    continue
            if trust is not None:
                trust.defer_update(*_as_weighted(used, claims, factors), pos, cov,
                                   rejected)
            return Epoch(LOW_CONFIDENCE, position=pos, covariance=0.5 * (cov + cov.T),
                         detail='failed the consistency checks (core.robust)', **common)
        if status != _estimators.STATUS_OK or not bool(res.converged[0]):
            return Epoch(NOT_CONVERGED, **common)
        if not finite:
            return Epoch(DEGENERATE_GEOMETRY, detail='non-finite position', **common)
        if not covariance_ok(cov):
            return Epoch(BAD_COVARIANCE, **common)
        d2, dof, worst, excess_worst = _gate_at(estimator, bs, used, pos, kwargs, outlier_gate)
        if excess_worst > 1.0:
            remaining = used[:worst] + used[worst + 1:]
            if len(remaining) >= int(min_stations) and count_reason(remaining,
                                                                    horizontal) is None:
                rejected = rejected + [used[worst]]
                used = remaining
                continue
            return Epoch(INCONSISTENT_BEARINGS,
                         detail=f'{used[worst].station} d2={d2[worst]:.3g} but too few '
                                f'stations left to drop it', **common)
        solved = getattr(res, 'solve', None)
        n_free = 2 if solved is not None and str(solved[0]) == 'horizontal' else 3
        spare = int(sum(dof)) - n_free
        if rejected and spare <= 0:
            # Nothing checks the stations kept: which one was wrong is not known.
            return Epoch(LOW_CONFIDENCE, position=pos, covariance=0.5 * (cov + cov.T),
                         detail=f'no redundancy left after dropping '
                                f'{", ".join(b.station for b in rejected)}', **common)
        if trust is not None:
            trust.defer_update(*_as_weighted(used, claims, factors), pos, cov, rejected)
        residuals = {b.station: float(v) for b, v in zip(used, d2)}
        return Epoch(OK, position=pos, covariance=0.5 * (cov + cov.T), residuals=residuals,
                     chi2=_nansum(d2), dof=spare, **common)


def _solved(run, bs):
    """(position (3,), covariance (3, 3)) of a converged ``ok`` solve of ``bs`` with finite
    values, or None (any other status, or the estimator raised)."""
    try:
        res = run(bs)
    except Exception:  # noqa: B902 - a failed alternative solve is no alternative
        return None
    if str(res.status[0]) != _estimators.STATUS_OK or not bool(res.converged[0]):
        return None
    pos = np.asarray(res.position[0], dtype=float)
    cov = np.asarray(res.covariance[0], dtype=float)
    if not (np.isfinite(pos).all() and covariance_ok(cov)):
        return None
    return pos, cov


#: Most stations :func:`_refuted_station` leaves out in turn (one solve each): the three that
#: claim the smallest σ and the three farthest from the others, the likeliest to make a set
#: singular; this bounds a degenerate epoch of a large network to six solves.
REFUTE_CANDIDATES = 3


def _refuted_station(run, make_set, used, estimator, kwargs, outlier_gate, min_stations,
                     horizontal):
    """Index of the station whose d² (:func:`normalized_residuals`) at the fix of the
    others is largest and beyond its gate, among the candidates whose removal leaves a
    solvable set with an ``ok`` fix; None when there is none (a geometry that is degenerate
    whichever station is left out). Candidates: every station of a set of at most
    2 × :data:`REFUTE_CANDIDATES`, else those with the smallest σ_θ and those farthest from
    the median station position (one solve per candidate)."""
    n = len(used)
    order = range(n)
    if n > 2 * REFUTE_CANDIDATES:
        pos = np.array([b.position for b in used], dtype=float)
        far = np.linalg.norm(pos - np.median(pos, axis=0), axis=1)
        sig = [b.sigma_azimuth for b in used]
        order = sorted(set(sorted(range(n), key=sig.__getitem__)[:REFUTE_CANDIDATES])
                       | set(np.argsort(-far, kind='stable')[:REFUTE_CANDIDATES].tolist()))
    best, best_ratio = None, 1.0
    whole = make_set(used)
    for i in order:
        rest = used[:i] + used[i + 1:]
        if len(rest) < int(min_stations) or count_reason(rest, horizontal) is not None:
            continue
        fix = _solved(run, make_set(rest))
        if fix is None:
            continue
        d2, dof, _, _ = _gate_at(estimator, whole, used, fix[0], kwargs, outlier_gate)
        ratio = float(d2[i]) / gate_threshold(outlier_gate, int(dof[i]))
        if ratio > best_ratio:          # (NaN: not refuted)
            best, best_ratio = i, ratio
    return best


def station_position_factors(bs, pcov, position, estimator, kwargs):
    """Station -> (f_θ, f_ψ): the factors by which a station's stated σ grow to count its
    position covariance at the fix ``position`` (3,), m.

    A station displaced by δp_i turns its azimuth by g_θᵀ δp_i (first order; g the angle's
    gradient, :func:`.crlb.angle_jacobians`, Zong & Cui 2015 eqs. (6)-(8)), an error of
    variance g_θᵀ P_i g_θ, rad², independent of the angle noise: σ_eff² = σ² + g_θᵀ P_i g_θ
    with σ the estimator's own at the fix (core.registry.noise_sigmas: grown with range for
    ``wmle``), so f_θ = σ_eff / σ scales the σ the bearing states whatever the noise model;
    the same for ψ. (The az and el errors of one station are correlated; the factors leave
    that out.) 1 where the gradient is not finite (the fix on the station's axis).

    Args:
        bs: one-problem BearingSet (M = 1) with station ids.
        pcov: (N, 3, 3) the stations' position covariances P_i, m².
        position: (3,) fix, m; estimator, kwargs: the estimator and its options.
    """
    pos = np.asarray(position, dtype=float)
    saz, sel = _registry.noise_sigmas(estimator, bs, pos[None], kwargs)
    g_az, g_el = angle_jacobians(pos, bs.positions[0])
    P = np.asarray(pcov, dtype=float)
    with np.errstate(invalid='ignore', divide='ignore'):
        add_az = np.einsum('ni,nij,nj->n', g_az[0], P, g_az[0])
        add_el = np.einsum('ni,nij,nj->n', g_el[0], P, g_el[0])
        f_az = np.sqrt(1.0 + add_az / saz[0] ** 2)
        f_el = np.sqrt(1.0 + add_el / sel[0] ** 2)
    f_az = np.where(np.isfinite(f_az), f_az, 1.0)
    f_el = np.where(np.isfinite(f_el), f_el, 1.0)
    return {s: (float(a), float(e)) for s, a, e in zip(bs.stations, f_az, f_el)}


def _as_weighted(used, claims, factors):
    """(bearings, claims) for the station trust with the σ the fix weighted them with: the
    bearings and the claimed σ scaled by the station position ``factors`` (station ->
    (f_θ, f_ψ)); unchanged without factors. (The trust's deletion step removes each
    station's information at the σ it is given: at the stated σ it removed more than the
    station had added, and every station became untestable.)"""
    if not factors:
        return used, claims
    out = []
    for b in used:
        fa, fe = factors.get(b.station, (1.0, 1.0))
        out.append(replace(b, sigma_azimuth=b.sigma_azimuth * fa,
                           sigma_elevation=b.sigma_elevation * fe))
    scaled = {}
    for st, (a, e) in claims.items():
        fa, fe = factors.get(st, (1.0, 1.0))
        scaled[st] = (a * fa, e * fe)
    return out, scaled


def _scaled(bs, factors):
    """``bs`` with each station's σ multiplied by its ``factors`` (station -> (f_θ, f_ψ))."""
    f = [factors.get(s, (1.0, 1.0)) for s in bs.stations]
    fa = np.array([[a for a, _ in f]])
    fe = np.array([[e for _, e in f]])
    return BearingSet(bs.positions, bs.azimuth, bs.elevation, bs.sigma_az * fa,
                      bs.sigma_el * fe, bs.stations)


def _gate_at(estimator, bs, used, pos, kwargs, outlier_gate):
    """The gate's (d², dof, worst, its ratio) at the fix ``pos`` of the set ``bs`` (of the
    bearings ``used``), with the σ of the estimator's noise model and the stations' position
    covariances (:func:`_gate_one` on floats when those are zero, else :func:`_gate`)."""
    pcov = np.array([np.asarray(b.position_covariance, dtype=float) for b in used])
    saz, sel = _registry.noise_sigmas(estimator, bs, pos[None], kwargs)
    # Zero station covariances (fixed stations, the usual case) inflate nothing: the d²
    # on floats (same values, ~0.1 ms less per epoch at N = 10 in the live node).
    gate = _gate_one(bs, pos, saz, sel, outlier_gate) if not pcov.any() else None
    if gate is None:
        gated = BearingSet(bs.positions, bs.azimuth, bs.elevation, saz, sel, bs.stations)
        gate = _gate(gated, pos, pcov, outlier_gate)
    return gate


def _nansum(values):
    """float(np.nansum(values)) of a 1-D list or array: numpy's summation (its order and
    rounding) of the values with NaN as 0, without np.nansum's copies."""
    if type(values) is list:
        return float(np.add.reduce(np.array([0.0 if v != v else v for v in values])))
    return float(np.nansum(values))


def _gate(bearings, position, pcov, outlier_gate):
    """The gate's (d² (N,), dof (N,), index of the worst d²/threshold, that ratio) of one
    problem, with the station position covariances ``pcov`` (N, 3, 3) when any is non-zero;
    a NaN d² (estimate on a station's axis) counts 0."""
    d2, dof = normalized_residuals(bearings, position, pcov[None] if pcov.any() else None)
    d2, dof = d2[0], dof[0]
    thr = np.array([gate_threshold(outlier_gate, int(k)) for k in dof])
    with np.errstate(invalid='ignore'):
        excess = np.where(np.isfinite(d2), d2 / thr, 0.0)
    worst = int(np.argmax(excess))
    return d2, dof, worst, float(excess[worst])


def _gate_one(bearings, position, sigma_az, sigma_el, outlier_gate):
    """:func:`_gate` without station position covariance, on floats (:func:`residuals_one`):
    the same values and the same worst station (the first of equal ratios, as np.argmax),
    or None where floats cannot follow numpy (the caller runs :func:`_gate`)."""
    out = residuals_one(bearings, position, sigma_az, sigma_el)
    if out is None:
        return None
    d2, dof = out
    worst, top = 0, -math.inf
    for i, (v, k) in enumerate(zip(d2, dof)):
        thr = gate_threshold(outlier_gate, k)
        if thr == 0.0:
            return None
        r = v / thr if math.isfinite(v) else 0.0
        if r > top:
            worst, top = i, r
    return d2, dof, worst, top
