"""Maximum likelihood TMA with the speed constraint (T17), started from the closed forms.

Conventions as :mod:`bearing_loc_ros.core.tma`.
"""

import numpy as np

from ..estimator_spec import BEARING_SIGMA, declare, TMA
from ..fix import STATUS_DEGENERATE, STATUS_MAX_ITERATIONS, STATUS_OK
from .closed_form import estimate_from_sums
from .confidence import (MANOEUVRE_FRACTION, manoeuvre_speed, residuals, tangent_basis,
                         whitened_jacobian)
from .model import prepare, TMA_OPTIONS
from .observability import finish
from .roots import mirror_scale, resolve
from .sums import batch_sums


def _solve_alone(a, b):
    """x of a x = b for one (5, 5) system as ``np.linalg.solve`` gives it for that system
    alone, or the least-squares x where a is singular."""
    try:
        return np.linalg.solve(a[None], b[None, :, None])[0, :, 0]
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]


def _options(options, fn=None):
    """Options merged over the defaults of :data:`TMA_OPTIONS`, each value validated."""
    return (fn or tma_mle).spec.parse(options)


def _mle_start(data, sums, opts, methods=('ctls', 'ctls6', 'ple')):
    """Start of :func:`tma_mle`: of the closed forms, the one with the lowest ML cost (T17).

    With a 'ground' prior that no closed form's b fits and a manoeuvring observer (u of
    (T22) above 1 % of v_c: the closed forms assume a straight track, so their b can miss
    the prior), each closed form's b scaled to the ground speed closest to v_c (``closest``
    of :func:`estimate_from_sums`) competes too; the iteration then projects it onto the
    constraint. For a straight observer no root means the prior does not fit the bearings.
    Returns (p0, v, status, reason); status/reason of the first method where none is ok.
    """
    best = None
    best_cost = np.full(data.M, np.inf)
    tries = [(m, False) for m in methods]
    turning = np.zeros(data.M, dtype=bool)
    if opts['speed_reference'] == 'ground':
        turning = manoeuvre_speed(data) > MANOEUVRE_FRACTION * data.speed
        if np.any(turning):
            tries += [(m, True) for m in methods]
    for m, closest in tries:
        if closest and np.all(np.isfinite(best_cost) | ~turning):
            break
        p0, v, st, rs = estimate_from_sums(sums, m, data.speed, opts['speed_reference'],
                                           opts['min_bearings'], opts['alpha'],
                                           closest=closest)
        if best is None:
            best = [p0.copy(), v.copy(), st.copy(), rs.copy()]
        ok = (st == STATUS_OK) & (turning | (not closest))
        if np.any(ok):
            e, _ = residuals(data, np.where(ok[:, None], p0, 0.0),
                             np.where(ok[:, None], v, 0.0))
            c = np.where(ok, np.sum(e * e, axis=(1, 2)), np.inf)
            c = np.where(np.isfinite(c), c, np.inf)
            use = c < best_cost
            best_cost[use] = c[use]
            for arr, new in zip(best, (p0, v, st, rs)):
                arr[use] = new[use]
    return tuple(best)


@declare('tma_mle', TMA, TMA_OPTIONS, BEARING_SIGMA, inputs=('times', 'speed'))
def tma_mle(bearings, times, speed, **options):
    """Maximum likelihood TMA with the speed constraint, Gauss-Newton/Levenberg-Marquardt (T17).

    Minimises Σ_k wrap(θ̂_k − θ_k)²/σ_θk² + (ψ̂_k − ψ_k)²/σ_ψk² over x = (p0, v) with the angles
    θ̂, ψ̂ of p_k = p0 + v τ_k − δ_k (T3, the observer positions are used exactly) subject to
    (T5). The constraint is kept exactly by the parametrisation v = v_c s (− v_o for
    'ground') with s a unit vector updated on its tangent plane, s ← normalise(s + E δ):
    5 unknowns (p0, δ). Marquardt damping with Nielsen's gain-ratio update: a step is
    accepted only if it lowers the cost, so the result is never worse than the start and
    never NaN. Converged when the step is shorter than ``dtol`` (1e-3) standard deviations
    (hᵀJᵀJh < dtol²: far below the statistical error) or ``xtol`` (1e-10) relative.
    Start: ``start`` = (p0, v) arrays,
    else the closed form (:func:`tma_ctls`, :func:`tma_ctls6`, :func:`tma_ple`) with the lowest
    cost.
    Efficient (reaches the CRLB (T15)) at small noise: the reference of the benchmark.
    Options as :func:`tma_ple` plus ``start``, ``max_iterations`` (50), ``dtol``, ``xtol``.
    Status max_iterations: not converged, estimate kept (cost reduced).
    """
    opts = _options(options, tma_mle)
    start = opts.pop('start', None)
    max_it = int(opts.pop('max_iterations', 50))
    xtol = float(opts.pop('xtol', 1e-10))
    dtol = float(opts.pop('dtol', 1e-3))
    data = prepare(bearings, times, speed, opts['speed_reference'])
    if start is None:
        sums = batch_sums(bearings, times)
        p0, v, status, reason = _mle_start(data, sums, opts)
    else:
        p0 = np.array(np.broadcast_to(np.asarray(start[0], float), (data.M, 3)))
        v = np.array(np.broadcast_to(np.asarray(start[1], float), (data.M, 3)))
        status = np.full(data.M, STATUS_OK, dtype=object)
        reason = np.full(data.M, '', dtype=object)
        bad = ~(np.all(np.isfinite(p0), -1) & np.all(np.isfinite(v), -1))
        status[bad], reason[bad] = STATUS_DEGENERATE, 'start: non-finite initial state'
    M = data.M
    vc = data.speed
    ref = opts['speed_reference']
    off = data.v_o if ref == 'ground' else np.zeros((M, 3))
    active = status == STATUS_OK
    # Project the start onto the constraint manifold (T5).
    s = np.where(active[:, None], v + off, [1.0, 0.0, 0.0])
    s = s / np.where(np.linalg.norm(s, axis=-1) > 0, np.linalg.norm(s, axis=-1), 1.0)[:, None]
    p0 = np.where(active[:, None], p0, 0.0)
    v = vc[:, None] * s - off
    k = mirror_scale(v, data.v_o, vc) if ref == 'ground' else np.full(M, np.nan)
    k = np.where(active, k, np.nan)
    p0_b, v_b = k[:, None] * p0, k[:, None] * v
    p0, v, iters, converged = _refine(data, p0, v, active, off, max_it, dtol, xtol)
    status = status.copy()
    reason = reason.copy()
    two = np.isfinite(k)
    if np.any(two):
        # (T23): the mirror of the start is the other range of the ground-speed prior;
        # refine from it too, keep the better fit, or neither when they fit alike.
        i = np.nonzero(two)[0]
        sub = data.take(i)
        pb, vb, it_b, cv_b = _refine(sub, p0_b[i], v_b[i], np.ones(len(i), bool), off[i],
                                     max_it, dtol, xtol)
        alt_p, alt_v = np.full((M, 3), np.nan), np.full((M, 3), np.nan)
        alt_p[i], alt_v[i] = pb, vb
        p0, v, status, reason, take_b = resolve(data, p0, v, status, reason, two, ref,
                                                alternative=(alt_p, alt_v))
        tb = np.nonzero(take_b[i])[0]
        iters[i] += it_b
        converged[i[tb]] = cv_b[tb]
        gone = status != STATUS_OK
        active &= ~gone
    nc = active & ~converged
    status[nc] = STATUS_MAX_ITERATIONS
    reason[nc] = f'mle: not converged in {max_it} iterations (estimate kept, cost reduced)'
    p0 = np.where(active[:, None], p0, np.nan)
    v = np.where(active[:, None], v, np.nan)
    return finish('mle', data, p0, v, status, reason, iters, converged, opts)


def _refine(data, p0, v, active, off, max_it, dtol, xtol):
    """Marquardt iteration of (T17) from (p0, v) on the constraint, for the ``active`` rows.

    ``off`` (M, 3): v_o for 'ground', 0 for 'relative' (v + off = v_c s). Returns
    (p0, v, iterations (M,), converged (M,)); a step is kept only if it lowers the cost.
    """
    M = data.M
    vc = data.speed
    p0, v = p0.copy(), v.copy()
    s = v + off
    s = s / np.where(np.linalg.norm(s, axis=-1) > 0, np.linalg.norm(s, axis=-1), 1.0)[:, None]
    e, d = residuals(data, p0, v)
    cost = np.sum(e * e, axis=(1, 2))
    mu = np.full(M, 1e-9)
    nu = np.full(M, 2.0)
    iters = np.zeros(M, dtype=int)
    converged = np.zeros(M, dtype=bool)
    running = active & np.isfinite(cost)
    for _ in range(max_it):
        if not np.any(running):
            break
        r = np.nonzero(running)[0]
        iters[r] += 1
        E = tangent_basis(s[r])
        J = whitened_jacobian(d[r], data.s_az[r], data.s_el[r], E, vc[r], data.tau[r])
        Jt = np.swapaxes(J, -1, -2)
        JtJ = Jt @ J
        Jte = (Jt @ e[r].reshape(len(r), -1, 1))[..., 0]
        dg = np.diagonal(JtJ, axis1=1, axis2=2)
        dg = np.where(dg > 0, dg, 1.0)
        A = JtJ + (mu[r, None] * dg)[:, :, None] * np.eye(5)
        try:
            step = -np.linalg.solve(A, Jte[..., None])[..., 0]
        except np.linalg.LinAlgError:
            # One singular row makes the batch call raise: each row is solved as it would
            # be alone (least squares only where its own matrix is singular), so no row's
            # step depends on the others of the batch.
            step = -np.stack([_solve_alone(a, b_) for a, b_ in zip(A, Jte)])
        p_new = p0[r] + step[:, :3]
        s_new = s[r] + np.einsum('mij,mj->mi', E, step[:, 3:])
        s_new /= np.linalg.norm(s_new, axis=-1, keepdims=True)
        v_new = vc[r, None] * s_new - off[r]
        sub = data.take(r)
        e_new, d_new = residuals(sub, p_new, v_new)
        c_new = np.sum(e_new * e_new, axis=(1, 2))
        # Gain ratio ρ = actual / predicted decrease of the cost |e + J h|² (Nielsen 1999).
        dec = np.einsum('mi,mij,mj->m', step, JtJ, step)
        pred = -2.0 * np.sum(step * Jte, -1) - dec
        acc = np.isfinite(c_new) & (c_new < cost[r])
        with np.errstate(divide='ignore', invalid='ignore'):
            rho = np.where(pred > 0, (cost[r] - c_new) / pred, 0.0)
        ra = r[acc]
        p0[ra], s[ra], v[ra] = p_new[acc], s_new[acc], v_new[acc]
        e[ra], d[ra], cost[ra] = e_new[acc], d_new[acc], c_new[acc]
        mu[ra] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * np.clip(rho[acc], 0, 1) - 1.0) ** 3)
        mu[ra] = np.maximum(mu[ra], 1e-15)
        nu[ra] = 2.0
        rj = r[~acc]
        mu[rj] *= nu[rj]
        nu[rj] *= 2.0
        rel = np.maximum(np.linalg.norm(step[:, :3], axis=-1)
                         / np.maximum(np.linalg.norm(p_new, axis=-1), 1e-300),
                         np.linalg.norm(step[:, 3:], axis=-1))
        # Converged when the step is below dtol standard deviations (its Mahalanobis length
        # in the Fisher information JᵀJ) or below xtol relative; a rejected step that small
        # also ends the iteration (rounding), the current estimate is kept.
        done = (dec < dtol ** 2) | (rel < xtol) | (mu[r] > 1e12)
        converged[r[done]] = True
        running[r[done]] = False
    return p0, v, iters, converged
