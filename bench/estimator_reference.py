"""Reference inputs and outputs of every estimator, to check that faster code gives the same fixes.

Generates seeded problems (the station layouts of Wang, Zhang & Wu (2006) and of Zong & Cui
(2015), random layouts with N = 3-10 stations mixing azimuth-only and azimuth-elevation
bearings, the six-station line at σ = 1° and 3°, and single-station TMA problems of the kind
of Lin et al.), runs every estimator on
them and either writes the inputs with the results to ``test/data/estimators_reference.npz``
(``--write``: only when the estimators' answers are meant to change) or compares the current
results with the stored ones (default). test/test_estimators_reference.py checks the current
code against the stored inputs and outputs (relative 1e-9).

Run: .venv/bin/python bench/estimator_reference.py [--write]
"""
import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from bearing_loc_ros.core.bearings import simulate_bearings  # noqa: E402

PATH = os.path.join(os.path.dirname(HERE), 'test', 'data', 'estimators_reference.npz')
MULTI = ('ls', 'tls', 'ctls', 'ctls_am', 'mle', 'wmle')
TMA = ('ple', 'ctls', 'ctls6', 'mle')
LINE = np.array([[x, 0.0, 0.0] for x in (-3000.0, -1800.0, -600.0, 600.0, 1800.0, 3000.0)])
SEED000 = np.array([[30000.0, -10000.0, 100.0], [30000.0, 20000.0, 200.0],
                    [-30000.0, 5000.0, 150.0]])


def _groups():
    """{name: BearingSet} of seeded multi-station problems."""
    rng = np.random.default_rng(20261201)
    out = {}
    tgt = rng.uniform([30000.0, -20000.0, 3000.0], [60000.0, 30000.0, 7000.0], (24, 3))
    out['seed000'] = simulate_bearings(tgt, SEED000, 3e-3, rng=rng)
    for deg in (0.5, 1.0, 3.0):
        tgt = rng.uniform([-3000.0, 1000.0, -500.0], [3000.0, 7000.0, 500.0], (24, 3))
        out[f'line_{deg:g}deg'] = simulate_bearings(tgt, LINE, np.deg2rad(deg), rng=rng)
    for N in (3, 4, 6, 10):
        st = rng.uniform(-20e3, 20e3, (N, 3))
        st[:, 2] = rng.uniform(0.0, 200.0, N)
        tgt = rng.uniform([-10e3, -10e3, 500.0], [10e3, 10e3, 7e3], (24, 3))
        mask = np.arange(N) % 3 != 1
        out[f'random_n{N}'] = simulate_bearings(tgt, st, 2e-3, has_elevation=mask, rng=rng)
    return out


def _tma_problem():
    """(BearingSet, times, speed) of seeded single-station TMA problems (as in Lin et al.)."""
    from bearing_loc_ros.core.tma import simulate_tma
    rng = np.random.default_rng(1001)
    t = np.arange(0.0, 200.0, 10.0)
    obs = np.stack([50.0 * t, 2000.0 * np.sin(t / 60.0), np.full_like(t, 300.0)], axis=1)
    bs, times = simulate_tma(t, [8000.0, 12000.0, 1500.0], [-8.0, 3.0, 0.0], obs,
                             np.deg2rad(0.3), rng=rng, M=16)
    return bs, times, 60.0


def run_multi(method, bs):
    """Estimator ``method`` on ``bs`` (wmle with d_ref = 1000 m)."""
    from bearing_loc_ros.core.estimators import locate
    from bearing_loc_ros.core.registry import scoped_options
    return locate(method, bs, **scoped_options(method, {'reference_range': 1000.0}))


def run_tma(method, bs, times, speed):
    """TMA estimator ``tma_<method>`` on the TMA problems (stored under ``tma/<method>``)."""
    from bearing_loc_ros.core import tma
    return tma.tma('tma_' + method, bs, times, speed)


def compute():
    """{key: array} of inputs and outputs."""
    data = {}
    for g, bs in _groups().items():
        for f in ('positions', 'azimuth', 'elevation', 'sigma_az', 'sigma_el'):
            data[f'{g}/in/{f}'] = getattr(bs, f)
        for m in MULTI:
            r = run_multi(m, bs)
            data[f'{g}/{m}/position'] = r.position
            data[f'{g}/{m}/covariance'] = r.covariance
            data[f'{g}/{m}/iterations'] = r.iterations
            data[f'{g}/{m}/status'] = r.status.astype('U24')
    bs, times, speed = _tma_problem()
    for f in ('positions', 'azimuth', 'elevation', 'sigma_az', 'sigma_el'):
        data[f'tma/in/{f}'] = getattr(bs, f)
    data['tma/in/times'] = times
    data['tma/in/speed'] = np.array(speed)
    for m in TMA:
        r = run_tma(m, bs, times, speed)
        data[f'tma/{m}/position'] = r.position
        data[f'tma/{m}/velocity'] = r.velocity
        data[f'tma/{m}/covariance'] = r.covariance
        data[f'tma/{m}/status'] = r.status.astype('U24')
    return data


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--write', action='store_true', help='store the current results')
    args = p.parse_args(argv)
    data = compute()
    if args.write:
        os.makedirs(os.path.dirname(PATH), exist_ok=True)
        np.savez_compressed(PATH, **data)
        print(f'wrote {os.path.relpath(PATH)} ({os.path.getsize(PATH)} bytes)')
        return 0
    ref = np.load(PATH)
    bad = [k for k in ref.files if '/in/' not in k and not k.endswith('status')
           and not np.allclose(ref[k], data[k], rtol=1e-9, atol=0.0, equal_nan=True)]
    bad += [k for k in ref.files if k.endswith('status') and not np.array_equal(ref[k], data[k])]
    print('\n'.join(sorted(bad)) if bad else 'all results match the reference')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
