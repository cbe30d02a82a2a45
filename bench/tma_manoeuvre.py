"""TMA with a manoeuvring observer: the speed prior relative to the fitted track or ground.

The observer flies 250 m/s north for 50 s, then 250 m/s east (a 90° turn); the target starts
at (100, 100, 10) km with velocity (−340, 80, −1.21) m/s (ground speed 349.3 m/s), seen in
azimuth and elevation every 0.2 s for 100 s at σ = 0.1°, ``--runs`` Monte Carlo runs. Each
TMA estimator of Lin et al. (core.tma) runs with ``speed_reference: relative`` and the
paper's prior 380 m/s, and with ``ground`` and the target's true ground speed. Printed per
case: statuses, and over every fix at t = 100 s (whatever its status) the RMSE, the mean
NEES (3 expected) and how many exceed the χ²₃ 0.9999 quantile. With ``relative`` the prior is the
speed relative to the observer's fitted straight-line track (docs/tma.md (T2)), which no one
can state for a turning observer: docs/tma.md, "Model".

    .venv/bin/python bench/tma_manoeuvre.py [--runs 200]
    .venv/bin/python bench/tma_manoeuvre.py --noise     # u of a straight, noisy observer
    .venv/bin/python bench/tma_manoeuvre.py --gps-step  # a step in the observer positions

``--noise``: the departure u of test (T22) (core.tma.confidence.manoeuvre_speed) for the
paper's straight observer (Lin et al.: 250 m/s north) whose positions carry white noise of
1, 3 and 5 m per axis, over windows of 20, 50 and 100 s: median and largest over the runs,
against the bound 0.01 v_c = 3.8 m/s.

``--gps-step``: the paper's straight observer whose reported positions are off by a step of
30-1000 m along x from 50 s on (a GPS fault: the bearings are taken from the true track),
``tma_mle`` with both priors (``relative`` 380.13 m/s, the exact relative speed; ``ground``
349.3 m/s): how many fixes are ``ok``, their mean NEES and how many exceed χ²₃ 0.9999.
"""
import argparse
import math
import os
import sys
from collections import Counter

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bearing_loc_ros.core.evaluation import CONFIDENT_WRONG_NEES  # noqa: E402
from bearing_loc_ros.core.tma import simulate_tma, tma  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=int, default=200)
    ap.add_argument('--seed', type=int, default=3)
    ap.add_argument('--noise', action='store_true',
                    help='u of (T22) for a straight observer with noisy positions')
    ap.add_argument('--gps-step', action='store_true',
                    help='fixes of a straight observer whose positions step from 50 s on')
    a = ap.parse_args()
    if a.noise:
        return noise_table(a.runs, a.seed)
    if a.gps_step:
        return gps_step_table(a.runs, a.seed)
    t = np.arange(0.0, 100.01, 0.2)
    north, east = np.array([0.0, 250.0, 0.0]), np.array([250.0, 0.0, 0.0])
    obs = np.where(t[:, None] < 50, north * t[:, None], 50.0 * north + east * (t[:, None] - 50))
    p0, v = np.array([100e3, 100e3, 10e3]), np.array([-340.0, 80.0, -1.21])
    bs, _ = simulate_tma(t, p0, v, obs, math.radians(0.1), rng=np.random.default_rng(a.seed),
                         M=a.runs)
    truth = p0 + v * t[-1]
    print('estimator  speed_reference  prior m/s  statuses                       RMSE m  '
          'NEES  confidently wrong (every fix)')
    for name in ('tma_ple', 'tma_ctls', 'tma_ctls6', 'tma_mle'):
        for ref, speed in (('relative', 380.0), ('ground', float(np.linalg.norm(v)))):
            r = tma(name, bs, t, speed, speed_reference=ref)
            e = r.position - truth
            nees = np.einsum('mi,mij,mj->m', e, np.linalg.inv(r.covariance[:, :3, :3]), e)
            stats = dict(sorted(Counter(str(s) for s in r.status).items()))
            rmse = math.sqrt(float((e * e).sum(axis=1).mean()))
            print(f'{name:10s} {ref:16s} {speed:9.1f}  {str(stats):30s} {rmse:6.0f}  '
                  f'{float(nees.mean()):5.1f}  {int((nees > CONFIDENT_WRONG_NEES).sum())}')


def noise_table(runs, seed):
    """Print u (T22) of a straight observer with white position noise (module docstring)."""
    from bearing_loc_ros.core.bearings import BearingSet
    from bearing_loc_ros.core.tma import confidence, model
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 100.01, 0.2)
    obs = np.array([0.0, 250.0, 0.0]) * t[:, None]
    print('window s  noise m  u median m/s  u max m/s  (bound 3.8 m/s)')
    for window in (20.0, 50.0, 100.0):
        keep = t <= window
        bs, tk = simulate_tma(t[keep], [100e3, 100e3, 10e3], [-340.0, 80.0, -1.21],
                              obs[keep], math.radians(0.1), rng=rng, M=runs)
        for noise in (1.0, 3.0, 5.0):
            noisy = BearingSet(bs.positions + rng.normal(0.0, noise, bs.positions.shape),
                               bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el)
            u = confidence.manoeuvre_speed(model.prepare(noisy, tk, 380.0, 'relative'))
            print(f'{window:8.0f}  {noise:7.0f}  {np.median(u):12.2f}  {u.max():9.2f}')


def gps_step_table(runs, seed):
    """Print the fixes of a straight observer with a step in its positions (docstring)."""
    from bearing_loc_ros.core.bearings import BearingSet
    t = np.arange(0.0, 100.01, 0.2)
    v_o = np.array([0.0, 250.0, 0.0])
    p0, v = np.array([100e3, 100e3, 10e3]), np.array([-340.0, 80.0, -1.21])
    bs, tk = simulate_tma(t, p0, v, v_o * t[:, None], math.radians(0.1),
                          rng=np.random.default_rng(seed), M=runs)
    truth = p0 + v * t[-1]
    print('step m  speed_reference  ok    mean NEES of ok  ok NEES > 21.1  RMSE of ok m')
    for step in (0.0, 30.0, 100.0, 300.0, 1000.0):
        pos = bs.positions.copy()
        pos[:, t >= 50.0, 0] += step
        moved = BearingSet(pos, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el)
        for ref, speed in (('relative', float(np.linalg.norm(v - v_o))),
                           ('ground', float(np.linalg.norm(v)))):
            r = tma('tma_mle', moved, tk, speed, speed_reference=ref)
            ok = np.nonzero(r.status == 'ok')[0]
            e = r.position[ok] - truth
            nees = np.array([x @ np.linalg.solve(c[:3, :3], x)
                             for x, c in zip(e, r.covariance[ok])])
            mean = f'{nees.mean():15.3g}' if len(ok) else f'{"–":>15s}'
            rmse = f'{math.sqrt(float((e * e).sum(axis=1).mean())):12.0f}' if len(ok) \
                else f'{"–":>12s}'
            print(f'{step:6.0f}  {ref:15s}  {len(ok):4d}  {mean}  '
                  f'{int((nees > CONFIDENT_WRONG_NEES).sum()):14d}  {rmse}')


if __name__ == '__main__':
    main()
