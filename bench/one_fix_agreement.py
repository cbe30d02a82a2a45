"""One problem per call against the batch path, on the seed scenarios (prints figures).

A call with one problem (the fusion node, ``bearing_loc locate`` on one problem) runs the
estimators and the robust steps on Python floats (core/ml_single.py, core/robust_single.py);
a batch runs them on arrays. This script solves the same noisy bearings both ways and prints,
per scenario and σ, the number of status differences, the largest relative difference of the
nonlinearity ν where the robust steps ran, and the largest position difference relative to
the rms station range, for ``ok`` and for ``low_confidence`` fixes, and for the latter also
relative to the fix's own σ (square root of the largest covariance eigenvalue).

Scenarios: Zong & Cui (2015) (config/scenarios/seed003.yaml, σ grows with range; ``wmle``
robust), six stations with constant σ (six_station_const.yaml; ``mle``, robust by default)
and Wang, Zhang & Wu (2006) (seed000.yaml at 1.5 and 4.5 mrad; ``mle``).

``--random``: instead, random problems (the geometry of bench/bench_estimators.py: N = 3, 4,
5, 6, 8, 10 stations, σ 2, 20 and 60 mrad, 0 or 15 % outliers of 0.3-1.5 rad, two seeds,
``--trials`` problems each), each solved one problem per call twice, on floats and with the
float steps forced onto the batch path (core.robust_single.refine raising Fallback):
statuses, convergence flags and exclusions compared, and per (estimator, status) the largest
and 99th-percentile position difference relative to the rms station range, the share above
1e-9, and the largest covariance difference relative to its largest entry.

Run: .venv/bin/python bench/one_fix_agreement.py [--trials 300] [--random [--trials 100]]
"""

import argparse
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bearing_loc_ros.core import evaluation as ev  # noqa: E402
from bearing_loc_ros.core.estimators import locate  # noqa: E402
from bearing_loc_ros.core.simulation import load_scenario  # noqa: E402
from bearing_loc_ros.scenarios import resolve_scenario  # noqa: E402

CASES = (('config/scenarios/seed003.yaml', 'wmle', {'robust': True}, (0.5, 1, 2, 3, 5)),
         ('config/scenarios/six_station_const.yaml', 'mle', {}, (1, 3, 5)),
         ('config/scenarios/seed000.yaml', 'mle', {},
          (math.degrees(1.5e-3), math.degrees(4.5e-3))))


def compare(path, name, opts, sigma_deg, trials, seed):
    """(status differences, max rel. diff ok, max rel. diff low_confidence, the same in σ,
    number of ok fixes, number of low_confidence fixes, max rel. diff of ν)."""
    tr = ev.trials_from_scenario(load_scenario(resolve_scenario(path)), trials, 0)
    if name == 'wmle':
        opts = dict(opts, reference_range=tr.reference_range() or 1000.0)
    f = tr.sigma_factor()
    s = math.radians(sigma_deg)
    b = ev.noisy_bearings(tr, s * f, s * f, np.random.default_rng(seed))
    b.sigma_az = np.full_like(b.sigma_az, s)
    b.sigma_el = np.where(b.has_elevation, s, np.nan)
    batch = locate(name, b, **opts)
    diff, ok, lc, lc_sigma, nu = 0, 0.0, 0.0, 0.0, 0.0
    n_ok = int(np.count_nonzero(batch.status == 'ok'))
    n_lc = int(np.count_nonzero(batch.status == 'low_confidence'))
    for m in range(b.M):
        one = locate(name, b.problem(m), **opts)
        if one.status[0] != batch.status[m]:
            diff += 1
            continue
        a, b_nu = one.nonlinearity[0], batch.nonlinearity[m]
        if np.isnan(a) != np.isnan(b_nu):
            nu = np.inf
        elif not np.isnan(a):
            nu = max(nu, abs(a - b_nu) / b_nu)
        if not np.all(np.isfinite(one.position[0])):
            continue
        dx = np.max(np.abs(one.position[0] - batch.position[m]))
        scale = np.sqrt(np.mean(np.sum((b.positions[m] - batch.position[m]) ** 2, axis=1)))
        if batch.status[m] == 'ok':
            ok = max(ok, dx / scale)
        elif batch.status[m] == 'low_confidence':
            lc = max(lc, dx / scale)
            lc_sigma = max(lc_sigma, dx / np.sqrt(np.linalg.eigvalsh(batch.covariance[m])[-1]))
    return diff, ok, lc, lc_sigma, n_ok, n_lc, nu


def random_problems(m_per_case):
    """The ``--random`` comparison (module docstring); prints one line per (estimator, status)."""
    from bench_estimators import problems
    from bearing_loc_ros.core import robust_single
    from bearing_loc_ros.core.bearings import BearingSet
    refine = robust_single.refine

    def forced(*args, **kwargs):
        raise robust_single.Fallback('forced onto the batch path')

    worst, mismatches, compared, fallbacks = {}, 0, 0, 0
    for seed in range(2):
        for N in (3, 4, 5, 6, 8, 10):
            for sig in (2e-3, 2e-2, 6e-2):
                for out in (0.0, 0.15):
                    rng = np.random.default_rng(1000 * seed + 10 * N + int(sig * 1e3)
                                                + int(out * 100))
                    _, bs = problems(N, m_per_case, rng)
                    az = (bs.azimuth + rng.normal(0, 1, bs.azimuth.shape) * (sig - 2e-3)
                          + (rng.random(bs.azimuth.shape) < out)
                          * rng.uniform(0.3, 1.5, bs.azimuth.shape))
                    bs = BearingSet.from_arrays(
                        bs.positions, az, bs.elevation, np.full_like(bs.sigma_az, sig),
                        np.where(np.isfinite(bs.elevation), sig, np.nan))
                    for name, opts in (('wmle', {'robust': True}), ('mle', {})):
                        d_ref = 1000.0 if name == 'wmle' else None
                        for m in range(bs.M):
                            one = bs.problem(m)
                            x = locate(name, one, robust=False).position[0].tolist()
                            try:
                                refine(one, x, d_ref)
                            except robust_single.Fallback:
                                fallbacks += 1          # the floats hand it over anyway
                                continue
                            a = locate(name, one, **opts)
                            robust_single.refine = forced
                            try:
                                b = locate(name, one, **opts)
                            finally:
                                robust_single.refine = refine
                            compared += 1
                            if (a.status[0] != b.status[0] or a.converged[0] != b.converged[0]
                                    or not np.array_equal(a.excluded[0], b.excluded[0])):
                                mismatches += 1
                                continue
                            if not np.isfinite(b.nonlinearity[0]):
                                continue
                            sc = np.sqrt(np.mean(np.sum((b.position[0] - one.positions[0]) ** 2,
                                                        axis=1)))
                            r = np.abs(a.position[0] - b.position[0]).max() / sc
                            c = (np.abs(a.covariance[0] - b.covariance[0]).max()
                                 / np.abs(b.covariance[0]).max())
                            w = worst.setdefault((name, str(b.status[0])), ([], 0.0))
                            worst[(name, str(b.status[0]))] = (w[0] + [r], max(w[1], c))
    print(f'{compared} problems compared one per call, floats against the batch path; '
          f'{mismatches} status, convergence or exclusion differences; {fallbacks} handed '
          'to the batch path by the floats themselves')
    print('| estimator | status | fixes | max position difference | 99th percentile | '
          'share above 1e-9 | max covariance difference |')
    print('|---|---|---:|---:|---:|---:|---:|')
    for (name, status), (r, c) in sorted(worst.items()):
        r = np.array(r)
        print(f'| {name} | {status} | {r.size} | {r.max():.1e} | {np.percentile(r, 99):.1e} | '
              f'{np.mean(r > 1e-9):.4f} | {c:.1e} |')


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--trials', type=int, default=None,
                    help='problems per row (300), or per case with --random (100)')
    ap.add_argument('--random', action='store_true',
                    help='random problems, floats against the forced batch path')
    a = ap.parse_args()
    if a.random:
        random_problems(a.trials or 100)
        return
    a.trials = a.trials or 300
    print(f'{a.trials} problems per row; position differences: max over coordinates, '
          'relative to the rms station range (and to the fix\'s own σ)')
    print('| scenario | estimator | σ | status differences | ν | ok fixes | '
          'low_confidence fixes |')
    print('|---|---|---|---:|---:|---|---|')
    for path, name, opts, sigmas in CASES:
        for k, sd in enumerate(sigmas):
            diff, ok, lc, lcs, n_ok, n_lc, nu = compare(path, name, opts, sd, a.trials, k)
            label = name + (' robust' if opts.get('robust') else '')
            ok_text = f'{n_ok}: {ok:.1e}' if n_ok else '0'
            lc_text = f'{n_lc}: {lc:.1e} ({lcs:.1e} of its σ)' if n_lc else '0'
            print(f'| {os.path.basename(path)} | {label} | {sd:.3f}° | {diff} | {nu:.1e} | '
                  f'{ok_text} | {lc_text} |', flush=True)


if __name__ == '__main__':
    main()
