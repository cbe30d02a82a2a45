"""Latency and throughput of every estimator, next to scipy.optimize.least_squares.

For N = 3, 10, 100, 1000 stations (random geometry within ±20 km, targets 0.5-7 km high,
σ = 2 mrad, every third station azimuth-only) this prints, per estimator:

* latency: wall time of one call with M = 1 problem (ms, best of several runs);
* throughput: fixes per second of one batched call with M = min(10000, 100000 / N) problems;
* iterations: mean iterations in the batch.

The reference is scipy.optimize.least_squares (method 'lm', analytic Jacobian, the same
whitened residuals as ``mle``: (measured − predicted)/σ with the azimuth wrapped, started from
``ls``), solving the same ML problems one by one (a Python loop; at most 200 problems timed).
The last table gives the per-iteration cost of the default estimator (one evaluation of the
residuals, normal matrix and gradient over the M × N bearings), which is what grows with N.
Single-threaded: OMP/BLAS threads are pinned to 1 before numpy is imported.

Run: .venv/bin/python bench/bench_estimators.py [--quick]
"""
import argparse
import os
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

from bearing_loc_ros.core import estimators as est  # noqa: E402
from bearing_loc_ros.core.bearings import BearingSet, simulate_bearings  # noqa: E402
from bearing_loc_ros.core.conventions import wrap_angle  # noqa: E402
from bearing_loc_ros.core.crlb import angle_jacobians  # noqa: E402

METHODS = sorted(est.ESTIMATORS)


def problems(N, M, rng):
    st = rng.uniform(-20e3, 20e3, size=(N, 3))
    st[:, 2] = rng.uniform(0.0, 200.0, N)
    tgt = rng.uniform([-10e3, -10e3, 500.0], [10e3, 10e3, 7e3], size=(M, 3))
    bs = simulate_bearings(tgt, st, 2e-3, rng=rng)
    el = np.where(np.arange(N) % 3 == 1, np.nan, bs.elevation)
    return tgt, BearingSet.from_arrays(bs.positions, bs.azimuth, el, bs.sigma_az, bs.sigma_el)


def best_time(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def scipy_ml(bs, x0):
    """Solve each problem's ML (seed 003 eq. (3)) with scipy least_squares, one by one."""
    out = np.empty((bs.M, 3))
    nfev = np.empty(bs.M)
    for m in range(bs.M):
        pos = bs.positions[m]
        az, el = bs.azimuth[m], bs.elevation[m]
        has = np.isfinite(el)
        saz, sel = bs.sigma_az[m], bs.sigma_el[m][has]

        def fun(x):
            d = x - pos
            r_az = wrap_angle(az - np.arctan2(d[:, 1], d[:, 0])) / saz
            r_el = (el[has] - np.arctan2(d[has, 2], np.hypot(d[has, 0], d[has, 1]))) / sel
            return np.concatenate([r_az, r_el])

        def jac(x):
            g_az, g_el = angle_jacobians(x, pos)
            return -np.concatenate([g_az[0] / saz[:, None], g_el[0][has] / sel[:, None]])

        sol = least_squares(fun, x0[m], jac=jac, method='lm', xtol=1e-10)
        out[m] = sol.x
        nfev[m] = sol.nfev
    return out, nfev


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--quick', action='store_true', help='N = 3 and 100 only, smaller M')
    ap.add_argument('--seed', type=int, default=0)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    sizes = [3, 100] if a.quick else [3, 10, 100, 1000]
    t_start = time.perf_counter()
    rows = []
    per_iter = []
    for N in sizes:
        M = min(10000, 100000 // N) // (10 if a.quick else 1)
        _, one = problems(N, 1, rng)
        _, batch = problems(N, M, rng)
        for method in METHODS:
            fn = est.ESTIMATORS[method]
            lat, _ = best_time(lambda: fn(one), 20 if N <= 100 else 5)
            thr, res = best_time(lambda: fn(batch), 3 if M * N <= 30000 else 1)
            rows.append((N, method, lat * 1e3, M, M / thr, res.iterations.mean(),
                         res.converged.mean()))
        # scipy reference on the same problems, one by one.
        x0 = est.ls(batch).position
        ms = min(M, 200)
        sub = BearingSet(batch.positions[:ms], batch.azimuth[:ms], batch.elevation[:ms],
                         batch.sigma_az[:ms], batch.sigma_el[:ms])
        x_ls1 = est.ls(one).position
        lat, _ = best_time(lambda: scipy_ml(one, x_ls1), 5)
        thr, (xs, nfev) = best_time(lambda: scipy_ml(sub, x0[:ms]), 1)
        mine = est.mle(sub).position
        dev = np.max(np.linalg.norm(xs - mine, axis=1))
        rows.append((N, 'scipy least_squares (ML)', lat * 1e3, ms, ms / thr, nfev.mean(), 1.0))
        # Per-iteration cost of the default estimator: one evaluation over M × N bearings.
        prob = est._MLProblem(batch)
        xb = np.nan_to_num(est.mle(batch).position).T.copy()
        t_eval, _ = best_time(lambda: prob.pack(xb[0], xb[1], xb[2]), 5)
        prob1 = est._MLProblem(one)
        x1 = np.nan_to_num(est.mle(one).position).T.copy()
        t_eval1, _ = best_time(lambda: prob1.pack(x1[0], x1[1], x1[2]), 50)
        per_iter.append((N, t_eval1 * 1e6, M, t_eval * 1e6, t_eval * 1e9 / (M * N), dev))

    print(f'N stations, M problems; seed {a.seed}; one thread '
          f'({time.perf_counter() - t_start:.0f} s to run)\n')
    print('| N | estimator | latency M=1 (ms) | batch M | throughput (fixes/s) '
          '| mean iterations | converged |')
    print('|---|---|---|---|---|---|---|')
    for N, name, lat, M, thr, it, conv in rows:
        it_s = f'{it:.1f}' + (' (nfev)' if name.startswith('scipy') else '')
        print(f'| {N} | {name} | {lat:.2f} | {M} | {thr:,.0f} | {it_s} | {conv:.3f} |')
    print('\nPer iteration of the default estimator (mle): one cost/normal-matrix evaluation')
    print('| N | M=1 (µs) | batch M | batch (µs) | ns per bearing | max |x_scipy − x_mle| (m) |')
    print('|---|---|---|---|---|---|')
    for N, t1, M, tb, nsb, dev in per_iter:
        print(f'| {N} | {t1:.0f} | {M} | {tb:,.0f} | {nsb:.1f} | {dev:.1e} |')


if __name__ == '__main__':
    main()
