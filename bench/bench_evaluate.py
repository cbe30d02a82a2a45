"""Wall time of the full Zong & Cui (2015) Monte Carlo evaluation (docs/benchmarks.md).

The target: 1000 trials x 6 σ values x 5 estimators (ls, tls, ctls, mle, wmle) on
config/scenarios/seed003.yaml in under 60 s on one core. This runs exactly what
``bearing_loc evaluate`` runs (core.evaluation.evaluate over trials_from_scenario), first the
joint sweep alone (the 6 × 5 grid), then all three sweeps (joint, azimuth-only,
elevation-only: 18 noise levels), and prints the wall time of each and the time per fix of
every estimator. Pin it to one core with ``taskset -c 0`` to measure the one-core figure;
numpy's BLAS threads are limited to one here (OMP/OPENBLAS/MKL_NUM_THREADS=1 set before
numpy is imported).

Run: .venv/bin/python bench/bench_evaluate.py [--trials 1000] [--seed 0]
"""
import argparse
import os
import time

for _v in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_v, '1')

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ESTIMATORS = ['ls', 'tls', 'ctls', 'mle', 'wmle']
SIGMAS = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--trials', type=int, default=1000)
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    from bearing_loc_ros.core import evaluation as ev
    from bearing_loc_ros.core.simulation import load_scenario
    sc = load_scenario(os.path.join(REPO, 'config', 'scenarios', 'seed003.yaml'))
    t0 = time.perf_counter()
    tr = ev.trials_from_scenario(sc, args.trials, args.seed)
    t_trials = time.perf_counter() - t0
    from bearing_loc_ros.core import registry
    # d_ref (Zong & Cui 2015 eqs. (9)-(10)) for the estimators whose noise model uses it
    opts = {e: registry.check(e, {'reference_range': tr.reference_range()})
            for e in ESTIMATORS}
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'
    print(f'seed003: {args.trials} trials, estimators {",".join(ESTIMATORS)}, '
          f'σ {SIGMAS} deg, CPUs usable: {affinity}; trial geometry {t_trials:.3f} s')
    for sweeps in (('joint',), ('joint', 'azimuth', 'elevation')):
        t0 = time.perf_counter()
        rows = ev.evaluate(ESTIMATORS, tr, SIGMAS, sweeps, args.seed, 0.5, opts)
        dt = time.perf_counter() - t0
        print(f'sweeps {"+".join(sweeps):26s}: {len(rows):3d} estimator runs, '
              f'{len(rows) * tr.M} fixes, {dt:6.2f} s wall')
        per = {}
        for r in rows:
            per.setdefault(r.estimator, []).append(r.time_per_fix_s)
    print('time per fix (mean over levels): '
          + ', '.join(f'{k} {1e6 * sum(v) / len(v):.1f} µs' for k, v in per.items()))


if __name__ == '__main__':
    main()
