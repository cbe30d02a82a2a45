"""Speed of the estimators one fix at a time and in batches, next to scipy least_squares (lm).

Problems: random geometry within ±20 km (station heights 0-200 m), targets 0.5-7 km high,
σ = 2 mrad, every third station azimuth-only. The reference is
scipy.optimize.least_squares(method='lm', analytic Jacobian) on the same whitened residuals
as ``mle`` ((measured − predicted)/σ, azimuth wrapped), started from ``ls``, one problem per
call. Everything is measured in this one run, so the ratios compare like with like.

* One fix: ``locate(name, bearings)`` with a one-problem BearingSet (validation included, as
  the fusion node and ``bearing_loc locate`` call it), for N = 3, 4, 6, 10 bearings, for every
  estimator and the variants ``mle plain`` (``robust=False``), ``wmle robust`` and the
  horizontal solve (known target altitude, σ_z = 10 m) of ``mle`` without and with ``robust``
  and of ``wmle`` with ``robust``:
  median
  and 90th percentile per call over ``--problems`` problems (each call timed alone, best of 3
  calls in a row; the estimators take turns problem by problem, so load changes hit all
  alike), and the ratio scipy / estimator (above 1: faster than scipy) and estimator / mle.
* Batch: one call with M = 10,000 problems of N = 3 (and N = 10): fixes per second (the
  estimators take turns, best of 3), and the ratio of the robust default ``mle`` to
  ``mle plain``.
* ``--large``: batch throughput also at N = 100 and 1000 (M = 100,000 / N).

Single-threaded (OMP/BLAS threads pinned to 1 before numpy is imported). The median
|x_scipy − x_mle| shows both solve the same problem.

Profile one fix (pyinstrument is a bench-only tool: ``.venv/bin/pip install pyinstrument``):
``.venv/bin/python bench/bench_estimators.py --profile mle`` (or ``--profile 'wmle robust'``).

Run: .venv/bin/python bench/bench_estimators.py [--quick] [--large] [--problems 300]
"""
import argparse
import os
import sys
import time

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core import estimators as est  # noqa: E402
from bearing_loc_ros.core.bearings import BearingSet, simulate_bearings  # noqa: E402
from bearing_loc_ros.core.conventions import wrap_angle  # noqa: E402
from bearing_loc_ros.core.crlb import angle_jacobians  # noqa: E402

ITERATIVE = ('mle', 'wmle', 'ctls_am', 'ctls')
METHODS = ('mle', 'wmle', 'ctls_am', 'ctls', 'ls', 'tls')
#: Rows besides METHODS: label -> (estimator, options, horizontal solve). ``mle`` is robust by
#: default (core.robust); ``mle plain`` is the paper's estimator alone.
VARIANTS = {
    'mle plain': ('mle', {'robust': False}, False),
    'wmle robust': ('wmle', {'robust': True}, False),
    'mle horizontal': ('mle', {}, True),
    'mle horizontal robust': ('mle', {'robust': True}, True),
    'wmle horizontal robust': ('wmle', {'robust': True}, True),
}
#: Rows of the batch table (the robust ``wmle`` refits every fix: one-fix table only).
BATCH = ('mle', 'mle plain', 'wmle', 'ctls_am', 'ctls', 'ls', 'tls', 'mle horizontal')


def problems(N, M, rng):
    """(targets (M, 3), BearingSet) of M random problems with N stations."""
    st = rng.uniform(-20e3, 20e3, size=(N, 3))
    st[:, 2] = rng.uniform(0.0, 200.0, N)
    tgt = rng.uniform([-10e3, -10e3, 500.0], [10e3, 10e3, 7e3], size=(M, 3))
    bs = simulate_bearings(tgt, st, 2e-3, rng=rng)
    el = np.where(np.arange(N) % 3 == 1, np.nan, bs.elevation)
    return tgt, BearingSet.from_arrays(bs.positions, bs.azimuth, el, bs.sigma_az, bs.sigma_el)


def split(bs):
    """One one-problem BearingSet per problem (built before timing)."""
    return [BearingSet(bs.positions[m:m + 1].copy(), bs.azimuth[m:m + 1].copy(),
                       bs.elevation[m:m + 1].copy(), bs.sigma_az[m:m + 1].copy(),
                       bs.sigma_el[m:m + 1].copy()) for m in range(bs.M)]


def scipy_problem(one):
    """(fun, jac) of one problem's whitened ML residuals (Zong & Cui 2015 eq. (3))."""
    pos = one.positions[0]
    az, el = one.azimuth[0], one.elevation[0]
    has = np.isfinite(el)
    saz, sel = one.sigma_az[0], one.sigma_el[0][has]

    def fun(x):
        d = x - pos
        r_az = wrap_angle(az - np.arctan2(d[:, 1], d[:, 0])) / saz
        r_el = (el[has] - np.arctan2(d[has, 2], np.hypot(d[has, 0], d[has, 1]))) / sel
        return np.concatenate([r_az, r_el])

    def jac(x):
        g_az, g_el = angle_jacobians(x, pos)
        return -np.concatenate([g_az[0] / saz[:, None], g_el[0][has] / sel[:, None]])

    return fun, jac


def runner(label, targets):
    """fn(bearings, rows) running row label (a METHODS name or a VARIANTS label).

    ``targets`` (M, 3): a horizontal solve is given the true target altitudes of ``rows``
    (σ_z = 10 m), as a known-altitude deployment would state them.
    """
    from bearing_loc_ros.core.horizontal import locate_horizontal
    name, opts, horizontal = VARIANTS.get(label, (label, {}, False))
    if horizontal:
        return lambda b, rows: locate_horizontal(name, b, targets[rows, 2], 10.0, **opts)
    return lambda b, rows: est.locate(name, b, **opts)


def interleaved(fns, items, repeat=3):
    """{name: seconds per call (best of ``repeat`` calls in a row) for every item}, outputs.

    The functions take turns problem by problem, so a change of machine load hits every
    estimator alike and the ratios stay comparable; the best of ``repeat`` calls in a row
    leaves out the first call's cold caches.
    """
    times = {name: np.full(len(items), np.inf) for name in fns}
    out = {name: [None] * len(items) for name in fns}
    for k, item in enumerate(items):
        for name, fn in fns.items():
            for _ in range(repeat):
                t0 = time.perf_counter()
                res = fn(item)
                times[name][k] = min(times[name][k], time.perf_counter() - t0)
            out[name][k] = res
    return times, out


def single_fix_table(sizes, n_problems, rng):
    """Rows (N, name, median ms, p90 ms, scipy/this, this/mle) and scipy agreement."""
    rows, agree = [], []
    for N in sizes:
        tgt, bs = problems(N, n_problems, rng)
        ones = split(bs)
        x0 = [est.ls(b).position[0] for b in ones]
        setups = [scipy_problem(b) for b in ones]
        fns = {label: (lambda k, run=runner(label, tgt): run(ones[k], slice(k, k + 1)))
               for label in METHODS + tuple(VARIANTS)}
        fns['scipy lm'] = lambda k: least_squares(setups[k][0], x0[k], jac=setups[k][1],
                                                  method='lm', xtol=1e-10)
        t, out = interleaved(fns, range(len(ones)))
        med = {name: (np.median(v), np.percentile(v, 90)) for name, v in t.items()}
        x_mle = est.locate('mle', bs).position
        agree.append((N, np.median(np.linalg.norm(np.array([s.x for s in out['scipy lm']])
                                                  - x_mle, axis=1))))
        for name, (m, p90) in med.items():
            rows.append((N, name, m * 1e3, p90 * 1e3, med['scipy lm'][0] / m,
                         m / med['mle'][0]))
    return rows, agree


def batch_table(sizes, M_of, rng, repeat=3):
    """Rows (N, name, M, fixes/s, mean iterations, converged fraction)."""
    rows = []
    for N in sizes:
        M = M_of(N)
        tgt, bs = problems(N, M, rng)
        best = dict.fromkeys(BATCH, np.inf)
        res = {}
        # The estimators take turns (best of ``repeat``), so load changes hit all alike.
        for _ in range(repeat if M * N <= 100000 else 1):
            for label in BATCH:
                run = runner(label, tgt)
                t0 = time.perf_counter()
                res[label] = run(bs, slice(None))
                best[label] = min(best[label], time.perf_counter() - t0)
        for label in BATCH:
            rows.append((N, label, M, M / best[label], res[label].iterations.mean(),
                         res[label].converged.mean()))
        ms = min(M, 200)
        ones = split(BearingSet(bs.positions[:ms], bs.azimuth[:ms], bs.elevation[:ms],
                                bs.sigma_az[:ms], bs.sigma_el[:ms]))
        setups = [scipy_problem(b) for b in ones]
        x0 = est.ls(bs).position[:ms]
        t0 = time.perf_counter()
        nfev = [least_squares(f, x0[k], jac=j, method='lm', xtol=1e-10).nfev
                for k, (f, j) in enumerate(setups)]
        rows.append((N, 'scipy lm (one by one)', ms, ms / (time.perf_counter() - t0),
                     float(np.mean(nfev)), 1.0))
    return rows


def profile(name, N=6, calls=2000):
    """pyinstrument profile of ``calls`` single-fix calls of ``name`` (a METHODS name or a
    VARIANTS label, e.g. 'wmle robust')."""
    from pyinstrument import Profiler
    tgt, bs = problems(N, calls, np.random.default_rng(1))
    ones = split(bs)
    run = runner(name, tgt)
    p = Profiler(interval=1e-4)
    p.start()
    for k, b in enumerate(ones):
        run(b, slice(k, k + 1))
    p.stop()
    print(p.output_text(unicode=True, color=False, show_all=False))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--quick', action='store_true', help='fewer problems, N = 3 and 10 only')
    ap.add_argument('--large', action='store_true', help='batch also at N = 100 and 1000')
    ap.add_argument('--problems', type=int, default=300, help='problems per N (one fix)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--profile', metavar='ESTIMATOR', help='profile single fixes and exit')
    a = ap.parse_args(argv)
    if a.profile:
        profile(a.profile)
        return 0
    rng = np.random.default_rng(a.seed)
    t_start = time.perf_counter()
    n_problems = 100 if a.quick else a.problems
    sizes = (3, 10) if a.quick else (3, 4, 6, 10)
    single, agree = single_fix_table(sizes, n_problems, rng)
    batch_sizes = (3, 10) + ((100, 1000) if a.large else ())
    batch = batch_table(batch_sizes, lambda N: min(10000, 100000 // N) // (10 if a.quick else 1),
                        rng)
    print(f'seed {a.seed}, one thread, {n_problems} problems per N '
          f'({time.perf_counter() - t_start:.0f} s to run)\n')
    print('One fix: locate(name, one problem), time per call')
    print('| N | estimator | median (ms) | p90 (ms) | scipy lm / this | this / mle |')
    print('|---|---|---|---|---|---|')
    for N, name, m, p90, vs_scipy, vs_mle in single:
        print(f'| {N} | {name} | {m:.3f} | {p90:.3f} | {vs_scipy:.2f} | {vs_mle:.2f} |')
    print('\nMedian |x_scipy − x_mle| (m): '
          + ', '.join(f'N={N}: {d:.1e}' for N, d in agree))
    print('\nBatch: one call with M problems')
    print('| N | estimator | M | fixes/s | mean iterations | converged |')
    print('|---|---|---|---|---|---|')
    for N, name, M, thr, it, conv in batch:
        it_s = f'{it:.1f}' + (' (nfev)' if name.startswith('scipy') else '')
        print(f'| {N} | {name} | {M} | {thr:,.0f} | {it_s} | {conv:.3f} |')
    thr = {(N, name): t for N, name, _, t, _, _ in batch}
    print('\nBatch mle (robust, the default) / mle plain, same run: '
          + ', '.join(f'N={N}: {thr[N, "mle"] / thr[N, "mle plain"]:.2f}'
                      for N in batch_sizes))
    return 0


if __name__ == '__main__':
    sys.exit(main())
